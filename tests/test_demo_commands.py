"""The demo prints each training as a stand-alone command: run alone, it must train the same run."""
from __future__ import annotations

import shlex

import pytest
from typer.testing import CliRunner

from offdyn_bench import demo
from offdyn_bench.cli import app


def test_printed_training_commands_ask_for_the_runs_the_demo_trains(tmp_path, monkeypatch, capsys):
    import baselines.train

    trained: list[dict] = []  # what the demo itself asks train() for
    monkeypatch.setattr(demo, "_train_or_reuse", lambda algo, task, steps, out, **kwargs: trained.append(
        {"algo": algo, "task": task, "steps": steps, "out": out, "eval_episodes": demo.DEMO_EVAL_EPISODES, **kwargs}))
    demo.demo_training(tmp_path / "demo out", steps=4000, n_seeds=2)  # a space in the path must survive quoting
    printed = [line.split(":", 1)[1].strip() for line in capsys.readouterr().out.splitlines()
               if "offdyn-bench train " in line]
    assert len(printed) == len(trained) == 3

    asked: list[dict] = []  # what each printed command asks train() for
    monkeypatch.setattr(baselines.train, "train", lambda algo, task, **kwargs: asked.append(
        {"algo": algo, "task": task, **kwargs}))
    for command in printed:
        words = shlex.split(command)
        assert words[:2] == ["offdyn-bench", "train"], command
        result = CliRunner().invoke(app, words[1:])
        assert result.exit_code == 0, result.output

    for by_demo, by_command in zip(trained, asked):
        assert by_command["algo"] == by_demo["algo"] and by_command["task"] == by_demo["task"]
        assert by_command["steps"] == by_demo["steps"] and by_command["n_seeds"] == by_demo["n_seeds"]
        assert by_command["out"] == by_demo["out"]
        assert by_command["eval_episodes"] == by_demo["eval_episodes"]
        assert by_command["dataset"] == by_demo.get("dataset")
        assert by_command["overrides"] == by_demo["overrides"], by_demo["algo"]


@pytest.mark.parametrize("value", ["[64, 64]", "a'b", "x y=z"])
def test_set_flags_quote_values_for_the_shell(value):
    words = shlex.split("train" + demo.set_flags({"key": value}))
    assert words == ["train", "--set", f"key={value}"]
