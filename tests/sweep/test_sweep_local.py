"""The local backend: a tiny sweep end to end, skipping on re-run, retries of a failing run, and
runs killed mid-training (the train subprocess alone, or the whole sweep) losing nothing."""

from __future__ import annotations

import datetime
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import STATE_FILE, run_sweep, summary_lines
from offdyn_bench.sweep.runs import expand

TASK = "invertedpendulum-gravity-3.0"
runner = CliRunner()


def _state(out: Path) -> dict:
    return json.loads((out / STATE_FILE).read_text())


def test_a_tiny_sweep_trains_and_evaluates_every_run(finished_sweep):
    report = finished_sweep
    out = report.spec.out
    assert [run.run_id for run in report.runs] == [f"sac-source/{TASK}/seed-0", f"sac-source/{TASK}/seed-1"]
    state = _state(out)
    for run in report.runs:
        evaluation = json.loads((run.folder / "evaluation.json").read_text())
        assert evaluation["method"] == "sac-source" and [s["seed"] for s in evaluation["seeds"]] == list(run.seeds)
        assert len(evaluation["seeds"][0]["returns"]) == 2
        entry = state["runs"][run.run_id]
        assert entry["status"] == "done" and entry["attempts"] == 1
        assert entry["wall_time_s"] > 0 and entry["cpu_time_s"] > 0
        assert entry["history"][0]["ok"] is True and entry["history"][0]["exit_code"] is None
        # The evaluations' share of the attempt: some of it, not all (the training took the rest).
        assert 0 < entry["history"][0]["evaluate_wall_time_s"] < entry["history"][0]["wall_time_s"]
        # When it started (UTC): CPU seconds measured on different days can differ.
        started = datetime.datetime.fromisoformat(entry["history"][0]["started_at"])
        assert started.utcoffset() == datetime.timedelta(0)
        assert abs((datetime.datetime.now(datetime.UTC) - started).total_seconds()) < 3600
        assert entry["mean_return"] == pytest.approx(sum(evaluation["seeds"][0]["returns"]) / 2)
        assert (run.folder / "result.json").exists()
    assert report.launched == 2 and not report.failed
    assert state["spec"]["steps"] == 300 and state["backend"] == "local"
    # Both seeds, merged for `leaderboard submit`; a tiny sweep says why it is no submission.
    merged = json.loads((out / "submission" / "sac-source" / TASK / "evaluation.json").read_text())
    assert [s["seed"] for s in merged["seeds"]] == [0, 1]
    text = "\n".join(summary_lines(report))
    assert "2/2 runs done, 0 failed" in text and "not a leaderboard submission" in text
    assert "not at a protocol budget" in text and "not the protocol's core suite" in text
    assert "protocol claims" not in text  # one method: no claim compares anything


def test_the_summary_names_the_claims_command_once_two_methods_are_done(finished_sweep):
    import dataclasses

    report = finished_sweep
    other = dataclasses.replace(report.runs[1], method="dap")  # as if a second method had finished
    both = dataclasses.replace(report, runs=[report.runs[0], other],
                               records={report.runs[0].run_id: report.records[report.runs[0].run_id],
                                        other.run_id: report.records[report.runs[1].run_id]})
    [line] = [line for line in summary_lines(both) if "protocol claims" in line]
    assert line.endswith(f"offdyn-bench protocol claims {report.spec.out}/runs/*/*/*/evaluation.json")


