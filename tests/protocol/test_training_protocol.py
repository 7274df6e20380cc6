"""`train` under the protocol: budgets set steps, tracks refuse misfits, target steps are counted,
and the official dataset is the default."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from baselines.train import train
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError
from offdyn_bench.protocol import ProtocolError
from offdyn_bench.protocol.training import resolve_run

PENDULUM = "invertedpendulum-gravity-3.0"
TINY = {"sac.hidden_sizes": "[16, 16]", "sac.batch_size": "16", "random_steps": "20", "warmup_steps": "30"}


def _plan(algo="dap", **kwargs):
    settings = dict(steps=None, track=None, budget="lite", dataset="collect:random:100", needs_dataset=True,
                    target_step_every=None, progress=False, echo=lambda line: None)
    settings.update(kwargs)
    return resolve_run(algo, "hopper-gravity-0.5", **settings)


def test_budgets_set_steps_and_tracks_default_to_the_methods_own():
    plan = _plan()
    assert (plan.steps, plan.track, plan.budget, plan.target_step_limit) == (100_000, "offline-target", "lite", 0)
    online = _plan("darc-online", needs_dataset=False, dataset=None, target_step_every=10, budget="full")
    assert (online.steps, online.track, online.target_step_limit) == (1_000_000, "online-target", 100_000)
    reference = _plan("sac-target", needs_dataset=False, dataset=None, budget=None, steps=500)
    assert (reference.track, reference.target_step_limit) == (None, None)


@pytest.mark.parametrize("kwargs, message", [
    ({"steps": 5}, "--steps 5 contradicts --budget lite"),
    ({"budget": None}, "pass --steps N or --budget"),
    ({"budget": "medium"}, "unknown budget 'medium'"),
    ({"track": "online-target"}, "dap belongs on the 'offline-target' track"),
])
def test_protocol_misfits_are_refused(kwargs, message):
    with pytest.raises(OffdynError, match=message):
        _plan(**kwargs)


def test_the_online_track_limits_target_steps():
    with pytest.raises(ProtocolError, match="would take 20000 target steps per seed; the online-target track allows "
                                            "10000"):
        _plan("darc-online", needs_dataset=False, dataset=None, target_step_every=5)


def test_the_official_dataset_is_installed_and_used_by_default(monkeypatch):
    calls = []
    monkeypatch.setattr("offdyn_bench.datasets.ensure.ensure_dataset",
                        lambda ident, **kwargs: calls.append(ident))
    lines = []
    plan = _plan(dataset=None, echo=lines.append)
    assert plan.dataset == calls[0] == "offdyn/hopper-gravity-0p5/source-policy-v0"
    assert "official offline-target dataset" in lines[0]


def test_a_task_without_an_official_dataset_asks_for_one(tmp_path):
    with pytest.raises(OffdynError, match="has no official one .* pass --dataset"):
        train("cql", PENDULUM, steps=10, out=tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


def test_an_online_run_records_its_track_and_target_steps(tmp_path):
    result = train("darc-online", PENDULUM, steps=60, out=tmp_path / "run", overrides=TINY, eval_episodes=1,
                   progress=False)
    assert result["track"] == "online-target" and result["target_steps_per_seed"] == 6
    assert json.loads((tmp_path / "run" / "config.json").read_text())["track"] == "online-target"


def test_train_cli_refuses_a_misfit_before_writing(tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["train", "darc-online", "--task", PENDULUM, "--budget", "lite",
                                      "--track", "offline-target", "--out", str(out), "--no-progress"])
    assert result.exit_code == 2 and "belongs on the 'online-target' track" in result.output
    assert not out.exists()
