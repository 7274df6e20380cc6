"""Tiny sweeps: RL on source on an InvertedPendulum pair, a few hundred steps, 32x32 networks."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest

TASK = "invertedpendulum-gravity-3.0"
TINY_OVERRIDES = {"sac.hidden_sizes": [32, 32], "sac.batch_size": 32, "random_steps": 40}


def _tiny_spec(out: Path, **changes: Any) -> dict[str, Any]:
    spec = {"methods": ["sac-source"], "tasks": [TASK], "seeds": 2, "track": "offline-target", "steps": 300,
            "out": str(out), "evaluation_episodes": 2,
            "training": {"eval_episodes": 1, "checkpoint_every": 100},
            "overrides": {"sac-source": dict(TINY_OVERRIDES)}, "max_retries": 1}
    spec.update(changes)
    return spec


def _write_spec(path: Path, spec: dict[str, Any]) -> Path:
    path.write_text(json.dumps(spec))
    return path


def _attempt_headers(log: Path) -> int:
    return sum(line.startswith("=== attempt ") and " of " in line for line in log.read_text().splitlines())


@pytest.fixture
def tiny_spec():
    """``tiny_spec(out, **changes)``: the spec of a tiny sweep (2 seeds, 300 steps) as data."""
    return _tiny_spec


@pytest.fixture
def write_spec():
    """``write_spec(path, spec)``: the spec as a JSON file."""
    return _write_spec


@pytest.fixture
def attempt_headers():
    """``attempt_headers(log)``: how many attempts a run's log records."""
    return _attempt_headers


@pytest.fixture(scope="session")
def finished_sweep(tmp_path_factory):
    """A tiny sweep run once with the local backend (2 runs, 2 workers), shared by the session's
    tests (once per pytest-xdist worker that runs one of them): they read it, and whatever runs it
    again or writes into it works on a copy."""
    from offdyn_bench.sweep import parse_spec
    from offdyn_bench.sweep.driver import run_sweep

    root = tmp_path_factory.mktemp("sweep")
    report = run_sweep(parse_spec(_tiny_spec(root / "out"), source="tiny"), workers=2, echo=None)
    return report


SHARED_SOURCE_TASKS = ["invertedpendulum-gravity-3.0", "invertedpendulum-kinematic-slider-hard"]


@pytest.fixture(scope="module")
def shared_source_sweep(tmp_path_factory):
    """A tiny sac-source sweep on two tasks with one source (1 seed, 2 workers): one training."""
    from offdyn_bench.sweep import parse_spec
    from offdyn_bench.sweep.driver import run_sweep

    root = tmp_path_factory.mktemp("shared")
    spec = parse_spec(_tiny_spec(root / "out", tasks=SHARED_SOURCE_TASKS, seeds=1), source="shared")
    return run_sweep(spec, workers=2, echo=None)


def _train_process_of(folder: Path) -> int | None:
    """The pid of the `train` subprocess writing into ``folder`` (Linux: read from /proc)."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            args = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"train" in args and str(folder).encode() in args:
            return int(entry.name)
    return None


def _wait_for(condition, timeout: float = 600.0) -> None:
    # Generous: beside other work on two cores, the tiny trainings it waits on get a sliver of CPU
    # (the Ray kill test once waited over 240 s for its victim that way); the condition is unchanged.
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting"
        time.sleep(0.02)


@pytest.fixture
def train_process_of():
    """``train_process_of(folder)``: the pid of the `train` subprocess writing into it, or None."""
    return _train_process_of


@pytest.fixture
def wait_for():
    """``wait_for(condition, timeout=600)``: poll until ``condition()`` is true, or fail."""
    return _wait_for


def _run_record(status: str):
    from offdyn_bench.sweep.driver import RunRecord

    return RunRecord(method="sac-source", task="t", seeds=[0], folder="f", log="l", status=status)


@pytest.fixture
def run_record():
    """``run_record(status)``: a state-file record with that status and nothing else, for the progress line."""
    return _run_record
