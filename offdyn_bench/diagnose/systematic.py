"""Is what is left of the residual systematic? A residual that the state and the command predict
is a model error, whatever a noise model fitted to its spread would say.

The test regresses the normalized one-step residual on quadratic features of the observation and
the applied command, fitted on training episodes and scored on held-out ones (so a regression that
merely memorizes rows scores nothing). Noise in the command or the sensors is unpredictable from
the state that precedes it: its held-out R^2 is about zero. A missing effect, a wrong geometry or a
wrong contact model is a function of state and command: it scores well above zero.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from offdyn_bench.diagnose.residual import Hypothesis, ResidualEvaluator

# Held-out R^2 above this marks the residual systematic. Pure noise scores about -features/rows
# (a ridge fit of nothing); a tenth of the residual's energy predictable is a model error worth
# reporting, and a level noise never reaches on held-out episodes.
SYSTEMATIC_R2 = 0.1
MAX_ROWS = 6000


@dataclasses.dataclass(frozen=True)
class Predictability:
    """How much of the residual quadratic features of state and command predict on held-out
    episodes (1 - SSE / sum of squares about zero), over all dimensions and per dimension."""

    heldout_r2: float
    per_dimension: tuple[float, ...]
    features: int
    rows: int

    @property
    def systematic(self) -> bool:
        return self.heldout_r2 >= SYSTEMATIC_R2

    def to_json(self) -> dict[str, object]:
        return {"heldout_r2": self.heldout_r2, "per_dimension_r2": list(self.per_dimension),
                "features": self.features, "rows": self.rows, "systematic": self.systematic,
                "threshold": SYSTEMATIC_R2}


def _features(observations: np.ndarray, commands: np.ndarray, mean: np.ndarray, scale: np.ndarray) -> np.ndarray:
    base = (np.concatenate([observations, commands], axis=1) - mean) / scale
    upper = np.triu_indices(base.shape[1])
    products = (base[:, :, None] * base[:, None, :])[:, upper[0], upper[1]]
    return np.concatenate([np.ones((len(base), 1)), base, products], axis=1)


def residual_predictability(evaluator: ResidualEvaluator, hypothesis: Hypothesis, *, ridge: float = 1.0,
                            seed: int = 0) -> Predictability:
    """Fit the residual of ``hypothesis`` on training rows, score it on held-out episodes."""
    rng = np.random.default_rng(seed)
    rows = {}
    for subset in ("train", "heldout"):
        all_rows = evaluator.subsets[subset]
        rows[subset] = np.sort(rng.choice(len(all_rows), size=min(MAX_ROWS, len(all_rows)), replace=False))
    train_residual, = evaluator.residuals([hypothesis], "train")
    heldout_residual, = evaluator.residuals([hypothesis], "heldout")
    train_residual, heldout_residual = train_residual[rows["train"]], heldout_residual[rows["heldout"]]
    train_rows = evaluator.subsets["train"][rows["train"]]
    heldout_rows = evaluator.subsets["heldout"][rows["heldout"]]
    commands = evaluator.applied_actions(hypothesis)
    observations = evaluator.data.observations[:, evaluator.dims]  # state coordinates (not e.g. contact forces)
    raw = np.concatenate([observations[train_rows], commands[train_rows]], axis=1)
    mean, scale = raw.mean(axis=0), raw.std(axis=0)
    scale = np.where(scale > 1e-12, scale, 1.0)
    x_train = _features(observations[train_rows], commands[train_rows], mean, scale)
    x_heldout = _features(observations[heldout_rows], commands[heldout_rows], mean, scale)
    gram = x_train.T @ x_train + ridge * np.eye(x_train.shape[1])
    gram[0, 0] -= ridge  # the intercept is not shrunk: a constant offset is the plainest systematic error
    coefficients = np.linalg.solve(gram, x_train.T @ train_residual)
    left = heldout_residual - x_heldout @ coefficients
    energy = np.sum(heldout_residual**2, axis=0)
    per_dim = 1.0 - np.sum(left**2, axis=0) / np.maximum(energy, 1e-300)
    total = 1.0 - float(np.sum(left**2)) / max(float(np.sum(energy)), 1e-300)
    return Predictability(heldout_r2=total, per_dimension=tuple(float(x) for x in per_dim),
                          features=int(x_train.shape[1]), rows=int(len(train_rows)))
