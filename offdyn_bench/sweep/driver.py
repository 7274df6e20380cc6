"""The sweep driver: expand the spec, skip what is finished, hand the rest to a backend, retry
failures up to ``max_retries`` times, keep the state file and the progress line current, and end
with a summary and the leaderboard commands.

The state file (``<out>/sweep.json``, replaced atomically after every change) records, per run,
its status (``pending``, ``running``, ``done``, ``failed``), every attempt (exit code, error,
wall and CPU time, host) and the totals. It is a record, not the source of truth: a run counts as
done when its folder holds a complete ``evaluation.json``, so a deleted or stale state file
loses nothing, and a run marked ``running`` by a sweep that was killed is simply run again (its
train command resumes from the checkpoints).
"""

from __future__ import annotations

import dataclasses
import datetime
import fcntl
import heapq
import json
import math
import os
import re
import socket
import time
from collections.abc import Callable, Collection
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

from baselines.run_folder import (
    LOCK_HELD_ERRNOS,
    TrainingProgress,
    exclusive_folder_lock,
    training_progress,
    write_json_atomic,
)
from offdyn_bench.errors import OffdynError
from offdyn_bench.json_values import is_finite_number
from offdyn_bench.sweep.backends import Backend, LocalBackend, RayBackend, cpus_for, default_workers
from offdyn_bench.sweep.execute import AttemptOutcome
from offdyn_bench.sweep.runs import (
    EVALUATION_FILE,
    RUNS_DIR,
    Run,
    expand,
    finished_evaluation,
    mean_return,
    official_datasets,
    run_finished,
    settings_conflict,
)
from offdyn_bench.sweep.spec import SpecError, SweepSpec

STATE_FILE = "sweep.json"
STATE_FORMAT = "offdyn-bench/sweep-state"
LOCK_FILE = ".sweep.lock"
PROGRESS_EVERY_S = 30.0

Echo = Callable[[str], None]


def _is_seconds(value: Any) -> bool:
    return is_finite_number(value) and value >= 0


def _seconds_of(history: list[Any], key: str) -> float:
    """The sum of ``key`` over the attempts of a stored history; a value that is not a
    non-negative finite number (a hand-edited or damaged state file) counts nothing."""
    return float(sum(attempt[key] for attempt in history
                     if isinstance(attempt, dict) and _is_seconds(attempt.get(key))))


@dataclasses.dataclass
class RunRecord:
    """One run's line in the state file."""

    method: str
    task: str
    seeds: list[int]
    folder: str
    log: str
    status: str = "pending"
    attempts: int = 0
    """Attempts started, over every invocation of the sweep."""
    wall_time_s: float = 0.0
    cpu_time_s: float = 0.0
    mean_return: float | None = None
    error: str | None = None
    history: list[dict[str, Any]] = dataclasses.field(default_factory=list)

    @property
    def evaluate_wall_time_s(self) -> float | None:
        """Wall time its attempts spent in evaluate commands; None where an attempt predates the count."""
        spent = [a.get("evaluate_wall_time_s") for a in self.history if isinstance(a, dict)]
        if not spent or not all(_is_seconds(x) for x in spent):
            return None
        return float(sum(spent))

    @classmethod
    def of(cls, run: Run, stored: dict[str, Any] | None) -> RunRecord:
        record = cls(method=run.method, task=run.task, seeds=list(run.seeds), folder=str(run.folder),
                     log=str(run.log))
        if isinstance(stored, dict):
            history = stored.get("history")
            record.history = list(history) if isinstance(history, list) else []
            # Attempts are counted when they start: one cut short by a killed driver has no outcome.
            stored_attempts = stored.get("attempts")
            record.attempts = max(len(record.history),
                                  stored_attempts if isinstance(stored_attempts, int) else 0)
            record.wall_time_s = _seconds_of(record.history, "wall_time_s")
            record.cpu_time_s = _seconds_of(record.history, "cpu_time_s")
        return record

    def add(self, attempt: int, outcome: AttemptOutcome) -> None:
        self.history.append({"attempt": attempt, **outcome.to_dict()})
        self.wall_time_s = round(self.wall_time_s + outcome.wall_time_s, 3)
        self.cpu_time_s = round(self.cpu_time_s + outcome.cpu_time_s, 3)


