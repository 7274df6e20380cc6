"""``offdyn-bench sweep SPEC --status``: where a sweep stands, read from another shell while it
runs in the background (or after it stopped), without running, locking or writing anything.

The run folders say what is done (as for the driver); the state file says which runs failed and
how many attempts each took; the sweep's lock says whether a driver is still at work. A run the
state file marks ``running`` while no driver holds the lock was cut short with its driver: the
next sweep resumes it from its checkpoints, so it counts as pending here too.
"""

from __future__ import annotations

import dataclasses
import datetime
import time
from collections.abc import Collection
from typing import Any

from baselines.run_folder import TrainingProgress, training_progress
from offdyn_bench.json_values import is_integer
from offdyn_bench.sweep.driver import (
    STATE_FILE,
    RunRecord,
    _Progress,
    check_out_is_folder,
    failure_lines,
    read_state,
    run_table,
    sweep_running,
)
from offdyn_bench.sweep.runs import Run, expand, finished_evaluation, mean_return, run_finished
from offdyn_bench.sweep.spec import SweepSpec


@dataclasses.dataclass
class SweepStatus:
    """A sweep's state as read from its output folder."""

    spec: SweepSpec
    runs: list[Run]
    records: dict[str, RunRecord]
    trainings: dict[str, TrainingProgress | None]
    """Per run id, how far its training has got (None where none started, or the run only scores
    another run's policy), read once for the table and the ETA alike."""
    driving: bool
    """Whether a sweep driver holds the output folder's lock now."""
    driver: dict[str, Any]
    """What the state file records of the driver that wrote it last (pid, host, start, capacity,
    ``--start-before`` limit); {} for a state file from before drivers recorded it."""

    def count(self, status: str) -> int:
        return sum(record.status == status for record in self.records.values())

    def steps(self) -> dict[str, str]:
        """Per run id with a training under way or done, the share of its steps done (``37%``)."""
        steps = {run_id: f"{100 * progress.fraction:.0f}%" for run_id, progress in self.trainings.items()
                 if progress is not None}
        return steps | {run_id: "100%" for run_id, record in self.records.items() if record.status == "done"}

    def evaluations(self) -> dict[str, str]:
        """Per run id whose curve records it, the share of its training's wall time its evaluations
        took (``12%``): where a run's time goes, e.g. on a GPU shared by several runs."""
        return {run_id: f"{100 * progress.evaluation_share:.0f}%" for run_id, progress in self.trainings.items()
                if progress is not None and progress.evaluation_share is not None}


def read_status(spec: SweepSpec, skip: Collection[str] = ()) -> SweepStatus:
    """Read the sweep of ``spec`` from its output folder (an empty one: every run pending), leaving
    out the runs ``skip`` names (``--skip-published``, as the sweep itself does)."""
    runs = [run for run in expand(spec) if run.run_id not in skip]
    check_out_is_folder(spec.out)
    state = read_state(spec.out / STATE_FILE)
    stored = state.get("runs") if isinstance(state.get("runs"), dict) else {}
    driver = state.get("driver") if isinstance(state.get("driver"), dict) else {}
    driving = sweep_running(spec.out)
    records: dict[str, RunRecord] = {}
    trainings: dict[str, TrainingProgress | None] = {}
    for run in runs:
        entry = stored.get(run.run_id)
        record = RunRecord.of(run, entry)
        said = entry.get("status") if isinstance(entry, dict) else None
        if run_finished(run):
            record.status = "done"
            evaluation = finished_evaluation(run)
            record.mean_return = mean_return(evaluation) if evaluation is not None else None
        elif said == "failed":
            record.status = "failed"
            record.error = entry.get("error") if isinstance(entry.get("error"), str) else None
        elif said == "running" and driving:
            record.status = "running"
        else:
            record.status = "pending"
        records[run.run_id] = record
        progress = trainings[run.run_id] = training_progress(run.folder) if run.shared_training is None else None
        if (record.status != "done" and progress is not None and progress.spent is not None
                and progress.spent[0] > record.wall_time_s):
            # The state file counts finished attempts; a training under way, its own count so far.
            record.wall_time_s, record.cpu_time_s = progress.spent
    return SweepStatus(spec, runs, records, trainings, driving, driver)


def _moment(text: Any) -> datetime.datetime | None:
    try:
        moment = datetime.datetime.fromisoformat(text)
    except (TypeError, ValueError):
        return None
    return moment if moment.tzinfo is not None else None


def status_lines(status: SweepStatus, spec_path: str = "SPEC") -> list[str]:
    """Who is running the sweep, a line per run, its failures and the progress line with an ETA."""
    out, driver = status.spec.out, status.driver
    started, until = _moment(driver.get("started_at")), _moment(driver.get("starts_runs_until"))
    stored_capacity = driver.get("capacity")
    capacity = stored_capacity if is_integer(stored_capacity) and stored_capacity > 0 else None
    left = status.count("pending") + status.count("running")
    if status.driving:
        who = (f"pid {driver['pid']} on {driver['host']}" if isinstance(driver.get("pid"), int)
               and isinstance(driver.get("host"), str) else "a driver")
        since = f", started {started:%Y-%m-%d %H:%M} UTC" if started is not None else ""
        limit = ""
        if until is not None:
            limit = (f"; starts runs until {until:%Y-%m-%d %H:%M} UTC" if until.timestamp() > time.time()
                     else "; starts no more runs (--start-before has passed)")
        head = f"sweep {out}: running ({who}{since}{limit})"
    elif left:
        head = (f"sweep {out}: no sweep is running on it; {left} run(s) to go: run `offdyn-bench sweep "
                f"{spec_path}` to continue (runs cut short resume from their checkpoints)")
    else:
        head = f"sweep {out}: no sweep is running on it; every run has ended"
    lines = [head, *run_table(status.runs, status.records, status.steps(), status.evaluations()),
             *failure_lines(status.runs, status.records)]
    progress = _Progress(None, len(status.runs), {
        run.run_id: "train" if run.shared_training is None else "score" for run in status.runs},
        clock=time.time, progress_of=status.trainings.get,
        launch_until=until.timestamp() if status.driving and until is not None else None)
    for run in status.runs:
        record = status.records[run.run_id]
        if record.status == "done":
            progress.add_wall(run.run_id, record.wall_time_s, record.evaluate_wall_time_s)
    # The ETA at the driver's own pace; for a stopped sweep, at the pace it last ran (or one at a time).
    line = progress.line(status.records, capacity or max(1, status.count("running")))
    if not status.driving and left:
        line += f" if run again with {capacity or 1} run(s) at once"
    return [*lines, line]
