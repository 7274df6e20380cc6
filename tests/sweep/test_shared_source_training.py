"""RL on source trains once per source: tasks that share a source simulator score the same policy.

The premise is checked, not assumed: a sac-source run trained on one task is bit for bit the run
trained on another task with the same source, and scoring it there gives the very returns a run
of its own would.
"""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest

from offdyn_bench.errors import OffdynError
from offdyn_bench.evaluate import evaluate
from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import STATE_FILE
from offdyn_bench.sweep.runs import expand

# Both InvertedPendulum pairs have the nominal pendulum as their source.
FIRST, SECOND = "invertedpendulum-gravity-3.0", "invertedpendulum-kinematic-slider-hard"


def test_source_keys_group_tasks_by_the_simulator_they_train_in():
    from offdyn_bench.tasks import get_task

    assert get_task(FIRST).source_key == get_task(SECOND).source_key
    assert get_task("hopper-gravity-0.5").source_key == get_task("hopper-friction-0.5").source_key
    assert get_task("hopper-gravity-0.5").source_key != get_task("walker2d-gravity-2.0").source_key
    # An H2O pair's source carries its own effect: it is not the nominal robot's source.
    assert get_task("halfcheetah-h2o-gravity-2.0").source_key != get_task("halfcheetah-gravity-0.5").source_key
    assert get_task("wheellegged-standstill").source_key != get_task("wheellegged-movestraight").source_key


def test_the_core_suite_trains_rl_on_source_once_per_robot_and_seed(tmp_path, tiny_spec):
    from offdyn_bench.protocol import CORE_SUITE

    spec = parse_spec(tiny_spec(tmp_path / "out", methods=["sac-source", "sac-target"], tasks="core", seeds=5,
                                steps=None, budget="lite", overrides={}))
    runs = expand(spec)
    source_runs = [run for run in runs if run.method == "sac-source"]
    target_runs = [run for run in runs if run.method == "sac-target"]
    assert len(source_runs) == len(target_runs) == 5 * len(CORE_SUITE)
    robots = {task.split("-")[0] for task in CORE_SUITE}
    trained = {run.training_folder for run in source_runs}
    assert len(trained) == 5 * len(robots)  # Hopper, Walker2d, HalfCheetah, Ant
    assert len({run.training_folder for run in target_runs}) == 5 * len(CORE_SUITE)  # every target its own
    for run in source_runs:
        if run.shared_training is None:
            assert run.training_folder == run.folder
            continue
        donor = next(other for other in source_runs if other.folder == run.shared_training)
        assert donor.shared_training is None and donor.seeds == run.seeds
        assert donor.task.split("-")[0] == run.task.split("-")[0]
        assert run.train_args == donor.train_args and run.settings == donor.settings
        args = list(run.evaluate_args)
        assert args[args.index("--agent") + 1] == str(donor.folder)
        assert args[args.index("--task") + 1] == run.task
        assert args[args.index("--out") + 1] == str(run.folder / "evaluation.json")
    # RL on source is scored on both sides of every task (the gap); RL on target only in the target.
    for run in source_runs:
        args = list(run.source_evaluate_args)
        assert args[args.index("--agent") + 1] == str(run.training_folder)
        assert args[args.index("--task") + 1] == run.task and args[args.index("--side") + 1] == "source"
        assert args[args.index("--out") + 1] == str(run.folder / "evaluation-source.json")
    assert all(run.source_evaluate_args == () for run in target_runs)


def test_the_second_task_scores_the_first_tasks_policy_without_training(shared_source_sweep):
    first, second = shared_source_sweep.runs
    assert (first.task, second.task) == (FIRST, SECOND) and second.shared_training == first.folder
    assert not shared_source_sweep.failed
    assert (first.folder / "result.json").exists() and (first.folder / "checkpoints").is_dir()
    # Nothing was trained for the second task: its folder holds its evaluations only, both sides.
    assert sorted(p.name for p in second.folder.iterdir()) == ["evaluation-source.json", "evaluation.json"]
    log = second.log.read_text()
    assert f"scores the policy trained in {first.folder}" in log and " train " not in log
    state = json.loads((shared_source_sweep.spec.out / STATE_FILE).read_text())
    assert all(state["runs"][run.run_id]["status"] == "done" for run in shared_source_sweep.runs)
    record = json.loads((second.folder / "evaluation.json").read_text())
    assert record["task"] == SECOND and record["method"] == "sac-source"
    assert record["agent"]["trained_task"] == FIRST and record["agent"]["path"] == str(first.folder)
    # Scoring the shared policy is no departure from the protocol: only the tiny sweep's own are noted.
    assert len(record["notes"]) == 2 and all("steps" in note or "episodes" in note for note in record["notes"])


