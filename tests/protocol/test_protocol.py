"""The protocol as data: tracks, budgets, the core suite, reference scores, normalized scores."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offdyn_bench import protocol
from offdyn_bench.datasets.manifest import read_manifest
from offdyn_bench.datasets.recipes import dataset_id
from offdyn_bench.errors import OffdynError
from offdyn_bench.protocol import (
    BUDGETS,
    CORE_SUITE,
    EPISODE_SEEDS,
    EVAL_EPISODES,
    PROTOCOL_VERSION,
    TRACKS,
    ProtocolError,
    check_method_on_track,
    normalized_score,
    official_dataset,
    record_oracle_reference,
    reference_scores,
)
from offdyn_bench.protocol.references import read_reference_file
from offdyn_bench.tasks import TASKS


def test_tracks_cover_every_reference_implementation():
    from baselines.cli import ALGORITHM_NAMES

    placed = [m for t in TRACKS.values() for m in t.methods] + list(protocol.REFERENCE_METHODS)
    assert sorted(placed) == sorted(ALGORITHM_NAMES)
    assert TRACKS["online-target"].target_step_budget(BUDGETS["lite"].source_steps) == 10_000
    assert TRACKS["offline-target"].target_step_budget(BUDGETS["full"].source_steps) == 0


def test_the_registry_and_the_protocol_agree_on_every_methods_track():
    from baselines.algorithms import ALGORITHMS

    for name, algorithm in ALGORITHMS.items():
        expected = protocol.track_of_method(name) or "reference"
        assert algorithm.track == expected, name


def test_a_method_is_refused_on_a_track_it_does_not_fit():
    check_method_on_track("dap", "offline-target")
    check_method_on_track("sac-source", "online-target")  # a reference point, scored on every track
    with pytest.raises(ProtocolError, match="darc-online belongs on the 'online-target' track"):
        check_method_on_track("darc-online", "offline-target")
    with pytest.raises(OffdynError, match="unknown track 'ofline-target'; closest valid names: 'offline-target'"):
        check_method_on_track("dap", "ofline-target")


def test_evaluation_seeds_are_fixed_and_disjoint_from_training_and_dataset_seeds():
    from baselines.train import EVAL_SEED

    assert len(EPISODE_SEEDS) == EVAL_EPISODES == 20
    assert EPISODE_SEEDS == tuple(range(EPISODE_SEEDS[0], EPISODE_SEEDS[0] + 20))
    assert not set(EPISODE_SEEDS) & set(range(EVAL_SEED, EVAL_SEED + 1000))


def test_core_suite_covers_every_locomotion_robot_and_shift_family():
    pairs = [TASKS[name] for name in CORE_SUITE]
    assert {p.robot for p in pairs} == {"Ant", "HalfCheetah", "Hopper", "Walker2d"}
    assert {p.shift for p in pairs} >= {"gravity", "friction", "kinematic", "morph", "joint-noise"}
    assert all(not p.source_effects for p in pairs)  # nominal sources: the shipped behaviour policies


def test_every_core_task_has_both_datasets_with_hashes_in_the_manifest():
    manifest = read_manifest()
    for task in CORE_SUITE:
        for quality in ("source-policy", "random"):
            ident = dataset_id(task, quality)
            assert ident in manifest and manifest.get(ident).files, f"{ident} lacks recorded hashes"
    assert official_dataset("hopper-gravity-0.5", "offline-target") == "offdyn/hopper-gravity-0p5/source-policy-v0"
    assert official_dataset("hopper-gravity-0.5", "online-target") is None


def test_the_shipped_reference_file_has_a_random_reference_for_every_core_task():
    data = read_reference_file()
    assert data["protocol_version"] == PROTOCOL_VERSION
    scores = reference_scores()
    for task in CORE_SUITE:
        random = scores[task]["random"]
        assert len(random.returns) == EVAL_EPISODES
        assert random.mean_return == pytest.approx(np.mean(random.returns))
        assert random.provenance["episode_seeds"] == list(EPISODE_SEEDS)
        assert random.provenance["versions"]["mujoco"] == "3.17.0"


def test_every_shipped_oracle_is_a_protocol_result_of_sac_target():
    """The oracle references that ship (assets/reference_scores.json) anchor normalized scores:
    each must be sac-target's final policies, at least MIN_SEEDS training seeds with the protocol's
    episodes, its mean the mean of its stored returns, and above the task's random reference."""
    from offdyn_bench.protocol import MIN_SEEDS

    for task, kinds in reference_scores().items():
        for kind, score in kinds.items():
            if not kind.startswith("oracle/"):
                continue
            provenance = score.provenance
            assert provenance["method"] == "sac-target" and kind == f"oracle/{provenance['budget']}", task
            assert len(provenance["seeds"]) >= MIN_SEEDS and provenance["episodes_per_seed"] == EVAL_EPISODES, task
            assert provenance["episode_seeds"] == list(EPISODE_SEEDS), task
            assert len(score.returns) == len(provenance["seeds"]) * EVAL_EPISODES, task
            assert score.mean_return == pytest.approx(np.mean(score.returns)), task
            assert score.mean_return > kinds["random"].mean_return, task
            assert all(run["steps"] == protocol.get_budget(provenance["budget"]).source_steps
                       for run in provenance["runs"]), task


