"""Screen every candidate cheaply, then fit the most promising ones.

Screening perturbs each candidate once (a finite-difference step for smooth effects, a few trial
values for dead zones, saturations and delays), all hypotheses in one batched
``mujoco.rollout`` call on a small subset, and scores how much one-step residual each would
remove: for a smooth effect the linearized (Gauss-Newton) reduction, which is the score test of
"this parameter is at its nominal value". Fits then run on a larger subset: smooth effects by
``mujoco.minimize.least_squares``, thresholds on nested grids, delays by enumeration; intervals come
from the Jacobian at the optimum (``mujoco.sysid.calculate_intervals``).
"""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Sequence

import mujoco.minimize
import numpy as np

from offdyn_bench.diagnose.candidates import Candidate
from offdyn_bench.diagnose.residual import Hypothesis, ResidualEvaluator

try:  # the confidence-interval helper of mujoco.sysid (the mujoco[sysid] extra)
    from mujoco.sysid import calculate_intervals as _calculate_intervals
except ImportError:  # pragma: no cover - the pinned stack has it
    _calculate_intervals = None


@dataclasses.dataclass(frozen=True)
class ScreenScore:
    candidate: Candidate
    reduction: float  # predicted drop of the screening subset's sum of squared residuals
    start: float  # the value the screen suggests as the fit's starting point


@dataclasses.dataclass(frozen=True)
class Fit:
    candidate: Candidate
    value: float
    interval: tuple[float, float]
    on_bound: bool
    sse: float  # on the fit subset


def _sse(residual: np.ndarray) -> float:
    return float(np.sum(residual**2))


def same_target(candidate: Candidate, hypothesis: Hypothesis) -> bool:
    return any(candidate.matches(e) for e in hypothesis)


def screen(evaluator: ResidualEvaluator, hypothesis: Hypothesis, candidates: Sequence[Candidate]) -> list[ScreenScore]:
    """Score every candidate not yet in ``hypothesis``; best first."""
    base, = evaluator.search_residuals([hypothesis], "screen")
    sse0 = _sse(base)
    trials: list[tuple[Candidate, float]] = []
    for candidate in candidates:
        if same_target(candidate, hypothesis):
            continue
        if candidate.search == "smooth":
            value = candidate.nominal + candidate.probe
            if value > candidate.high:
                value = candidate.nominal - candidate.probe
            trials.append((candidate, value))
        trials.extend((candidate, candidate.clip(value)) for value in candidate.trials)
    residuals = evaluator.search_residuals([hypothesis + (c.effect(v),) for c, v in trials], "screen")
    best: dict[Candidate, ScreenScore] = {}
    probed: set[Candidate] = set()
    for (candidate, value), residual in zip(trials, residuals):
        if candidate.search == "smooth" and candidate not in probed:  # the first trial is the probe
            probed.add(candidate)
            step = value - candidate.nominal
            column = (residual - base).ravel() / step
            norm = float(column @ column)
            if norm <= 0:
                continue
            delta = -float(column @ base.ravel()) / norm
            start = candidate.clip(candidate.nominal + delta)
            moved = start - candidate.nominal
            reduction = sse0 - _sse(base.ravel() + column * moved)
        else:
            start, reduction = value, sse0 - _sse(residual)
        if candidate not in best or reduction > best[candidate].reduction:
            best[candidate] = ScreenScore(candidate, reduction, start)
    return sorted(best.values(), key=lambda s: -s.reduction)


def _interval(candidate: Candidate, value: float, residual: np.ndarray, column: np.ndarray) -> tuple[float, float]:
    """95% interval from the Jacobian column at the optimum (Gauss-Newton covariance)."""
    if candidate.search in ("integer", "categorical"):
        return (value, value)
    if _calculate_intervals is not None:
        _, half = _calculate_intervals([residual.ravel()], column.reshape(-1, 1))
        half_width = float(half[0])
    else:  # pragma: no cover
        s2 = _sse(residual) / max(1, residual.size - 1)
        half_width = 1.96 * float(np.sqrt(s2 / max(float(column @ column), 1e-300)))
    if not np.isfinite(half_width):
        return (candidate.low, candidate.high)
    return (max(candidate.low, value - half_width), min(candidate.high, value + half_width))


def _jacobian_column(evaluator: ResidualEvaluator, hypothesis: Hypothesis, candidate: Candidate, value: float,
                     residual: np.ndarray, subset: str) -> np.ndarray:
    step = 0.01 * (candidate.high - candidate.low) if candidate.search == "threshold" else 0.05 * candidate.probe
    if value + step > candidate.high:
        step = -step
    moved, = evaluator.search_residuals([hypothesis + (candidate.effect(value + step),)], subset)
    return (moved - residual).ravel() / step


def fit(evaluator: ResidualEvaluator, hypothesis: Hypothesis, candidate: Candidate, start: float,
        subset: str = "fit") -> Fit:
    """Fit ``candidate``'s value with ``hypothesis`` held fixed."""
    resolution = 0.0
    if candidate.search == "smooth":
        value = _fit_smooth(evaluator, hypothesis, candidate, start, subset)
    elif candidate.search == "threshold":
        value, resolution = _fit_threshold(evaluator, hypothesis, candidate, subset)
    else:  # integers and categories: every value is tried
        value = _fit_integer(evaluator, hypothesis, candidate, subset)
    residual, = evaluator.search_residuals([hypothesis + (candidate.effect(value),)], subset)
    if candidate.search in ("integer", "categorical"):
        interval = (value, value)
    else:
        low, high = _interval(candidate, value, residual,
                              _jacobian_column(evaluator, hypothesis, candidate, value, residual, subset))
        # A grid cannot locate a threshold closer than its last spacing, whatever the curvature says.
        interval = (min(low, max(candidate.low, value - resolution)), max(high, min(candidate.high, value + resolution)))
    return Fit(candidate, value, interval, candidate.on_bound(value), _sse(residual))


