"""Every number on the board, recomputed from the raw returns of the stored submissions.

A method's score on a task and training seed is the normalized score of that seed's mean target
return (the normalization is linear, so this equals the mean of its normalized episode returns).
A submission becomes a score matrix ``(seeds, tasks)`` over the tasks whose references exist at
its budget; aggregates use the protocol's statistics (IQM, mean, optimality gap with
stratified-bootstrap 95% intervals; probability of improvement; performance profiles). Raw
returns are reported for every task, with or without references.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from leaderboard.submission import Submission
from offdyn_bench.protocol.statistics import Interval

BOOTSTRAP_REPS = 2000
BOOTSTRAP_SEED = 0
CONFIDENCE = 0.95
PROFILE_TAUS = np.linspace(-25.0, 125.0, 151)
"""Thresholds of the performance profiles on the normalized scale (0 random, 100 oracle)."""


@dataclasses.dataclass(frozen=True)
class Normalization:
    """Which tasks a budget's normalized scores cover, and why the others are left out."""

    budget: str
    scored_tasks: tuple[str, ...]
    excluded: Mapping[str, str]
    """task -> why it has no normalized score (a missing reference, an oracle below random)."""
    references: Mapping[str, tuple[float, float]]
    """task -> (J_random, J_oracle) of the scored tasks."""
    below_zero_command: Mapping[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    """Scored tasks whose oracle does not beat their zero-command reference (PROTOCOL.md §9): task ->
    (the zero command's return, its normalized score). Their scores are kept and flagged."""


@dataclasses.dataclass(frozen=True)
class Entry:
    """One row of the board: a submission and everything computed from it."""

    submission: Submission
    is_reference: bool
    raw_mean: Mapping[str, float]
    """task -> mean target return over seeds and episodes (every task)."""
    raw_seed_std: Mapping[str, float]
    """task -> standard deviation across training seeds of the per-seed mean return."""
    normalized: np.ndarray | None
    """``(seeds, scored tasks)`` normalized scores; None when the budget has no scored task."""
    iqm: Interval | None
    mean: Interval | None
    optimality_gap: Interval | None

    @property
    def group(self) -> tuple[str, str]:
        return (self.submission.track, self.submission.budget)


@dataclasses.dataclass(frozen=True)
class Improvement:
    """P(X > Y) of two entries of one track and budget, over the budget's scored tasks."""

    x: str
    y: str
    track: str
    budget: str
    probability: Interval


@dataclasses.dataclass(frozen=True)
class Board:
    tasks: tuple[str, ...]
    """The core suite, in protocol order: the columns of the raw returns."""
    normalizations: Mapping[str, Normalization]
    """budget -> the normalization used by that budget's entries (budgets present on the board)."""
    entries: tuple[Entry, ...]
    """Sorted by track, budget, IQM (highest first; unscored last), method name."""
    improvements: tuple[Improvement, ...]


def normalization_for(budget: str, tasks: Sequence[str], references: Path | None) -> Normalization:
    """The tasks of ``tasks`` that have a random and an oracle reference at ``budget``."""
    from offdyn_bench.protocol import ProtocolError, reference_pair, reference_scores
    from offdyn_bench.protocol.references import normalize

    scored, excluded, pairs, below = [], {}, {}, {}
    recorded = reference_scores(references)
    for task in tasks:
        try:
            pairs[task] = reference_pair(task, budget, references)
        except ProtocolError as error:
            excluded[task] = str(error)
            continue
        scored.append(task)
        zero = recorded.get(task, {}).get("zero-command")
        j_random, j_oracle = pairs[task]
        if zero is not None and not j_oracle > zero.mean_return:
            below[task] = (zero.mean_return, float(normalize(np.float64(zero.mean_return), j_random, j_oracle)))
    return Normalization(budget, tuple(scored), excluded, pairs, below)


def _entry(submission: Submission, normalization: Normalization, reference_methods: Sequence[str],
           references: Path | None) -> Entry:
    from offdyn_bench.protocol import normalized_score, statistics

    per_seed = {task: result.returns.mean(axis=1) for task, result in submission.tasks.items()}
    raw_mean = {task: float(result.returns.mean()) for task, result in submission.tasks.items()}
    raw_std = {task: float(values.std()) for task, values in per_seed.items()}
    normalized = aggregates = None
    if normalization.scored_tasks:
        normalized = np.stack([normalized_score(per_seed[task], task, submission.budget, references)
                               for task in normalization.scored_tasks], axis=1)
        name = "/".join(submission.key)
        aggregates = statistics.aggregate({name: normalized}, reps=BOOTSTRAP_REPS, confidence=CONFIDENCE,
                                          seed=BOOTSTRAP_SEED)[name]
    return Entry(submission=submission, is_reference=submission.method in reference_methods,
                 raw_mean=raw_mean, raw_seed_std=raw_std, normalized=normalized,
                 iqm=aggregates["iqm"] if aggregates else None,
                 mean=aggregates["mean"] if aggregates else None,
                 optimality_gap=aggregates["optimality_gap"] if aggregates else None)


def _sort_key(entry: Entry) -> tuple[object, ...]:
    iqm = entry.iqm.point if entry.iqm is not None else float("inf")
    return (entry.submission.track, entry.submission.budget, entry.iqm is None, -iqm, entry.submission.method)


def score_board(submissions: Sequence[Submission], *, references: Path | None = None) -> Board:
    """Score every submission (``references``: the reference-score file, default the shipped one)."""
    from offdyn_bench import protocol
    from offdyn_bench.protocol import statistics

    tasks = tuple(protocol.CORE_SUITE)
    budgets = sorted({s.budget for s in submissions})
    normalizations = {budget: normalization_for(budget, tasks, references) for budget in budgets}
    reference_methods = tuple(getattr(protocol, "REFERENCE_METHODS", {}))
    entries = sorted((_entry(s, normalizations[s.budget], reference_methods, references) for s in submissions),
                     key=_sort_key)

    improvements = []
    by_group: dict[tuple[str, str], list[Entry]] = {}
    for entry in entries:
        if entry.normalized is not None:
            by_group.setdefault(entry.group, []).append(entry)
    for (track, budget), group in sorted(by_group.items()):
        for x in group:
            for y in group:
                if x is y:
                    continue
                seed = statistics.method_seed(BOOTSTRAP_SEED, f"{x.submission.method}>{y.submission.method}")
                probability = statistics.probability_of_improvement_ci(
                    x.normalized, y.normalized, reps=BOOTSTRAP_REPS, confidence=CONFIDENCE, seed=seed)
                improvements.append(Improvement(x.submission.method, y.submission.method, track, budget,
                                                probability))
    return Board(tasks=tasks, normalizations=normalizations, entries=tuple(entries),
                 improvements=tuple(improvements))


def performance_profile(entry: Entry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(profile, low, high) of ``entry`` at :data:`PROFILE_TAUS`; requires scored tasks."""
    from offdyn_bench.protocol import statistics

    assert entry.normalized is not None
    profile = statistics.performance_profile(entry.normalized, PROFILE_TAUS)
    low, high = statistics.performance_profile_ci(entry.normalized, PROFILE_TAUS, reps=BOOTSTRAP_REPS,
                                                  confidence=CONFIDENCE, seed=BOOTSTRAP_SEED)
    return profile, low, high
