"""Aggregate statistics of the fixed evaluation protocol, with stratified-bootstrap intervals.

The set of statistics from Agarwal et al., "Deep Reinforcement Learning at the Edge of the
Statistical Precipice" (NeurIPS 2021), the one their ``rliable`` library computes, implemented
here on numpy alone so that it is reproducible byte for byte: every bootstrap draws from
``numpy.random.Generator(PCG64(seed))``, and the same input with the same seed gives the same
output bytes. (``rliable`` itself needs pandas<3 and ignores its ``random_state``.)

Input convention: one score matrix per method, of shape ``(n_runs, n_tasks)``: one row per
training seed, one column per task, holding normalized scores on the protocol's 0..100 scale
(0 = random policy, 100 = oracle). Every method compared must be scored on the same tasks.

Point estimates (each a plain ``float``), with rliable's definitions:

* :func:`iqm`: interquartile mean of all ``n_runs * n_tasks`` scores pooled. It follows
  ``scipy.stats.trim_mean(scores.ravel(), 0.25)``: ``floor(0.25 * n)`` scores are cut from each
  end of the sorted scores and the rest averaged; no fraction of a score is weighted, so with
  ``n = 10`` the mean of the middle 6 is taken, and with ``n < 4`` nothing is cut.
* :func:`mean`: mean of all scores (equal to the mean of the per-task means).
* :func:`median`: median of the per-task mean scores (rliable's ``aggregate_median``; not the
  median of the pooled scores).
* :func:`optimality_gap`: mean of ``max(threshold - score, 0)``, the amount by which a method
  falls short of ``threshold`` (100, the oracle, by default).
* :func:`probability_of_improvement`: ``P(X > Y)``, averaged over tasks.
* :func:`performance_profile`: for each threshold ``tau``, the mean over tasks of the fraction of
  runs scoring above ``tau`` (rliable's run-score distribution).

Intervals: :func:`stratified_bootstrap_ci` resamples runs with replacement independently within
each task (column), evaluates the statistic on every resampled matrix and reports the percentile
interval (the ``confidence``-central range of the bootstrap distribution, linear interpolation
between order statistics). A percentile interval usually, but not always, contains its point
estimate: with few runs and a skewed distribution it may lie to one side. All bootstrap
functions draw the resampling indices in the same fixed order, so the same ``seed`` on the same
shapes resamples the same runs whatever statistic is evaluated on them.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
from collections.abc import Callable, Iterator, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from offdyn_bench.errors import OffdynError

__all__ = [
    "AGGREGATE_STATISTICS",
    "BatchedStatistic",
    "Interval",
    "Statistic",
    "StatisticsError",
    "aggregate",
    "iqm",
    "mean",
    "median",
    "method_seed",
    "optimality_gap",
    "performance_profile",
    "performance_profile_ci",
    "probability_of_improvement",
    "probability_of_improvement_ci",
    "stratified_bootstrap_ci",
]

#: The statistics :func:`aggregate` reports per method, in this order.
AGGREGATE_STATISTICS: tuple[str, ...] = ("iqm", "mean", "median", "optimality_gap")

# Resampling indices are drawn in blocks of this many bootstrap samples. It is fixed (never derived
# from the input's size) because the block size decides which random numbers go where: a
# size-dependent block would make two functions given the same seed resample different runs.
_DRAW_BLOCK = 256
# Upper bound on the elements of a temporary array when a statistic is evaluated on a batch of
# samples (pairwise comparisons grow as runs_x * runs_y * tasks per sample): about 32 MiB.
_MAX_BATCH_ELEMENTS = 1 << 22


class StatisticsError(OffdynError):
    """Invalid input to a protocol statistic: a malformed score matrix or a parameter out of range."""


@dataclasses.dataclass(frozen=True)
class Interval:
    """A point estimate with its bootstrap confidence interval ``[low, high]``."""

    point: float
    low: float
    high: float

    @property
    def width(self) -> float:
        return self.high - self.low


#: A statistic of one score matrix (n_runs, n_tasks).
Statistic = Callable[[NDArray[np.float64]], float]
#: A statistic evaluated on a stack of score matrices: (batch, n_runs, n_tasks) -> (batch,).
BatchedStatistic = Callable[[NDArray[np.float64]], NDArray[np.float64]]


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------


def _score_matrix(scores: ArrayLike, name: str = "scores") -> NDArray[np.float64]:
    """``scores`` as a finite float64 matrix of shape (n_runs, n_tasks), or a StatisticsError."""
    try:
        matrix = np.asarray(scores, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise StatisticsError(
            f"{name}: expected a numeric array of shape (n_runs, n_tasks); could not read it as "
            f"numbers ({error})"
        ) from None
    if matrix.ndim != 2:
        raise StatisticsError(
            f"{name}: expected a 2-D array of shape (n_runs, n_tasks), got {matrix.ndim}-D shape "
            f"{matrix.shape}; a single task's runs are a column, e.g. scores.reshape(-1, 1)"
        )
    n_runs, n_tasks = matrix.shape
    if n_runs == 0 or n_tasks == 0:
        raise StatisticsError(
            f"{name}: expected at least one run and one task, got shape (n_runs={n_runs}, "
            f"n_tasks={n_tasks})"
        )
    finite = np.isfinite(matrix)
    if not finite.all():
        run, task = np.argwhere(~finite)[0]
        raise StatisticsError(
            f"{name}: expected finite scores, got {matrix[run, task]} at run {run}, task {task} "
            f"({int((~finite).sum())} non-finite in all)"
        )
    return matrix


def _same_tasks(first: NDArray[np.float64], second: NDArray[np.float64], names: tuple[str, str]) -> None:
    if first.shape[1] != second.shape[1]:
        raise StatisticsError(
            f"{names[0]} has {first.shape[1]} tasks but {names[1]} has {second.shape[1]}; methods "
            f"are compared on the same tasks, in the same column order"
        )


def _check_finite_number(value: float, parameter: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise StatisticsError(f"invalid {parameter}={value!r}; expected a finite number")
    if not math.isfinite(value):
        raise StatisticsError(f"invalid {parameter}={value!r}; expected a finite number")
    return float(value)


def _check_bootstrap_parameters(reps: int, confidence: float, seed: int) -> None:
    if isinstance(reps, bool) or not isinstance(reps, (int, np.integer)) or reps < 1:
        raise StatisticsError(f"invalid reps={reps!r}; expected an integer >= 1 (bootstrap samples)")
    if (
        isinstance(confidence, bool)
        or not isinstance(confidence, (int, float, np.floating))
        or not 0.0 < confidence < 1.0
    ):
        raise StatisticsError(
            f"invalid confidence={confidence!r}; expected a number strictly between 0 and 1, "
            f"e.g. 0.95"
        )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise StatisticsError(f"invalid seed={seed!r}; expected an integer >= 0")


def _thresholds(taus: ArrayLike) -> NDArray[np.float64]:
    try:
        values = np.asarray(taus, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise StatisticsError(f"taus: expected a 1-D array of numbers ({error})") from None
    if values.ndim != 1 or values.size == 0:
        raise StatisticsError(
            f"taus: expected a non-empty 1-D array of score thresholds, got shape {values.shape}"
        )
    if not np.isfinite(values).all():
        raise StatisticsError("taus: expected finite score thresholds, got a NaN or infinity")
    return values


# --------------------------------------------------------------------------------------------
# Statistics on a batch of score matrices, shape (batch, n_runs, n_tasks) -> (batch,)
# --------------------------------------------------------------------------------------------


def _iqm_batch(batch: NDArray[np.float64]) -> NDArray[np.float64]:
    pooled = batch.reshape(batch.shape[0], -1)
    n = pooled.shape[1]
    cut = int(0.25 * n)  # scipy.stats.trim_mean: whole scores only, rounded down
    # A full sort (not a partition) puts the kept scores in one order whatever order the runs
    # came in, so a permutation of runs gives the same bytes.
    kept = np.sort(pooled, axis=1)[:, cut : n - cut]
    return kept.mean(axis=1)


def _mean_batch(batch: NDArray[np.float64]) -> NDArray[np.float64]:
    return batch.mean(axis=1).mean(axis=1)


def _median_batch(batch: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.median(batch.mean(axis=1), axis=1)


def _optimality_gap_batch(batch: NDArray[np.float64], threshold: float = 100.0) -> NDArray[np.float64]:
    shortfall = np.maximum(threshold - batch, 0.0)
    return shortfall.mean(axis=1).mean(axis=1)


def _improvement_batch(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """P(X > Y) per sample for stacks x (batch, n_x, n_tasks) and y (batch, n_y, n_tasks).

    Per task, the Mann-Whitney U statistic over n_x * n_y: every pair (x_i, y_j) counts 1 when
    x_i > y_j and 1/2 when they tie. Counted as integers (twice U), so it is exact."""
    n_x, n_y = x.shape[1], y.shape[1]
    per_sample = n_x * n_y * x.shape[2]
    step = max(1, _MAX_BATCH_ELEMENTS // per_sample)
    result = np.empty(x.shape[0])
    for start in range(0, x.shape[0], step):
        xs = x[start : start + step, :, None, :]
        ys = y[start : start + step, None, :, :]
        twice_u = 2 * np.count_nonzero(xs > ys, axis=(1, 2)) + np.count_nonzero(xs == ys, axis=(1, 2))
        result[start : start + step] = (twice_u / (2 * n_x * n_y)).mean(axis=1)
    return result


def _profile_batch(batch: NDArray[np.float64], taus: NDArray[np.float64]) -> NDArray[np.float64]:
    """(batch, n_runs, n_tasks) -> (batch, n_taus): per tau, the mean over tasks of the fraction of
    runs scoring above it."""
    per_sample = batch.shape[1] * batch.shape[2] * taus.size
    step = max(1, _MAX_BATCH_ELEMENTS // per_sample)
    result = np.empty((batch.shape[0], taus.size))
    for start in range(0, batch.shape[0], step):
        above = batch[start : start + step, :, :, None] > taus
        result[start : start + step] = above.mean(axis=1).mean(axis=1)
    return result


# --------------------------------------------------------------------------------------------
# Point estimates
# --------------------------------------------------------------------------------------------


def iqm(scores: ArrayLike) -> float:
    """Interquartile mean of all runs x tasks pooled: ``scipy.stats.trim_mean(x.ravel(), 0.25)``.

    ``floor(n / 4)`` of the ``n`` pooled scores are cut from each end, the rest averaged."""
    return float(_iqm_batch(_score_matrix(scores)[None])[0])


def mean(scores: ArrayLike) -> float:
    """Mean of all scores (with equal runs per task, the mean of the per-task means)."""
    return float(_mean_batch(_score_matrix(scores)[None])[0])


def median(scores: ArrayLike) -> float:
    """Median over tasks of each task's mean score (rliable's definition)."""
    return float(_median_batch(_score_matrix(scores)[None])[0])


def optimality_gap(scores: ArrayLike, threshold: float = 100.0) -> float:
    """Mean over all runs and tasks of ``max(threshold - score, 0)``: how far a method falls short
    of ``threshold`` (100 = the oracle on the normalized scale); scores above it earn no credit."""
    threshold = _check_finite_number(threshold, "threshold")
    return float(_optimality_gap_batch(_score_matrix(scores)[None], threshold)[0])


def probability_of_improvement(x: ArrayLike, y: ArrayLike) -> float:
    """``P(X > Y)``: the probability that a run of method X beats a run of method Y on a task drawn
    uniformly, ties counting 1/2.

    ``x`` is ``(n_runs_x, n_tasks)`` and ``y`` is ``(n_runs_y, n_tasks)``; per task the Mann-Whitney
    U statistic over ``n_runs_x * n_runs_y``, then the mean over tasks. ``P(X > Y) + P(Y > X) = 1``.
    """
    x_matrix = _score_matrix(x, "x")
    y_matrix = _score_matrix(y, "y")
    _same_tasks(x_matrix, y_matrix, ("x", "y"))
    return float(_improvement_batch(x_matrix[None], y_matrix[None])[0])


def performance_profile(scores: ArrayLike, taus: ArrayLike) -> NDArray[np.float64]:
    """The run-score distribution: for each threshold in ``taus``, the mean over tasks of the
    fraction of runs with a score strictly above it. Returns an array shaped like ``taus``."""
    return _profile_batch(_score_matrix(scores)[None], _thresholds(taus))[0]


# --------------------------------------------------------------------------------------------
# Stratified bootstrap
# --------------------------------------------------------------------------------------------


def method_seed(seed: int, method: str) -> int:
    """The bootstrap seed :func:`aggregate` uses for ``method``: derived from the protocol seed and
    the method's name alone (the first 8 bytes of ``sha256(f"{seed}:{method}")``), so adding or
    removing another method never changes this one's intervals."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise StatisticsError(f"invalid seed={seed!r}; expected an integer >= 0")
    digest = hashlib.sha256(f"{int(seed)}:{method}".encode()).digest()
    return int.from_bytes(digest[:8], "little")


