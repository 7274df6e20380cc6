"""One attempt at one run, as a worker executes it (in a thread of the local pool or a Ray task):
``offdyn-bench train`` then ``offdyn-bench evaluate`` (for RL on source, on both sides of the
task), each in a subprocess.

Subprocesses keep a crash, a kill or a leak of one run out of the sweep, and they are the very
commands a person would type. A run folder that already holds ``result.json`` is only evaluated
(``train`` refuses a finished folder); one with checkpoints resumes from them (``train`` does it).
Both commands append to the run's log, under a header naming the attempt. A folder another process
is still training in (a ``train`` orphaned by a killed worker) is waited for, not failed on.
"""

from __future__ import annotations

import dataclasses
import fcntl
import os
import shlex
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from baselines.run_folder import LOCK_FILE, LOCK_HELD_ERRNOS
from offdyn_bench.sweep.runs import (
    RESULT_FILE,
    Run,
    evaluation_path,
    finished_evaluation,
    mean_return,
    settings_conflict,
)
from offdyn_bench.versions import utc_now


@dataclasses.dataclass(frozen=True)
class AttemptOutcome:
    """What one attempt did, as the state file records it."""

    ok: bool
    stage: str
    """The last stage reached: ``train``, ``evaluate`` or ``check`` (the written evaluation)."""
    exit_code: int | None
    """Of the failing command (negative: killed by that signal); None when no command failed."""
    error: str | None
    wall_time_s: float
    cpu_time_s: float
    """User plus system CPU time of the attempt's subprocesses."""
    host: str
    mean_return: float | None = None
    """Mean target return over the evaluated seeds and episodes (when ``ok``)."""
    evaluate_wall_time_s: float = 0.0
    """The part of ``wall_time_s`` its evaluate commands took: what a run that only scores a
    policy costs, which the sweep's ETA needs before any such run has finished."""
    cuda_visible_devices: str | None = None
    """The worker's ``CUDA_VISIBLE_DEVICES`` (None: unset), which its commands inherit: on the Ray
    backend with ``gpus_per_run`` > 0, the GPUs Ray assigned this attempt."""
    started_at: str | None = None
    """When the attempt started (UTC): CPU seconds measured on different days can differ (PROTOCOL §8)."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def command_line(args: tuple[str, ...] | list[str]) -> list[str]:
    """The full command of ``offdyn-bench <args>``: this interpreter running the package, so a
    worker uses the environment it was started in, with or without the console script on PATH."""
    return [sys.executable, "-m", "offdyn_bench", *args]


def execute_run(run: Run, attempt: int) -> AttemptOutcome:
    """Train (unless finished) and evaluate ``run``; never raises for a failing command."""
    host = socket.gethostname()
    gpus = os.environ.get("CUDA_VISIBLE_DEVICES")
    started_at = utc_now()
    started = time.monotonic()
    cpu = 0.0
    evaluating = 0.0
    run.log.parent.mkdir(parents=True, exist_ok=True)
    with open(run.log, "a", buffering=1) as log:
        log.write(f"=== attempt {attempt} of {run.run_id} on {host}, {time.strftime('%Y-%m-%d %H:%M:%S')}"
                  + (f", CUDA_VISIBLE_DEVICES={gpus}" if gpus is not None else "") + "\n")

        def outcome(ok: bool, stage: str, exit_code: int | None = None, error: str | None = None,
                    mean_return: float | None = None) -> AttemptOutcome:
            result = AttemptOutcome(ok=ok, stage=stage, exit_code=exit_code, error=error,
                                    wall_time_s=round(time.monotonic() - started, 3), cpu_time_s=round(cpu, 3),
                                    host=host, mean_return=mean_return, evaluate_wall_time_s=round(evaluating, 3),
                                    cuda_visible_devices=gpus, started_at=started_at)
            log.write(f"=== attempt {attempt}: {'done' if ok else 'failed at ' + stage}"
                      + (f" ({error})" if error else "") + "\n")
            return result

        trained_in = run.training_folder
        if run.shared_training is not None:
            log.write(f"=== {run.run_id} scores the policy trained in {trained_in} (same method, seeds and source)\n")
        _wait_for_other_trainer(trained_in, log)
        if (trained_in / RESULT_FILE).exists():
            mismatch = _finished_run_mismatch(run)
            if mismatch is not None:
                return outcome(False, "train", error=mismatch)
            log.write(f"=== {trained_in} holds a finished training run (result.json): evaluating it\n")
        else:
            checkpoints = sorted((trained_in / "checkpoints").glob("step_*")) if trained_in.is_dir() else []
            if checkpoints:
                log.write(f"=== resuming: {trained_in} holds checkpoints up to {checkpoints[-1].name}\n")
            code, used = _run_logged(command_line(run.train_args), log)
            cpu += used
            if code != 0:
                return outcome(False, "train", code, _exit_text("train", code, run.log))
        sides = [("target", run.evaluate_args)] + ([("source", run.source_evaluate_args)]
                                                   if run.source_evaluate_args else [])
        for side, args in sides:
            if finished_evaluation(run, side) is not None:
                # An earlier attempt (or a sweep before the source side was owed) wrote it.
                log.write(f"=== the {side} side is evaluated already: {evaluation_path(run, side)}\n")
                continue
            evaluation_started = time.monotonic()
            code, used = _run_logged(command_line(args), log)
            cpu += used
            evaluating += time.monotonic() - evaluation_started
            if code != 0:
                return outcome(False, "evaluate", code, _exit_text("evaluate", code, run.log))
            if finished_evaluation(run, side) is None:
                return outcome(False, "check", error=f"{evaluation_path(run, side)} does not hold the expected "
                                                     f"{run.evaluation_episodes} episodes of seeds {list(run.seeds)}")
        record = finished_evaluation(run)
        if record is None:  # removed or replaced while the source side ran
            return outcome(False, "check", error=f"{evaluation_path(run, 'target')} changed during the attempt")
        return outcome(True, "check", mean_return=mean_return(record))


def _wait_for_other_trainer(folder: Path, log: Any) -> None:
    """Wait while another process trains in ``folder`` (it holds the folder's lock): a train
    left running by a killed worker or a killed sweep driver. It finishes the run (or dies), and
    this attempt then evaluates (or resumes) it, instead of failing on the lock every retry."""
    try:
        fd = os.open(folder / LOCK_FILE, os.O_RDWR)
    except OSError:
        return  # no lock file: nobody has trained here yet
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            if error.errno not in LOCK_HELD_ERRNOS:
                return
            log.write(f"=== waiting: another process is training in {folder} (its {LOCK_FILE} is locked)\n")
            log.flush()
            fcntl.flock(fd, fcntl.LOCK_EX)
            log.write("=== the other process has let go of the folder\n")
    finally:
        os.close(fd)  # releases the lock for the train command


def _run_logged(command: list[str], log: Any) -> tuple[int, float]:
    """Run ``command`` with its output appended to ``log``; (exit code, CPU seconds it used)."""
    log.write(f"$ {shlex.join(command)}\n")
    log.flush()
    process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    # wait4 reports this child's own resource use, exact even while other threads run other children.
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    return process.returncode, usage.ru_utime + usage.ru_stime


def _exit_text(stage: str, code: int, log: Path) -> str:
    if code < 0:
        return f"{stage} was killed by signal {-code}; see {log}"
    return f"{stage} exited with code {code}: {_last_error_line(log)}; see {log}"


def _last_error_line(log: Path) -> str:
    """The command's own last ``error: ...`` line, else its last output line."""
    try:
        lines = [line.strip() for line in log.read_text(errors="replace").splitlines()
                 if line.strip() and not line.startswith("$ ") and not line.startswith("===")]
    except OSError:
        return "no output"
    errors = [line for line in lines if line.startswith("error:")]
    text = (errors or lines or ["no output"])[-1]
    return text if len(text) <= 300 else text[:297] + "..."


def _finished_run_mismatch(run: Run) -> str | None:
    """Why the finished run in ``run.training_folder`` is not this run, or None."""
    conflict = settings_conflict(run)
    if conflict is None:
        return None
    return f"{run.training_folder} holds a finished run with other settings ({conflict}); move it away or change out"
