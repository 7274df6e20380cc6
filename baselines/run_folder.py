"""A training run's folder on disk: the checks made before anything is written, the lock that
keeps two processes out of one folder, and reading back what an interrupted run left.

The files (``config.json``, ``metrics.jsonl``, ``result.json``, ``checkpoints/``) are described in
:mod:`baselines.train`. ``.lock`` is the lock file: it stays after a run, holds nothing, and is
only ever locked, never deleted (deleting a lock file lets two processes lock two different files).
"""

from __future__ import annotations

import dataclasses
import errno
import fcntl
import json
import os
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Any

from baselines.limits import FINITE, NON_NEGATIVE, integer
from offdyn_bench.errors import OffdynError

CONFIG_FILE, METRICS_FILE, RESULT_FILE = "config.json", "metrics.jsonl", "result.json"
LOCK_FILE = ".lock"
_POSITIVE_INTEGER = integer(1)


@dataclasses.dataclass(frozen=True)
class TrainingCompute:
    """What a training took, summed over its attempts (a first run and every resume)."""

    wall_time_s: float
    cpu_time_s: float
    """Process CPU time: every thread's, so it exceeds the wall time when torch uses several."""
    attempts: int
    complete: bool
    """False when the run resumed from a checkpoint written before checkpoints carried compute:
    the attempts before it are then missing from the times."""
    reference_updates: float | None = None
    """The same CPU time counted in updates of the reference workload
    (:mod:`offdyn_bench.machine_speed`) at the machine's speed while it ran: each stretch of CPU
    divided by the workload's time per update measured at its start. Comparable between machines
    and days where CPU seconds are not. None when an attempt did not measure it (trained before
    trainings did, or a timer that read zero)."""

    def to_dict(self) -> dict[str, Any]:
        return {"wall_time_s": round(self.wall_time_s, 3), "cpu_time_s": round(self.cpu_time_s, 3),
                "attempts": self.attempts, "complete": self.complete} | (
            {"reference_updates": round(self.reference_updates, 1)} if self.reference_updates is not None else {})

    @property
    def reference_update_s(self) -> float | None:
        """The workload's time per update averaged over the training's CPU: how fast its machine
        was, on the whole (None where unknown)."""
        if not self.reference_updates:
            return None
        return self.cpu_time_s / self.reference_updates

    @classmethod
    def parse(cls, stored: object) -> TrainingCompute | None:
        """The compute a checkpoint's counters or a ``result.json`` hold under ``compute``, or None
        when there is none (written before compute was recorded) or it is something else than
        non-negative finite times, a positive attempt count and a completeness flag."""
        if not isinstance(stored, dict):
            return None
        times = [stored.get("wall_time_s"), stored.get("cpu_time_s")]
        attempts, complete = stored.get("attempts"), stored.get("complete")
        updates = stored.get("reference_updates")
        if not (all(NON_NEGATIVE.accepts(t) for t in times) and _POSITIVE_INTEGER.accepts(attempts)
                and isinstance(complete, bool) and (updates is None or NON_NEGATIVE.accepts(updates))):
            return None
        return cls(float(times[0]), float(times[1]), attempts, complete,
                   float(updates) if updates is not None else None)