def test_random_reference_is_reproducible(tmp_path):
    path = tmp_path / "refs.json"
    first = protocol.record_random_reference("invertedpendulum-gravity-3.0", path, episodes=[5, 6])
    second = protocol.record_random_reference("invertedpendulum-gravity-3.0", path, episodes=[5, 6])
    assert first.returns == second.returns
    assert list(reference_scores(path)) == ["invertedpendulum-gravity-3.0"]


def test_zero_command_reference_is_the_zero_command_stepped_and_reproducible(tmp_path):
    """The zero command in the Ant's friction x5 target: the Ant stands, unactuated, for the whole
    episode and earns its survival reward (about 1 per step, less contact cost). Recorded twice, the
    same returns; stepping zeros by hand gives them too."""
    import gymnasium

    from offdyn_bench.tasks import get_task

    path = tmp_path / "refs.json"
    first = protocol.record_zero_command_reference("ant-friction-5.0", path, episodes=[5])
    second = protocol.record_zero_command_reference("ant-friction-5.0", path, episodes=[5])
    assert first.returns == second.returns and first.kind == "zero-command"
    env = get_task("ant-friction-5.0").make("target")
    env.reset(seed=5)
    total, steps, done = 0.0, 0, False
    while not done:
        _, reward, terminated, truncated, _ = env.step(np.zeros(8, dtype=np.float32))
        total, steps, done = total + float(reward), steps + 1, terminated or truncated
    assert first.returns == (total,) and steps == 1000 and 0.9 * steps < total <= steps
    stored = reference_scores(path)["ant-friction-5.0"]
    assert set(stored) == {"zero-command"} and stored["zero-command"].returns == (total,)
    assert stored["zero-command"].provenance["command"] == \
        "offdyn-bench protocol reference zero-command --task ant-friction-5.0"
    # Beside a random reference of the same task, each keeps its own entry.
    protocol.record_random_reference("ant-friction-5.0", path, episodes=[5])
    assert set(reference_scores(path)["ant-friction-5.0"]) == {"random", "zero-command"}
    assert isinstance(env.action_space, gymnasium.spaces.Box)


def test_every_core_suite_pair_has_a_zero_command_reference():
    for task in CORE_SUITE:
        zero = reference_scores()[task]["zero-command"]
        assert len(zero.returns) == EVAL_EPISODES and zero.provenance["episode_seeds"] == list(EPISODE_SEEDS), task


def _refs(tmp_path, random=10.0, oracle=110.0, budget="lite"):
    path = tmp_path / "refs.json"
    path.write_text(json.dumps({
        "format": "offdyn-bench/reference-scores", "format_version": 1, "protocol_version": PROTOCOL_VERSION,
        "tasks": {"hopper-gravity-0.5": {
            "random": {"mean_return": random, "returns": [random], "provenance": {}},
            "oracle": {budget: {"mean_return": oracle, "returns": [oracle], "provenance": {}}}}}}))
    return path


