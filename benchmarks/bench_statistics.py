"""Stratified-bootstrap intervals: the vectorised statistics against a per-sample loop, in one run.

    .venv/bin/python benchmarks/bench_statistics.py [--runs 10] [--tasks 20] [--reps 2000]

The reference is how rliable evaluates a bootstrap: one Python-level step per sample, which draws
that sample's stratified indices and calls scipy (``scipy.stats.trim_mean`` for the IQM,
``scipy.stats.mannwhitneyu`` per task for the probability of improvement). The suite draws every
sample's indices in a few calls and evaluates a whole block of samples at once. Both are timed
here on the same scores, best of ``--repeat``; the figure is the ratio of the two wall times (load
on the machine scales both). The intervals are printed side by side as a check. Both draw from
PCG64 with the same seed; for the IQM the two consume the stream in the same order (when
``runs * tasks`` is even), so the intervals agree to rounding; for P(X > Y) the reference draws
x and y sample by sample, the suite block by block, so they agree to within bootstrap noise.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import scipy.stats

from offdyn_bench.protocol.statistics import (
    Interval,
    iqm,
    probability_of_improvement_ci,
    stratified_bootstrap_ci,
)


def per_sample_iqm_ci(scores: np.ndarray, reps: int, confidence: float, seed: int) -> Interval:
    generator = np.random.Generator(np.random.PCG64(seed))
    n_runs, n_tasks = scores.shape
    tasks = np.arange(n_tasks)
    values = np.empty(reps)
    for rep in range(reps):
        sample = scores[generator.integers(0, n_runs, size=(n_runs, n_tasks)), tasks]
        values[rep] = scipy.stats.trim_mean(sample, 0.25, axis=None)
    tail = (1 - confidence) / 2
    low, high = np.quantile(values, [tail, 1 - tail])
    return Interval(float(scipy.stats.trim_mean(scores, 0.25, axis=None)), float(low), float(high))


def per_sample_improvement_ci(x: np.ndarray, y: np.ndarray, reps: int, confidence: float, seed: int) -> Interval:
    def probability(a: np.ndarray, b: np.ndarray) -> float:
        per_task = [
            scipy.stats.mannwhitneyu(a[:, t], b[:, t], alternative="greater").statistic / (len(a) * len(b))
            for t in range(a.shape[1])
        ]
        return float(np.mean(per_task))

    generator = np.random.Generator(np.random.PCG64(seed))
    tasks = np.arange(x.shape[1])
    values = np.empty(reps)
    for rep in range(reps):
        xs = x[generator.integers(0, len(x), size=x.shape), tasks]
        ys = y[generator.integers(0, len(y), size=y.shape), tasks]
        values[rep] = probability(xs, ys)
    tail = (1 - confidence) / 2
    low, high = np.quantile(values, [tail, 1 - tail])
    return Interval(probability(x, y), float(low), float(high))


def best_time(function: Callable[[], Interval], repeat: int) -> tuple[float, Interval]:
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - start)
    return best, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=10, help="training seeds per method")
    parser.add_argument("--tasks", type=int, default=20)
    parser.add_argument("--reps", type=int, default=2000, help="bootstrap samples")
    parser.add_argument("--repeat", type=int, default=1, help="timed repetitions; the best is kept")
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    x = rng.normal(60, 15, size=(args.runs, args.tasks))
    y = rng.normal(50, 15, size=(args.runs, args.tasks))
    print(f"scores: {args.runs} runs x {args.tasks} tasks, {args.reps} bootstrap samples, 95% intervals")
    print(f"{'statistic':<26}{'suite s':>10}{'per-sample s':>14}{'speed-up':>10}   intervals (suite | per-sample)")
    cases = [
        (
            "IQM",
            lambda: stratified_bootstrap_ci(x, iqm, reps=args.reps, seed=1),
            lambda: per_sample_iqm_ci(x, args.reps, 0.95, 1),
        ),
        (
            "P(X > Y)",
            lambda: probability_of_improvement_ci(x, y, reps=args.reps, seed=1),
            lambda: per_sample_improvement_ci(x, y, args.reps, 0.95, 1),
        ),
    ]
    for name, suite, reference in cases:
        suite_seconds, suite_interval = best_time(suite, args.repeat)
        reference_seconds, reference_interval = best_time(reference, args.repeat)
        print(
            f"{name:<26}{suite_seconds:>10.4f}{reference_seconds:>14.4f}{reference_seconds / suite_seconds:>9.1f}x"
            f"   {suite_interval.point:.4f} [{suite_interval.low:.4f}, {suite_interval.high:.4f}]"
            f" | {reference_interval.point:.4f} [{reference_interval.low:.4f}, {reference_interval.high:.4f}]"
        )


if __name__ == "__main__":
    main()