@dataclasses.dataclass
class SweepReport:
    """What a sweep ended with."""

    spec: SweepSpec
    runs: list[Run]
    records: dict[str, RunRecord]
    launched: int
    """Attempts started by this invocation (0: everything was already done)."""
    submissions: dict[str, list[str]]
    """Per method whose runs all finished: [] when its merged folder is a leaderboard submission,
    else the reasons it is not."""
    submitted: dict[str, Path]
    state_path: Path

    start_before: float | None = None
    """The ``--start-before`` limit in seconds (None: none)."""
    skipped: tuple[str, ...] = ()
    """Run ids of the spec left out as published already (``--skip-published``)."""

    @property
    def failed(self) -> list[Run]:
        return [run for run in self.runs if self.records[run.run_id].status == "failed"]

    @property
    def not_started(self) -> list[Run]:
        """Runs left pending because ``start_before`` had passed: the next sweep runs them."""
        return [run for run in self.runs if self.records[run.run_id].status == "pending"]


def check_out_is_folder(out: Path) -> None:
    """Refuse an ``out`` that exists as something else than a folder."""
    if out.exists() and not out.is_dir():
        raise OffdynError(f"out {str(out)!r} exists and is not a folder; expected the sweep's output folder")


def _check_out(out: Path) -> None:
    check_out_is_folder(out)
    ancestor = out.absolute()
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
        raise OffdynError(f"out {str(out)!r} cannot be written: {str(ancestor)!r} is not a writable folder")


def _sweep_lock(out: Path) -> AbstractContextManager[None]:
    """One sweep driver per output folder at a time (a second one stops at once, naming it)."""
    return exclusive_folder_lock(out, LOCK_FILE, f"another sweep is running on {str(out)!r} (its {LOCK_FILE} is "
                                                 "locked); wait for it or use another out")


def sweep_running(out: Path) -> bool:
    """Whether a sweep driver holds ``out``'s lock now (creates nothing). The probe holds a shared
    lock for an instant; a driver starting in that instant stops with "another sweep is running"."""
    try:
        fd = os.open(out / LOCK_FILE, os.O_RDONLY)
    except OSError:
        return False  # no lock file: no sweep has run there
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as error:
        return error.errno in LOCK_HELD_ERRNOS
    finally:
        os.close(fd)  # releases the probe's lock
    return False


def _utc(epoch_s: float) -> str:
    return datetime.datetime.fromtimestamp(epoch_s, datetime.UTC).isoformat(timespec="seconds")


