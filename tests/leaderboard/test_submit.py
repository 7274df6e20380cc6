"""``leaderboard submit``: a submission from the evaluation.json files of a runs folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from leaderboard.assemble import assemble_submission
from leaderboard.cli import leaderboard_app
from leaderboard.submission import SubmissionError, read_submission_file

SUITE = ("hopper-gravity-0.5", "walker2d-gravity-2.0", "ant-gravity-0.1")


def _submit(*args: str):
    return CliRunner().invoke(leaderboard_app, ["submit", *args])


def test_submit_round_trip(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs")
    out = tmp_path / "dap.json"
    result = _submit(str(tmp_path / "runs"), "--method", "my-dap", "--description", "DAP, lite budget",
                     "--code-url", "https://example.org/dap", "--commit", "abcdef1", "--track", "offline-target",
                     "--budget", "lite", "--out", str(out))
    assert result.exit_code == 0, result.output
    assert "3 tasks x 3 seeds" in result.output
    submission = read_submission_file(out)
    assert submission.key == ("my-dap", "offline-target", "lite")
    assert submission.code_url == "https://example.org/dap" and submission.commit == "abcdef1"
    assert submission.tasks["walker2d-gravity-2.0"].returns.mean(axis=1).tolist() == [50.0, 90.0, 130.0]
    # The learning curve comes from metrics.jsonl next to each evaluation.json.
    curve = submission.tasks["hopper-gravity-0.5"].learning_curve
    assert [p.step for p in curve] == [500, 1000]
    assert curve[1].target_return == (10.0, 20.0, 30.0)
    assert submission.document["tasks"]["hopper-gravity-0.5"]["policy_sha256"] == "ab" * 32
    # Submitting again does not overwrite the file silently.
    before = out.read_bytes()
    result = _submit(str(tmp_path / "runs"), "--method", "other", "--out", str(out))
    assert result.exit_code == 2 and "exists; pass --force" in result.output
    assert out.read_bytes() == before


def test_no_learning_curves(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs")
    submission = assemble_submission(tmp_path / "runs", method="dap", learning_curves=False)
    assert all(not r.learning_curve for r in submission.tasks.values())
    assert "learning_curve" not in submission.document["tasks"]["hopper-gravity-0.5"]


def _fails(runs: Path, *fragments: str, **options) -> None:
    with pytest.raises(SubmissionError) as caught:
        assemble_submission(runs, method=options.pop("method", "dap"), **options)
    for fragment in fragments:
        assert fragment in str(caught.value), str(caught.value)


def test_missing_task(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs", SUITE[:2])
    _fails(tmp_path / "runs", "no evaluation of ant-gravity-0.1", "2 of 3 core-suite tasks")


def test_unknown_task(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs")
    other = tmp_path / "runs" / "dap" / "hopper-gravity-0.5"
    moved = tmp_path / "runs" / "dap" / "extra"
    moved.mkdir()
    document = json.loads((other / "evaluation.json").read_text())
    document["task"] = "hopper-friction-0.1"
    (moved / "evaluation.json").write_text(json.dumps(document))
    _fails(tmp_path / "runs", "evaluates hopper-friction-0.1, which is not in the core suite")


def test_tasks_screened_beside_the_core_suite_are_left_out_only_when_asked(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs")
    whole = assemble_submission(tmp_path / "runs", method="dap").document
    screened = tmp_path / "runs" / "dap" / "screened"
    screened.mkdir()
    document = json.loads((tmp_path / "runs" / "dap" / "hopper-gravity-0.5" / "evaluation.json").read_text())
    (screened / "evaluation.json").write_text(json.dumps(document | {"task": "hopper-friction-0.1"}))
    _fails(tmp_path / "runs", "evaluates hopper-friction-0.1, which is not in the core suite",
           "pass --core-suite-only to leave out the tasks evaluated beside it")
    # Left out, the submission is exactly the one without the screened task, and the command says so.
    assert assemble_submission(tmp_path / "runs", method="dap", core_suite_only=True).document == whole
    out = tmp_path / "dap.json"
    result = _submit(str(tmp_path / "runs"), "--method", "dap", "--core-suite-only", "--out", str(out))
    assert result.exit_code == 0, result.output
    assert "left out hopper-friction-0.1 (1 evaluation(s)): not in the core suite" in result.output
    assert read_submission_file(out).document == whole
    # A name that is no task at all is an error even then: it is never quietly dropped.
    (screened / "evaluation.json").write_text(json.dumps(document | {"task": "hopper-friction-0.11"}))
    _fails(tmp_path / "runs", "evaluates hopper-friction-0.11, which is not in the core suite", core_suite_only=True)
    shutil.rmtree(tmp_path / "runs" / "dap")
    (tmp_path / "runs" / "dap").mkdir(parents=True)
    (tmp_path / "runs" / "dap" / "evaluation.json").write_text(json.dumps(document | {"task": "hopper-friction-0.1"}))
    _fails(tmp_path / "runs", "no evaluation of a core-suite task under", "(only of hopper-friction-0.1)",
           core_suite_only=True)


def test_duplicate_task(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs")
    copy = tmp_path / "runs" / "again"
    copy.mkdir()
    (copy / "evaluation.json").write_text((tmp_path / "runs" / "dap" / "ant-gravity-0.1" / "evaluation.json")
                                          .read_text())
    _fails(tmp_path / "runs", "two evaluations of ant-gravity-0.1", "keep one per task")


@pytest.mark.parametrize("field, value", [("track", "online-target"), ("budget", "full"),
                                          ("protocol_version", "0.9"), ("method", "h2o")])
def test_mixed_evaluations(tmp_path: Path, write_runs, field: str, value: str) -> None:
    write_runs(tmp_path / "runs")
    path = tmp_path / "runs" / "dap" / "ant-gravity-0.1" / "evaluation.json"
    document = json.loads(path.read_text())
    document[field] = value
    path.write_text(json.dumps(document))
    _fails(tmp_path / "runs", f"the evaluations disagree on {field}", repr(value))


def test_mixed_versions(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs", SUITE[:2])
    write_runs(tmp_path / "runs", SUITE[2:], versions={"offdyn_bench": "0.1.0", "mujoco": "3.17.0",
                                                       "torch": "2.12.0", "gymnasium": "1.4.0"})
    _fails(tmp_path / "runs", "the evaluations disagree on versions", "'torch': '2.12.0'")


def test_track_option_must_match(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs")
    _fails(tmp_path / "runs", "--track online-target but the evaluations", track="online-target")


def test_no_evaluations_and_bad_files(tmp_path: Path, write_runs) -> None:
    (tmp_path / "empty").mkdir()
    _fails(tmp_path / "empty", "no evaluation.json under", "offdyn-bench evaluate")
    _fails(tmp_path / "nowhere", "does not exist")
    write_runs(tmp_path / "runs")
    path = tmp_path / "runs" / "dap" / "ant-gravity-0.1" / "evaluation.json"
    path.write_text('{"format": "something-else"}')
    _fails(tmp_path / "runs", "not an offdyn-bench evaluation")
    path.write_text('{"format": "offdyn-bench/evaluation", "format_version": 1, "seeds": [NaN]}')
    _fails(tmp_path / "runs", "NaN is not valid JSON")


def test_bad_method_name_and_bad_curve(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs")
    _fails(tmp_path / "runs", "$.method.name", method="../escape")
    metrics = tmp_path / "runs" / "dap" / "hopper-gravity-0.5" / "metrics.jsonl"
    metrics.write_text(json.dumps({"step": 10, "target_return": [1.0]}) + "\n")
    _fails(tmp_path / "runs", "target_return has 1 per-seed values", "--no-learning-curves")


def test_cli_error_is_one_line_with_exit_code_2(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs", SUITE[:1])
    out = tmp_path / "s.json"
    result = _submit(str(tmp_path / "runs"), "--method", "dap", "--out", str(out))
    assert result.exit_code == 2
    assert result.output.startswith("error: no evaluation of walker2d-gravity-2.0, ant-gravity-0.1")
    assert result.output.count("\n") == 1
    assert not out.exists()


def _split_per_seed(runs: Path) -> Path:
    """The runs of ``write_runs`` as a sweep keeps them: one folder, evaluation and curve per training seed."""
    per_seed = runs.parent / "per-seed"
    for path in sorted(runs.rglob("evaluation.json")):
        record = json.loads(path.read_text())
        curve = [json.loads(line) for line in (path.parent / "metrics.jsonl").read_text().splitlines()]
        for index, seed in enumerate(record["seeds"]):
            folder = per_seed / record["method"] / record["task"] / f"seed-{seed['seed']}"
            folder.mkdir(parents=True)
            part = record | {"seeds": [seed], "agent": record["agent"] | {"policy_sha256": {str(seed["seed"]): "cd" * 32}}}
            (folder / "evaluation.json").write_text(json.dumps(part))
            (folder / "metrics.jsonl").write_text("".join(
                json.dumps(line | {"target_return": [line["target_return"][index]]}) + "\n" for line in curve))
    return per_seed


def test_a_sweeps_per_seed_runs_merge_into_the_submission_of_one_folder(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs")
    per_seed = _split_per_seed(tmp_path / "runs")
    whole = assemble_submission(tmp_path / "runs", method="dap")
    _fails(per_seed, "two evaluations of ant-gravity-0.1", "pass --merge-seeds")
    merged = assemble_submission(per_seed, method="dap", merge_seeds=True)
    for task, result in whole.tasks.items():
        assert merged.tasks[task].returns.tolist() == result.returns.tolist(), task
        assert merged.tasks[task].learning_curve == result.learning_curve, task
        assert merged.document["tasks"][task]["policy_sha256"] == {str(s): "cd" * 32 for s in range(3)}
    # The command line, with a curve missing for one seed: that task is submitted without a curve.
    (per_seed / "dap" / "walker2d-gravity-2.0" / "seed-1" / "metrics.jsonl").unlink()
    out = tmp_path / "dap.json"
    result = _submit(str(per_seed), "--method", "dap", "--merge-seeds", "--out", str(out))
    assert result.exit_code == 0, result.output
    assert "3 tasks x 3 seeds" in result.output
    submission = read_submission_file(out)
    assert not submission.tasks["walker2d-gravity-2.0"].learning_curve
    assert submission.tasks["hopper-gravity-0.5"].learning_curve == whole.tasks["hopper-gravity-0.5"].learning_curve


def test_per_seed_runs_that_do_not_belong_together_are_refused(tmp_path: Path, write_runs) -> None:
    write_runs(tmp_path / "runs")
    per_seed = _split_per_seed(tmp_path / "runs")
    twice = per_seed / "dap" / "ant-gravity-0.1" / "again"
    twice.mkdir()
    (twice / "evaluation.json").write_text((per_seed / "dap" / "ant-gravity-0.1" / "seed-2" / "evaluation.json")
                                           .read_text())
    _fails(per_seed, "hold a training seed twice", merge_seeds=True)
    shutil.rmtree(twice)
    path = per_seed / "dap" / "ant-gravity-0.1" / "seed-2" / "evaluation.json"
    record = json.loads(path.read_text())
    path.write_text(json.dumps(record | {"episode_seeds": record["episode_seeds"][::-1]}))
    _fails(per_seed, "the evaluations of dap on ant-gravity-0.1 disagree on episode_seeds", merge_seeds=True)