def test_the_shared_score_is_the_score_of_a_run_trained_on_the_task_itself(shared_source_sweep, tmp_path):
    """Train sac-source on the second task directly, with the same settings: the policy has the
    same bytes and its returns in the second task's target are the shared evaluation's."""
    import subprocess

    from offdyn_bench.sweep.execute import command_line

    first, second = shared_source_sweep.runs
    direct = tmp_path / "direct"
    args = list(first.train_args)
    args[args.index("--task") + 1] = SECOND
    args[args.index("--out") + 1] = str(direct)
    subprocess.run(command_line(args), check=True, capture_output=True)
    own = evaluate(direct, episodes=2, progress=False, out=tmp_path / "own.json")
    shared = json.loads((second.folder / "evaluation.json").read_text())
    assert own["task"] == shared["task"] == SECOND
    assert own["agent"]["policy_sha256"] == shared["agent"]["policy_sha256"]
    assert own["seeds"] == shared["seeds"]
    # The premise itself: the two trainings wrote the same final state and counters (the compute
    # each measured, and when each started, are measurements, not state).
    final = f"checkpoints/step_{300:09d}"
    states = [(folder / final / "state.safetensors").read_bytes() for folder in (direct, first.folder)]
    assert states[0] == states[1]
    counters = [json.loads((folder / final / "trainer.json").read_text()) for folder in (direct, first.folder)]
    assert all(c.pop("compute")["attempts"] == 1 for c in counters)
    assert all(isinstance(c.pop("started_at"), str) for c in counters) and counters[0] == counters[1]


def test_a_run_is_scored_on_another_task_only_where_its_policy_would_be_the_same(shared_source_sweep, tmp_path):
    first = shared_source_sweep.runs[0]
    with pytest.raises(OffdynError, match=r"trained on 'invertedpendulum-gravity-3.0', whose source is not "
                                          r"'hopper-gravity-0.5''s source"):
        evaluate(first.folder, "hopper-gravity-0.5", episodes=1, progress=False, out=tmp_path / "x.json")
    # A method that trains on target data or in the target is never scored on another task.
    config = json.loads((first.folder / "config.json").read_text())
    target_run = tmp_path / "as-target"
    shutil.copytree(first.folder, target_run)
    (target_run / "config.json").write_text(json.dumps(config | {"algo": "sac-target"}))
    with pytest.raises(OffdynError, match=r"only a run of a method that trains in the source alone \(sac-source\)"):
        evaluate(target_run, SECOND, episodes=1, progress=False, out=tmp_path / "y.json")
    assert not (tmp_path / "x.json").exists() and not (tmp_path / "y.json").exists()


def test_dry_run_names_the_policy_a_shared_run_scores(tmp_path, tiny_spec, write_spec):
    from typer.testing import CliRunner

    from offdyn_bench.cli import app

    spec = write_spec(tmp_path / "spec.json", tiny_spec(tmp_path / "out", tasks=[FIRST, SECOND], seeds=1))
    result = CliRunner().invoke(app, ["sweep", str(spec), "--dry-run"])
    assert result.exit_code == 0, result.output
    first = tmp_path / "out" / "runs" / "sac-source" / FIRST / "seed-0"
    assert f"sac-source/{SECOND}/seed-0 (to run, scores the policy of {first})" in result.output
    assert not (tmp_path / "out").exists()


def test_runs_scoring_a_failed_training_fail_with_it_without_retrying_it(tmp_path, tiny_spec, write_spec):
    from offdyn_bench.sweep.driver import run_sweep

    out = tmp_path / "out"
    spec = parse_spec(tiny_spec(out, tasks=[FIRST, SECOND], seeds=1, max_retries=1), source="failing")
    # The first task's folder holds something else: `train` refuses it on every attempt.
    blocked = out / "runs" / "sac-source" / FIRST / "seed-0"
    blocked.mkdir(parents=True)
    (blocked / "notes.txt").write_text("not a run")
    report = run_sweep(spec, workers=2, echo=None)
    first, second = report.runs
    assert report.records[first.run_id].status == "failed" and report.records[first.run_id].attempts == 2
    shared = report.records[second.run_id]
    assert shared.status == "failed" and shared.attempts == 0  # never launched: it would repeat the failure
    assert shared.error == f"the training it scores ({first.run_id}) failed; see {first.log}"
    assert not second.log.exists() and sorted(p.name for p in blocked.iterdir()) == ["notes.txt"]


