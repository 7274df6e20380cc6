"""Is what is left of the residual systematic? A residual that the state and the command predict
is a model error, whatever a noise model fitted to its spread would say.

Two predictors of the normalized one-step residual from the observation and the applied command
are fitted on training episodes and scored on held-out ones (so a predictor that merely memorizes
rows scores nothing): a ridge regression on quadratic features, for errors that vary smoothly
over the state space (a mass, a gear), and the mean residual of the nearest training rows, for
errors that live in a small region of it (a joint limit, a contact that differs). Noise in the
command or the sensors is unpredictable from the state that precedes it: its held-out R^2 is about
zero for the first and about -1/k for the second. A missing effect, a wrong geometry or a wrong
contact model is a function of state and command: one of the two scores well above zero.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from offdyn_bench.diagnose.residual import Hypothesis, ResidualEvaluator, physics_key
from offdyn_bench.effects.model import ModelEffect

# Held-out R^2 above this marks the residual systematic. Pure noise scores about -features/rows
# (a ridge fit of nothing); a tenth of the residual's energy predictable is a model error worth
# reporting, and a level noise never reaches on held-out episodes.
SYSTEMATIC_R2 = 0.1
MAX_ROWS = 6000
NEIGHBOURS = 10


@dataclasses.dataclass(frozen=True)
class Predictability:
    """How much of the residual state and command predict on held-out episodes (1 - SSE / sum of
    squares about zero): the better of the two predictors, over all dimensions and per dimension."""

    heldout_r2: float
    per_dimension: tuple[float, ...]
    features: int
    rows: int
    quadratic_r2: float = 0.0
    neighbour_r2: float = 0.0

    @property
    def systematic(self) -> bool:
        return self.heldout_r2 >= SYSTEMATIC_R2

    def to_json(self) -> dict[str, object]:
        return {"heldout_r2": self.heldout_r2, "per_dimension_r2": list(self.per_dimension),
                "quadratic_r2": self.quadratic_r2, "nearest_neighbour_r2": self.neighbour_r2,
                "neighbours": NEIGHBOURS,
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
    energy = np.sum(heldout_residual**2, axis=0)

    def scores(predicted: np.ndarray) -> tuple[float, np.ndarray]:
        left = heldout_residual - predicted
        per_dim = 1.0 - np.sum(left**2, axis=0) / np.maximum(energy, 1e-300)
        return 1.0 - float(np.sum(left**2)) / max(float(np.sum(energy)), 1e-300), per_dim

    quadratic, quadratic_dims = scores(x_heldout @ coefficients)
    from scipy.spatial import cKDTree

    base_train = x_train[:, 1:1 + raw.shape[1]]  # the standardized observation and command
    base_heldout = x_heldout[:, 1:1 + raw.shape[1]]
    _, neighbours = cKDTree(base_train).query(base_heldout, k=min(NEIGHBOURS, len(base_train)))
    neighbour, neighbour_dims = scores(train_residual[np.atleast_2d(neighbours.T).T].mean(axis=1))
    best, dims = (quadratic, quadratic_dims) if quadratic >= neighbour else (neighbour, neighbour_dims)
    return Predictability(heldout_r2=best, per_dimension=tuple(float(x) for x in dims),
                          features=int(x_train.shape[1]), rows=int(len(train_rows)),
                          quadratic_r2=quadratic, neighbour_r2=neighbour)


# A noise hypothesis is refused when the H-step error grows this much beyond what the fitted noise
# makes it grow: independent kicks add up like a random walk, a model error coherently.
HORIZON_EXCESS = 1.5


@dataclasses.dataclass(frozen=True)
class HorizonCheck:
    """The H-step open-loop error observed, against the one a fitted action noise would give."""

    observed: float
    under_noise: float

    @property
    def ratio(self) -> float:
        return self.observed / max(self.under_noise, 1e-300)

    @property
    def consistent(self) -> bool:
        return self.ratio <= HORIZON_EXCESS


def horizon_under_action_noise(evaluator: ResidualEvaluator, hypothesis: Hypothesis, std: float, *,
                               seed: int = 0) -> HorizonCheck | None:
    """Roll the training windows forward H steps once with the recorded commands and once with the
    commands plus noise of ``std``: if the data's own noise were that, the recorded H-step
    observations would differ from the noiseless prediction by as much as the noisy rollouts do.
    ``None`` when no window of H steps exists."""
    starts = evaluator.windows["train"]
    if len(starts) == 0 or evaluator.horizon < 2:
        return None
    starts = starts[: max(1, MAX_ROWS // evaluator.horizon)]
    observed, = evaluator.residuals([hypothesis], "train", evaluator.horizon)
    source = evaluator.source
    model = source.model_with(tuple(e for e in physics_key(hypothesis, evaluator.rebuilt) if isinstance(e, ModelEffect)))
    offsets = np.arange(evaluator.horizon)
    commands = evaluator.applied_actions(hypothesis)[starts[:, None] + offsets]
    rng = np.random.default_rng(seed)
    noisy = commands + std * rng.standard_normal(commands.shape)
    low, high = source.base_model.actuator_ctrlrange.T
    limited = source.base_model.actuator_ctrllimited.astype(bool)
    noisy = np.where(limited, np.clip(noisy, low, high), noisy)
    states = evaluator._states_for(hypothesis)[starts]  # the start states the residual uses
    both = source.predict(model, np.concatenate([states, states]), np.concatenate([commands, noisy]))
    read = source.observation_map.observe(source.qpos_qvel(both[:, -1]))
    spread = (read[: len(starts)] - read[len(starts):]) / evaluator.horizon_spread
    return HorizonCheck(observed=float(np.sqrt(np.mean(observed[: len(starts)] ** 2))),
                        under_noise=float(np.sqrt(np.mean(spread**2))))
