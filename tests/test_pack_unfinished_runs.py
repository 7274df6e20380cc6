"""``scripts/pack_unfinished_runs.py``: a sweep's unfinished runs leave a machine with their newest
checkpoint, and a sweep elsewhere resumes them to the result an uninterrupted run has."""

from __future__ import annotations

import json
import tarfile

from cut_short_runs import TASK, pack_unfinished, train_tiny_source


def test_an_unfinished_run_travels_with_its_newest_checkpoint_and_resumes_to_the_uninterrupted_result(tmp_path):
    runs = tmp_path / "sweep" / "runs" / "sac-source" / TASK
    cut_short, finished, unstarted = runs / "seed-0", runs / "seed-1", runs / "seed-2"
    assert train_tiny_source(cut_short, stop_after=200) is None
    train_tiny_source(finished)
    (finished / "evaluation.json").write_text("{}")  # evaluated: nothing to carry
    unstarted.mkdir()  # no checkpoint: nothing to resume from

    [line] = pack_unfinished(tmp_path / "sweep", tmp_path / "back").stdout.splitlines()
    assert line.startswith(f"packed: sac-source/{TASK}/seed-0 at step 200, ")
    [archive] = (tmp_path / "back").iterdir()
    assert line.endswith(f" MiB, {archive.name}") and archive.name == f"partial.sac-source.{TASK}.seed-0.tar"
    with tarfile.open(archive) as tar:
        names = tar.getnames()
        tar.extractall(tmp_path / "elsewhere", filter="data")
    folder = f"runs/sac-source/{TASK}/seed-0"
    assert f"{folder}/config.json" in names and f"{folder}/checkpoints/step_000000200/state.safetensors" in names
    assert not any("step_000000100" in name or name.endswith(".lock") for name in names)

    resumed = train_tiny_source(tmp_path / "elsewhere" / folder)
    uninterrupted = train_tiny_source(tmp_path / "straight")
    assert resumed["returns"] == uninterrupted["returns"]
    assert [json.loads(line)["target_return"] for line in (tmp_path / "elsewhere" / folder / "metrics.jsonl")
            .read_text().splitlines()] == [json.loads(line)["target_return"] for line in
                                           (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]


def test_runs_over_what_may_come_back_are_named_and_leave_no_archive(tmp_path):
    for seed in (0, 1):
        train_tiny_source(tmp_path / "sweep" / "runs" / "sac-source" / TASK / f"seed-{seed}", stop_after=100 + 100 * seed)
    one_file = pack_unfinished(tmp_path / "sweep", tmp_path / "back", "--max-files", "1")
    # the most advanced run first
    assert one_file.stdout.splitlines()[0].startswith(f"packed: sac-source/{TASK}/seed-1 at step 200")
    assert one_file.stdout.splitlines()[1] == f"left out: sac-source/{TASK}/seed-0 at step 100 (no more files may come back)"
    too_small = pack_unfinished(tmp_path / "sweep", tmp_path / "small", "--max-bytes", "1000")
    assert all(line.startswith("left out: ") and "over what may come back" in line
               for line in too_small.stdout.splitlines())
    assert not any((tmp_path / "small").iterdir())