def _resampled_blocks(
    matrices: Sequence[NDArray[np.float64]], reps: int, seed: int
) -> Iterator[tuple[NDArray[np.float64], ...]]:
    """Stratified bootstrap samples of every matrix, in blocks of at most ``_DRAW_BLOCK``.

    Within each task (column) the runs are drawn with replacement, independently of the other
    tasks: a sample never moves a score from one task to another. Per block, the indices of each
    matrix are drawn in turn from one PCG64 stream."""
    generator = np.random.Generator(np.random.PCG64(int(seed)))
    for start in range(0, reps, _DRAW_BLOCK):
        size = min(_DRAW_BLOCK, reps - start)
        block = []
        for matrix in matrices:
            n_runs, n_tasks = matrix.shape
            runs = generator.integers(0, n_runs, size=(size, n_runs, n_tasks))
            block.append(matrix[runs, np.arange(n_tasks)])
        yield tuple(block)


def _percentile_interval(point: float, distribution: NDArray[np.float64], confidence: float) -> Interval:
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(distribution, [tail, 1.0 - tail])
    return Interval(point=float(point), low=float(low), high=float(high))


_BATCHED_BUILTINS: dict[Callable[..., float], Callable[..., NDArray[np.float64]]] = {
    iqm: _iqm_batch,
    mean: _mean_batch,
    median: _median_batch,
    optimality_gap: _optimality_gap_batch,
}


