"""`sweep SPEC --status`: where a sweep stands, read from another shell, with nothing written.

A driver at work is one that holds the output folder's lock (the tests hold it themselves); a run
the state file marks running with no driver is one cut short, pending for the next sweep."""

from __future__ import annotations

import datetime
import json
import os
import re
import socket
from pathlib import Path

from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.sweep.driver import STATE_FILE, _sweep_lock, sweep_running

TASK = "invertedpendulum-gravity-3.0"
SEED_0, SEED_1 = f"sac-source/{TASK}/seed-0", f"sac-source/{TASK}/seed-1"
runner = CliRunner()


def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``folder`` with its size and modification time."""
    return {str(path): (path.stat().st_size, path.stat().st_mtime_ns) for path in folder.rglob("*") if path.is_file()}


def _status(spec_path: Path) -> list[str]:
    result = runner.invoke(app, ["sweep", str(spec_path), "--status"])
    assert result.exit_code == 0, result.output
    return result.output.splitlines()


def _row(lines: list[str], run_id: str) -> list[str]:
    [row] = [line for line in lines if line.startswith(run_id + " ")]
    return row.split()


def _half_trained(out: Path, run_id: str, steps_done: int, of_steps: int = 300,
                  evaluation_s: float | None = None) -> None:
    """A run folder as a training leaves it part-way: its config and a learning curve to ``steps_done``
    (with ``evaluation_s``, each line's evaluation took that long, as lines record it now)."""
    folder = out / "runs" / run_id
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"steps": of_steps}))
    evaluation = {} if evaluation_s is None else {"evaluation_wall_time_s": evaluation_s}
    (folder / "metrics.jsonl").write_text("".join(
        json.dumps({"step": step, "wall_time_s": step / 10.0, "cpu_time_s": step / 12.5} | evaluation) + "\n"
        for step in range(50, steps_done + 1, 50)))


def _state(out: Path, runs: dict[str, dict], driver: dict | None = None) -> None:
    state = {"format": "offdyn-bench/sweep-state", "format_version": 1, "backend": "local", "runs": runs}
    if driver is not None:
        state["driver"] = driver
    (out / STATE_FILE).write_text(json.dumps(state))


def _entry(status: str, attempts: int = 1, **more) -> dict:
    return {"status": status, "attempts": attempts, "history": [], **more}


def test_status_of_a_finished_sweep_reads_its_folders_and_writes_nothing(finished_sweep, tmp_path, tiny_spec,
                                                                         write_spec):
    out = finished_sweep.spec.out
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(out))
    before = _snapshot(out)
    lines = _status(spec_path)
    assert _snapshot(out) == before
    assert lines[0] == f"sweep {out}: no sweep is running on it; every run has ended"
    for run in finished_sweep.runs:
        row = _row(lines, run.run_id)
        record = finished_sweep.records[run.run_id]
        assert row[1:3] == ["done", "100%"] and re.fullmatch(r"\d+%", row[3]) and row[4] == "1"  # row[3]: eval
        assert float(row[-1]) == round(record.mean_return, 1)
    assert lines[-1] == "sweep: 2/2 done, 0 running, 0 failed, 0 pending; ETA 0s"
    # The driver that ran it recorded itself for this view.
    driver = json.loads((out / STATE_FILE).read_text())["driver"]
    assert driver["pid"] == os.getpid() and driver["host"] == socket.gethostname()
    assert driver["capacity"] == 2 and driver["starts_runs_until"] is None
    assert datetime.datetime.fromisoformat(driver["started_at"]).tzinfo is not None


def test_status_while_a_driver_runs_shows_each_trainings_steps_and_the_start_before_limit(tmp_path, tiny_spec,
                                                                                          write_spec):
    out = tmp_path / "out"
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(out))
    _half_trained(out, SEED_0, steps_done=150)
    now = datetime.datetime.now(datetime.UTC)
    until = now + datetime.timedelta(minutes=50, seconds=30)
    _state(out, {SEED_0: _entry("running"), SEED_1: _entry("pending", attempts=0)},
           driver={"pid": 4242, "host": "node-7", "started_at": now.isoformat(), "capacity": 1,
                   "starts_runs_until": until.isoformat()})
    with _sweep_lock(out):
        assert sweep_running(out)
        lines = _status(spec_path)
    assert lines[0] == (f"sweep {out}: running (pid 4242 on node-7, started {now:%Y-%m-%d %H:%M} UTC; "
                        f"starts runs until {until:%Y-%m-%d %H:%M} UTC)")
    # Its wall and CPU so far: the training's own count at its last curve line (no attempt has ended).
    assert _row(lines, SEED_0)[1:6] == ["running", "50%", "1", "15s", "12s"]
    assert _row(lines, SEED_1)[1:4] == ["pending", "-", "0"]
    # Seed 0's curve: 50 steps per 5 s, so 30 s a run; half of it left, then a whole run for seed 1.
    assert re.fullmatch(r"sweep: 0/2 done, 1 running, 0 failed, 1 pending; ETA 45s; starts runs for 50m(29|30)s more",
                        lines[-1]), lines[-1]
    assert not sweep_running(out)


