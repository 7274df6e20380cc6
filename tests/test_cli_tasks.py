"""The command line: tasks list/show and the demo, as a user runs them."""

from __future__ import annotations

import json

import pytest

from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.tasks import TASKS

runner = CliRunner()


def test_tasks_list_shows_the_grid_and_every_pair():
    result = runner.invoke(app, ["tasks", "list"])
    assert result.exit_code == 0, result.output
    assert f"{len(TASKS)} pairs, {2 * len(TASKS)} registered Gymnasium ids" in result.output
    for name in TASKS:
        assert name in result.output


def test_tasks_list_filters_and_json():
    result = runner.invoke(app, ["tasks", "list", "--robot", "hopper", "--shift", "gravity", "--json"])
    assert result.exit_code == 0, result.output
    pairs = json.loads(result.output)
    assert [p["name"] for p in pairs] == ["hopper-gravity-0.1", "hopper-gravity-0.5",
                                          "hopper-gravity-2.0", "hopper-gravity-5.0"]
    assert pairs[1]["target_effects"] == [{"kind": "gravity", "target": None, "scale": 0.5}]


def test_tasks_show_reports_compiled_differences_in_words():
    result = runner.invoke(app, ["tasks", "show", "hopper-gravity-0.5"])
    assert result.exit_code == 0, result.output
    assert "opt.gravity: [0 0 -9.81] -> [0 0 -4.905]" in result.output
    result = runner.invoke(app, ["tasks", "show", "walker2d-morph-thigh-hard"])
    assert "body_mass[thigh]" in result.output and "(x0.008)" in result.output


def test_tasks_show_unknown_name_suggests_close_matches():
    result = runner.invoke(app, ["tasks", "show", "hoper-gravity-0.5"])
    assert result.exit_code == 2
    assert "closest valid names: 'hopper-gravity-0.5'" in result.output
    assert "Traceback" not in result.output


def test_demo_runs_end_to_end_without_training(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the default --out is relative, as `make demo` runs it
    result = runner.invoke(app, ["demo", "--training-steps", "0"])
    assert result.exit_code == 0, result.output
    assert "same actions in source and target" in result.output
    # The dataset rebuilds byte for byte and the diagnosis finds the gravity nobody declared to it.
    assert "bytes identical to the manifest's sha256" in result.output
    assert "| 1 | gravity on all | 0.5 " in result.output
    assert (tmp_path / "demo-out" / "diagnosis" / "diagnosis.json").is_file()


@pytest.mark.slow
def test_demo_with_training_scores_darc_above_rl_on_source(tmp_path):
    result = runner.invoke(app, ["demo", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    rows = {line.split()[0]: float(line.split()[1]) for line in result.output.splitlines()
            if line.strip().split()[:1] in (["random"], ["sac-source"], ["darc"])}
    assert rows["darc"] > rows["sac-source"] > rows["random"]


@pytest.mark.parametrize(("option", "value", "message"), [
    ("--robot", "hoppr", "error: unknown robot 'hoppr'; closest valid names: 'Hopper'"),
    ("--shift", "gravty", "error: unknown shift family 'gravty'; closest valid names: 'gravity'"),
])
def test_tasks_list_unknown_filter_is_an_error_with_the_closest_names(option, value, message):
    result = runner.invoke(app, ["tasks", "list", option, value])
    assert result.exit_code == 2
    assert result.output.strip() == message or result.output.startswith(message), result.output
    assert "Traceback" not in result.output and len(result.output.strip().splitlines()) == 1


def test_tasks_list_filters_ignore_the_robots_case_and_say_when_nothing_matches():
    pendulum = runner.invoke(app, ["tasks", "list", "--robot", "invertedpendulum"])
    assert pendulum.exit_code == 0
    pendulum_pairs = [p for p in TASKS.values() if p.robot == "InvertedPendulum"]
    assert "invertedpendulum-gravity-3.0" in {p.name for p in pendulum_pairs}
    assert [line.split()[0] for line in pendulum.output.splitlines()] == [p.name for p in pendulum_pairs]
    nothing = runner.invoke(app, ["tasks", "list", "--robot", "InvertedPendulum", "--shift", "friction"])
    assert nothing.exit_code == 0
    families = ", ".join(sorted({p.shift for p in pendulum_pairs}))
    assert f"no pair of InvertedPendulum has the shift 'friction'; its shift families: {families}" in nothing.output


def test_tasks_show_prints_plain_text_without_rst_markup():
    result = runner.invoke(app, ["tasks", "show", "hopper-joint-noise-0.5"])
    assert result.exit_code == 0, result.output
    assert "- Add Gaussian noise N(0, std^2) to the command" in result.output
    assert "`" not in result.output


def test_plain_text_strips_every_effect_docstrings_markup():
    from offdyn_bench.effects import EFFECT_KINDS
    from offdyn_bench.task_commands import plain_text

    assert plain_text("Clip to ``[-limit, limit]``, see :class:`ChannelEffects`.") == "Clip to [-limit, limit], see ChannelEffects."
    for cls in EFFECT_KINDS.values():
        assert "`" not in plain_text(cls.__doc__.strip().splitlines()[0])
