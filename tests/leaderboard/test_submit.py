"""``leaderboard submit``: a submission from the evaluation.json files of a runs folder."""

from __future__ import annotations

import json
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