def test_running_the_same_sweep_again_launches_nothing(finished_sweep, tmp_path, monkeypatch):
    import dataclasses
    import shutil

    # On a copy: the finished sweep is shared with other modules' tests, which read its state file.
    out = tmp_path / "copy"
    shutil.copytree(finished_sweep.spec.out, out)
    spec = dataclasses.replace(finished_sweep.spec, out=out)
    runs = expand(spec)
    before = {run.run_id: (run.folder / "evaluation.json").stat().st_mtime_ns for run in runs}
    logs = {run.run_id: run.log.read_text() for run in runs}

    def no_subprocess(*args, **kwargs):
        raise AssertionError(f"a subprocess was started: {args}")

    monkeypatch.setattr("offdyn_bench.sweep.execute.subprocess.Popen", no_subprocess)
    lines = []
    again = run_sweep(spec, workers=2, echo=lines.append)
    assert again.launched == 0 and not again.failed
    assert lines == [f"sweep: 2 runs under {out} (2 already evaluated, 0 to run)"]
    for run in again.runs:
        assert (run.folder / "evaluation.json").stat().st_mtime_ns == before[run.run_id]
        assert run.log.read_text() == logs[run.run_id]
        assert again.records[run.run_id].attempts == 1 and again.records[run.run_id].status == "done"


def test_dry_run_marks_finished_runs(finished_sweep, tmp_path, write_spec):
    spec = finished_sweep.spec.to_dict()
    spec_path = write_spec(tmp_path / "spec.json", {key: spec[key] for key in (
        "methods", "tasks", "seeds", "track", "steps", "out", "evaluation_episodes", "training", "overrides")})
    result = runner.invoke(app, ["sweep", str(spec_path), "--dry-run"])
    assert result.exit_code == 0, result.output
    assert f"sac-source/{TASK}/seed-0 (done)" in result.output


