"""``scripts/pack_unfinished_runs.py``: a sweep's unfinished runs leave a machine with their newest
checkpoint, and a sweep elsewhere resumes them to the result an uninterrupted run has."""

from __future__ import annotations

import json
import subprocess
import sys
import tarfile
from pathlib import Path

from baselines.train import train

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "pack_unfinished_runs.py"
TASK = "invertedpendulum-gravity-3.0"
TINY = {"sac.hidden_sizes": "[32, 32]", "sac.batch_size": "32", "random_steps": "40"}


def _train(out: Path, stop_after: int | None = None):
    return train("sac-source", TASK, steps=300, out=out, checkpoint_every=100, eval_every=100, eval_episodes=1,
                 progress=False, overrides=TINY, stop_after=stop_after)


def _pack(sweep_out: Path, destination: Path, *options: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), str(sweep_out), str(destination), *options], cwd=REPO,
                          capture_output=True, text=True, check=True, timeout=300)


def test_an_unfinished_run_travels_with_its_newest_checkpoint_and_resumes_to_the_uninterrupted_result(tmp_path):
    runs = tmp_path / "sweep" / "runs" / "sac-source" / TASK
    cut_short, finished, unstarted = runs / "seed-0", runs / "seed-1", runs / "seed-2"
    assert _train(cut_short, stop_after=200) is None
    _train(finished)
    (finished / "evaluation.json").write_text("{}")  # evaluated: nothing to carry
    unstarted.mkdir()  # no checkpoint: nothing to resume from

    [line] = _pack(tmp_path / "sweep", tmp_path / "back").stdout.splitlines()
    assert line.startswith(f"packed: sac-source/{TASK}/seed-0 at step 200, ")
    [archive] = (tmp_path / "back").iterdir()
    assert line.endswith(f" MiB, {archive.name}") and archive.name == f"partial.sac-source.{TASK}.seed-0.tar"
    with tarfile.open(archive) as tar:
        names = tar.getnames()
        tar.extractall(tmp_path / "elsewhere", filter="data")
    folder = f"runs/sac-source/{TASK}/seed-0"
    assert f"{folder}/config.json" in names and f"{folder}/checkpoints/step_000000200/state.safetensors" in names
    assert not any("step_000000100" in name or name.endswith(".lock") for name in names)

    resumed = _train(tmp_path / "elsewhere" / folder)
    uninterrupted = _train(tmp_path / "straight")
    assert resumed["returns"] == uninterrupted["returns"]
    assert [json.loads(line)["target_return"] for line in (tmp_path / "elsewhere" / folder / "metrics.jsonl")
            .read_text().splitlines()] == [json.loads(line)["target_return"] for line in
                                           (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]


def test_runs_over_what_may_come_back_are_named_and_leave_no_archive(tmp_path):
    for seed in (0, 1):
        _train(tmp_path / "sweep" / "runs" / "sac-source" / TASK / f"seed-{seed}", stop_after=100 + 100 * seed)
    one_file = _pack(tmp_path / "sweep", tmp_path / "back", "--max-files", "1")
    # the most advanced run first
    assert one_file.stdout.splitlines()[0].startswith(f"packed: sac-source/{TASK}/seed-1 at step 200")
    assert one_file.stdout.splitlines()[1] == f"left out: sac-source/{TASK}/seed-0 at step 100 (no more files may come back)"
    too_small = _pack(tmp_path / "sweep", tmp_path / "small", "--max-bytes", "1000")
    assert all(line.startswith("left out: ") and "over what may come back" in line
               for line in too_small.stdout.splitlines())
    assert not any((tmp_path / "small").iterdir())