def _batched(statistic: Callable[..., float], vectorized: bool) -> BatchedStatistic:
    """A batch version of ``statistic``: the built-in one where there is one, else a loop."""
    if vectorized:
        return statistic  # type: ignore[return-value]
    if statistic in _BATCHED_BUILTINS:
        return _BATCHED_BUILTINS[statistic]
    # functools.partial(optimality_gap, threshold=50.0) keeps the vectorised path.
    if (
        isinstance(statistic, functools.partial)
        and statistic.func in _BATCHED_BUILTINS
        and not statistic.args
    ):
        keywords = dict(statistic.keywords)
        if "threshold" in keywords:
            keywords["threshold"] = _check_finite_number(keywords["threshold"], "threshold")
        return functools.partial(_BATCHED_BUILTINS[statistic.func], **keywords)

    def loop(batch: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.array([statistic(sample) for sample in batch], dtype=np.float64)

    return loop


def _evaluate(batched: BatchedStatistic, batch: NDArray[np.float64], what: str) -> NDArray[np.float64]:
    values = np.asarray(batched(batch), dtype=np.float64)
    if values.shape != (batch.shape[0],):
        raise StatisticsError(
            f"statistic returned shape {values.shape} on the {what}, a stack of shape "
            f"{batch.shape}; expected shape ({batch.shape[0]},), one number per score matrix (a "
            f"vectorized statistic maps (batch, n_runs, n_tasks) to (batch,))"
        )
    if not np.isfinite(values).all():
        raise StatisticsError(f"statistic returned a non-finite value on the {what}; expected finite numbers")
    return values


def stratified_bootstrap_ci(
    scores: ArrayLike,
    statistic: Statistic,
    *,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
    vectorized: bool = False,
) -> Interval:
    """Point estimate and stratified-bootstrap percentile interval of ``statistic(scores)``.

    ``reps`` bootstrap samples each resample the runs of every task (column) with replacement,
    independently per task; the interval is the central ``confidence`` range of the statistic over
    the samples. ``statistic`` maps a ``(n_runs, n_tasks)`` matrix to a float. For :func:`iqm`,
    :func:`mean`, :func:`median`, :func:`optimality_gap` (also as ``functools.partial`` with a
    ``threshold``) all samples are evaluated at once; any other callable is called once per
    sample, unless ``vectorized=True`` says it takes a stack ``(batch, n_runs, n_tasks)`` and
    returns ``(batch,)``. Same scores and seed, same bytes.
    """
    matrix = _score_matrix(scores)
    _check_bootstrap_parameters(reps, confidence, seed)
    batched = _batched(statistic, vectorized)
    point = _evaluate(batched, matrix[None], "input scores")[0]
    distribution = np.concatenate(
        [_evaluate(batched, sample, "bootstrap samples") for (sample,) in _resampled_blocks([matrix], reps, seed)]
    )
    return _percentile_interval(point, distribution, confidence)


def probability_of_improvement_ci(
    x: ArrayLike, y: ArrayLike, *, reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> Interval:
    """:func:`probability_of_improvement` with a percentile interval from a stratified bootstrap
    that resamples the runs of ``x`` and of ``y`` independently within each task."""
    x_matrix = _score_matrix(x, "x")
    y_matrix = _score_matrix(y, "y")
    _same_tasks(x_matrix, y_matrix, ("x", "y"))
    _check_bootstrap_parameters(reps, confidence, seed)
    point = _improvement_batch(x_matrix[None], y_matrix[None])[0]
    distribution = np.concatenate(
        [_improvement_batch(xs, ys) for xs, ys in _resampled_blocks([x_matrix, y_matrix], reps, seed)]
    )
    return _percentile_interval(point, distribution, confidence)


def performance_profile_ci(
    scores: ArrayLike,
    taus: ArrayLike,
    *,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A pointwise stratified-bootstrap band ``(low, high)`` around :func:`performance_profile`:
    at each ``tau``, the central ``confidence`` range over the bootstrap samples."""
    matrix = _score_matrix(scores)
    thresholds = _thresholds(taus)
    _check_bootstrap_parameters(reps, confidence, seed)
    distribution = np.concatenate(
        [_profile_batch(sample, thresholds) for (sample,) in _resampled_blocks([matrix], reps, seed)]
    )
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(distribution, [tail, 1.0 - tail], axis=0)
    return low, high


def aggregate(
    scores_by_method: Mapping[str, ArrayLike],
    *,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
    optimality_threshold: float = 100.0,
) -> dict[str, dict[str, Interval]]:
    """IQM, mean, median and optimality gap of every method, each with its interval.

    Returns ``{method: {"iqm": Interval, "mean": ..., "median": ..., "optimality_gap": ...}}`` in
    the mapping's order. Every method must have the same number of tasks (runs may differ). A
    method's four statistics are evaluated on the same bootstrap samples, drawn with the seed
    :func:`method_seed` derives from ``seed`` and the method's name: its intervals equal
    ``stratified_bootstrap_ci(scores, iqm, seed=method_seed(seed, method))`` and so on, and do not
    change when other methods are added or removed.
    """
    if not isinstance(scores_by_method, Mapping) or not scores_by_method:
        raise StatisticsError(
            "scores_by_method: expected a non-empty mapping of method name to a score matrix of "
            "shape (n_runs, n_tasks)"
        )
    _check_bootstrap_parameters(reps, confidence, seed)
    threshold = _check_finite_number(optimality_threshold, "optimality_threshold")
    matrices: dict[str, NDArray[np.float64]] = {}
    for method, scores in scores_by_method.items():
        if not isinstance(method, str) or not method:
            raise StatisticsError(f"method names must be non-empty strings, got {method!r}")
        matrices[method] = _score_matrix(scores, f"scores of {method!r}")
    first = next(iter(matrices))
    for method, matrix in matrices.items():
        _same_tasks(matrices[first], matrix, (f"method {first!r}", f"method {method!r}"))

    statistics: dict[str, Callable[[NDArray[np.float64]], NDArray[np.float64]]] = {
        "iqm": _iqm_batch,
        "mean": _mean_batch,
        "median": _median_batch,
        "optimality_gap": functools.partial(_optimality_gap_batch, threshold=threshold),
    }
    results: dict[str, dict[str, Interval]] = {}
    for method, matrix in matrices.items():
        distributions: dict[str, list[NDArray[np.float64]]] = {name: [] for name in statistics}
        for (sample,) in _resampled_blocks([matrix], reps, method_seed(seed, method)):
            for name, batched in statistics.items():
                distributions[name].append(batched(sample))
        results[method] = {
            name: _percentile_interval(
                batched(matrix[None])[0], np.concatenate(distributions[name]), confidence
            )
            for name, batched in statistics.items()
        }
    return results