def check_writable(out: Path) -> None:
    """Raise unless ``out`` is, or can be created as, a folder this process can write in."""
    if out.exists():
        if not out.is_dir():
            raise OffdynError(f"--out {str(out)!r} exists and is not a folder; expected a folder (new or a run's)")
        if not os.access(out, os.W_OK | os.X_OK):
            raise OffdynError(f"--out {str(out)!r} is not writable by this user; choose a folder you can write in")
        return
    # The nearest existing ancestor decides: a file there, or no write permission, fails later.
    ancestor = out.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OffdynError(f"--out {str(out)!r} lies under {str(ancestor)!r}, which is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise OffdynError(f"--out {str(out)!r} cannot be created: {str(ancestor)!r} is not writable by this user")


def read_config(out: Path) -> dict[str, Any]:
    """``config.json`` of an existing run, or a clear error when it is damaged."""
    path = out / CONFIG_FILE
    try:
        stored = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise OffdynError(f"{str(path)!r} is damaged (not valid JSON: {error}), so it cannot tell which run "
                          f"{str(out)!r} holds; use a new --out folder") from None
    except OSError as error:
        raise OffdynError(f"cannot read {str(path)!r}: {error.strerror}") from None
    if not isinstance(stored, dict) or not isinstance(stored.get("config"), dict):
        raise OffdynError(f"{str(path)!r} is damaged (expected a JSON object with the run's settings); "
                          "use a new --out folder")
    return stored


def holds_files(out: Path) -> bool:
    """True when ``out`` holds anything but the lock file."""
    return any(p.name != LOCK_FILE for p in out.iterdir())


LOCK_HELD_ERRNOS = (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)
"""What a non-blocking ``flock`` fails with when another descriptor holds the lock."""


@contextmanager
def exclusive_folder_lock(folder: Path, lock_file: str, in_use: str) -> Iterator[None]:
    """Hold an exclusive lock on ``folder`` (created if missing) through ``lock_file`` for the
    block; a second holder, in this process or another, gets ``OffdynError(in_use)`` at once
    instead of waiting."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / lock_file, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as error:
        raise OffdynError(f"cannot create folder {str(folder)!r}: {error.strerror}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            if error.errno in LOCK_HELD_ERRNOS:
                raise OffdynError(in_use) from None
            raise OffdynError(f"cannot lock folder {str(folder)!r}: {error.strerror}") from None
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def run_folder_lock(out: Path) -> AbstractContextManager[None]:
    """Hold an exclusive lock on run folder ``out`` (created if missing) for the block."""
    return exclusive_folder_lock(out, LOCK_FILE, f"--out {str(out)!r} is in use by another training process (its "
                                                 f"{LOCK_FILE} is locked); wait for it to finish or use another folder")


def read_metrics(out: Path, resume_step: int) -> tuple[list[str], list[str]]:
    """The learning-curve lines an interrupted run keeps when it resumes from ``resume_step``, and
    notes on what was dropped. A line cut by a kill (the last one, unparseable) is dropped; so are
    lines after ``resume_step``, which the resumed run writes again."""
    path = out / METRICS_FILE
    if not path.exists():
        return [], []
    text = path.read_text(errors="replace")
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    kept, notes, later = [], [], 0
    for number, line in enumerate(lines, start=1):
        try:
            entry = json.loads(line)
            step = int(entry["step"])
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            if number == len(lines):
                notes.append(f"{METRICS_FILE}: dropped a partial last line (line {number}, cut off by the "
                             "interruption)")
                continue
            raise OffdynError(f"{str(path)!r} line {number} is damaged ({line[:60]!r}); expected one JSON "
                              "object per line; repair or remove that line to resume") from None
        if step <= resume_step:
            kept.append(line)
        else:
            later += 1
    if later:
        notes.append(f"{METRICS_FILE}: dropped {later} line(s) after step {resume_step}, written after the "
                     "checkpoint the run resumes from")
    return kept, notes


@dataclasses.dataclass(frozen=True)
class TrainingProgress:
    """How far a training has got, for estimates (:func:`training_progress`)."""

    fraction: float
    """The share of its steps up to its last learning-curve line."""
    seconds_per_run: float | None
    """A whole run's wall time at the pace between its last two curve lines (None before there are
    two, or where their times do not increase). The latest pace, not the mean: the first steps,
    random actions with no updates, go many times faster than the rest."""
    compute: TrainingCompute | None
    """What ``result.json`` records once it has finished (None before, or from before trainings
    recorded compute)."""
    spent: tuple[float, float] | None = None
    """Wall and CPU seconds at its last learning-curve line, over every attempt (None before the
    first line, or where that line's times are not non-negative numbers)."""
    evaluation_wall_s: float | None = None
    """Wall seconds its evaluations took, summed over the curve's lines (None where no line records
    it: curves from before lines did)."""

    @property
    def evaluation_share(self) -> float | None:
        """The share of its wall time its evaluations took (None where either is unknown)."""
        if self.evaluation_wall_s is None or self.spent is None or self.spent[0] <= 0:
            return None
        return min(1.0, self.evaluation_wall_s / self.spent[0])


def training_progress(out: Path) -> TrainingProgress | None:
    """How far the training in ``out`` has got. None: no training started there, or files that
    cannot be read as one (an estimate only skips them; resuming says what is wrong)."""
    try:
        steps = json.loads((out / CONFIG_FILE).read_text()).get("steps")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return None
    if not _POSITIVE_INTEGER.accepts(steps):
        return None
    points: list[tuple[int, Any, Any]] = []
    evaluation_wall_s = None
    try:
        for line in (out / METRICS_FILE).read_text(errors="replace").splitlines():
            try:
                entry = json.loads(line)
                step, wall, cpu = entry.get("step"), entry.get("wall_time_s"), entry.get("cpu_time_s")
                evaluation = entry.get("evaluation_wall_time_s")
            except (ValueError, AttributeError):
                continue  # a line cut off by a kill
            if _POSITIVE_INTEGER.accepts(step) and step <= steps:
                points.append((step, wall, cpu))
                if NON_NEGATIVE.accepts(evaluation):
                    evaluation_wall_s = (evaluation_wall_s or 0.0) + float(evaluation)
    except OSError:
        pass  # no curve yet: nothing evaluated
    points.sort(key=lambda point: point[0])
    per_run = None
    if len(points) >= 2:
        (step_a, wall_a, _), (step_b, wall_b, _) = points[-2:]
        if FINITE.accepts(wall_a) and FINITE.accepts(wall_b) and step_b > step_a and wall_b > wall_a:
            per_run = (wall_b - wall_a) / (step_b - step_a) * steps
    spent = None
    if points and NON_NEGATIVE.accepts(points[-1][1]) and NON_NEGATIVE.accepts(points[-1][2]):
        spent = (float(points[-1][1]), float(points[-1][2]))
    return TrainingProgress(points[-1][0] / steps if points else 0.0, per_run, read_training_compute(out), spent,
                            evaluation_wall_s)


def read_training_compute(out: Path) -> TrainingCompute | None:
    """The compute the ``result.json`` in ``out`` records, or None (no finished training there, or
    one from before trainings recorded compute)."""
    try:
        result = json.loads((out / RESULT_FILE).read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    return TrainingCompute.parse(result.get("compute")) if isinstance(result, dict) else None


def write_lines_atomic(path: Path, lines: list[str]) -> None:
    _write_text_atomic(path, "".join(line + "\n" for line in lines))


def write_json_atomic(path: Path, data: Any) -> None:
    _write_text_atomic(path, json.dumps(data, indent=1))


def _write_text_atomic(path: Path, text: str) -> None:
    """The old file or the new one, never part of one; a failed write leaves no partial file."""
    partial = path.with_name(path.name + ".partial")
    try:
        partial.write_text(text)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