def test_normalized_score_by_hand(tmp_path):
    path = _refs(tmp_path)
    # 100 x (J - 10) / (110 - 10)
    np.testing.assert_allclose(normalized_score([10.0, 60.0, 110.0, -40.0], "hopper-gravity-0.5", "lite", path),
                               [0.0, 50.0, 100.0, -50.0])
    with pytest.raises(ProtocolError, match="no oracle/full reference score"):
        normalized_score(1.0, "hopper-gravity-0.5", "full", path)
    with pytest.raises(ProtocolError, match="NaN or infinite"):
        normalized_score([np.nan], "hopper-gravity-0.5", "lite", path)
    bad = _refs(tmp_path, random=50.0, oracle=40.0)
    with pytest.raises(ProtocolError, match="does not exceed the random"):
        normalized_score(1.0, "hopper-gravity-0.5", "lite", bad)


def test_oracle_provenance_paths_are_relative_to_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    five = [_evaluation(seed=s) for s in range(5)]
    for e in five:
        run = tmp_path / "runs" / "sac-target" / str(e["seeds"][0]["seed"])
        e["agent"]["path"] = str(run)
        e["train_command"] = f"offdyn-bench train sac-target --task hopper-gravity-0.5 --out {run}"
    elsewhere = "/data/elsewhere/run"  # a path outside the working directory stays as it is
    five[4]["agent"]["path"] = elsewhere
    record_oracle_reference(five, tmp_path / "refs.json")
    provenance = reference_scores(tmp_path / "refs.json")["hopper-gravity-0.5"]["oracle/lite"].provenance
    assert [r["path"] for r in provenance["runs"]] == [f"runs/sac-target/{s}" for s in range(4)] + [elsewhere]
    assert provenance["runs"][0]["train_command"].endswith("--out runs/sac-target/0")
    assert provenance["command"].startswith("offdyn-bench protocol reference oracle runs/sac-target/0/evaluation.json ")
    assert str(tmp_path) not in json.dumps(provenance)


def test_a_damaged_reference_file_is_a_clear_error(tmp_path):
    path = tmp_path / "refs.json"
    path.write_text('{"format": "offdyn-bench/reference-scores", "tasks": ')
    with pytest.raises(ProtocolError, match="cannot be read"):
        reference_scores(path)
    path.write_text(json.dumps({"format": "offdyn-bench/reference-scores", "protocol_version": "0.1", "tasks": {}}))
    with pytest.raises(ProtocolError, match="is for protocol '0.1'"):
        reference_scores(path)


def _evaluation(task="hopper-gravity-0.5", method="sac-target", budget="lite", seed=0, returns=(100.0, 120.0)):
    return {"format": "offdyn-bench/evaluation", "protocol_version": PROTOCOL_VERSION, "task": task,
            "budget": budget, "method": method, "agent": {"path": f"runs/{seed}", "policy_sha256": {}},
            "episode_seeds": [2_000_000, 2_000_001], "seeds": [{"seed": seed, "returns": list(returns)}],
            "versions": {"mujoco": "3.17.0"}}


def test_oracle_reference_from_evaluations(tmp_path):
    path = tmp_path / "refs.json"
    five = [_evaluation(seed=s, returns=(100.0 * (s + 1), 100.0 * (s + 1) + 20.0)) for s in range(5)]
    score = record_oracle_reference(five, path)
    assert score.mean_return == pytest.approx(310.0)  # mean of 100..500, +10
    stored = reference_scores(path)["hopper-gravity-0.5"]["oracle/lite"]
    assert stored.provenance["seeds"] == [0, 1, 2, 3, 4] and stored.returns[:4] == (100.0, 120.0, 200.0, 220.0)
    assert stored.provenance["runs"][0]["path"] == "runs/0"
    before = path.read_bytes()
    for evaluations, message in [
        ([_evaluation(method="dap")], "an oracle reference is sac-target"),
        ([_evaluation(), _evaluation(task="hopper-friction-0.5", seed=1)], "mix tasks"),
        ([_evaluation(budget=None)], "not at a protocol budget"),
        (five[:4] + [_evaluation(seed=0)], "a training seed twice"),
        (five[:4], "4 training seed\\(s\\); an oracle needs at least 5"),
        (five[:4] + [_evaluation(seed=9) | {"protocol_conformant": False, "notes": ["20 episodes"]}],
         "not a protocol result: 20 episodes"),
        (five[:4] + [_evaluation(seed=9, returns=(float("inf"),))], "NaN or infinite"),
        ([], "no evaluation given"),
    ]:
        with pytest.raises(ProtocolError, match=message):
            record_oracle_reference(evaluations, path)
        assert path.read_bytes() == before  # a refused oracle changes nothing


