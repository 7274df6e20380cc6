"""`sweep SPEC --skip-published`: fill in a reference grid with only the runs whose records are not
published yet (as `leaderboard coverage` counts them), in the run, the dry run and the status."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from leaderboard.reference_runs import REFERENCE_RUNS_DIR
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError
from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import run_sweep, summary_lines

TASK = "invertedpendulum-gravity-3.0"
runner = CliRunner()


def _published_dap(tmp_path: Path, task: str, drop_seed: int) -> Path:
    """DAP's published lite records of ``task`` under a root of their own, less one seed's."""
    root = tmp_path / "published"
    (root / "lite" / "dap").mkdir(parents=True)
    shutil.copy(REFERENCE_RUNS_DIR / "lite" / "compute.json", root / "lite" / "compute.json")
    shutil.copytree(REFERENCE_RUNS_DIR / "lite" / "dap" / task, root / "lite" / "dap" / task)
    shutil.rmtree(root / "lite" / "dap" / task / f"seed-{drop_seed}")
    return root


def _lite_spec(tmp_path: Path, task: str) -> Path:
    path = tmp_path / "lite.json"
    path.write_text(json.dumps({"methods": ["dap"], "tasks": [task], "seeds": 5, "track": "offline-target",
                                "budget": "lite", "out": str(tmp_path / "out")}))
    return path


def test_dry_run_and_status_leave_out_exactly_the_published_runs(tmp_path):
    task = "hopper-gravity-0.5"
    root = _published_dap(tmp_path, task, drop_seed=2)
    spec = _lite_spec(tmp_path, task)
    flags = ["--skip-published", "--reference-runs", str(root)]

    dry = runner.invoke(app, ["sweep", str(spec), "--dry-run", *flags])
    assert dry.exit_code == 0, dry.output
    marks = {line.split(" (")[0]: line.split(" (")[1].rstrip(")") for line in dry.output.splitlines()
             if line.startswith("dap/")}
    assert marks == {f"dap/{task}/seed-{s}": ("to run" if s == 2 else "published: skipped") for s in range(5)}
    assert "5 runs (4 published: skipped)" in dry.output

    status = runner.invoke(app, ["sweep", str(spec), "--status", *flags])
    assert status.exit_code == 0, status.output
    rows = [line.split()[0] for line in status.output.splitlines() if line.startswith("dap/")]
    assert rows == [f"dap/{task}/seed-2"]
    # the way to continue keeps the flag, so the same runs are left out
    assert f"offdyn-bench sweep {spec} --skip-published` to continue" in status.output
    assert not (tmp_path / "out").exists()  # neither wrote anything

    # Without the flag every run is listed (the published records change nothing by themselves).
    plain = runner.invoke(app, ["sweep", str(spec), "--dry-run"])
    assert plain.exit_code == 0 and "published" not in plain.output and "5 runs;" in plain.output


def test_a_run_of_several_seeds_some_published_is_refused_with_what_to_run_instead(tmp_path):
    """A lease's 5-seed run where single-seed runs published some seeds could not be published (a
    seed is published once): refused before anything runs, naming the published seeds; the spec
    with only the others goes through."""
    task = "hopper-gravity-0.5"
    root = _published_dap(tmp_path, task, drop_seed=2)
    spec = _lite_spec(tmp_path, task)
    grouped = json.loads(spec.read_text()) | {"seeds_per_run": 5}
    spec.write_text(json.dumps(grouped))
    flags = ["--skip-published", "--reference-runs", str(root)]
    for mode in (["--dry-run"], []):
        refused = runner.invoke(app, ["sweep", str(spec), *mode, *flags])
        assert refused.exit_code == 2, refused.output
        assert (f"1 run(s) of the spec train seeds that are published already in other seed folders: "
                f"dap/{task}/seeds-0-4 (seed(s) 0, 1, 3, 4 published)") in " ".join(refused.output.split())
        assert "give the spec only the unpublished seeds" in " ".join(refused.output.split())
    assert not (tmp_path / "out").exists()
    # --status only reads: it still shows where the sweep stands.
    assert runner.invoke(app, ["sweep", str(spec), "--status", *flags]).exit_code == 0
    spec.write_text(json.dumps(grouped | {"seeds": [2]}))
    dry = runner.invoke(app, ["sweep", str(spec), "--dry-run", *flags])
    assert dry.exit_code == 0 and f"dap/{task}/seed-2 (to run)" in dry.output, dry.output


def test_refusals_say_what_was_wrong_and_write_nothing(tmp_path):
    spec = _lite_spec(tmp_path, "hopper-gravity-0.5")
    alone = runner.invoke(app, ["sweep", str(spec), "--dry-run", "--reference-runs", str(tmp_path)])
    assert alone.exit_code == 2 and "give --skip-published too" in alone.output

    steps = tmp_path / "steps.json"
    steps.write_text(json.dumps({"methods": ["sac-source"], "tasks": [TASK], "seeds": 1, "track": "offline-target",
                                 "steps": 100, "out": str(tmp_path / "out")}))
    result = runner.invoke(app, ["sweep", str(steps), "--skip-published"])
    assert result.exit_code == 2 and "sets steps, not a protocol budget" in result.output

    missing = runner.invoke(app, ["sweep", str(spec), "--dry-run", "--skip-published", "--reference-runs",
                                  str(tmp_path / "nowhere")])
    assert missing.exit_code == 2 and "error:" in missing.output
    assert not (tmp_path / "out").exists()


def test_a_sweep_runs_only_what_is_not_skipped_and_assembles_no_partial_submission(tmp_path, tiny_spec):
    spec = parse_spec(tiny_spec(tmp_path / "out"), source="tiny")
    skipped = f"sac-source/{TASK}/seed-1"
    with pytest.raises(OffdynError, match="--submit assembles a method's submission from this sweep's own runs"):
        run_sweep(spec, echo=None, skip={skipped}, submit=True)
    assert not (tmp_path / "out").exists()

    report = run_sweep(spec, workers=1, echo=None, skip={skipped})
    assert [run.run_id for run in report.runs] == [f"sac-source/{TASK}/seed-0"]
    assert report.skipped == (skipped,) and report.launched == 1
    assert (tmp_path / "out" / "runs" / "sac-source" / TASK / "seed-0" / "evaluation.json").is_file()
    assert not (tmp_path / "out" / "runs" / "sac-source" / TASK / "seed-1").exists()
    lines = summary_lines(report)
    assert "skipped: 1 run(s) of the spec whose records are published already (--skip-published)" in lines
    assert any(line.startswith("sac-source: not a leaderboard submission: 1 of its runs were skipped as published")
               for line in lines), lines
    assert not (tmp_path / "out" / "submission").exists()
