"""What the data can and cannot resolve about the fitted effects.

At the fitted values, the Jacobian of the one-step residual with respect to every smooth effect
(in units of each candidate's probe step, so kilograms and radians weigh alike) tells which
combinations the data pin down: its singular values, and the directions whose singular value is
tiny against the largest, along which the effects can move together while the prediction barely
changes (scaling every mass and every force together, for instance; a weaker motor and a weaker
command, while commands stay in range).

Intervals come from an episode bootstrap of the fit, linearized at the optimum: episodes are
resampled with replacement and the Gauss-Newton step that refits every effect to the resample is
taken. Episodes, not rows, are the independent units (rows within one are correlated, and a
model error is shared by the rows of a state region), so these intervals are wider than the
row-wise curvature intervals and honest about misspecification that varies across the data.

Drift: the same linearized refit on the earlier and on the later half of the episodes (in
recording order). Every effect of the vocabulary is constant, so a value that moves between the
halves by far more than their bootstrap spread (a tyre wearing, a motor warming up) is something
the calibrated model cannot express: it is reported, with both values, not averaged away silently.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from offdyn_bench.diagnose.candidates import Candidate
from offdyn_bench.diagnose.residual import Hypothesis, ResidualEvaluator

# A direction whose singular value is below this fraction of the largest is not resolved: moving
# the effects along it changes the prediction twenty times less than along the best-resolved one.
# Not smaller: an exact symmetry of a contact-rich model still shows a few percent here, since a
# finite difference across a contact switching on is no derivative. The loop then tests each such
# direction on held-out data before it fixes a gauge.
UNRESOLVED_RATIO = 0.05
BOOTSTRAP_RESAMPLES = 400
# A value drifts when its two halves differ by more than this many standard errors of the
# difference (a few effects are tested at once, and the episodes of a recording are few).
DRIFT_Z = 4.0
# Each half needs this many episodes for its bootstrap spread to mean anything.
DRIFT_MIN_EPISODES = 4


@dataclasses.dataclass(frozen=True)
class Drift:
    """An effect whose fitted value differs between the earlier and the later episodes."""

    label: str
    earlier: float
    later: float
    z: float

    def to_json(self) -> dict[str, object]:
        return {"effect": self.label, "earlier_half": self.earlier, "later_half": self.later, "z": self.z}


@dataclasses.dataclass(frozen=True)
class Identifiability:
    labels: tuple[str, ...]
    singular_values: tuple[float, ...]
    unresolved: tuple[dict[str, float], ...]
    """Each unresolved direction as ``{effect label: component}`` (unit length in probe units)."""
    intervals: dict[str, tuple[float, float]]
    resamples: int
    drifts: tuple[Drift, ...] = ()
    """Effects whose value moves between the earlier and the later half of the episodes."""

    def to_json(self) -> dict[str, object]:
        top = max(self.singular_values) if self.singular_values else 0.0
        return {
            "effects": list(self.labels),
            "singular_values": list(self.singular_values),
            "relative_singular_values": [s / top if top > 0 else 0.0 for s in self.singular_values],
            "unresolved_directions": [dict(d) for d in self.unresolved],
            "interval_method": f"episode bootstrap ({self.resamples} resamples), linearized at the fit",
            "drifts": [d.to_json() for d in self.drifts],
        }


def _jacobian(evaluator: ResidualEvaluator, hypothesis: Hypothesis, fitted: Sequence[tuple[int, Candidate, float]],
              subset: str) -> tuple[np.ndarray, np.ndarray]:
    """Residual ``[rows, dims]`` at the fit and its Jacobian ``[rows, dims, k]`` per probe step,
    by central differences (a forward difference's curvature error would hide an exact symmetry
    behind a singular value of the order of the step)."""
    base, = evaluator.search_residuals([hypothesis], subset)
    moved_hypotheses, spans = [], []
    for index, candidate, value in fitted:
        half = 0.1 * candidate.probe
        up, down = min(value + half, candidate.high), max(value - half, candidate.low)
        spans.append((up - down) / candidate.probe)
        for moved in (up, down):
            moved_hypotheses.append(hypothesis[:index] + (candidate.effect(moved),) + hypothesis[index + 1:])
    moved = evaluator.search_residuals(moved_hypotheses, subset)
    columns = [(moved[2 * i] - moved[2 * i + 1]) / spans[i] for i in range(len(fitted))]
    return base, np.stack(columns, axis=2)


def identifiability(evaluator: ResidualEvaluator, hypothesis: Hypothesis,
                    fitted: Sequence[tuple[int, Candidate, float]], *, subset: str = "fit",
                    seed: int = 0) -> Identifiability | None:
    """Singular values, unresolved directions and episode-bootstrap intervals of the smooth
    effects ``fitted`` (``(position in hypothesis, candidate, value)``); ``None`` if there are none."""
    if not fitted:
        return None
    labels = tuple(candidate.label for _, candidate, _ in fitted)
    residual, jacobian = _jacobian(evaluator, hypothesis, fitted, subset)
    rows = evaluator.search_starts[subset]
    flat_j = jacobian.reshape(-1, len(fitted))
    _, singular, right = np.linalg.svd(flat_j, full_matrices=False)
    top = float(singular[0]) if singular.size else 0.0
    unresolved = []
    for s, direction in zip(singular, right):
        if top > 0 and s < UNRESOLVED_RATIO * top and len(fitted) > 1:
            unresolved.append({label: round(float(c), 4) for label, c in zip(labels, direction) if abs(c) > 0.05})

    # Per-episode normal equations; a resample adds them up with the episode's multiplicity.
    episodes, which = np.unique(evaluator.episode[rows], return_inverse=True)
    k = len(fitted)
    grams = np.zeros((len(episodes), k, k))
    moments = np.zeros((len(episodes), k))
    np.add.at(grams, which, np.einsum("rdk,rdl->rkl", jacobian, jacobian))
    np.add.at(moments, which, np.einsum("rdk,rd->rk", jacobian, residual))
    rng = np.random.default_rng(seed)
    values = np.array([value for _, _, value in fitted])
    probes = np.array([candidate.probe for _, candidate, _ in fitted])
    ridge = 1e-9 * max(top**2, 1e-300) * np.eye(k)

    def refits(chosen: np.ndarray) -> np.ndarray:
        """Linearized refits on bootstrap resamples of the episodes ``chosen`` (indices)."""
        draws = []
        for _ in range(BOOTSTRAP_RESAMPLES):
            counts = np.bincount(chosen[rng.integers(0, len(chosen), len(chosen))], minlength=len(episodes))
            gram = np.tensordot(counts, grams, axes=1) + ridge
            moment = np.tensordot(counts, moments, axes=1)
            draws.append(values - probes * np.linalg.solve(gram, moment))
        return np.array(draws)

    samples = refits(np.arange(len(episodes)))
    intervals = {}
    for i, (_, candidate, value) in enumerate(fitted):
        low, high = np.percentile(samples[:, i], [2.5, 97.5])
        low, high = min(low, value), max(high, value)  # a skewed resample keeps the fit inside
        intervals[labels[i]] = (float(max(candidate.low, low)), float(min(candidate.high, high)))
    # A direction along one effect alone is no trade-off between effects, only a weak lever: its
    # singular value is small against the others' (a tyre's friction next to a drive's), yet the
    # data may still pin it. It is unresolved only if its bootstrap interval spans a probe step.
    probe_of = {candidate.label: candidate.probe for _, candidate, _ in fitted}

    def pinned_alone(direction: dict[str, float]) -> bool:
        if len(direction) != 1:
            return False
        label, = direction
        low, high = intervals[label]
        return high - low < probe_of[label]

    unresolved = [d for d in unresolved if not pinned_alone(d)]
    drifts: list[Drift] = []
    if len(episodes) >= 2 * DRIFT_MIN_EPISODES:
        # np.unique sorted the episode indices, which count up in recording order.
        halves = np.array_split(np.arange(len(episodes)), 2)
        (earlier, spread_earlier), (later, spread_later) = [
            (np.median(draws, axis=0), np.std(draws, axis=0)) for draws in map(refits, halves)]
        for i, label in enumerate(labels):
            change = abs(float(later[i] - earlier[i]))
            spread = float(np.hypot(spread_earlier[i], spread_later[i]))
            z = change / spread if spread > 0 else (np.inf if change > 0 else 0.0)
            # Also a change that matters: a tenth of the candidate's probe step.
            if z > DRIFT_Z and change >= 0.1 * probes[i]:
                drifts.append(Drift(label, float(earlier[i]), float(later[i]), round(min(z, 1e6), 1)))
    return Identifiability(labels=labels, singular_values=tuple(float(s) for s in singular),
                           unresolved=tuple(unresolved), intervals=intervals, resamples=BOOTSTRAP_RESAMPLES,
                           drifts=tuple(drifts))
