"""Learning curves of scored runs: does a budget stop while the policy is still learning?

The protocol's budgets are chosen from measured learning curves (PROTOCOL.md §3, §7). Every run
``offdyn-bench train`` makes writes one (``metrics.jsonl``: per training seed, the mean target
return of the in-run evaluation episodes at every evaluation interval), and ``leaderboard
publish-runs`` publishes it beside the run's evaluation record. This module reads such curves
with the evaluation beside each (its method, task, budget and seeds), averages the seeds of one
method and task, and says how far the budget carried learning:

- the mean return at each quarter of the budget;
- the late plateau: the mean over the last quarter (a single noisy final point is no plateau);
- the step from which the seeds' mean curve stays at or above 90% of that plateau;
- the late slope: a least-squares line through the curve's second half, as the change per tenth of
  the budget in percent of the plateau. Near zero, learning has levelled off within the budget;
  clearly positive, the budget stops it while the policy still improves.

The in-run evaluation uses fewer episodes than the protocol; the score is the final policy's
evaluation record. A curve shows the trend, never the score.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from offdyn_bench.protocol.definition import ProtocolError

EVALUATION_BESIDE = "evaluation.json"
PLATEAU_FRACTION = 0.9


@dataclasses.dataclass(frozen=True)
class CurveSummary:
    budget: str
    method: str
    task: str
    seeds: tuple[int, ...]
    steps: tuple[int, ...]
    mean_returns: tuple[float, ...]
    """The seeds' mean target return at each of ``steps``."""

    def _arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.steps, dtype=float), np.asarray(self.mean_returns, dtype=float)

    @property
    def quarter_returns(self) -> tuple[float, float, float, float]:
        """The mean curve at 1/4, 2/4, 3/4 and all of the budget (interpolated between evaluations)."""
        steps, returns = self._arrays()
        q1, q2, q3, q4 = (float(np.interp(q * steps[-1] / 4, steps, returns)) for q in (1, 2, 3, 4))
        return q1, q2, q3, q4

    @property
    def plateau(self) -> float:
        """The mean curve's average over the last quarter of the budget."""
        steps, returns = self._arrays()
        return float(returns[steps > 0.75 * steps[-1]].mean())

    @property
    def steps_to_plateau(self) -> int | None:
        """The step from which the mean curve stays at or above 90% of the plateau. None: the
        plateau is not a positive return (a fraction of it means nothing), or the final
        evaluation is below 90% of it (the curve has not settled). "Stays": an early high point
        that is lost again (a fresh Ant standing still earns its healthy reward) is no learning."""
        plateau = self.plateau
        if plateau <= 0:
            return None
        below = [index for index, value in enumerate(self.mean_returns) if value < PLATEAU_FRACTION * plateau]
        if not below:
            return self.steps[0]
        return self.steps[below[-1] + 1] if below[-1] + 1 < len(self.steps) else None

    @property
    def late_slope(self) -> float | None:
        """The second half's least-squares slope, per tenth of the budget, in percent of the plateau
        (None: fewer than two evaluations in the second half, or a plateau that is not positive)."""
        steps, returns = self._arrays()
        half = steps >= 0.5 * steps[-1]
        plateau = self.plateau
        if half.sum() < 2 or plateau <= 0:
            return None
        slope = float(np.polyfit(steps[half], returns[half], 1)[0])
        return 100.0 * slope * (steps[-1] / 10) / plateau

    def to_dict(self) -> dict[str, Any]:
        return {"budget": self.budget, "method": self.method, "task": self.task, "seeds": list(self.seeds),
                "steps": list(self.steps), "mean_returns": list(self.mean_returns),
                "quarter_returns": list(self.quarter_returns), "plateau": self.plateau,
                "steps_to_plateau": self.steps_to_plateau, "late_slope_percent_per_tenth": self.late_slope}


def read_curves(paths: Sequence[Path]) -> list[CurveSummary]:
    """One summary per (budget, method, task) of the ``metrics.jsonl`` files ``paths``, each read
    with the ``evaluation.json`` beside it and checked as ``leaderboard publish-runs`` checks it."""
    from leaderboard.assemble import read_evaluation_strict
    from leaderboard.reference_runs import check_reference_curve

    if not paths:
        raise ProtocolError("no learning curve given; expected metrics.jsonl files of `offdyn-bench train` runs "
                            "(or as `leaderboard publish-runs` publishes them)")
    groups: dict[tuple[str, str, str], list[tuple[Path, int, tuple[int, ...], list[float]]]] = {}
    for path in paths:
        path = Path(path)
        record_path = path.parent / EVALUATION_BESIDE
        if not record_path.is_file():
            raise ProtocolError(f"{path}: no {EVALUATION_BESIDE} beside it; a curve is read with the evaluation of "
                                "the run it belongs to (its method, task, budget and seeds): evaluate the run first")
        record = read_evaluation_strict(record_path)
        curve = check_reference_curve(path, record)
        steps = tuple(point["step"] for point in curve)
        key = (str(record.get("budget")), str(record["method"]), str(record["task"]))
        for index, seed in enumerate(record["seeds"]):
            groups.setdefault(key, []).append((path, int(seed["seed"]), steps,
                                               [float(point["target_return"][index]) for point in curve]))
    summaries = []
    for (budget, method, task), members in sorted(groups.items()):
        first_path, _, steps, _ = members[0]
        for path, _, other, _ in members[1:]:
            if other != steps:
                raise ProtocolError(f"{budget}/{method}/{task}: {path} was evaluated at other steps than "
                                    f"{first_path}; curves are averaged only over the same steps")
        seeds = [seed for _, seed, _, _ in members]
        repeated = sorted(seed for seed, count in Counter(seeds).items() if count > 1)
        if repeated:
            raise ProtocolError(f"{budget}/{method}/{task}: training seed(s) {repeated} given twice; give each "
                                "run's curve once")
        order = np.argsort(seeds, kind="stable")
        mean = np.mean([members[i][3] for i in order], axis=0)
        summaries.append(CurveSummary(budget, method, task, tuple(sorted(seeds)), steps,
                                      tuple(float(x) for x in mean)))
    return summaries


def _cell(value: float | int | None, fmt: str = "{:.1f}") -> str:
    return "-" if value is None else fmt.format(value)


def curves_markdown(summaries: Sequence[CurveSummary]) -> str:
    lines = ["| budget/method/task | seeds | at 1/4 | at 2/4 | at 3/4 | at 4/4 | plateau (last 1/4) | "
             "stays above 90% of it from step | late slope (% of plateau per 1/10) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for summary in summaries:
        quarters = " | ".join(f"{value:.1f}" for value in summary.quarter_returns)
        lines.append(f"| {summary.budget}/{summary.method}/{summary.task} | {len(summary.seeds)} | {quarters} | "
                     f"{summary.plateau:.1f} | {_cell(summary.steps_to_plateau, '{:d}')} | "
                     f"{_cell(summary.late_slope, '{:+.1f}')} |")
    lines += ["", "Means over the training seeds' in-run evaluations (fewer episodes than the protocol's; the "
                  "score is the evaluation record). Late slope: a least-squares line through the curve's second "
                  "half; clearly positive, the budget stops learning that still goes on."]
    return "\n".join(lines) + "\n"
