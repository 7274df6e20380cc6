"""``offdyn-bench protocol curves``: how far a budget carried learning, against hand-computed
quarters, plateaus, steps to the plateau and late slopes, on curves read beside their evaluations."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from leaderboard.reference_runs import REFERENCE_RUNS_DIR
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError
from offdyn_bench.protocol.curves import CurveSummary, curves_markdown, read_curves

STEPS = tuple(range(10_000, 100_001, 10_000))


def write_run(folder: Path, seeds: dict[int, list[float]], *, steps=STEPS, task: str = "hopper-gravity-0.5",
              method: str = "sac-target") -> Path:
    """A run folder as `train` and `evaluate` leave it: metrics.jsonl (one line per evaluation, a
    mean return per seed) and the evaluation.json that names its method, task, budget and seeds."""
    folder.mkdir(parents=True)
    lines = [json.dumps({"step": step, "target_return": [curve[i] for curve in seeds.values()],
                         "target_return_mean": 0.0, "train": {}, "wall_time_s": 1.0}) for i, step in enumerate(steps)]
    (folder / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    record = {"format": "offdyn-bench/evaluation", "format_version": 1, "protocol_version": "1.0", "task": task,
              "task_version": 0, "target_env_id": "x", "track": "offline-target", "budget": "lite",
              "method": method, "steps": steps[-1], "episode_seeds": [0], "versions": {},
              "seeds": [{"seed": seed, "returns": [1.0]} for seed in seeds]}
    (folder / "evaluation.json").write_text(json.dumps(record))
    return folder / "metrics.jsonl"


def test_a_curve_still_rising_at_the_end_of_the_budget():
    # Return = step / 100: 250 at a quarter, 1000 at the end; the last quarter (80k, 90k, 100k)
    # averages 900; the curve stays above 90% of it (810) from 90k; the slope, 0.01 per step, is 100
    # per tenth of the budget (10k steps): 11.1% of the plateau.
    summary = CurveSummary("lite", "sac-target", "t", (0,), STEPS, tuple(step / 100 for step in STEPS))
    assert summary.quarter_returns == pytest.approx((250.0, 500.0, 750.0, 1000.0))
    assert summary.plateau == pytest.approx(900.0)
    assert summary.steps_to_plateau == 90_000
    assert summary.late_slope == pytest.approx(100 * 100 / 900)


def test_a_curve_that_levelled_off_early():
    # 100 at 10k, then 500 from 20k on: the plateau is 500, reached at 20k, with no late slope.
    returns = (100.0,) + (500.0,) * 9
    summary = CurveSummary("lite", "sac-target", "t", (0,), STEPS, returns)
    assert summary.quarter_returns == pytest.approx((500.0, 500.0, 500.0, 500.0))
    assert (summary.plateau, summary.steps_to_plateau) == (pytest.approx(500.0), 20_000)
    assert summary.late_slope == pytest.approx(0.0, abs=1e-9)


def test_an_early_high_point_that_is_lost_again_is_not_the_plateau_reached():
    # An Ant standing still at first (900), then falling, then climbing to 40: the last quarter
    # averages 40; the curve stays above 36 only from 80k on, not from the first evaluation.
    returns = (900.0, -10.0, 5.0, 10.0, 20.0, 25.0, 30.0, 40.0, 40.0, 40.0)
    assert CurveSummary("lite", "sac-source", "t", (0,), STEPS, returns).steps_to_plateau == 80_000
    # A final evaluation below 90% of the plateau: the curve has not settled.
    falling = (0.0,) * 7 + (100.0, 100.0, 50.0)
    summary = CurveSummary("lite", "sac-source", "t", (0,), STEPS, falling)
    assert summary.plateau == pytest.approx(250 / 3) and summary.steps_to_plateau is None


def test_a_plateau_below_zero_has_no_fraction_to_reach():
    summary = CurveSummary("lite", "sac-target", "t", (0,), STEPS, tuple(-1.0 - i for i in range(10)))
    assert summary.steps_to_plateau is None and summary.late_slope is None
    assert "| - | - |" in curves_markdown([summary])


def test_seeds_of_one_task_are_averaged_across_runs_and_tasks_kept_apart(tmp_path):
    a = write_run(tmp_path / "a", {0: [float(s) for s in STEPS], 1: [0.0] * 10})
    b = write_run(tmp_path / "b", {2: [300.0] * 10})
    c = write_run(tmp_path / "c", {0: [7.0] * 10}, task="walker2d-gravity-2.0")
    hopper, walker = read_curves([b, a, c])
    assert (hopper.task, hopper.seeds, walker.task, walker.seeds) == ("hopper-gravity-0.5", (0, 1, 2),
                                                                     "walker2d-gravity-2.0", (0,))
    assert hopper.mean_returns == pytest.approx([(step + 0.0 + 300.0) / 3 for step in STEPS])
    assert walker.mean_returns == pytest.approx([7.0] * 10)


def test_curves_that_cannot_be_read_together_are_refused(tmp_path):
    a = write_run(tmp_path / "a", {0: [1.0] * 10})
    other_steps = write_run(tmp_path / "b", {1: [1.0] * 5}, steps=tuple(range(20_000, 100_001, 20_000)))
    with pytest.raises(OffdynError, match=r"lite/sac-target/hopper-gravity-0.5: .*/b/metrics.jsonl was evaluated "
                                          r"at other steps than .*/a/metrics.jsonl"):
        read_curves([a, other_steps])
    with pytest.raises(OffdynError, match=r"training seed\(s\) \[0\] given twice"):
        read_curves([a, a])
    lonely = tmp_path / "lonely" / "metrics.jsonl"
    lonely.parent.mkdir()
    lonely.write_text((tmp_path / "a" / "metrics.jsonl").read_text())
    with pytest.raises(OffdynError, match=r"no evaluation.json beside it; .*evaluate the run first"):
        read_curves([lonely])
    short = write_run(tmp_path / "short", {3: [1.0] * 5}, steps=STEPS[:5])
    record = json.loads((short.parent / "evaluation.json").read_text())
    (short.parent / "evaluation.json").write_text(json.dumps(record | {"steps": 100_000}))
    with pytest.raises(OffdynError, match=r"the curve ends at step 50000, but the evaluation beside it scores the "
                                          r"policy of step 100000"):
        read_curves([short])
    with pytest.raises(OffdynError, match=r"no learning curve given"):
        read_curves([])


def test_the_command_prints_the_table_and_json_and_refuses_plainly(tmp_path):
    path = write_run(tmp_path / "a", {0: [float(s) / 100 for s in STEPS]})
    result = CliRunner().invoke(app, ["protocol", "curves", str(path)])
    assert result.exit_code == 0, result.output
    assert "| lite/sac-target/hopper-gravity-0.5 | 1 | 250.0 | 500.0 | 750.0 | 1000.0 | 900.0 | 90000 | +11.1 |" \
        in result.output
    result = CliRunner().invoke(app, ["protocol", "curves", str(path), "--json"])
    assert json.loads(result.output)[0]["steps_to_plateau"] == 90_000
    result = CliRunner().invoke(app, ["protocol", "curves", str(tmp_path / "a" / "evaluation.json")])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert 'evaluation.json:1: expected an object with "step" and "target_return"' in result.output


def test_the_published_reference_curves_summarize():
    paths = sorted(REFERENCE_RUNS_DIR.glob("*/*/*/*/metrics.jsonl"))
    if not paths:
        pytest.skip("no learning curve is published yet")
    summaries = read_curves(paths)
    for summary in summaries:
        # Every published curve ends at the budget its records were scored at.
        assert summary.steps[-1] == {"lite": 100_000, "full": 1_000_000}[summary.budget]
        assert min(summary.mean_returns) <= summary.plateau <= max(summary.mean_returns)