def read_state(path: Path) -> dict[str, Any]:
    """The state file's contents; {} where it is missing, unreadable or not a sweep's state."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        # The record only: run folders say what is done. A damaged one is started afresh.
        return {}
    return data if isinstance(data, dict) and data.get("format") == STATE_FORMAT else {}


_DURATION = re.compile(r"(?:(\d+(?:\.\d+)?)h)?(?:(\d+(?:\.\d+)?)m)?(?:(\d+(?:\.\d+)?)s)?")


def parse_duration(text: str, option: str = "--start-before") -> float:
    """``90m``, ``2h``, ``1h30m``, ``45s`` as seconds (above 0); an :class:`OffdynError` otherwise."""
    match = _DURATION.fullmatch(text.strip())
    if not text.strip() or match is None or not any(match.groups()):
        raise OffdynError(f"{option} {text!r}: expected a duration such as 90m, 2h, 1h30m or 45s")
    hours, minutes, seconds = (float(part) if part else 0.0 for part in match.groups())
    total = hours * 3600 + minutes * 60 + seconds
    if total <= 0:
        raise OffdynError(f"{option} {text!r}: expected a duration above 0")
    return total


def format_duration(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "?"
    if 0 < seconds < 0.5:
        return "<1s"  # some time was spent: "0s" would read as none
    seconds = round(seconds)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}h{minutes:02d}m" if hours else (f"{minutes}m{secs:02d}s" if minutes else f"{secs}s")


def _finish_time(running: list[float], waiting: list[float], capacity: int) -> float:
    """When the last run ends: the runs in flight hold their slots for the time they have left,
    and each waiting run, in order, takes the first slot to come free (as the driver starts them).
    Not the total work over the slots: two runs in flight with 1 and 3 minutes left end in 3."""
    slots = sorted(running) + [0.0] * max(0, max(1, capacity) - len(running))
    heapq.heapify(slots)
    for duration in waiting:
        heapq.heappush(slots, heapq.heappop(slots) + duration)
    return max(slots) if slots else 0.0


class _Progress:
    """Counts and ETA of the whole sweep, printed on every change and every PROGRESS_EVERY_S.

    The ETA weighs each remaining run by the mean wall time of finished runs of its kind: a run
    that trains, or one that only scores another run's policy (seconds, not the training's
    minutes; counting it as a training would put a source-only sweep's ETA hours late). Before any
    scoring run has finished, one counts what finished trainings spent in their own evaluate
    commands (the same work); before that, the mean of all finished runs. A finished
    training counts what it took over all its attempts (its own count, carried in its checkpoints)
    when that is more than the sweep saw: a run resumed from a checkpoint is not a short run.
    A running training counts its remaining steps at its own latest pace (from its learning
    curve), and before any training has finished that pace stands in for the mean. Another
    remaining training with steps done (resumed from a killed sweep) counts the part of the mean
    its remaining steps take; one that has evaluated nothing yet, the part of the mean it has not
    used since it started. The ETA is when the last of them ends with the runs laid on the
    sweep's slots as the driver starts them (:func:`_finish_time`)."""

    def __init__(self, echo: Echo | None, total: int, kinds: dict[str, str] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 progress_of: Callable[[str], TrainingProgress | None] | None = None,
                 launch_until: float | None = None) -> None:
        self.echo, self.total, self.clock = echo, total, clock
        self.launch_until = launch_until
        """``clock`` time after which no run starts (``--start-before``); None: no limit."""
        self.kinds = kinds or {}
        """Per run id, ``train`` or ``score``; a run not named trains."""
        self.progress_of = progress_of or (lambda _run_id: None)
        """Per run id, how far its training has got (:func:`baselines.run_folder.training_progress`)."""
        self.walls: dict[str, list[float]] = {"train": [], "score": []}
        self.evaluate_walls: list[float] = []
        """Per finished training, the wall time of its evaluate commands."""
        self.started: dict[str, float] = {}
        """Per run id in flight, when its current attempt started (``clock``)."""
        self.looked: dict[str, TrainingProgress | None] = {}
        """Per remaining training run, its progress when last looked at."""
        self.last_line, self.last_time = "", 0.0

    def launching(self) -> bool:
        """Whether runs may still start (``--start-before`` has not passed)."""
        return self.launch_until is None or self.clock() < self.launch_until

    def start(self, run_id: str) -> None:
        self.started[run_id] = self.clock()

    def kind(self, run_id: str) -> str:
        return self.kinds.get(run_id, "train")

    def add_wall(self, run_id: str, wall: float, evaluate_wall: float | None = None) -> None:
        if self.kind(run_id) == "train":
            if evaluate_wall:
                self.evaluate_walls.append(evaluate_wall)
            progress = self.progress_of(run_id)
            if progress is not None and progress.compute is not None and progress.compute.complete:
                wall = max(wall, progress.compute.wall_time_s)
        if wall > 0:  # a run found finished, its time measured by nobody, says nothing about the mean
            self.walls[self.kind(run_id)].append(wall)
        self.started.pop(run_id, None)
        self.looked.pop(run_id, None)

    def _look(self, run_id: str, running: bool) -> TrainingProgress | None:
        if self.kind(run_id) != "train":
            return None
        # A waiting run's folder does not change: read once. A running one is read at every line.
        if running or run_id not in self.looked:
            self.looked[run_id] = self.progress_of(run_id)
        return self.looked[run_id]

    def line(self, records: dict[str, RunRecord], capacity: int) -> str:
        return "".join(self._line_and_countdown(records, capacity))

    def _line_and_countdown(self, records: dict[str, RunRecord], capacity: int) -> tuple[str, str]:
        """The line, and apart from it the ``--start-before`` countdown (it changes every second)."""
        counts = {status: 0 for status in ("done", "running", "failed", "pending")}
        for record in records.values():
            counts[record.status] = counts.get(record.status, 0) + 1
        launching = self.launching()
        # Past --start-before the sweep ends when the runs in flight do: pending ones wait for the next.
        remaining = [run_id for run_id, record in records.items()
                     if record.status == "running" or (launching and record.status == "pending")]
        looks = {run_id: self._look(run_id, records[run_id].status == "running") for run_id in remaining}
        paces = {run_id: look.seconds_per_run for run_id, look in looks.items()
                 if records[run_id].status == "running" and look is not None and look.seconds_per_run is not None}
        walls_of = dict(self.walls)
        walls_of["train"] = self.walls["train"] or list(paces.values())
        every = [wall for walls in walls_of.values() for wall in walls]
        eta = None
        if not remaining:
            eta = 0.0
        elif every:
            def mean_wall(kind: str) -> float:
                # A kind with no finished run yet borrows: scoring, the trainings' own evaluations;
                # failing those, the mean of all finished runs.
                walls = walls_of[kind] or (self.evaluate_walls if kind == "score" else []) or every
                return sum(walls) / len(walls)

            def left(run_id: str) -> float:
                look = looks[run_id]
                fraction = look.fraction if look is not None else 0.0
                if run_id in paces:
                    return paces[run_id] * (1.0 - fraction)
                expected = mean_wall(self.kind(run_id))
                if fraction > 0:
                    return expected * (1.0 - fraction)
                if records[run_id].status == "running" and run_id in self.started:
                    # Past its kind's mean it is taken to be about done, not to take the mean again.
                    return max(0.0, expected - (self.clock() - self.started[run_id]))
                return expected

            eta = _finish_time([left(run_id) for run_id in remaining if records[run_id].status == "running"],
                               [left(run_id) for run_id in remaining if records[run_id].status != "running"],
                               capacity)
        countdown = ""
        text = (f"sweep: {counts['done']}/{self.total} done, {counts['running']} running, {counts['failed']} failed, "
                f"{counts['pending']} pending; ETA {format_duration(eta)}")
        if self.launch_until is not None and launching:
            countdown = f"; starts runs for {format_duration(self.launch_until - self.clock())} more"
        elif self.launch_until is not None:
            text += "; starts no more runs (--start-before)"
        return text, countdown

    def show(self, records: dict[str, RunRecord], capacity: int, force: bool = False) -> None:
        if self.echo is None:
            return
        text, countdown = self._line_and_countdown(records, capacity)
        now = time.monotonic()
        # A countdown alone is no change: it would print a line at every wait of the driver's loop.
        if force or text != self.last_line or now - self.last_time >= PROGRESS_EVERY_S:
            self.echo(text + countdown)
            self.last_line, self.last_time = text, now


