"""``sweep --start-before``: a sweep that must end inside an allocation starts nothing after the
limit, lets the runs in flight finish, leaves the rest pending, and the next sweep continues."""

from __future__ import annotations

import json
import time

import pytest
from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError
from offdyn_bench.sweep import driver, parse_spec
from offdyn_bench.sweep.backends import LocalBackend
from offdyn_bench.sweep.driver import STATE_FILE, parse_duration, run_sweep, summary_lines

runner = CliRunner()


class _ClockThatJumps:
    """The driver's ``time``, with ``monotonic`` 10 hours ahead once ``jump`` is called."""

    def __init__(self) -> None:
        self.offset = 0.0

    def jump(self) -> None:
        self.offset = 10 * 3600.0

    def monotonic(self) -> float:
        return time.monotonic() + self.offset

    def __getattr__(self, name: str):
        return getattr(time, name)


def test_runs_in_flight_at_the_limit_finish_and_the_rest_wait_for_the_next_sweep(tmp_path, tiny_spec, monkeypatch):
    spec = parse_spec(tiny_spec(tmp_path / "out"), source="tiny")
    clock = _ClockThatJumps()
    monkeypatch.setattr(driver, "time", clock)
    submit = LocalBackend.submit

    def submit_then_pass_the_limit(self, run, attempt):
        handle = submit(self, run, attempt)
        clock.jump()  # the limit passes while the first run trains
        return handle

    monkeypatch.setattr(LocalBackend, "submit", submit_then_pass_the_limit)
    lines: list[str] = []
    report = run_sweep(spec, workers=1, echo=lines.append, start_before=3600.0)
    first, second = report.runs
    assert report.launched == 1 and not report.failed
    assert report.records[first.run_id].status == "done" and (first.folder / "evaluation.json").is_file()
    assert report.not_started == [second] and not second.folder.exists()
    state = json.loads((spec.out / STATE_FILE).read_text())
    assert state["runs"][second.run_id]["status"] == "pending" and state["runs"][second.run_id]["attempts"] == 0
    assert any("--start-before 1h00m has passed; 1 run(s) left pending for the next sweep" in line for line in lines)
    assert any(line.endswith("; starts no more runs (--start-before)") for line in lines)
    assert ("left pending: 1 run(s), not started (or not retried) as --start-before 1h00m had passed; run the "
            "same sweep again to continue" in summary_lines(report))

    monkeypatch.setattr(LocalBackend, "submit", submit)
    again = run_sweep(spec, workers=1, echo=None)  # no limit now: it finishes the rest, and only the rest
    assert again.launched == 1 and not again.not_started
    assert all(record.status == "done" for record in again.records.values())
    assert again.records[first.run_id].attempts == 1


def test_an_attempt_that_fails_after_the_limit_is_not_retried(tmp_path, tiny_spec, monkeypatch):
    spec = parse_spec(tiny_spec(tmp_path / "out", seeds=1, max_retries=2), source="tiny")
    blocked = spec.out / "runs" / "sac-source" / "invertedpendulum-gravity-3.0" / "seed-0"
    blocked.mkdir(parents=True)
    (blocked / "notes.txt").write_text("not a run")  # `train` refuses this folder on every attempt
    clock = _ClockThatJumps()
    monkeypatch.setattr(driver, "time", clock)
    submit = LocalBackend.submit
    monkeypatch.setattr(LocalBackend, "submit", lambda self, run, attempt: (submit(self, run, attempt), clock.jump())[0])
    report = run_sweep(spec, workers=1, echo=None, start_before=60.0)
    (run,) = report.runs
    record = report.records[run.run_id]
    assert report.launched == 1 and record.attempts == 1 and record.status == "pending"
    assert "is not empty and holds no training run" in record.error  # kept for the next sweep to show
    assert report.not_started == [run] and not report.failed


class _ClockThatRaces(_ClockThatJumps):
    """The driver's ``time``, an hour later at every reading."""

    def monotonic(self) -> float:
        self.offset += 3600.0
        return time.monotonic() + self.offset


