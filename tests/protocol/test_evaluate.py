"""`evaluate`: run folders and user agents scored under the protocol, and the score report."""

from __future__ import annotations

import json
import shlex
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from typer.testing import CliRunner

from baselines.train import train
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError
from offdyn_bench.evaluate import EvaluationError, evaluate, read_evaluation, train_command_settings
from offdyn_bench.protocol import EPISODE_SEEDS, PROTOCOL_VERSION, ProtocolError
from offdyn_bench.protocol.report import score_report
from offdyn_bench.protocol.statistics import iqm

PENDULUM = "invertedpendulum-gravity-3.0"
TINY = {"sac.hidden_sizes": "[16, 16]", "sac.batch_size": "16", "random_steps": "20"}


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "sac-source"
    train("sac-source", PENDULUM, steps=60, out=out, seed=3, n_seeds=2, overrides=TINY, eval_episodes=1,
          progress=False)
    return out


@pytest.fixture
def agent_module(tmp_path, monkeypatch):
    """A user's agent package: a zero-torque agent, a broken one and a non-agent."""
    (tmp_path / "my_agents.py").write_text(textwrap.dedent("""
        import numpy as np

        class Zero:
            resets = 0
            def reset(self):
                Zero.resets += 1
            def act(self, observation):
                return np.zeros(1)

        def make(task, seed):
            return Zero()

        def make_function():
            return lambda observation: np.full(1, 0.5)

        def nan_agent():
            return lambda observation: np.full(1, np.nan)

        def wrong_shape():
            return lambda observation: np.zeros(3)

        def not_an_agent():
            return 42
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "my_agents"
    sys.modules.pop("my_agents", None)


def test_a_run_folder_is_evaluated_per_training_seed(finished_run):
    record = evaluate(finished_run, progress=False)
    assert record["task"] == PENDULUM and record["method"] == "sac-source"
    assert [s["seed"] for s in record["seeds"]] == [3, 4]
    assert all(len(s["returns"]) == 20 for s in record["seeds"])
    assert record["episode_seeds"] == list(EPISODE_SEEDS)
    assert record["protocol_version"] == PROTOCOL_VERSION and record["versions"]["mujoco"] == "3.17.0"
    # 60 steps is no protocol budget: recorded, and said.
    assert record["budget"] is None and not record["protocol_conformant"]
    assert any("not at a protocol budget" in n for n in record["notes"])
    assert set(record["agent"]["policy_sha256"]) == {"3", "4"}
    # Where the evaluation and the training ran (PROTOCOL §8: another CPU model, another policy).
    from offdyn_bench.versions import machine

    assert record["machine"] == machine() and record["training_machines"] == [machine()]
    # And which code evaluated and trained it, and when it trained (the version stays 0.1.0).
    from offdyn_bench.versions import source_revision

    result = json.loads((finished_run / "result.json").read_text())
    assert record["source_revision"] == source_revision()
    assert record["training_provenance"] == {key: result[key] for key in ("source_revisions", "started_at",
                                                                          "finished_at")}
    assert record["training_provenance"]["source_revisions"] == [source_revision()]
    assert read_evaluation(finished_run / "evaluation.json") == json.loads(json.dumps(record))
    # Deterministic: the same run gives the same returns.
    assert evaluate(finished_run, progress=False, out=finished_run / "again.json")["seeds"] == record["seeds"]


def test_the_records_train_command_trains_the_same_policy(finished_run, tmp_path):
    """The record's train command carries the settings the run changed from its method's defaults
    (``--set``), so running it trains the same policies; without them it would train another run."""
    record = evaluate(finished_run, progress=False, out=tmp_path / "record.json")
    words = shlex.split(record["train_command"])
    settings = train_command_settings(record["train_command"])
    assert settings == TINY  # the fixture's settings, and nothing else
    again = tmp_path / "again"
    words[words.index("--out") + 1] = str(again)
    subprocess.run([sys.executable, "-m", "offdyn_bench", *words[1:], "--eval-episodes", "1", "--no-progress"],
                   check=True, capture_output=True, timeout=300)
    retrained = evaluate(again, progress=False, out=tmp_path / "again.json")
    assert retrained["agent"]["policy_sha256"] == record["agent"]["policy_sha256"]
    assert retrained["train_command"] == record["train_command"].replace(str(finished_run), str(again))


def test_the_source_side_gives_the_gap_and_is_no_protocol_result(finished_run, tmp_path):
    record = evaluate(finished_run, progress=False, side="source", episodes=2, out=tmp_path / "source.json")
    assert record["side"] == "source" and record["env_id"].endswith("-source-v0")
    assert any("in the source" in note for note in record["notes"]) and not record["protocol_conformant"]
    with pytest.raises(EvaluationError, match="side 'real'"):
        evaluate(finished_run, progress=False, side="real")


def test_default_records_of_the_source_side_or_another_task_never_replace_the_protocol_record(finished_run):
    protocol_record = finished_run / "evaluation.json"
    evaluate(finished_run, progress=False, episodes=1)
    before = protocol_record.read_bytes()
    source = evaluate(finished_run, progress=False, side="source", episodes=1)
    other = "invertedpendulum-kinematic-slider-hard"  # the same nominal source: the same policy scores there
    elsewhere = evaluate(finished_run, other, progress=False, episodes=1)
    elsewhere_source = evaluate(finished_run, other, progress=False, side="source", episodes=1)
    assert protocol_record.read_bytes() == before
    assert read_evaluation(finished_run / "evaluation-source.json")["seeds"] == source["seeds"]
    assert read_evaluation(finished_run / f"evaluation-{other}.json")["task"] == elsewhere["task"] == other
    assert read_evaluation(finished_run / f"evaluation-{other}-source.json")["side"] == elsewhere_source["side"]
    for name in ("evaluation-source.json", f"evaluation-{other}.json", f"evaluation-{other}-source.json"):
        (finished_run / name).unlink()  # the module's other tests read the folder


def test_run_agents_match_the_trainers_own_deployed_policy(finished_run):
    """The evaluator reads the actor out of the checkpoint; the trainer's final evaluation used the
    same policy on episode seed 1,000,000: replaying that seed must give the same return."""
    import gymnasium

    from offdyn_bench.evaluate import episode_returns, load_run_agents

    result = json.loads((finished_run / "result.json").read_text())
    loaded = load_run_agents(finished_run)
    env = gymnasium.make("offdyn/InvertedPendulum-gravity-3.0-target-v0")
    for seed, agent in loaded.agents:
        assert episode_returns(agent, env, [1_000_000], "t") == pytest.approx(result["returns"][str(seed)], rel=1e-5)


def test_episode_lengths_and_time_limits_are_recorded_beside_the_returns(agent_module, tmp_path):
    """InvertedPendulum pays 1 per step while the pole is up and 0 for the step it falls, so a fallen
    episode is one step longer than its return. Zero torque lets the pole fall (terminated); a
    5-step time limit stops it first (truncated)."""
    import gymnasium

    from offdyn_bench.evaluate import run_episode

    record = evaluate(f"{agent_module}:make", PENDULUM, seeds=[0], episodes=3, progress=False, method="zero")
    entry = record["seeds"][0]
    assert entry["lengths"] == [round(r) + 1 for r in entry["returns"]] and all(1 < n < 1000 for n in entry["lengths"])
    assert entry["truncated"] == [False, False, False]
    zero = sys.modules[agent_module].Zero()
    short = gymnasium.make("offdyn/InvertedPendulum-gravity-3.0-target-v0", max_episode_steps=5)
    episode = run_episode(zero, short, EPISODE_SEEDS[0], "t")
    assert (episode.length, episode.truncated, episode.episode_return) == (5, True, 5.0)
    long = gymnasium.make("offdyn/InvertedPendulum-gravity-3.0-target-v0")
    episode = run_episode(zero, long, EPISODE_SEEDS[0], "t")
    assert (episode.length, episode.truncated) == (entry["lengths"][0], False)
    # The command line says how many episodes ran to the time limit.
    result = CliRunner().invoke(app, ["evaluate", "--agent", f"{agent_module}:make", "--task", PENDULUM,
                                      "--episodes", "2", "--no-progress", "--out", str(tmp_path / "e.json")])
    assert result.exit_code == 0, result.output
    assert "(0/2 episodes ran to the time limit)" in result.output


def test_a_user_agent_from_a_factory(agent_module):
    record = evaluate(f"{agent_module}:make", PENDULUM, seeds=[0, 1], episodes=3, progress=False, method="zero")
    assert [s["seed"] for s in record["seeds"]] == [0, 1]
    assert record["method"] == "zero" and record["agent"]["kind"] == "factory"
    assert record["training_machines"] is None and record["machine"]["cpu"]  # no training of ours to describe
    assert record["training_provenance"] is None and "source_revision" in record
    assert sys.modules[agent_module].Zero.resets == 6  # reset() before every episode
    plain = evaluate(f"{agent_module}:make_function", PENDULUM, episodes=2, progress=False)
    assert len(plain["seeds"]) == 1 and len(plain["seeds"][0]["returns"]) == 2


@pytest.mark.parametrize("spec, message", [
    ("no_such_module_xyz:make", "cannot import 'no_such_module_xyz'"),
    ("{mod}:missing", "has no callable 'missing'"),
    ("{mod}:not_an_agent", "returned int"),
    ("{mod}:nan_agent", "NaN or infinite action"),
    ("{mod}:wrong_shape", r"action of shape \(3,\); expected \(1,\)"),
    ("just-a-name", "neither a run folder nor 'package.module:factory'"),
])
def test_bad_agents_are_clear_errors(agent_module, tmp_path, spec, message):
    out = tmp_path / "evaluation.json"
    with pytest.raises(EvaluationError, match=message):
        evaluate(spec.format(mod=agent_module), PENDULUM, episodes=1, progress=False, out=out)
    assert not out.exists()


def test_bad_run_folders_are_clear_errors(finished_run, tmp_path):
    with pytest.raises(EvaluationError, match="no config.json: it is not a training run folder"):
        evaluate(tmp_path, progress=False)
    unfinished = tmp_path / "unfinished"
    train("sac-source", PENDULUM, steps=40, out=unfinished, overrides=TINY, eval_episodes=1, progress=False,
          checkpoint_every=20, stop_after=20)
    with pytest.raises(EvaluationError, match="has not finished"):
        evaluate(unfinished, progress=False)
    # Another task with the same source would score the same policy (tests/sweep/test_shared_source_training.py).
    with pytest.raises(EvaluationError, match="trained on 'invertedpendulum-gravity-3.0', whose source is not"):
        evaluate(finished_run, "hopper-gravity-0.5", progress=False)
    with pytest.raises(ProtocolError, match="the run trained for 60 steps; budget 'lite' is 100000 steps"):
        evaluate(finished_run, budget="lite", progress=False)
    with pytest.raises(OffdynError, match="unknown track 'nowhere'; valid names: .*'offline-target', 'online-target'"):
        evaluate(finished_run, track="nowhere", progress=False)
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    with pytest.raises(EvaluationError, match="is a file"):
        evaluate(finished_run, progress=False, out=blocker / "evaluation.json")


@pytest.mark.parametrize("edit, message", [
    (lambda config: [], "config.json holds a JSON list; expected the object `offdyn-bench train` writes"),
    (lambda config: {**config, "steps": "60"}, "'steps' is '60' \\(expected a positive whole number\\)"),
    (lambda config: {k: v for k, v in config.items() if k != "task"}, "'task' is missing \\(expected a name\\)"),
    (lambda config: {**config, "seeds": [3, True]}, "'seeds' is \\[3, True\\] \\(expected a non-empty list"),
    (lambda config: {**config, "seeds": [3, 4, 5]},
     r"lists 3 training seed\(s\) \[3, 4, 5\], but its checkpoint holds 2 policy\(ies\)"),
])
def test_a_damaged_config_of_a_finished_run_is_a_clear_error_and_writes_nothing(
        finished_run, tmp_path, edit, message):
    """A finished run whose config.json was hand-edited or damaged is refused before any episode
    runs, saying which setting is wrong; the CLI prints it without a traceback."""
    damaged = tmp_path / "run"
    # Without the records the module's other tests write into the run folder.
    shutil.copytree(finished_run, damaged, ignore=shutil.ignore_patterns("evaluation*.json"))
    config = json.loads((damaged / "config.json").read_text())
    (damaged / "config.json").write_text(json.dumps(edit(config)))
    with pytest.raises(EvaluationError, match=message):
        evaluate(damaged, progress=False, out=tmp_path / "e.json")
    assert not (tmp_path / "e.json").exists()
    result = CliRunner().invoke(app, ["evaluate", "--agent", str(damaged), "--no-progress"])
    assert result.exit_code == 2 and result.output.startswith("error: ") and "Traceback" not in result.output
    assert not (damaged / "evaluation.json").exists()


def test_a_damaged_result_of_a_finished_run_is_a_clear_error(finished_run, tmp_path):
    damaged = tmp_path / "run"
    shutil.copytree(finished_run, damaged)
    (damaged / "result.json").write_text("[1, 2]")
    with pytest.raises(EvaluationError, match="result.json holds a JSON list; expected the object"):
        evaluate(damaged, progress=False, out=tmp_path / "e.json")


def test_evaluate_cli(finished_run, tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["evaluate", "--agent", str(finished_run), "--no-progress",
                                 "--out", str(tmp_path / "e.json")])
    assert result.exit_code == 0, result.output
    assert "seed 3: mean target return" in result.output and "not a protocol result" in result.output
    source = runner.invoke(app, ["evaluate", "--agent", str(finished_run), "--no-progress", "--side", "source",
                                 "--episodes", "1"])
    assert source.exit_code == 0, source.output
    assert "seed 3: mean source return" in source.output and "normalized" not in source.output
    assert f"wrote {finished_run / 'evaluation-source.json'}" in source.output
    (finished_run / "evaluation-source.json").unlink()  # the module's other tests read the folder
    bad = runner.invoke(app, ["evaluate", "--agent", str(tmp_path / "nothing"), "--no-progress"])
    assert bad.exit_code == 2 and bad.output.startswith("error: ") and "Traceback" not in bad.output
    seeds = runner.invoke(app, ["evaluate", "--agent", "m:f", "--task", PENDULUM, "--seeds", "0,x"])
    assert seeds.exit_code == 2 and "comma-separated integers" in seeds.output


def _record(method, task, per_seed_returns):
    return {"method": method, "task": task, "budget": None,
            "seeds": [{"seed": i, "returns": list(r)} for i, r in enumerate(per_seed_returns)]}


def test_score_report_by_hand():
    references = {"a": (0.0, 10.0), "b": (10.0, 110.0)}
    records = [_record("m1", "a", [[1.0, 3.0], [5.0, 5.0]]),  # seed means 2, 5 -> 20, 50
               _record("m1", "b", [[60.0], [110.0]]),         # 50, 100
               _record("m2", "a", [[0.0], [0.0]]),            # 0, 0
               _record("m2", "b", [[10.0], [10.0]])]          # 0, 0
    report = score_report(records, references=references)
    m1 = next(m for m in report.methods if m.method == "m1")
    np.testing.assert_allclose(m1.normalized, [[20.0, 50.0], [50.0, 100.0]])
    # IQM of {20, 50, 50, 100}: trim one from each end -> mean(50, 50)
    assert report.aggregates["m1"]["iqm"].point == pytest.approx(iqm(m1.normalized)) == pytest.approx(50.0)
    assert report.aggregates["m2"]["optimality_gap"].point == pytest.approx(100.0)
    assert report.improvement["m1>m2"].point == pytest.approx(1.0)
    assert score_report(records, references=references).to_dict() == report.to_dict()  # reproducible
    raw_only = score_report(records, references={"a": (0.0, 10.0)})
    assert not raw_only.aggregates and "missing for b" in raw_only.note
    with pytest.raises(ProtocolError, match="methods cover different tasks"):
        score_report(records[:3], references=references)


def test_a_tasks_seeds_may_come_in_one_record_per_run():
    """A sweep evaluates each seed in its own run folder: those records score like one record
    holding every seed; a seed given twice is refused."""
    references = {"a": (0.0, 10.0)}
    whole = score_report([_record("m1", "a", [[1.0, 3.0], [5.0, 5.0], [10.0, 10.0]])], references=references)
    per_run = [_record("m1", "a", [[1.0, 3.0]]), _record("m1", "a", [[5.0, 5.0], [10.0, 10.0]])]
    per_run[1]["seeds"] = [{"seed": 1, "returns": [5.0, 5.0]}, {"seed": 2, "returns": [10.0, 10.0]}]
    assert score_report(per_run, references=references).to_dict() == whole.to_dict()
    with pytest.raises(ProtocolError, match=r"training seed\(s\) \[0\] of task 'a' are in two evaluations"):
        score_report([per_run[0], per_run[0]], references=references)
    source_side = dict(per_run[0], side="source")
    with pytest.raises(ProtocolError, match="a source-side evaluation .* give both sides to `offdyn-bench protocol gap`"):
        score_report([source_side, per_run[1]], references=references)


def test_a_matl_run_is_evaluated_with_its_robot_policy(tmp_path):
    """TRPO-based runs carry no SAC actor: evaluate reads their deployed (robot) policy."""
    small = {"trpo.hidden_sizes": "[16, 16]", "discriminator.hidden_sizes": "[16]", "rollout_steps": "20",
             "trpo.value_iterations": "5"}
    run = tmp_path / "matl"
    train("matl", PENDULUM, steps=400, out=run, n_seeds=2, overrides=small, eval_episodes=1, progress=False)
    record = evaluate(run, episodes=2, progress=False)
    assert record["method"] == "matl" and record["track"] == "online-target"
    assert [s["seed"] for s in record["seeds"]] == [0, 1] and set(record["agent"]["policy_sha256"]) == {"0", "1"}
    # The trainer's final evaluation used the same deployed policy on episode seed 1,000,000.
    import gymnasium

    from offdyn_bench.evaluate import episode_returns, load_run_agents

    result = json.loads((run / "result.json").read_text())
    env = gymnasium.make("offdyn/InvertedPendulum-gravity-3.0-target-v0")
    for seed, agent in load_run_agents(run).agents:
        assert episode_returns(agent, env, [1_000_000], "t") == pytest.approx(result["returns"][str(seed)], rel=1e-5)


@pytest.mark.parametrize("record, message", [
    ({"format": "offdyn-bench/evaluation"}, "'task' is not a task name"),
    ({"format": "offdyn-bench/evaluation", "task": "hopper-gravity-0.5", "method": 3, "seeds": []},
     "'method' is not a string or null"),
    ({"format": "offdyn-bench/evaluation", "task": "hopper-gravity-0.5", "seeds": {}}, "'seeds' is not a non-empty list"),
    ({"format": "offdyn-bench/evaluation", "task": "hopper-gravity-0.5", "seeds": [{"seed": -1, "returns": [1.0]}]},
     r"seeds\[0\].seed is not a non-negative integer"),
    ({"format": "offdyn-bench/evaluation", "task": "hopper-gravity-0.5", "seeds": [{"seed": 0, "returns": ["1"]}]},
     r"seeds\[0\].returns is not a non-empty list of numbers"),
    ({"format": "offdyn-bench/evaluation", "task": "hopper-gravity-0.5", "seeds": [{"seed": True, "returns": [1]}]},
     r"seeds\[0\].seed is not a non-negative integer"),
])
def test_a_malformed_evaluation_is_a_clear_error_for_every_reader(tmp_path, record, message):
    path = tmp_path / "evaluation.json"
    path.write_text(json.dumps(record))
    with pytest.raises(EvaluationError, match=message):
        read_evaluation(path)
    for command in (["protocol", "score"], ["protocol", "claims"], ["protocol", "reference", "oracle"]):
        result = CliRunner().invoke(app, [*command, str(path)])
        assert result.exit_code == 2 and "error: " in result.output and "Traceback" not in result.output, result.output


def test_a_failing_factory_and_bad_options_are_clear_errors(tmp_path):
    (tmp_path / "failing_agents.py").write_text("def make(task, seed):\n    raise RuntimeError('no weights for ' + task)\n")
    sys.path.insert(0, str(tmp_path))
    try:
        with pytest.raises(EvaluationError, match="--agent 'failing_agents:make': the factory failed for training seed "
                                                  "0 with RuntimeError: no weights for hopper-gravity-0.5"):
            evaluate("failing_agents:make", "hopper-gravity-0.5", seeds=[0], progress=False)
        # A wrong option is refused before the factory is called at all.
        for options, message in [({"side": "sideways"}, "side 'sideways'"), ({"budget": "huge"}, "unknown budget"),
                                 ({"track": "nowhere"}, "unknown track")]:
            with pytest.raises(OffdynError, match=message):
                evaluate("failing_agents:make", "hopper-gravity-0.5", seeds=[0], progress=False, **options)
    finally:
        sys.path.remove(str(tmp_path))