def make_backend(name: str, spec: SweepSpec, workers: int | None) -> Backend:
    if name == "local":
        return LocalBackend(workers if workers is not None else default_workers(spec.cpus_per_run))
    if name == "ray":
        local_cpus = None if workers is None else cpus_for(workers, spec.cpus_per_run)
        return RayBackend(address=spec.ray_address, cpus_per_run=spec.cpus_per_run,
                          gpus_per_run=spec.gpus_per_run, local_cpus=local_cpus, device=spec.device)
    raise OffdynError(f"--backend {name!r}; expected local or ray")


def run_sweep(spec: SweepSpec, *, backend: str = "local", workers: int | None = None, echo: Echo | None = print,
              submit: bool = False, description: str = "", start_before: float | None = None,
              skip: Collection[str] = ()) -> SweepReport:
    """Run every run of ``spec`` that is not finished; return the report (failed runs included).

    ``start_before``: seconds after which no run (or retry) starts; the runs in flight finish and
    the rest stay pending (:attr:`SweepReport.not_started`), for a sweep that must end inside an
    allocation or a lease. Run the sweep again to continue.

    ``skip``: run ids left out altogether (``--skip-published``: those whose records are published
    already, :func:`leaderboard.coverage.reference_coverage`). A method with skipped runs gets no
    merged submission folder: its results are the published records plus this sweep's."""
    began, began_wall = time.monotonic(), time.time()
    if start_before is not None and not (math.isfinite(start_before) and start_before > 0):
        raise OffdynError(f"--start-before {start_before!r}: expected a duration above 0 seconds")
    if backend not in ("local", "ray"):
        raise OffdynError(f"--backend {backend!r}; expected local or ray")
    if workers is not None and workers < 1:
        raise OffdynError(f"--workers {workers}: expected an integer >= 1")
    if submit and skip:
        raise OffdynError("--submit assembles a method's submission from this sweep's own runs; with "
                          "--skip-published the published ones are not among them. Publish the finished runs "
                          "(offdyn-bench leaderboard publish-runs) instead, or drop --skip-published")
    everything = expand(spec)  # every refusal before anything is written
    skipped = [run for run in everything if run.run_id in skip]
    runs = [run for run in everything if run.run_id not in skip]
    _check_out(spec.out)
    conflicts = [(run, why) for run in runs if (why := settings_conflict(run)) is not None]
    if conflicts:
        shown = "; ".join(f"{run.run_id} ({why})" for run, why in conflicts[:3])
        more = f"; and {len(conflicts) - 3} more" if len(conflicts) > 3 else ""
        raise SpecError(f"{spec.out} holds {len(conflicts)} run(s) made with other settings than the spec's: "
                        f"{shown}{more}; use another out, or the settings they were made with")
    say = echo or (lambda _line: None)
    # The backend before anything is written: a Ray cluster that could never place a run is
    # refused with nothing changed. None when every run is evaluated already.
    engine: Backend | None = None
    if not all(run_finished(run) for run in runs):
        engine = make_backend(backend, spec, workers)
    try:
        with _sweep_lock(spec.out):
            state_path = spec.out / STATE_FILE
            stored = read_state(state_path).get("runs") or {}
            records = {run.run_id: RunRecord.of(run, stored.get(run.run_id)) for run in runs}
            others = {key: value for key, value in stored.items() if key not in records}
            # Who writes the state, for `sweep --status` from another shell (whether it is still
            # alive is told by the lock, not by this record).
            driver: dict[str, Any] = {
                "pid": os.getpid(), "host": socket.gethostname(), "started_at": _utc(began_wall),
                "capacity": None,
                "starts_runs_until": None if start_before is None else _utc(began_wall + start_before)}

            def save() -> None:
                write_json_atomic(state_path, {
                    "format": STATE_FORMAT, "format_version": 1, "spec": spec.to_dict(), "backend": backend,
                    "driver": driver,
                    "runs": {key: dataclasses.asdict(record) for key, record in records.items()} | others,
                })

            pending = []
            for run in runs:
                record = records[run.run_id]
                evaluation = finished_evaluation(run) if run_finished(run) else None
                if evaluation is not None:
                    record.status, record.error = "done", None
                    record.mean_return = mean_return(evaluation)
                else:
                    record.status = "pending"
                    pending.append(run)
            save()
            evaluated = len(runs) - len(pending)
            published = f", {len(skipped)} published already and skipped" if skipped else ""
            say(f"sweep: {len(runs)} runs under {spec.out} ({evaluated} already evaluated, {len(pending)} to run"
                f"{published})")

            launched = 0
            if pending:
                for dataset in official_datasets(pending):
                    from offdyn_bench.datasets.ensure import ensure_dataset

                    ensure_dataset(dataset, progress=False, echo=lambda line: say(f"dataset: {line}"))
                if engine is None:
                    engine = make_backend(backend, spec, workers)
                folder_of = {run.run_id: run.folder for run in runs}
                progress = _Progress(echo, len(runs), {
                    run.run_id: "train" if run.shared_training is None else "score" for run in runs},
                    clock=time.monotonic, progress_of=lambda run_id: training_progress(folder_of[run_id]),
                    launch_until=None if start_before is None else began + start_before)
                for run in runs:
                    if records[run.run_id].status == "done":
                        progress.add_wall(run.run_id, records[run.run_id].wall_time_s,
                                          records[run.run_id].evaluate_wall_time_s)
                tries_left = {run.run_id: 1 + spec.max_retries for run in pending}
                in_flight: dict[Any, Run] = {}
                trainer_of = {run.folder: run for run in runs if run.shared_training is None}

                def may_start(r: Run) -> bool:
                    # A run that scores another's policy waits until that run is done (then it
                    # only evaluates) or has failed for good (then so has it).
                    return r.shared_training is None or records[
                        trainer_of[r.training_folder].run_id].status in ("done", "failed")

                try:
                    while pending or in_flight:
                        capacity = driver["capacity"] = engine.capacity
                        if pending and not in_flight and not progress.launching():
                            say(f"sweep: --start-before {format_duration(start_before)} has passed; "
                                f"{len(pending)} run(s) left pending for the next sweep")
                            break
                        while pending and len(in_flight) < capacity and progress.launching():
                            # A run that scores another's policy, once it may start, goes first:
                            # seconds of scoring give a result that would otherwise wait behind
                            # every training still to start.
                            ready = next((r for r in pending if r.shared_training is not None and may_start(r)),
                                         None) or next((r for r in pending if may_start(r)), None)
                            if ready is None:
                                break
                            run = ready
                            pending.remove(run)
                            donor = trainer_of.get(run.training_folder) if run.shared_training is not None else None
                            if donor is not None and records[donor.run_id].status == "failed":
                                # Its training is the run that failed: retrying it here would repeat that.
                                record = records[run.run_id]
                                record.status = "failed"
                                record.error = f"the training it scores ({donor.run_id}) failed; see {donor.log}"
                                say(f"sweep: {run.run_id} failed: {record.error}")
                                continue
                            record = records[run.run_id]
                            record.status = "running"
                            record.attempts += 1
                            in_flight[engine.submit(run, record.attempts)] = run
                            progress.start(run.run_id)
                            launched += 1
                        save()
                        progress.show(records, capacity)
                        for handle in engine.wait(list(in_flight), timeout=min(PROGRESS_EVERY_S, 5.0)):
                            run = in_flight.pop(handle)
                            record = records[run.run_id]
                            outcome = engine.outcome(handle, run)
                            record.add(record.attempts, outcome)
                            tries_left[run.run_id] -= 1
                            if outcome.ok:
                                record.status, record.error, record.mean_return = "done", None, outcome.mean_return
                                progress.add_wall(run.run_id, record.wall_time_s, record.evaluate_wall_time_s)
                            elif tries_left[run.run_id] > 0:
                                record.status, record.error = "pending", outcome.error
                                say(f"sweep: {run.run_id} attempt {record.attempts} failed ({outcome.error}); "
                                    f"retrying ({tries_left[run.run_id]} attempt(s) left)")
                                pending.append(run)
                            else:
                                record.status, record.error = "failed", outcome.error
                                say(f"sweep: {run.run_id} failed after {record.attempts} attempt(s): {outcome.error}")
                        save()
                finally:
                    for run in in_flight.values():
                        # Interrupted: the next sweep runs it again, resuming from its checkpoints.
                        records[run.run_id].status = "pending"
                    save()
                progress.show(records, 0, force=True)

            submissions: dict[str, list[str]] = {}
            submitted: dict[str, Path] = {}
            from offdyn_bench.sweep.submission import leaderboard_blockers, write_submission_folder
            from offdyn_bench.sweep.submission import submit as submit_method

            for method in spec.methods:
                method_runs = [run for run in runs if run.method == method]
                if any(records[run.run_id].status != "done" for run in method_runs):
                    continue
                left_out = sum(run.method == method for run in skipped)
                if left_out:
                    submissions[method] = [(f"{left_out} of its runs were skipped as published (--skip-published); "
                                            "its results are the published records and this sweep's")]
                    continue
                if len({run.dataset_tag for run in method_runs}) > 1:
                    # Merging a task's runs would pool datasets; their records are published run by run.
                    submissions[method] = [(f"it trains on {len(spec.datasets)} target dataset qualities per task "
                                            f"(datasets: {', '.join(spec.datasets)}); a submission holds one")]
                    continue
                folder = write_submission_folder(spec, method, method_runs)
                merged = [json.loads(path.read_text()) for path in sorted(folder.glob("*/evaluation.json"))]
                reasons = [reason for record in merged for reason in leaderboard_blockers(spec, record)]
                submissions[method] = list(dict.fromkeys(reasons))
                if submit and not submissions[method]:
                    submitted[method] = submit_method(spec, method, description)
            return SweepReport(spec=spec, runs=runs, records=records, launched=launched, submissions=submissions,
                               submitted=submitted, state_path=state_path, start_before=start_before,
                               skipped=tuple(run.run_id for run in skipped))
    finally:
        if engine is not None:
            engine.close()


