"""A submission assembled from what `train` and `evaluate` really write (not a fixture of their
format): the two ends of the pipeline agree."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from baselines.train import train
from leaderboard.assemble import assemble_submission
from leaderboard.submission import SubmissionError
from offdyn_bench import evaluate as evaluate_module
from offdyn_bench import protocol
from offdyn_bench.protocol.definition import Budget

TASK = "invertedpendulum-gravity-3.0"
TINY = {"sac.hidden_sizes": "[16, 16]", "sac.batch_size": "16", "random_steps": "20"}
EPISODES = 3
STEPS = 50


@pytest.fixture
def pendulum_protocol(monkeypatch: pytest.MonkeyPatch) -> None:
    """The protocol shrunk to one fast task, 3 seeds, 3 episodes and a 50-step budget."""
    seeds = tuple(range(2_000_000, 2_000_000 + EPISODES))
    for module in (protocol, evaluate_module):
        monkeypatch.setattr(module, "EVAL_EPISODES", EPISODES)
        monkeypatch.setattr(module, "EPISODE_SEEDS", seeds)
    monkeypatch.setattr(protocol, "CORE_SUITE", (TASK,))
    monkeypatch.setattr(protocol, "MIN_SEEDS", 3)
    monkeypatch.setattr(evaluate_module, "BUDGETS", {"lite": Budget("lite", STEPS, "test budget")})


def _evaluated_run(root: Path, **evaluate_options) -> Path:
    run = root / "sac-source" / TASK
    train("sac-source", TASK, steps=STEPS, out=run, n_seeds=3, overrides=TINY, eval_episodes=1, progress=False)
    evaluate_module.evaluate(run, episodes=EPISODES, progress=False, **evaluate_options)
    return run


def test_a_submission_from_real_train_and_evaluate_output_validates(tmp_path, pendulum_protocol):
    _evaluated_run(tmp_path / "runs")
    with pytest.raises(SubmissionError, match="name no track .* pass --track"):
        assemble_submission(tmp_path / "runs", method="my-sac")
    submission = assemble_submission(tmp_path / "runs", method="my-sac", description="SAC in the source",
                                     track="offline-target")
    task = submission.document["tasks"][TASK]
    assert (submission.document["budget"], submission.document["track"]) == ("lite", "offline-target")
    assert [s["seed"] for s in task["seeds"]] == [0, 1, 2]
    assert set(task["policy_sha256"]) == {"0", "1", "2"}
    assert task["learning_curve"]  # from the run's metrics.jsonl


def test_records_that_are_no_protocol_result_are_refused(tmp_path, pendulum_protocol):
    # A source-side record written where the protocol record belongs (evaluate's default never does).
    run = _evaluated_run(tmp_path / "runs", side="source", out=tmp_path / "runs" / "sac-source" / TASK / "evaluation.json")
    with pytest.raises(SubmissionError, match="evaluates the source side"):
        assemble_submission(tmp_path / "runs", method="my-sac")
    record = json.loads((run / "evaluation.json").read_text())
    record.update(side="target", protocol_conformant=False, notes=["trained on dataset 'x'"])
    (run / "evaluation.json").write_text(json.dumps(record))
    with pytest.raises(SubmissionError, match="is not a protocol result: trained on dataset 'x'"):
        assemble_submission(tmp_path / "runs", method="my-sac")