def test_a_failing_run_is_retried_exactly_max_retries_times_and_reported(tmp_path, tiny_spec, write_spec,
                                                                         attempt_headers):
    out = tmp_path / "out"
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(out, max_retries=2))
    # A folder that holds something else: `train` refuses it on every attempt (exit code 2).
    blocked = out / "runs" / "sac-source" / TASK / "seed-1"
    blocked.mkdir(parents=True)
    (blocked / "notes.txt").write_text("not a run")
    result = runner.invoke(app, ["sweep", str(spec_path), "--workers", "2", "--quiet"])
    assert result.exit_code == 1, result.output
    state = _state(out)
    failed = state["runs"][f"sac-source/{TASK}/seed-1"]
    assert failed["status"] == "failed" and failed["attempts"] == 3  # the first attempt and 2 retries
    assert [a["exit_code"] for a in failed["history"]] == [2, 2, 2]
    assert "is not empty and holds no training run" in failed["error"]
    log = out / "logs" / "sac-source" / TASK / "seed-1.log"
    assert attempt_headers(log) == 3 and str(log) in failed["error"]
    assert state["runs"][f"sac-source/{TASK}/seed-0"]["status"] == "done"
    assert (out / "runs" / "sac-source" / TASK / "seed-0" / "evaluation.json").exists()
    assert f"failed: sac-source/{TASK}/seed-1 after 3 attempt(s)" in result.output
    assert f"(log: {log})" in result.output and "1/2 runs done, 1 failed" in result.output
    # A method with a failed run gets no merged evaluations.
    assert "sac-source: not every run finished" in result.output and not (out / "submission").exists()


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds the train subprocess through /proc")
def test_a_train_subprocess_killed_mid_run_is_retried_and_resumes(tmp_path, tiny_spec, attempt_headers,
                                                                 train_process_of, wait_for):
    spec = parse_spec(tiny_spec(tmp_path / "out", steps=1000, seeds=2,
                                training={"eval_episodes": 1, "checkpoint_every": 100, "eval_every": 250}))
    victim = expand(spec)[0]
    outcome = {}
    sweep = threading.Thread(target=lambda: outcome.setdefault("report", run_sweep(spec, workers=2, echo=None)))
    sweep.start()
    wait_for(lambda: any((victim.folder / "checkpoints").glob("step_*")) and train_process_of(victim.folder))
    os.kill(train_process_of(victim.folder), signal.SIGKILL)
    sweep.join(timeout=300)
    report = outcome["report"]
    record = report.records[victim.run_id]
    assert record.status == "done" and record.attempts == 2
    assert record.history[0]["exit_code"] == -signal.SIGKILL and "killed by signal 9" in record.history[0]["error"]
    assert "=== resuming: " in victim.log.read_text() and attempt_headers(victim.log) == 2
    other = report.runs[1]
    assert report.records[other.run_id].status == "done" and report.records[other.run_id].attempts == 1
    assert not report.failed


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds the train subprocess through /proc")
def test_a_killed_sweep_driver_keeps_finished_runs_and_the_rerun_completes(tmp_path, tiny_spec, write_spec,
                                                                            attempt_headers, train_process_of,
                                                                            wait_for):
    spec_path = write_spec(tmp_path / "spec.json", tiny_spec(
        tmp_path / "out", steps=1000, training={"eval_episodes": 1, "checkpoint_every": 100, "eval_every": 250}))
    first, second = expand(parse_spec(json.loads(spec_path.read_text())))
    # One run at a time. Only the driver is killed: the second run's train goes on, orphaned,
    # holding its folder's lock, as when a worker machine loses the driver.
    sweep = subprocess.Popen([sys.executable, "-m", "offdyn_bench", "sweep", str(spec_path), "--workers", "1",
                              "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             start_new_session=True)
    try:
        wait_for(lambda: (first.folder / "evaluation.json").exists()
                  and any((second.folder / "checkpoints").glob("step_*")) and train_process_of(second.folder))
    finally:
        sweep.kill()
        sweep.wait()
    finished_at = (first.folder / "evaluation.json").stat().st_mtime_ns
    assert json.loads((tmp_path / "out" / STATE_FILE).read_text())["runs"][second.run_id]["status"] == "running"

    report = run_sweep(parse_spec(json.loads(spec_path.read_text())), workers=1, echo=None)
    assert report.launched == 1 and not report.failed
    assert (first.folder / "evaluation.json").stat().st_mtime_ns == finished_at
    assert report.records[first.run_id].attempts == 1 and attempt_headers(first.log) == 1
    record = report.records[second.run_id]
    # The attempt the killed driver started is counted; it has no outcome.
    assert record.status == "done" and record.attempts == 2 and [a["attempt"] for a in record.history] == [2]
    assert attempt_headers(second.log) == 2 and (second.folder / "evaluation.json").exists()
    # The re-run waited for the orphaned train (or found it finished), never failing on its lock.
    log = second.log.read_text()
    assert "=== waiting: another process is training in" in log or "holds a finished training run" in log
    assert train_process_of(second.folder) is None


def test_merged_evaluation_holds_each_runs_returns_and_curves(finished_sweep):
    from offdyn_bench.sweep.submission import SUBMISSION_DIR

    out = finished_sweep.spec.out
    runs = finished_sweep.runs
    records = [json.loads((run.folder / "evaluation.json").read_text()) for run in runs]
    merged = json.loads((out / SUBMISSION_DIR / "sac-source" / TASK / "evaluation.json").read_text())
    assert merged["seeds"] == records[0]["seeds"] + records[1]["seeds"]
    assert merged["agent"]["policy_sha256"] == {**records[0]["agent"]["policy_sha256"],
                                                **records[1]["agent"]["policy_sha256"]}
    for field in ("task", "task_version", "target_env_id", "episode_seeds", "versions", "track", "method", "steps"):
        assert merged[field] == records[0][field]
    assert merged["protocol_conformant"] is False and merged["notes"] == records[0]["notes"]
    assert merged["merged_from"] == [str(run.folder / "evaluation.json") for run in runs]
    assert merged["machines"] == [{"evaluation": r["machine"], "training": r["training_machines"]} for r in records]
    assert merged["provenance"] == [{"evaluation_source_revision": r["source_revision"],
                                     "training": r["training_provenance"]} for r in records]
    assert all(p["training"]["started_at"] <= p["training"]["finished_at"] for p in merged["provenance"])
    # One machine ran it all; the trainings ran on one torch thread (the sweep's --threads 1).
    assert all([t["cpu"] for t in m["training"]] == [m["evaluation"]["cpu"]] for m in merged["machines"])
    assert all([t["torch_threads"] for t in m["training"]] == [1] for m in merged["machines"])
    curves = [[json.loads(line) for line in (run.folder / "metrics.jsonl").read_text().splitlines()] for run in runs]
    merged_curve = [json.loads(line) for line in
                    (out / SUBMISSION_DIR / "sac-source" / TASK / "metrics.jsonl").read_text().splitlines()]
    assert [entry["step"] for entry in merged_curve] == [entry["step"] for entry in curves[0]]
    assert [entry["target_return"] for entry in merged_curve] == [
        a["target_return"] + b["target_return"] for a, b in zip(*curves)]
    # The leaderboard reads the merged record as an evaluation; a tiny sweep's is refused as no protocol result.
    from leaderboard.assemble import assemble_submission
    from leaderboard.submission import SubmissionError

    with pytest.raises(SubmissionError, match="is not a protocol result: trained for 300 steps"):
        assemble_submission(out / SUBMISSION_DIR / "sac-source", method="sac-source")


def test_evaluations_made_differently_are_not_merged(finished_sweep):
    from offdyn_bench.errors import OffdynError
    from offdyn_bench.sweep.submission import merge_evaluations

    runs = finished_sweep.runs
    records = [json.loads((run.folder / "evaluation.json").read_text()) for run in runs]
    sources = [run.folder / "evaluation.json" for run in runs]
    other = dict(records[1], versions=dict(records[1]["versions"], mujoco="3.16.0"))
    with pytest.raises(OffdynError, match=f"the evaluations of sac-source on {TASK} disagree on versions"):
        merge_evaluations([records[0], other], sources)
    with pytest.raises(OffdynError, match="hold a training seed twice"):
        merge_evaluations([records[0], records[0]], sources)


def test_a_spec_changed_under_finished_runs_is_refused_and_changes_nothing(finished_sweep, tmp_path):
    import shutil

    from offdyn_bench.sweep import SpecError

    out = tmp_path / "copy"
    shutil.copytree(finished_sweep.spec.out, out)
    state_before = (out / STATE_FILE).read_bytes()
    data = {key: value for key, value in finished_sweep.spec.to_dict().items()
            if key in ("methods", "tasks", "seeds", "track", "steps", "evaluation_episodes", "training")}
    changed = parse_spec(data | {"out": str(out), "overrides": {"sac-source": {
        "sac.hidden_sizes": [32, 32], "sac.batch_size": 16, "random_steps": 40}}})
    with pytest.raises(SpecError, match=r"holds 2 run\(s\) made with other settings than the spec's: "
                                        rf"sac-source/{TASK}/seed-0 \(differs in: config\.sac\.batch_size\)"):
        run_sweep(changed, workers=1, echo=None)
    assert (out / STATE_FILE).read_bytes() == state_before


def test_the_eta_weighs_each_remaining_run_by_the_time_runs_of_its_kind_took(run_record):
    # A source-only sweep: one training scored on three more tasks. Counting the three scoring
    # runs as trainings would say 80 minutes; they take seconds.
    from offdyn_bench.sweep.driver import RunRecord, _Progress, format_duration


    kinds = {"train-0": "train", "score-0": "score", "train-1": "train",
             "score-1": "score", "score-2": "score", "score-3": "score"}
    records = {"train-0": run_record("done"), "score-0": run_record("done"), "train-1": run_record("running"),
               "score-1": run_record("pending"), "score-2": run_record("pending"), "score-3": run_record("pending")}
    progress = _Progress(None, len(records), kinds)
    assert progress.line(records, capacity=1).endswith("ETA ?")  # nothing finished: no estimate
    progress.add_wall("train-0", 1200.0)
    # No scoring run finished yet, and no time known for the training's evaluations: each
    # borrows the mean of what did finish.
    assert progress.line(records, capacity=1).endswith("ETA 1h20m")
    # With it, each counts what the training's own evaluate commands took: the same work.
    timed = _Progress(None, len(records), kinds)
    timed.add_wall("train-0", 1200.0, evaluate_wall=8.0)
    assert timed.line(records, capacity=1).endswith(f"ETA {format_duration(1200.0 + 3 * 8.0)}")
    # A record's evaluations over its attempts; unknown where an attempt was recorded before the count.
    assert RunRecord("m", "t", [0], "f", "l", history=[{"evaluate_wall_time_s": 2.5},
                                                       {"evaluate_wall_time_s": 1.0}]).evaluate_wall_time_s == 3.5
    assert RunRecord("m", "t", [0], "f", "l", history=[{"wall_time_s": 9.0},
                                                       {"evaluate_wall_time_s": 1.0}]).evaluate_wall_time_s is None
    progress.add_wall("score-0", 6.0)
    assert progress.line(records, capacity=1) == "sweep: 2/6 done, 1 running, 0 failed, 3 pending; ETA 20m18s"
    # Two workers: the scoring runs go beside the training, which ends last (a run is not split).
    assert progress.line(records, capacity=2).endswith("ETA 20m00s")
    # A running training 15 minutes in has 5 of its 20 left; one past the mean counts as about done.
    now = [100.0]
    progress.clock = lambda: now[0]
    progress.start("train-1")
    now[0] += 900.0
    assert progress.line(records, capacity=1).endswith("ETA 5m18s")
    now[0] += 3600.0
    assert progress.line(records, capacity=1).endswith("ETA 18s")
    for run_id in ("train-1", "score-1", "score-2", "score-3"):
        records[run_id].status = "done"
    assert progress.line(records, capacity=1).endswith("ETA 0s")


def test_the_eta_counts_the_steps_a_training_has_left_and_the_whole_time_a_resumed_one_took(run_record):
    from baselines.run_folder import TrainingCompute, TrainingProgress
    from offdyn_bench.sweep.driver import _Progress, format_duration


    # done-0 was resumed: the sweep saw its last attempt (700 s); its training counted 1,600 s.
    trainings = {"done-0": TrainingProgress(1.0, 1500.0, TrainingCompute(1600.0, 1550.0, 2, True)),
                 "running": TrainingProgress(0.75, None, None), "resumed": TrainingProgress(0.5, 900.0, None),
                 "fresh": None}
    records = {"done-0": run_record("done"), "running": run_record("running"), "resumed": run_record("pending"),
               "fresh": run_record("pending")}
    progress = _Progress(None, len(records), progress_of=trainings.get)
    progress.add_wall("done-0", 700.0)
    assert progress.walls["train"] == [1600.0]
    # Left: a quarter of the running one, half of the one resumed from a checkpoint (its old pace
    # is not this machine's now: the mean counts), all of the fresh one.
    assert progress.line(records, capacity=1).endswith(f"ETA {format_duration(1600.0 * (0.25 + 0.5 + 1.0))}")
    # Read again while it runs (the waiting ones are not); with a pace, its own pace counts.
    trainings["running"] = TrainingProgress(0.9, 2000.0, None)
    trainings["resumed"] = TrainingProgress(0.0, None, None)
    assert progress.line(records, capacity=1).endswith(f"ETA {format_duration(200.0 + 1600.0 * (0.5 + 1.0))}")
    # A count from before checkpoints carried compute is partial: the sweep's own time stands.
    partial = _Progress(None, 1, progress_of=lambda _: TrainingProgress(1.0, None, TrainingCompute(300.0, 290.0, 2,
                                                                                                    False)))
    partial.add_wall("done-0", 700.0)
    found = _Progress(None, 1, progress_of=lambda _: TrainingProgress(1.0, None, None))
    found.add_wall("done-0", 0.0)  # found finished, measured by nobody
    assert partial.walls["train"] == [700.0] and found.walls["train"] == []


def test_before_any_training_finishes_the_eta_takes_the_running_ones_pace(run_record):
    from baselines.run_folder import TrainingProgress
    from offdyn_bench.sweep.driver import _Progress


    looks = {"running": TrainingProgress(0.05, None, None), "fresh": None}
    records = {"running": run_record("running"), "fresh": run_record("pending")}
    progress = _Progress(None, 2, progress_of=looks.get)
    progress.start("running")
    assert progress.line(records, capacity=1).endswith("ETA ?")  # one curve line: no pace yet
    looks["running"] = TrainingProgress(0.5, 2000.0, None)  # at its latest pace a run takes 2000 s
    # Half of one is left, and all of the other.
    assert progress.line(records, capacity=1).endswith("ETA 50m00s")
    # With two slots the other starts at once beside it and ends last: a whole run, 2000 s.
    assert progress.line(records, capacity=2).endswith("ETA 33m20s")


def test_a_datasets_sweep_trains_one_run_per_quality_and_submits_none(tmp_path, tiny_spec, monkeypatch):
    """Two qualities, one seed: two trainings, each on its own dataset, each folder naming it; the
    records are kept run by run (a merged submission would pool the datasets)."""
    monkeypatch.delenv("OFFDYN_REMOTE")  # the sweep rebuilds both datasets from their recipes
    spec = parse_spec(tiny_spec(tmp_path / "out", methods=["cql"], tasks=["hopper-gravity-0.5"], seeds=1, steps=60,
                                datasets=["random", "source-policy"],
                                training={"eval_episodes": 1, "checkpoint_every": 30},
                                overrides={"cql": {"sac.hidden_sizes": [16, 16], "sac.batch_size": 16,
                                                   "n_action_samples": 2}}), source="tiny")
    report = run_sweep(spec, workers=2, echo=None)
    slug = "offdyn/hopper-gravity-0p5"
    assert [run.run_id for run in report.runs] == ["cql/hopper-gravity-0.5/random-v0.seed-0",
                                                   "cql/hopper-gravity-0.5/source-policy-v0.seed-0"]
    for run, quality in zip(report.runs, ("random", "source-policy")):
        record = json.loads((run.folder / "evaluation.json").read_text())
        assert record["dataset"]["dataset_id"] == f"{slug}/{quality}-v0"
        assert json.loads((run.folder / "config.json").read_text())["dataset"] == f"{slug}/{quality}-v0"
    assert not (spec.out / "submission").exists()
    text = "\n".join(summary_lines(report))
    assert "cql: not a leaderboard submission: it trains on 2 target dataset qualities per task" in text


def test_the_eta_is_when_the_last_run_ends_on_the_sweeps_slots(run_record):
    from offdyn_bench.sweep.driver import _finish_time, _Progress

    # Two runs in flight with 1 and 3 minutes left end in 3 minutes, not in the 2 of their work over two slots.
    assert _finish_time([60.0, 180.0], [], capacity=2) == 180.0
    # A waiting run takes the first slot to come free: 60 + 100; the third, the next: 150 + 50.
    assert _finish_time([60.0, 150.0], [100.0, 50.0], capacity=2) == 200.0
    assert _finish_time([], [30.0, 30.0, 30.0], capacity=2) == 60.0
    assert _finish_time([], [30.0], capacity=0) == 30.0  # no slot reported: still one at a time
    assert _finish_time([], [], capacity=4) == 0.0


    records = {"a": run_record("done"), "b": run_record("running"), "c": run_record("running")}
    now = [0.0]
    progress = _Progress(None, len(records), clock=lambda: now[0])
    progress.add_wall("a", 600.0)
    progress.start("b")
    now[0] = 540.0
    progress.start("c")
    now[0] = 600.0  # b is about done, c has 9 of its 10 minutes left
    assert progress.line(records, capacity=2).endswith("ETA 9m00s")


@pytest.mark.parametrize(("seconds", "shown"), [
    (None, "?"), (float("nan"), "?"), (float("inf"), "?"),
    (0.0, "0s"), (0.3, "<1s"), (0.6, "1s"), (59.4, "59s"), (59.6, "1m00s"),
    (3599.6, "1h00m"), (7260.0, "2h01m"),
])
def test_durations_read_in_the_largest_units_and_time_spent_never_reads_as_none(seconds, shown):
    from offdyn_bench.sweep.driver import format_duration

    assert format_duration(seconds) == shown