def run_table(runs: list[Run], records: dict[str, RunRecord], steps: dict[str, str] | None = None,
              evaluations: dict[str, str] | None = None) -> list[str]:
    """A line per run: status, attempts, compute over finished attempts, mean return; and with
    ``steps`` (per run id, how far its training has got) a column for it, and with ``evaluations``
    (per run id, the share of its time its evaluations took) one for that where any run has it."""
    steps_column = f" {'steps':>5s}" if steps is not None else ""
    evaluations = evaluations or None
    evaluation_column = f" {'eval':>5s}" if evaluations is not None else ""
    header = (f"{'run':58s} {'status':7s}{steps_column}{evaluation_column} {'tries':>5s} {'wall':>8s} {'cpu':>8s} "
              f"{'return':>9s}")
    lines = [header, "-" * len(header)]
    for run in runs:
        record = records[run.run_id]
        mean = f"{record.mean_return:9.1f}" if record.mean_return is not None else f"{'-':>9s}"
        step = f" {steps.get(run.run_id, '-'):>5s}" if steps is not None else ""
        step += f" {evaluations.get(run.run_id, '-'):>5s}" if evaluations is not None else ""
        lines.append(f"{run.run_id:58s} {record.status:7s}{step} {record.attempts:5d} "
                     f"{format_duration(record.wall_time_s):>8s} {format_duration(record.cpu_time_s):>8s} {mean}")
    return lines