def test_the_sweep_gives_each_tasks_source_target_gap(shared_source_sweep):
    """Both sides of both tasks come from the sweep alone, and `protocol gap` reads them: one
    source return (both tasks share the source, so the same policy scores the same there) and each
    task's own target return."""
    from offdyn_bench.protocol.gap import measure_gaps
    from offdyn_bench.sweep.driver import summary_lines

    first, second = shared_source_sweep.runs
    records = [json.loads((run.folder / name).read_text()) for run in (first, second)
               for name in ("evaluation.json", "evaluation-source.json")]
    sides = [(record["task"], record["side"]) for record in records]
    assert sides == [(FIRST, "target"), (FIRST, "source"), (SECOND, "target"), (SECOND, "source")]
    assert records[1]["seeds"] == records[3]["seeds"]  # one source simulator, one policy
    assert records[0]["seeds"] != records[2]["seeds"]  # two targets
    gaps = {gap.task: gap for gap in measure_gaps(records)}
    assert set(gaps) == {FIRST, SECOND}
    for index, task in ((0, FIRST), (2, SECOND)):
        target = [float(x) for x in records[index]["seeds"][0]["returns"]]
        source = [float(x) for x in records[index + 1]["seeds"][0]["returns"]]
        assert gaps[task].target_return == pytest.approx(sum(target) / len(target))
        assert gaps[task].source_return == pytest.approx(sum(source) / len(source))
    lines = summary_lines(shared_source_sweep)
    pattern = shared_source_sweep.spec.out / "runs" / "sac-source" / "*" / "*" / "evaluation*.json"
    assert f"each task's source-target gap (sac-source on both sides): offdyn-bench protocol gap {pattern}" in lines
    # The tiny sweep's records are at no protocol budget, so there is nothing to publish; at one there is.
    assert not any("publish-runs" in line for line in lines)
    at_budget = dataclasses.replace(shared_source_sweep, spec=dataclasses.replace(
        shared_source_sweep.spec, budget="lite", steps=None))
    out = shared_source_sweep.spec.out
    assert f"publish the finished runs' records: offdyn-bench leaderboard publish-runs {out}" in summary_lines(at_budget)


def test_a_sweep_made_before_the_source_side_adds_only_the_source_evaluations(shared_source_sweep, tmp_path):
    """A finished run missing its source-side record (a sweep of an earlier version) is not done:
    running the sweep again writes the source side and leaves the target record untouched."""
    from offdyn_bench.sweep.driver import run_sweep

    out = tmp_path / "out"
    shutil.copytree(shared_source_sweep.spec.out, out)
    spec = dataclasses.replace(shared_source_sweep.spec, out=out)
    runs = expand(spec)
    target_bytes = {run.run_id: (run.folder / "evaluation.json").read_bytes() for run in runs}
    for run in runs:
        (run.folder / "evaluation-source.json").unlink()
    report = run_sweep(spec, workers=1, echo=None)
    assert not report.failed
    for run in runs:
        assert (run.folder / "evaluation.json").read_bytes() == target_bytes[run.run_id]
        assert json.loads((run.folder / "evaluation-source.json").read_text())["side"] == "source"
        log = run.log.read_text().split("=== attempt 2 ")[-1]
        assert "the target side is evaluated already" in log and "--side source" in log
        assert " train " not in log


def test_a_run_scoring_a_finished_training_starts_before_the_next_training(tmp_path, tiny_spec, monkeypatch):
    """One worker, two seeds, two tasks: the second task's score of seed 0 (seconds) runs as soon as
    seed 0 is trained, not after seed 1's training."""
    from offdyn_bench.sweep import driver

    started: list[str] = []
    make_backend = driver.make_backend

    def recording_backend(*args, **kwargs):
        engine = make_backend(*args, **kwargs)
        submit = engine.submit

        def submit_and_record(run, attempt):
            started.append(run.run_id)
            return submit(run, attempt)

        engine.submit = submit_and_record
        return engine

    monkeypatch.setattr(driver, "make_backend", recording_backend)
    spec = parse_spec(tiny_spec(tmp_path / "out", tasks=[FIRST, SECOND], seeds=2), source="order")
    report = driver.run_sweep(spec, workers=1, echo=None)
    assert not report.failed
    assert started == [f"sac-source/{FIRST}/seed-0", f"sac-source/{SECOND}/seed-0",
                       f"sac-source/{FIRST}/seed-1", f"sac-source/{SECOND}/seed-1"]
