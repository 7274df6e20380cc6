"""The training loop and CLI: outputs, resume, bad input, and short smoke runs of every method."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from typer.testing import CliRunner

from baselines.algorithms import ALGORITHMS, get_algorithm
from baselines.checkpoint import STATE_FILE, latest_checkpoint
from baselines.data import TransitionDataset, collect_target_dataset, load_dataset
from baselines.train import train
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.tasks import get_task

PENDULUM = "invertedpendulum-kinematic-slider-hard"
TINY = {"sac.hidden_sizes": "[32, 32]", "sac.batch_size": "32", "random_steps": "40", "warmup_steps": "60"}


def _tiny(algo: str) -> dict[str, str]:
    if algo in ("cql",):
        return {k: v for k, v in TINY.items() if k.startswith("sac.")}
    if algo in ("sac-source", "sac-target", "h2o", "h2o-offline-source"):
        return {k: v for k, v in TINY.items() if k != "warmup_steps"}
    if algo == "dara":  # offline: its classifier-only phase instead of random steps
        return {k: v for k, v in TINY.items() if k.startswith("sac.")} | {"classifier_steps": "40"}
    if ALGORITHMS[algo].default_config().__module__ == "baselines.matl":  # TRPO-based: no SAC settings
        return {"trpo.hidden_sizes": "[32, 32]", "rollout_steps": "8"}  # 80 steps: one outer iteration
    return TINY


def _needs(algo: str, dataset) -> str | None:
    return str(dataset) if ALGORITHMS[algo].needs_dataset else None


# matl-f and fine-tuning start from a finished run (init_run): tests/baselines/test_matl.py runs them.
@pytest.mark.parametrize("algo", [a for a in ALGORITHMS if a not in ("matl-f", "fine-tuning")])
def test_every_method_runs_on_a_hopper_pair(tmp_path, algo, hopper_dataset):
    out = tmp_path / "run"
    # The offline-source methods get the same small random dataset as their source data.
    source = str(hopper_dataset) if ALGORITHMS[algo].needs_source_dataset else None
    result = train(algo, "hopper-gravity-0.5", steps=80, out=out, dataset=_needs(algo, hopper_dataset),
                   source_dataset=source, overrides=_tiny(algo), eval_every=40, eval_episodes=1, progress=False)
    assert {p.name for p in out.iterdir()} == {"config.json", "metrics.jsonl", "result.json", "checkpoints", ".lock"}
    assert [p.name for p in (out / "checkpoints").iterdir()] and all(
        {f.name for f in p.iterdir()} == {"state.safetensors", "trainer.json", "checksums.json"}
        for p in (out / "checkpoints").iterdir())
    assert result["warnings"] == []
    curve = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [c["step"] for c in curve] == [40, 80]
    assert all(np.isfinite(list(c["train"].values())).all() for c in curve)
    assert result["versions"]["mujoco"] and result["versions"]["torch"]
    assert result["task"]["name"] == "hopper-gravity-0.5" and result["task"]["version"] == 0
    assert len(result["returns"]["0"]) == 1 and np.isfinite(result["mean_return"])
    config = json.loads((out / "config.json").read_text())
    network = config["config"]["sac" if "sac" in config["config"] else "trpo"]
    assert config["algo"] == algo and network["hidden_sizes"] == [32, 32]
    if ALGORITHMS[algo].needs_dataset:
        assert result["dataset"]["sha256"] == config["dataset_provenance"]["sha256"]


@pytest.mark.parametrize("algo", ["dap-u", "darc-online"])
def test_a_killed_run_resumes_to_the_same_result(tmp_path, algo, pendulum_dataset):
    kwargs = dict(steps=120, dataset=_needs(algo, pendulum_dataset), overrides=TINY, eval_every=30,
                  eval_episodes=2, checkpoint_every=40, progress=False, seed=3, n_seeds=2)
    whole = train(algo, PENDULUM, out=tmp_path / "whole", **kwargs)
    assert train(algo, PENDULUM, out=tmp_path / "cut", stop_after=70, **kwargs) is None  # "killed" at step 70
    assert not (tmp_path / "cut" / "result.json").exists()
    resumed = train(algo, PENDULUM, out=tmp_path / "cut", **kwargs)
    assert resumed["returns"] == whole["returns"]
    curves = [[json.loads(x)["target_return"] for x in (tmp_path / d / "metrics.jsonl").read_text().splitlines()]
              for d in ("whole", "cut")]
    assert curves[0] == curves[1] and len(curves[0]) == 4
    a, b = (load_file(str(latest_checkpoint(tmp_path / d) / STATE_FILE)) for d in ("whole", "cut"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_seeds_trained_together_are_distinct_and_recorded(tmp_path):
    result = train("sac-target", PENDULUM, steps=60, out=tmp_path / "r", overrides=_tiny("sac-target"),
                   eval_episodes=1, progress=False, seed=5, n_seeds=3)
    assert result["seeds"] == [5, 6, 7] and set(result["returns"]) == {"5", "6", "7"}


def test_unknown_algorithm_and_task_are_named_with_suggestions(tmp_path):
    with pytest.raises(UnknownNameError, match="unknown algorithm 'dapu'.*'dap-u'"):
        train("dapu", PENDULUM, steps=10, out=tmp_path / "a")
    with pytest.raises(UnknownNameError, match="unknown task 'hopper-gravity-0.6'.*hopper-gravity-0.5"):
        train("dap", "hopper-gravity-0.6", steps=10, out=tmp_path / "b")
    with pytest.raises(UnknownNameError, match="unknown setting of darc 'warmup'"):
        train("darc", PENDULUM, steps=10, out=tmp_path / "c", overrides={"warmup": "5"})
    with pytest.raises(OffdynError, match="invalid sac.batch_size='big'"):
        train("darc", PENDULUM, steps=10, out=tmp_path / "d", overrides={"sac.batch_size": "big"})
    assert not any((tmp_path / x).exists() for x in "abcd")


def test_dataset_from_another_robot_is_refused_before_anything_is_written(tmp_path, hopper_dataset):
    with pytest.raises(OffdynError, match=r"observations have shape \(11,\).*expects \(4,\)"):
        train("dap", PENDULUM, steps=10, out=tmp_path / "run", dataset=str(hopper_dataset))
    assert not (tmp_path / "run").exists()
    with pytest.raises(OffdynError, match="needs a target dataset"):
        train("h2o", PENDULUM, steps=10, out=tmp_path / "run")
    with pytest.raises(OffdynError, match="expected collect:<policy>:<N>"):
        train("cql", PENDULUM, steps=10, out=tmp_path / "run", dataset="collect:random")
    with pytest.raises(OffdynError, match="does not exist"):
        train("cql", PENDULUM, steps=10, out=tmp_path / "run", dataset=str(tmp_path / "missing.npz"))
    assert not (tmp_path / "run").exists()


def test_a_run_folder_of_another_config_is_left_untouched(tmp_path):
    out = tmp_path / "run"
    train("sac-source", PENDULUM, steps=40, out=out, overrides=_tiny("sac-source"), eval_episodes=1, progress=False)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(OffdynError, match="finished run"):
        train("sac-source", PENDULUM, steps=40, out=out, overrides=_tiny("sac-source"), eval_episodes=1,
              progress=False)
    with pytest.raises(OffdynError, match="other settings.*differs in: steps, .*config"):
        train("sac-source", PENDULUM, steps=80, out=out, overrides=_tiny("sac-source") | {"sac.discount": "0.9"},
              eval_episodes=1, progress=False)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(OffdynError, match="not empty and holds no training run"):
        train("sac-source", PENDULUM, steps=40, out=tmp_path / "other")
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


def test_collected_datasets_round_trip_and_use_a_trained_policy(tmp_path):
    task = get_task(PENDULUM)
    data = collect_target_dataset(task, "random", 50, seed=1)
    assert len(data) == 50 and data.observations.shape == (50, 4) and data.actions.shape == (50, 1)
    assert data.truncations[-1] and data.terminations.any()  # random pendulum episodes end quickly
    data.save_npz(tmp_path / "d.npz")
    again, provenance = load_dataset(str(tmp_path / "d.npz"), task)
    assert again.sha256() == data.sha256() == provenance["sha256"]
    assert collect_target_dataset(task, "random", 50, seed=1).sha256() == data.sha256()
    train("sac-source", PENDULUM, steps=40, out=tmp_path / "behaviour", overrides=_tiny("sac-source"),
          eval_episodes=1, progress=False)
    by_policy, provenance = load_dataset(f"collect:{tmp_path / 'behaviour'}:30", task)
    assert len(by_policy) == 30 and provenance["kind"] == "collected"
    with pytest.raises(OffdynError, match="expected 'random' or a training run folder"):
        load_dataset("collect:nonsense:30", task)


def test_dataset_arrays_must_agree_in_length():
    with pytest.raises(OffdynError, match="differ in length"):
        TransitionDataset(np.zeros((3, 4)), np.zeros((2, 1)), np.zeros(3), np.zeros((3, 4)), np.zeros(3, bool),
                          np.zeros(3, bool))


def test_cli_train_and_its_errors(tmp_path):
    runner = CliRunner()
    out = tmp_path / "cli"
    ok = runner.invoke(app, ["train", "sac-source", "--task", PENDULUM, "--steps", "30", "--out", str(out),
                             "--set", "random_steps=10", "--set", "sac.hidden_sizes=[16]", "--set", "sac.batch_size=8",
                             "--eval-episodes", "1", "--no-progress"])
    assert ok.exit_code == 0, ok.output
    assert (out / "result.json").exists() and "mean target return" in ok.output
    bad = runner.invoke(app, ["train", "sac-sorce", "--task", PENDULUM, "--steps", "30", "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2 and "unknown algorithm 'sac-sorce'" in bad.output and "'sac-source'" in bad.output
    bad = runner.invoke(app, ["train", "dap", "--task", PENDULUM, "--steps", "30", "--out", str(tmp_path / "x"),
                              "--set", "nonsense"])
    assert bad.exit_code == 2 and "key=value" in bad.output
    assert not (tmp_path / "x").exists()
    shown = runner.invoke(app, ["train", "sac-source", "--print-config", "--set", "random_steps=10",
                                "--set", "sac.hidden_sizes=[16]", "--set", "sac.batch_size=8"])
    assert shown.exit_code == 0, shown.output
    assert json.loads(shown.stdout) == json.loads((out / "config.json").read_text())["config"]
    for missing, args in (("--task", ["--out", str(tmp_path / "x")]), ("--out", ["--task", PENDULUM])):
        bad = runner.invoke(app, ["train", "dap", "--steps", "30", *args])
        assert bad.exit_code == 2 and f"training needs {missing} (" in bad.output and "--print-config" in bad.output
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("algo", ["cql", "sac-target", "darc"])
def test_print_config_says_which_methods_take_a_setting(algo):
    """What gpu_reference_sweep.sh asks (does this method's config take cuda_graph?) and what a
    researcher asks (what will this run use?): the checked settings, or the setting's error."""
    runner = CliRunner()
    shown = runner.invoke(app, ["train", algo, "--print-config", "--set", "cuda_graph=true"])
    takes_it = hasattr(get_algorithm(algo).default_config(), "cuda_graph")
    assert (shown.exit_code == 0) == takes_it, shown.output
    if takes_it:
        assert json.loads(shown.stdout)["cuda_graph"] is True
    else:
        assert shown.stdout == "" and f"unknown setting of {algo} 'cuda_graph'" in shown.output
    bad = runner.invoke(app, ["train", algo, "--print-config", "--set", "sac.batch_size=-3"])
    assert bad.exit_code == 2 and "invalid setting sac.batch_size=-3" in bad.output and bad.stdout == ""


def test_python_dash_m_entry_points():
    for module in ("baselines", "offdyn_bench"):
        done = subprocess.run([sys.executable, "-m", module, "train", "--help"], capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 0 and "--dataset" in done.stdout, done.stderr


@pytest.mark.slow
def test_a_process_killed_mid_run_resumes_to_the_same_result(tmp_path, pendulum_dataset):
    import os
    import signal
    import time

    args = ["train", "dap", "--task", PENDULUM, "--steps", "600", "--dataset", str(pendulum_dataset),
            "--checkpoint-every", "100", "--eval-every", "100", "--eval-episodes", "2", "--no-progress"]
    for key, value in TINY.items():
        args += ["--set", f"{key}={value}"]
    whole = train("dap", PENDULUM, steps=600, out=tmp_path / "whole", dataset=str(pendulum_dataset), overrides=TINY,
                  checkpoint_every=100, eval_every=100, eval_episodes=2, progress=False)
    process = subprocess.Popen([sys.executable, "-m", "baselines", *args, "--out", str(tmp_path / "cut")])
    deadline = time.time() + 300
    while latest_checkpoint(tmp_path / "cut") is None and time.time() < deadline:
        time.sleep(0.05)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert not (tmp_path / "cut" / "result.json").exists()
    done = subprocess.run([sys.executable, "-m", "baselines", *args, "--out", str(tmp_path / "cut")],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert json.loads((tmp_path / "cut" / "result.json").read_text())["returns"] == whole["returns"]


def test_the_cli_lists_every_registered_algorithm_without_importing_torch():
    from baselines.cli import ALGORITHM_NAMES

    assert ALGORITHM_NAMES == tuple(ALGORITHMS)
    done = subprocess.run([sys.executable, "-c", "import sys, offdyn_bench.cli; print('torch' in sys.modules)"],
                          capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "False", done.stderr


def test_minari_ids_go_through_the_same_loader(monkeypatch):
    """Episodes (T+1 observations, T actions) become transitions; a fake stands in for a local dataset."""
    import types

    rng = np.random.default_rng(0)
    episodes = [types.SimpleNamespace(observations=rng.normal(size=(t + 1, 4)), actions=rng.uniform(-3, 3, (t, 1)),
                                      rewards=np.ones(t), terminations=np.arange(t) == t - 1, truncations=np.zeros(t))
                for t in (5, 7)]
    # The loader reads installed datasets through the suite's load_installed (which names the
    # install command when one is missing); a fake installed dataset stands in for it here.
    monkeypatch.setattr("offdyn_bench.datasets.ensure.load_installed", lambda dataset_id: types.SimpleNamespace(
        iterate_episodes=lambda: iter(episodes)))
    data, provenance = load_dataset("offdyn/test-pendulum/random-v0", get_task(PENDULUM))
    assert len(data) == 12 and provenance["kind"] == "minari"
    np.testing.assert_array_equal(data.next_observations[:5], episodes[0].observations[1:])
    assert data.terminations.sum() == 2


@pytest.mark.parametrize("algo", sorted(ALGORITHMS))
def test_a_recorded_config_rebuilds_exactly_from_its_overrides(algo):
    """What a run folder records (config_to_dict) turned into --set overrides (how a dataset's
    behaviour run is retrained) gives back the same config, every nested field included."""
    import dataclasses

    from baselines.algorithms import apply_overrides, config_overrides, config_to_dict

    algorithm = get_algorithm(algo)
    changed = algorithm.default_config()
    # Move one top-level number off its default, so a rebuild that ignored the overrides would fail.
    field = next(f for f in dataclasses.fields(changed)
                 if isinstance(getattr(changed, f.name), int) and not isinstance(getattr(changed, f.name), bool))
    setattr(changed, field.name, getattr(changed, field.name) + 1)
    if algo in ("fine-tuning", "matl-f"):  # only valid with the run they start from
        changed.init_run = "runs/direct-transfer"
    recorded = config_to_dict(changed)
    rebuilt = apply_overrides(algorithm.default_config(), config_overrides(recorded), algo)
    assert rebuilt == changed and config_to_dict(rebuilt) == recorded