def test_status_after_the_driver_was_killed_counts_its_runs_as_pending_to_resume(tmp_path, tiny_spec, write_spec):
    out = tmp_path / "out"
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(out))
    _half_trained(out, SEED_0, steps_done=100)
    _state(out, {SEED_0: _entry("running"),
                 SEED_1: _entry("failed", attempts=2, error="exit code 2: the dataset's sha256 does not match")},
           driver={"pid": 4242, "host": "node-7", "started_at": "2026-11-26T10:00:00+00:00", "capacity": 2,
                   "starts_runs_until": None})
    (out / ".sweep.lock").touch()  # left by the killed driver; nobody holds it
    lines = _status(spec_path)
    assert lines[0] == (f"sweep {out}: no sweep is running on it; 1 run(s) to go: run `offdyn-bench sweep "
                        f"{spec_path}` to continue (runs cut short resume from their checkpoints)")
    assert _row(lines, SEED_0)[1:4] == ["pending", "33%", "1"]
    assert _row(lines, SEED_1)[1:4] == ["failed", "-", "2"]
    log = out / "logs" / "sac-source" / TASK / "seed-1.log"
    assert (f"failed: {SEED_1} after 2 attempt(s): exit code 2: the dataset's sha256 does not match (log: {log})"
            in lines)
    assert lines[-1].startswith("sweep: 0/2 done, 0 running, 1 failed, 1 pending; ETA ")
    assert lines[-1].endswith(" if run again with 2 run(s) at once")


def test_status_of_a_sweep_never_run_creates_nothing(tmp_path, tiny_spec, write_spec):
    out = tmp_path / "never" / "out"
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(out))
    lines = _status(spec_path)
    assert not (tmp_path / "never").exists()
    assert lines[0].startswith(f"sweep {out}: no sweep is running on it; 2 run(s) to go")
    assert _row(lines, SEED_0)[1:4] == ["pending", "-", "0"]
    assert lines[-1] == "sweep: 0/2 done, 0 running, 0 failed, 2 pending; ETA ? if run again with 1 run(s) at once"


def test_status_refuses_options_that_would_run_or_write(tmp_path, tiny_spec, write_spec):
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(tmp_path / "out"))
    for extra in (["--dry-run"], ["--submit"], ["--start-before", "1h"]):
        result = runner.invoke(app, ["sweep", str(spec_path), "--status", *extra])
        assert result.exit_code == 2
        assert "error: --status only reads where the sweep stands" in result.output
    assert not (tmp_path / "out").exists()
    (tmp_path / "out").write_text("a file")
    result = runner.invoke(app, ["sweep", str(spec_path), "--status"])
    assert result.exit_code == 2 and result.output.startswith(f"error: out '{tmp_path / 'out'}' exists and is not "
                                                              "a folder; expected the sweep's output folder")


def test_a_damaged_state_file_is_read_as_far_as_it_holds_by_status_and_by_the_sweep(finished_sweep, tmp_path,
                                                                                      tiny_spec, write_spec):
    import shutil

    out = tmp_path / "out"
    shutil.copytree(finished_sweep.spec.out, out)
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(out))
    damaged = {"status": "running", "attempts": "three",
               "history": ["not an attempt", {"wall_time_s": "abc", "cpu_time_s": float("nan")},
                           {"wall_time_s": 12.5, "cpu_time_s": -1, "evaluate_wall_time_s": True}]}
    _state(out, {SEED_0: damaged, SEED_1: ["not", "a", "record"]},
           driver={"pid": "x", "host": 7, "started_at": "yesterday", "capacity": True, "starts_runs_until": "soon"})
    lines = _status(spec_path)
    assert lines[0] == f"sweep {out}: no sweep is running on it; every run has ended"
    # Attempts: its three history entries; times: the one valid number (12.5 s of wall).
    row = _row(lines, SEED_0)
    assert row[1:3] == ["done", "100%"] and re.fullmatch(r"\d+%", row[3]) and row[4:7] == ["3", "12s", "0s"]
    assert lines[-1] == "sweep: 2/2 done, 0 running, 0 failed, 0 pending; ETA 0s"
    # The sweep itself takes the same file, finds both runs done and writes a sound state.
    result = runner.invoke(app, ["sweep", str(spec_path), "--quiet"])
    assert result.exit_code == 0, result.output
    state = json.loads((out / STATE_FILE).read_text())
    assert {key: state["runs"][key]["status"] for key in (SEED_0, SEED_1)} == {SEED_0: "done", SEED_1: "done"}
    assert state["runs"][SEED_0]["wall_time_s"] == 12.5 and state["driver"]["pid"] == os.getpid()


def test_status_shows_the_share_of_each_trainings_time_its_evaluations_took(tmp_path, tiny_spec, write_spec):
    out = tmp_path / "out"
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(out))
    _half_trained(out, SEED_0, steps_done=150, evaluation_s=1.5)  # 3 evaluations, 4.5 s of 15 s
    _half_trained(out, SEED_1, steps_done=100)                     # a curve from before lines recorded it
    _state(out, {SEED_0: _entry("running"), SEED_1: _entry("running")})
    with _sweep_lock(out):
        lines = _status(spec_path)
    assert lines[1].split()[:5] == ["run", "status", "steps", "eval", "tries"]
    assert _row(lines, SEED_0)[1:7] == ["running", "50%", "30%", "1", "15s", "12s"]
    assert _row(lines, SEED_1)[1:5] == ["running", "33%", "-", "1"]


def test_status_has_no_eval_column_where_no_curve_records_it(tmp_path, tiny_spec, write_spec):
    out = tmp_path / "out"
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(out))
    _half_trained(out, SEED_0, steps_done=150)
    _state(out, {SEED_0: _entry("running"), SEED_1: _entry("pending", attempts=0)})
    with _sweep_lock(out):
        lines = _status(spec_path)
    assert "eval" not in lines[1].split() and _row(lines, SEED_0)[1:4] == ["running", "50%", "1"]
