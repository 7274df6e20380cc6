"""Both input formats, the JSON contract, and bad input: a clear error, never a traceback."""

from __future__ import annotations

import json

import gymnasium
import numpy as np
import pytest
from diagnose_target_data import record
from typer.testing import CliRunner

import offdyn_bench  # noqa: F401  (registers the task ids)
from offdyn_bench.cli import app
from offdyn_bench.diagnose import DiagnosisInputError, DiagnosisSettings, Transitions, diagnose, load_transitions
from offdyn_bench.diagnose.source import SourceSimulator

runner = CliRunner()
FAST = DiagnosisSettings(screen_rows=300, fit_rows=500)


@pytest.fixture(scope="module")
def delay_npz(tmp_path_factory: pytest.TempPathFactory):
    """A small dataset from a target with a one-step action delay."""
    path = tmp_path_factory.mktemp("data") / "delay.npz"
    np.savez(path, **record([{"kind": "action_delay", "steps": 1}], 600, seed=11))
    return path


def _write(tmp_path, **arrays) -> str:
    path = tmp_path / "data.npz"
    np.savez(path, **arrays)
    return str(path)


def test_episodes_follow_terminations_and_truncations() -> None:
    flags = np.array([False, True, False, False, True, False])
    data = Transitions(observations=np.zeros((6, 2)), actions=np.zeros((6, 1)), next_observations=np.zeros((6, 2)),
                       terminations=flags, truncations=np.zeros(6, dtype=bool))
    np.testing.assert_array_equal(data.episode_index, [0, 0, 1, 1, 1, 2])
    np.testing.assert_array_equal(data.step_in_episode, [0, 1, 0, 1, 2, 0])


def test_observation_map_of_hopper_is_found_by_probing() -> None:
    """Hopper-v5 observes qpos[1:] and qvel clipped to +-10: found without knowing the robot."""
    omap = SourceSimulator("Hopper-v5").observation_map
    np.testing.assert_array_equal(omap.source, np.arange(1, 12))
    assert omap.names[0] == "qpos[rootz]" and omap.names[-1] == "qvel[foot_joint]"
    np.testing.assert_array_equal(omap.high[5:], 10.0)
    assert np.all(np.isinf(omap.high[:5]))


def test_cli_writes_json_report_and_plot(delay_npz, tmp_path) -> None:
    out, json_path = tmp_path / "out", tmp_path / "result.json"
    result = runner.invoke(app, ["diagnose", "--env", "Hopper-v5", "--data", str(delay_npz),
                                 "--out", str(out), "--json", str(json_path)])
    assert result.exit_code == 0, result.output
    assert "action_delay on all" in result.output
    payload = json.loads(json_path.read_text())
    assert payload["effects_added"][0]["kind"] == "action_delay"
    assert payload["effects_added"][0]["target"] is None
    assert payload["effects_added"][0]["value"] == 1
    for key in ("error_before", "error_after"):
        assert set(payload[key]) >= {"one_step_nrmse", "heldout_one_step_nrmse", "horizon_nrmse"}
        assert all(isinstance(v, float) for v in payload[key].values())
    assert isinstance(payload["noise_floor"], float)
    assert payload["unexplained_residual"] is False
    assert len(payload["steps"]) == 1
    assert payload["steps"][0]["error_after"]["heldout_one_step_nrmse"] < payload["steps"][0]["error_before"]["heldout_one_step_nrmse"]
    assert json.loads((out / "diagnosis.json").read_text())["effects_added"] == payload["effects_added"]
    assert (out / "residual_per_dimension.png").stat().st_size > 1000
    assert "| 1 | action_delay on all |" in (out / "report.md").read_text()
    calibrated = payload["calibrated_env"]
    env = offdyn_bench.make_robot_env(calibrated["robot"], **calibrated["kwargs"])
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.ones(3))
    np.testing.assert_array_equal(info["applied_action"], 0.0)  # the first command arrives one step late


