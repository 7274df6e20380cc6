"""A small protocol (3 core tasks, 3 seeds, 4 episodes) and reference file, so the leaderboard's
tests build, score and serve real submissions in well under a second each.

Scores on the fixture are easy to compute by hand: hopper-gravity-0.5 has J_random 0 and
J_oracle 100 (normalized = J), walker2d-gravity-2.0 has 10 and 210 (normalized = (J - 10) / 2),
ant-gravity-0.1 has a random reference only, so it is shown raw and excluded from normalized scores.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest

SMALL_SUITE = ("hopper-gravity-0.5", "walker2d-gravity-2.0", "ant-gravity-0.1")
SMALL_EPISODES = 4
SMALL_EPISODE_SEEDS = tuple(range(2_000_000, 2_000_000 + SMALL_EPISODES))
SMALL_MIN_SEEDS = 3
REFERENCES = {"hopper-gravity-0.5": (0.0, 100.0), "walker2d-gravity-2.0": (10.0, 210.0),
              "ant-gravity-0.1": (-50.0, None)}
DEFAULT_SEED_MEANS = {"hopper-gravity-0.5": (10.0, 20.0, 30.0), "walker2d-gravity-2.0": (50.0, 90.0, 130.0),
                      "ant-gravity-0.1": (100.0, 200.0, 300.0)}
"""Per-seed mean returns of the default fixture method. Normalized: hopper 10, 20, 30; walker 20, 40,
60; pooled sorted 10 20 20 30 40 60: IQM (cut 1 each end) 27.5, mean 30, optimality gap 70."""


@pytest.fixture
def small_protocol(monkeypatch: pytest.MonkeyPatch) -> None:
    from offdyn_bench import protocol

    monkeypatch.setattr(protocol, "CORE_SUITE", SMALL_SUITE)
    monkeypatch.setattr(protocol, "EVAL_EPISODES", SMALL_EPISODES)
    monkeypatch.setattr(protocol, "EPISODE_SEEDS", SMALL_EPISODE_SEEDS)
    monkeypatch.setattr(protocol, "MIN_SEEDS", SMALL_MIN_SEEDS)


@pytest.fixture
def references_file(tmp_path: Path) -> Path:
    from offdyn_bench import protocol

    tasks: dict[str, Any] = {}
    for task, (j_random, j_oracle) in REFERENCES.items():
        entry: dict[str, Any] = {"random": {"mean_return": j_random, "returns": [j_random] * SMALL_EPISODES,
                                            "provenance": {"fixture": "tests/leaderboard/conftest.py"}}}
        if j_oracle is not None:
            entry["oracle"] = {"lite": {"mean_return": j_oracle, "returns": [j_oracle] * SMALL_EPISODES,
                                        "provenance": {"fixture": "tests/leaderboard/conftest.py"}}}
        tasks[task] = entry
    path = tmp_path / "reference_scores.json"
    path.write_text(json.dumps({"format": "offdyn-bench/reference-scores", "format_version": 1,
                                "protocol_version": protocol.PROTOCOL_VERSION, "tasks": tasks}))
    return path


def episode_returns(seed_mean: float) -> list[float]:
    """Four episode returns whose mean is ``seed_mean``."""
    return [seed_mean - 1.0, seed_mean + 1.0, seed_mean - 3.0, seed_mean + 3.0]


def _versions() -> dict[str, str | None]:
    return {"offdyn_bench": "0.1.0", "mujoco": "3.17.0", "torch": "2.13.0", "gymnasium": "1.4.0",
            "minari": "0.5.4", "numpy": "2.3.0", "python": "3.11.9"}


def _target_env_id(task: str) -> str:
    from offdyn_bench.tasks import TASKS

    return TASKS[task].env_id("target")


SubmissionFactory = Callable[..., dict[str, Any]]


@pytest.fixture
def make_submission(small_protocol: None) -> SubmissionFactory:
    """A valid submission document under the small protocol; keyword arguments change it."""

    def make(method: str = "alpha", *, track: str = "offline-target", budget: str = "lite",
             seed_means: dict[str, Sequence[float]] | None = None, seeds: Sequence[int] = (0, 1, 2),
             curves: bool = False) -> dict[str, Any]:
        means = seed_means or DEFAULT_SEED_MEANS
        tasks = {}
        for task in SMALL_SUITE:
            entry: dict[str, Any] = {
                "task_version": 0, "target_env_id": _target_env_id(task), "dataset": None,
                "episode_seeds": list(SMALL_EPISODE_SEEDS),
                "seeds": [{"seed": s, "returns": episode_returns(m)} for s, m in zip(seeds, means[task])],
            }
            if curves:
                entry["learning_curve"] = [{"step": step, "target_return": [m * step / 2000 for m in means[task]]}
                                           for step in (500, 1000, 1500, 2000)]
            tasks[task] = entry
        return {"format": "offdyn-bench/submission", "format_version": 1, "protocol_version": "1.0",
                "method": {"name": method, "description": f"the {method} method",
                           "code_url": "https://example.org/code", "commit": "0123abcd"},
                "track": track, "budget": budget, "versions": _versions(), "tasks": tasks}

    return make


EvaluationWriter = Callable[..., list[Path]]


@pytest.fixture
def write_runs(small_protocol: None) -> EvaluationWriter:
    """Run folders with an ``evaluation.json`` (and ``metrics.jsonl``) in the format ``evaluate`` writes."""

    def write(runs: Path, tasks: Sequence[str] = SMALL_SUITE, *, method: str = "dap", track: str = "offline-target",
              budget: str = "lite", versions: dict[str, Any] | None = None, metrics: bool = True) -> list[Path]:
        paths = []
        for task in tasks:
            folder = runs / method / task
            folder.mkdir(parents=True, exist_ok=True)
            means = DEFAULT_SEED_MEANS[task]
            evaluation = {
                "format": "offdyn-bench/evaluation", "format_version": 1, "protocol_version": "1.0",
                "task": task, "task_version": 0, "target_env_id": _target_env_id(task),
                "track": track, "budget": budget, "method": method,
                "agent": {"kind": "run", "path": str(folder), "policy_sha256": "ab" * 32},
                "dataset": None, "episode_seeds": list(SMALL_EPISODE_SEEDS),
                "seeds": [{"seed": s, "returns": episode_returns(m)} for s, m in enumerate(means)],
                "versions": versions or _versions(),
                "command": f"offdyn-bench evaluate --agent {folder} --task {task}",
            }
            (folder / "evaluation.json").write_text(json.dumps(evaluation))
            if metrics:
                lines = [{"step": step, "target_return": [m * step / 1000 for m in means],
                          "target_return_mean": 0.0, "train": {}, "wall_time_s": 1.0} for step in (500, 1000)]
                (folder / "metrics.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
            paths.append(folder / "evaluation.json")
        return paths

    return write