def _fit_smooth(evaluator: ResidualEvaluator, hypothesis: Hypothesis, candidate: Candidate, start: float,
                subset: str) -> float:
    # Work in units of the probe step so one tolerance suits kilograms and newton-metres alike.
    scale = candidate.probe

    def to_value(z: float) -> float:
        return candidate.clip(candidate.nominal + z * scale)

    def residual(z: np.ndarray) -> np.ndarray:
        values = [to_value(float(zi)) for zi in z[0]]
        parts = evaluator.search_residuals([hypothesis + (candidate.effect(v),) for v in values], subset)
        return np.stack([p.ravel() for p in parts], axis=1)

    bounds = [np.array([(candidate.low - candidate.nominal) / scale]),
              np.array([(candidate.high - candidate.nominal) / scale])]
    z0 = np.array([(candidate.clip(start) - candidate.nominal) / scale])
    z, _ = mujoco.minimize.least_squares(z0, residual, bounds=bounds, eps=1e-3, max_iter=10, xtol=1e-5, mu_factor=10.0,
                                         verbose=0, output=io.StringIO())
    return to_value(float(np.ravel(z)[0]))


def _fit_threshold(evaluator: ResidualEvaluator, hypothesis: Hypothesis, candidate: Candidate,
                   subset: str) -> tuple[float, float]:
    """Nested grids: a threshold changes the prediction only where a command crosses it, so the
    error is piecewise smooth (a saturation) or piecewise constant (a dead zone) and gradients
    mislead. Returns the value and the resolution it was located to."""
    low, high = candidate.low, candidate.high
    if candidate.kind == "action_deadzone":
        # Every threshold at or above the largest recorded command zeroes all of them alike: the
        # data tell thresholds apart only below it, so the grids spend their points there.
        magnitudes = _command_magnitudes(evaluator, hypothesis, candidate)
        largest = float(magnitudes[-1]) if magnitudes.size else 0.0
        if low < largest < high:
            high = largest
    best, step = candidate.nominal, high - low
    levels = 3 if candidate.kind == "action_deadzone" else 5
    for _ in range(levels):
        grid = np.linspace(low, high, 9)
        errors = [_sse(r) for r in evaluator.search_residuals([hypothesis + (candidate.effect(v),) for v in grid], subset)]
        best = float(grid[int(np.argmin(errors))])
        step = float(grid[1] - grid[0])
        low, high = max(candidate.low, best - step), min(candidate.high, best + step)
    if candidate.kind == "action_deadzone":
        # The error only changes where the threshold passes a recorded command: try the midpoints
        # between neighbouring command magnitudes inside the bracket (at most 32), on every
        # training row, since only rows whose command lies between two trials are re-simulated.
        subset = "train"
        for _ in range(4):
            inside = magnitudes[(magnitudes >= low) & (magnitudes <= high)]
            if inside.size < 2:
                break
            midpoints = 0.5 * (inside[1:] + inside[:-1])
            exhaustive = midpoints.size <= 32
            if not exhaustive:
                midpoints = midpoints[np.linspace(0, midpoints.size - 1, 32).round().astype(int)]
            trials = sorted({best, *midpoints.tolist()})
            errors = [_sse(r) for r in _residuals_one_by_one(evaluator, hypothesis, candidate, trials, subset)]
            i = int(np.argmin(errors))
            best = float(trials[i])
            low, high = trials[max(i - 1, 0)], trials[min(i + 1, len(trials) - 1)]
            step = (high - low) / 2
            if exhaustive:  # located between two neighbouring recorded commands
                break
    return best, step


def _command_magnitudes(evaluator: ResidualEvaluator, hypothesis: Hypothesis, candidate: Candidate) -> np.ndarray:
    """The distinct command magnitudes, sorted, on the actuators ``candidate`` acts on, in the
    search's training rows."""
    commands = evaluator.applied_actions(hypothesis)[evaluator.search_starts["train"]]
    mask = candidate.effect(candidate.nominal).dimension_mask(commands.shape[1], evaluator.source.base_model)  # type: ignore[attr-defined]
    return np.unique(np.abs(commands[:, mask]))


def _residuals_one_by_one(evaluator: ResidualEvaluator, hypothesis: Hypothesis, candidate: Candidate,
                          values: list[float], subset: str) -> list[np.ndarray]:
    """Residuals of neighbouring values one call at a time, so each reuses the previous rollout
    for every row the small change leaves alone."""
    return [evaluator.search_residuals([hypothesis + (candidate.effect(v),)], subset)[0] for v in values]


def _fit_integer(evaluator: ResidualEvaluator, hypothesis: Hypothesis, candidate: Candidate, subset: str) -> float:
    values = np.arange(int(candidate.low), int(candidate.high) + 1)
    residuals = evaluator.search_residuals([hypothesis + (candidate.effect(v),) for v in values], subset)
    return float(values[int(np.argmin([_sse(r) for r in residuals]))])