def test_protocol_show_prints_each_core_task_reference_with_the_oracle_seed_means(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from offdyn_bench.cli import app
    from offdyn_bench.protocol import references

    first, second = protocol.CORE_SUITE[0], protocol.CORE_SUITE[1]
    data = {"format": references.FORMAT, "format_version": 1, "protocol_version": protocol.PROTOCOL_VERSION,
            "tasks": {
                first: {"random": {"mean_return": 12.5, "returns": [12.0, 13.0], "provenance": {}},
                        "oracle": {"lite": {"mean_return": 250.0, "returns": [100.0, 200.0, 300.0, 400.0],
                                            "provenance": {"episodes_per_seed": 2}}}},
                second: {"random": {"mean_return": -3.0, "returns": [-3.0], "provenance": {}}}}}
    path = tmp_path / "reference_scores.json"
    path.write_text(json.dumps(data))
    monkeypatch.setattr(references, "REFERENCE_FILE", path)
    result = CliRunner().invoke(app, ["protocol", "show"])
    assert result.exit_code == 0, result.output
    lines = {line.split()[0]: line for line in result.output.splitlines() if line.startswith("  ")}
    # Seed-major episodes: seed means (100+200)/2 and (300+400)/2.
    assert lines[first].endswith("references: oracle/lite 250.0 [150.0, 350.0]; random 12.5")
    assert lines[second].endswith("references: random -3.0")
    assert lines[protocol.CORE_SUITE[2]].endswith("references: none yet")
    shown = json.loads(CliRunner().invoke(app, ["protocol", "show", "--json"]).output)
    assert shown["references"][first] == ["oracle/lite", "random"]


def test_each_h2o_table_dataset_is_official_on_the_h2o_settings_medium_the_default():
    """H2O's Table 1 reports every method on medium, medium-replay and medium-expert: on its
    settings each is an official dataset of the offline-target track; other tasks keep one."""
    from offdyn_bench.protocol import official_datasets

    slug = "offdyn/walker2d-h2o-friction-0p3"
    assert official_datasets("walker2d-h2o-friction-0.3", "offline-target") == (
        f"{slug}/medium-v0", f"{slug}/medium-replay-v0", f"{slug}/medium-expert-v0")
    assert official_dataset("walker2d-h2o-friction-0.3", "offline-target") == f"{slug}/medium-v0"
    assert official_datasets("hopper-gravity-0.5", "offline-target") == ("offdyn/hopper-gravity-0p5/source-policy-v0",)
    assert official_datasets("walker2d-h2o-friction-0.3", "online-target") == ()
    # Without the source simulator the H2O qualities are no setting of the paper's: one dataset.
    assert official_datasets("walker2d-h2o-friction-0.3", "offline-source-offline-target") == (
        f"{slug}/source-policy-v0",)
    assert not set(official_datasets("walker2d-h2o-friction-0.3", "offline-target")) & {
        official_dataset(task, "offline-target") for task in CORE_SUITE}


@pytest.mark.parametrize("used, conformant", [
    ("offdyn/halfcheetah-h2o-gravity-2p0/medium-replay-v0", True),
    ("offdyn/halfcheetah-h2o-gravity-2p0/medium-expert-v0", True),
    ("offdyn/halfcheetah-h2o-gravity-2p0/random-v0", False),
])
def test_a_record_on_any_h2o_table_dataset_is_a_protocol_result(used, conformant):
    from offdyn_bench.evaluate import LoadedAgents, _conformance

    loaded = LoadedAgents(agents=[], description={}, method="h2o", task="halfcheetah-h2o-gravity-2.0",
                          steps=100_000, dataset={"dataset_id": used})
    track, budget, notes = _conformance(loaded, "halfcheetah-h2o-gravity-2.0", "offline-target", None, EVAL_EPISODES)
    assert (track, budget) == ("offline-target", "lite") and (not notes) == conformant
    if not conformant:
        slug = "offdyn/halfcheetah-h2o-gravity-2p0"
        assert notes == [(f"trained on dataset {used!r}; the track's official dataset is '{slug}/medium-v0' or "
                          f"'{slug}/medium-replay-v0' or '{slug}/medium-expert-v0'")]