def test_the_command_exits_3_when_runs_were_left_and_refuses_a_bad_duration(tmp_path, tiny_spec, write_spec,
                                                                             monkeypatch):
    path = write_spec(tmp_path / "spec.json", tiny_spec(tmp_path / "out"))
    refused = runner.invoke(app, ["sweep", str(path), "--start-before", "ten minutes", "--quiet"])
    assert refused.exit_code == 2
    assert refused.output.strip() == ("error: --start-before 'ten minutes': expected a duration such as 90m, 2h, "
                                      "1h30m or 45s")
    assert not (tmp_path / "out").exists()
    # Half an hour has passed before the first run could start: nothing starts, both wait.
    monkeypatch.setattr(driver, "time", _ClockThatRaces())
    result = runner.invoke(app, ["sweep", str(path), "--start-before", "30m", "--quiet"])
    assert result.exit_code == 3, result.output
    assert "0/2 runs done, 0 failed" in result.output and "left pending: 2 run(s)" in result.output
    state = json.loads((tmp_path / "out" / STATE_FILE).read_text())
    assert {entry["status"] for entry in state["runs"].values()} == {"pending"}


@pytest.mark.parametrize(("text", "seconds"), [("90m", 5400), ("2h", 7200), ("1h30m", 5400), ("45s", 45),
                                               ("1.5h", 5400), ("1h0m30s", 3630)])
def test_durations_read_as_seconds(text, seconds):
    assert parse_duration(text) == seconds


@pytest.mark.parametrize(("text", "expected"), [("", "such as 90m"), ("10", "such as 90m"), ("-5m", "such as 90m"),
                                                ("1m2h", "such as 90m"), ("0h", "above 0"), ("h", "such as 90m")])
def test_a_duration_that_is_not_one_is_refused(text, expected):
    with pytest.raises(OffdynError, match=f"--start-before '{text}': expected a duration {expected}"):
        parse_duration(text)


def test_past_the_limit_the_eta_counts_only_the_runs_in_flight(run_record):
    from offdyn_bench.sweep.driver import _Progress


    records = {"a": run_record("done"), "b": run_record("running"), "c": run_record("pending"), "d": run_record("pending")}
    now = [0.0]
    progress = _Progress(None, len(records), clock=lambda: now[0], launch_until=3600.0)
    progress.add_wall("a", 1200.0)
    progress.start("b")
    now[0] = 300.0  # b has 15 of its 20 minutes left; c and d would start: 55 minutes on one worker
    assert progress.line(records, capacity=1) == ("sweep: 1/4 done, 1 running, 0 failed, 2 pending; ETA 55m00s; "
                                                  "starts runs for 55m00s more")
    now[0] = 3900.0  # past the limit: the sweep ends when b does, c and d left for the next sweep
    assert progress.line(records, capacity=1) == ("sweep: 1/4 done, 1 running, 0 failed, 2 pending; ETA 0s; "
                                                  "starts no more runs (--start-before)")


def test_the_countdown_alone_prints_no_new_progress_line(run_record):
    """The progress line is printed on a change (or every 30 s); the seconds left to start runs
    change at every wait of the driver's loop and would otherwise print a line each time."""
    from offdyn_bench.sweep.driver import _Progress


    records = {"a": run_record("running"), "b": run_record("pending")}
    now = [0.0]
    lines: list[str] = []
    progress = _Progress(lines.append, len(records), clock=lambda: now[0], launch_until=3600.0)
    progress.start("a")
    for second in (1.0, 6.0, 11.0):  # the driver's loop waits 5 s between looks
        now[0] = second
        progress.show(records, capacity=1)
    assert lines == ["sweep: 0/2 done, 1 running, 0 failed, 1 pending; ETA ?; starts runs for 59m59s more"]
    records["a"].status = "done"
    progress.add_wall("a", 600.0)
    now[0] = 16.0
    progress.show(records, capacity=1)  # a real change prints, with the countdown as it stands
    now[0] = 3700.0
    progress.show(records, capacity=1)  # so does passing the limit
    assert lines[1:] == ["sweep: 1/2 done, 0 running, 0 failed, 1 pending; ETA 10m00s; starts runs for 59m44s more",
                         "sweep: 1/2 done, 0 running, 0 failed, 1 pending; ETA 0s; starts no more runs (--start-before)"]