def failure_lines(runs: list[Run], records: dict[str, RunRecord]) -> list[str]:
    """A line per failed run: its attempts, its last error and its log."""
    return [f"failed: {run.run_id} after {records[run.run_id].attempts} attempt(s): {records[run.run_id].error} "
            f"(log: {run.log})" for run in runs if records[run.run_id].status == "failed"]


def summary_lines(report: SweepReport) -> list[str]:
    """The summary table, then what to do with the results."""
    from offdyn_bench.sweep.submission import SUBMISSION_DIR, submit_command

    lines = run_table(report.runs, report.records)
    done = sum(report.records[run.run_id].status == "done" for run in report.runs)
    total_wall = sum(report.records[run.run_id].wall_time_s for run in report.runs)
    total_cpu = sum(report.records[run.run_id].cpu_time_s for run in report.runs)
    lines.append(f"{done}/{len(report.runs)} runs done, {len(report.failed)} failed; compute over all attempts: "
                 f"{format_duration(total_wall)} wall, {format_duration(total_cpu)} CPU; state: {report.state_path}")
    if report.skipped:
        lines.append(f"skipped: {len(report.skipped)} run(s) of the spec whose records are published already "
                     "(--skip-published)")
    lines += failure_lines(report.runs, report.records)
    if report.not_started:
        lines.append(f"left pending: {len(report.not_started)} run(s), not started (or not retried) as "
                     f"--start-before {format_duration(report.start_before)} had passed; run the same sweep again "
                     "to continue")
    evaluated = {run.method for run in report.runs if report.records[run.run_id].status == "done"}
    if len(evaluated) > 1:
        pattern = report.spec.out / RUNS_DIR / "*" / "*" / "*" / EVALUATION_FILE
        lines.append(f"the papers' claims on what is done: offdyn-bench protocol claims {pattern}")
    gap_methods = sorted({run.method for run in report.runs
                          if run.source_evaluate_args and report.records[run.run_id].status == "done"})
    for method in gap_methods:
        # Both sides of each task: evaluation.json (target) and evaluation-source.json.
        pattern = report.spec.out / RUNS_DIR / method / "*" / "*" / "evaluation*.json"
        lines.append(f"each task's source-target gap ({method} on both sides): offdyn-bench protocol gap {pattern}")
    if done and report.spec.budget is not None:
        # Records at a protocol budget can be published run by run, long before a submission exists.
        lines.append(f"publish the finished runs' records: offdyn-bench leaderboard publish-runs {report.spec.out}")
    for method in report.spec.methods:
        if method not in report.submissions:
            lines.append(f"{method}: not every run finished; no merged evaluations yet")
            continue
        folder = report.spec.out / SUBMISSION_DIR / method
        reasons = report.submissions[method]
        if reasons and not folder.is_dir():
            lines.append(f"{method}: not a leaderboard submission: " + "; ".join(reasons))
            continue
        if reasons:
            lines.append(f"{method}: merged evaluations in {folder}; not a leaderboard submission: "
                         + "; ".join(reasons))
            continue
        lines.append(f"{method}: submit with: {submit_command(report.spec, method)}")
        if method in report.submitted:
            lines.append(f"{method}: wrote the submission {report.submitted[method]} (validated)")
    return lines
