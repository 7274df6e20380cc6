"""Pack a sweep's unfinished runs, each with its newest sound checkpoint, so another machine resumes them.

    python scripts/pack_unfinished_runs.py SWEEP_OUT DEST [--max-files N] [--max-bytes B]
    python scripts/pack_unfinished_runs.py --check SPEC ARCHIVE...   # each archive is a run of SPEC

For every run folder under ``SWEEP_OUT/runs/<method>/<task>/<label>`` without an
``evaluation.json`` (its training cut short, or trained but not yet evaluated) that holds a
checkpoint that verifies: one ``DEST/partial.<method>.<task>.<label>.tar`` holding the folder as
``runs/<method>/<task>/<label>/`` with that checkpoint only (the older one, the lock and nothing
else left out). Unpacked into another sweep's out of the same spec, the sweep resumes the run from
that checkpoint (``scripts/gpu_reference_sweep.sh`` does this between leases). The most advanced
runs go first, while the archives stay within ``--max-files`` and ``--max-bytes`` (what a lease
call brings back); the rest are named as left out. The sweep may still be running: each folder is
copied first and its checkpoint verified in the copy.

``--check SPEC ARCHIVE...`` says, before an archive travels, whether it holds one of the spec's runs
trained with the spec's settings (the sweep would refuse another): exit status 2 and an
``error:`` line naming what differs where one does not.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tarfile
import tempfile
from pathlib import Path

from baselines.checkpoint import (CHECKPOINT_DIR, DamagedCheckpointError, checkpoint_step, latest_checkpoint,
                                  load_checkpoint)
from baselines.run_folder import LOCK_FILE
from offdyn_bench.sweep.runs import EVALUATION_FILE, RUNS_DIR


def unfinished_runs(sweep_out: Path) -> list[tuple[Path, Path]]:
    """(run folder, its newest checkpoint that verifies) of each unevaluated run, most steps first."""
    found = []
    for folder in sorted((sweep_out / RUNS_DIR).glob("*/*/*")):
        if not folder.is_dir() or (folder / EVALUATION_FILE).exists():
            continue
        checkpoint = latest_checkpoint(folder)
        if checkpoint is not None:
            found.append((folder, checkpoint))
    return sorted(found, key=lambda pair: -checkpoint_step(pair[1]))


def pack_run(folder: Path, checkpoint: Path, destination: Path) -> Path | None:
    """The archive of ``folder`` with ``checkpoint`` only, or None when the copy's checkpoint does not
    verify (replaced while it was copied)."""
    label, task, method = folder.parts[-1], folder.parts[-2], folder.parts[-3]
    with tempfile.TemporaryDirectory() as tmp:
        staged = Path(tmp) / RUNS_DIR / method / task / label

        def leave_out(directory: str, names: list[str]) -> set[str]:
            here = Path(directory)
            if here == folder:
                return {LOCK_FILE} & set(names)
            if here == folder / CHECKPOINT_DIR:
                return {name for name in names if name != checkpoint.name}
            return set()

        try:
            shutil.copytree(folder, staged, ignore=leave_out)
            load_checkpoint(staged / CHECKPOINT_DIR / checkpoint.name)
        except (shutil.Error, OSError, DamagedCheckpointError):
            return None  # the sweep replaced or removed it meanwhile
        archive = destination / f"partial.{method}.{task}.{label}.tar"
        with tarfile.open(archive, "w") as tar:
            tar.add(Path(tmp) / RUNS_DIR, arcname=RUNS_DIR)
    return archive


def run_of_archive(archive: Path) -> str:
    """``<method>/<task>/<label>``: the run folder an archive of :func:`pack_run` holds."""
    with tarfile.open(archive) as tar:
        folders = {tuple(Path(name).parts[1:4]) for name in tar.getnames() if len(Path(name).parts) >= 4}
    if len(folders) != 1:
        raise ValueError(f"{archive}: expected the folder of one run under {RUNS_DIR}/, found {len(folders)}")
    return "/".join(folders.pop())


def check(spec_path: Path, archives: list[Path]) -> list[str]:
    """What is wrong with each archive as a run of the spec to resume ([] where nothing is)."""
    import dataclasses

    from offdyn_bench.sweep.runs import expand, settings_conflict
    from offdyn_bench.sweep.spec import load_spec

    runs = {run.run_id: run for run in expand(load_spec(spec_path))}
    problems = []
    for archive in archives:
        try:
            run_id = run_of_archive(archive)
        except (ValueError, tarfile.TarError, OSError) as error:
            problems.append(str(error))
            continue
        if run_id not in runs:
            problems.append(f"{archive.name} holds {run_id}, not a run of {spec_path} ({', '.join(runs)})")
            continue
        with tempfile.TemporaryDirectory() as tmp, tarfile.open(archive) as tar:
            tar.extractall(tmp, filter="data")
            run = dataclasses.replace(runs[run_id], folder=Path(tmp) / RUNS_DIR / run_id, shared_training=None)
            why = settings_conflict(run)
        if why is not None:
            problems.append(f"{archive.name} was trained with other settings than {spec_path}'s run ({why})")
    return problems


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--check"]:
        if len(argv) < 3:
            print("usage: pack_unfinished_runs.py --check SPEC ARCHIVE...", file=sys.stderr)
            return 2
        problems = check(Path(argv[1]), [Path(a) for a in argv[2:]])
        for problem in problems:
            print(f"error: {problem}", file=sys.stderr)
        return 2 if problems else 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sweep_out", type=Path)
    parser.add_argument("destination", type=Path)
    parser.add_argument("--max-files", type=int, default=5)
    parser.add_argument("--max-bytes", type=int, default=48 * 2**20)
    parser.add_argument("--max-file-bytes", type=int, default=16 * 2**20, help="the largest one archive may be")
    args = parser.parse_args(argv)
    if not (args.sweep_out / RUNS_DIR).is_dir():
        print(f"{args.sweep_out}: no {RUNS_DIR}/ folder: no runs to pack")
        return 0
    args.destination.mkdir(parents=True, exist_ok=True)
    files, used = 0, 0
    for folder, checkpoint in unfinished_runs(args.sweep_out):
        run_id = "/".join(folder.parts[-3:])
        step = checkpoint_step(checkpoint)
        if files >= args.max_files:
            print(f"left out: {run_id} at step {step} (no more files may come back)")
            continue
        archive = pack_run(folder, checkpoint, args.destination)
        if archive is None:
            print(f"left out: {run_id}: its checkpoint changed while it was copied", file=sys.stderr)
            continue
        size = archive.stat().st_size
        if size > args.max_file_bytes or used + size > args.max_bytes:
            archive.unlink()
            print(f"left out: {run_id} at step {step} ({size / 2**20:.1f} MiB: over what may come back)")
            continue
        files, used = files + 1, used + size
        print(f"packed: {run_id} at step {step}, {size / 2**20:.1f} MiB, {archive.name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