@pytest.mark.filterwarnings("ignore:`.*` is set to None:UserWarning")
def test_minari_dataset_by_id_and_path(tmp_path, monkeypatch) -> None:
    """A Minari dataset of this suite's layout (infos carry the full state): the gravity shift of a
    registered pair is found from its source id."""
    import minari
    from minari.data_collector.episode_buffer import EpisodeBuffer

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    env = gymnasium.make("offdyn/Hopper-gravity-0.5-target-v0")
    rng = np.random.default_rng(0)
    buffers = []
    for episode in range(10):
        obs, info = env.reset(seed=episode)
        observations, actions, states, terminations, truncations = [obs], [], [info["state"]], [], []
        for t in range(60):
            action = rng.uniform(-1, 1, 3).astype(np.float32)
            obs, _, terminated, truncated, info = env.step(action)
            observations.append(obs), actions.append(action), states.append(info["state"])
            terminations.append(terminated), truncations.append(truncated or t == 59)
            if terminated or truncated:
                break
        buffers.append(EpisodeBuffer(id=episode, seed=episode, observations=np.stack(observations),
                                     actions=np.stack(actions), rewards=np.zeros(len(actions)),
                                     terminations=np.array(terminations), truncations=np.array(truncations),
                                     infos={"state": np.stack(states)}))
    minari.create_dataset_from_buffers("test/hopper-gravity/random-v0", buffer=buffers,
                                       env="offdyn/Hopper-gravity-0.5-source-v0", algorithm_name="random")
    by_id = diagnose("offdyn/Hopper-gravity-0.5-source-v0", "test/hopper-gravity/random-v0", FAST)
    assert by_id.state_source == "stored qpos/qvel"
    assert [(e["kind"], e["target"]) for e in by_id.effects_added] == [("gravity", None)]
    assert by_id.effects_added[0]["value"] == pytest.approx(0.5, rel=0.01)
    assert by_id.calibrated_env["kwargs"]["extra_effects"][0]["kind"] == "gravity"
    by_path = load_transitions(tmp_path / "minari" / "test" / "hopper-gravity" / "random-v0", nq=6, nv=6)
    assert by_path.size == by_id.transitions and by_path.has_state
    assert not any("names" in note for note in by_id.notes)
    # Against the target (which declares the gravity shift) nothing is missing, and the tool says
    # the dataset was recorded for another id.
    against_target = diagnose("offdyn/Hopper-gravity-0.5-target-v0", by_path, FAST)
    assert against_target.effects_added == ()
    assert "the dataset names 'offdyn/Hopper-gravity-0.5-source-v0' as its env" in against_target.notes[0]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda a: {**a, "observations": a["observations"][:, :5]}, "observations have 5 dimensions"),
        (lambda a: {**a, "actions": a["actions"][:-3]}, "one row per transition"),
        (lambda a: {**a, "observations": np.where(np.arange(len(a["actions"]))[:, None] == 7, np.nan,
                                                   a["observations"])}, "NaN or infinite values in 1 row(s) (7)"),
        (lambda a: {k: v[:0] for k, v in a.items()}, "is empty"),
        (lambda a: {k: v for k, v in a.items() if k != "truncations"}, "lacks the array(s) ['truncations']"),
        (lambda a: {**a, "qpos": a["qpos"][:, :4]}, "qpos/qvel have 4/6 columns"),
    ],
    ids=["mismatched-dimensions", "mismatched-rows", "nan-row", "empty", "missing-array", "wrong-state-size"],
)
def test_bad_data_is_a_clear_error_without_traceback(tmp_path, change, message) -> None:
    arrays = dict(np.load(_bad_source(tmp_path)))
    path = _write(tmp_path, **change(arrays))
    result = runner.invoke(app, ["diagnose", "--env", "Hopper-v5", "--data", path])
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output
    assert isinstance(result.exception, SystemExit)


def _bad_source(tmp_path) -> str:
    return _write(tmp_path, **record([], 80, seed=12))


def test_env_that_does_not_match_the_data(delay_npz) -> None:
    result = runner.invoke(app, ["diagnose", "--env", "Walker2d-v5", "--data", str(delay_npz)])
    assert result.exit_code == 2
    assert "actions have 3 dimensions but Walker2d-v5 takes 6" in result.output


def test_unknown_env_and_missing_dataset(delay_npz, tmp_path) -> None:
    unknown = runner.invoke(app, ["diagnose", "--env", "Hoper-v5", "--data", str(delay_npz)])
    assert unknown.exit_code == 2 and "cannot build source env 'Hoper-v5'" in unknown.output
    missing = runner.invoke(app, ["diagnose", "--env", "Hopper-v5", "--data", str(tmp_path / "nope.npz")])
    assert missing.exit_code == 2 and "no such file" in missing.output
    not_minari = runner.invoke(app, ["diagnose", "--env", "Hopper-v5", "--data", "nobody/nothing-v0"])
    assert not_minari.exit_code == 2 and "dataset nobody/nothing-v0 is not installed" in not_minari.output
    assert "offdyn-bench datasets download nobody/nothing-v0" in not_minari.output


def test_too_little_data_is_refused() -> None:
    with pytest.raises(DiagnosisInputError, match="too few usable transitions"):
        diagnose("Hopper-v5", Transitions(**record([], 12, seed=13)))
