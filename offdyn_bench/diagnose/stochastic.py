"""Stochastic effects, read off the spread of the residual that no deterministic effect explains.

Observation noise is the noise floor itself (see :meth:`ResidualEvaluator.noise_floor`): it is
measured and reported, never added. Action noise leaves a residual that a per-step correction
of the command explains: with ``B_t`` the sensitivity of the prediction to the command (finite
differences through the same batched rollouts), the least-squares correction ``da_t`` of every row
is computed; if these corrections explain most of the residual, the residual lives in the action
channel and the spread of ``da`` is the noise's standard deviation.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from offdyn_bench.diagnose.residual import Hypothesis, ResidualEvaluator
from offdyn_bench.effects import ActionBias
from offdyn_bench.effects.model import actuator_name


@dataclasses.dataclass(frozen=True)
class ActionChannelShare:
    """How much of the residual a per-step command correction explains, and that correction."""

    share: float
    corrections: np.ndarray  # [rows, nu], in command units
    commands: np.ndarray  # [rows, nu], the commands the corrections apply to


def action_channel_share(evaluator: ResidualEvaluator, hypothesis: Hypothesis, subset: str = "screen",
                         step: float = 0.05) -> ActionChannelShare:
    """Fraction of the one-step residual explained by the best per-row command correction."""
    model = evaluator.source.base_model
    residual, = evaluator.residuals([hypothesis], subset)
    commands = evaluator.applied_actions(hypothesis)[evaluator.subsets[subset]]
    # Nudge every command towards the middle of its range, so a command at its limit is not
    # clipped back and read as insensitive.
    nudged = [hypothesis + (ActionBias(target=actuator_name(model, a), value=sign * step),)
              for a in range(model.nu) for sign in (1.0, -1.0)]
    moved = evaluator.residuals(nudged, subset)
    columns = []
    for a in range(model.nu):
        up, down = (moved[2 * a] - residual) / step, (residual - moved[2 * a + 1]) / step
        inward = (commands[:, a] > 0)[:, None]
        columns.append(np.where(inward, down, up))
    sensitivity = np.stack(columns, axis=2)  # [rows, dims, nu]
    corrections = np.empty((len(residual), model.nu))
    explained = np.empty_like(residual)
    for t in range(len(residual)):
        solution, *_ = np.linalg.lstsq(sensitivity[t], -residual[t], rcond=None)
        corrections[t] = solution
        explained[t] = -sensitivity[t] @ solution
    total = float(np.sum(residual**2))
    share = 1.0 - float(np.sum((residual - explained) ** 2)) / total if total > 0 else 0.0
    return ActionChannelShare(share=share, corrections=corrections, commands=commands)


@dataclasses.dataclass(frozen=True)
class NoiseEstimate:
    """A fitted action noise: its standard deviation and a 95% interval."""

    std: float
    interval: tuple[float, float]
    share: float


def estimate_action_noise(evaluator: ResidualEvaluator, hypothesis: Hypothesis, *,
                          min_share: float = 0.8) -> NoiseEstimate | None:
    """Action noise on every actuator, when the residual lives in the action channel and the
    corrections look like zero-mean noise unrelated to the command; None otherwise."""
    found = action_channel_share(evaluator, hypothesis)
    if found.share < min_share:
        return None
    corrections = found.corrections
    # Systematic command errors (a gain, a bias, a dead zone) correlate with the command or have
    # a mean: the deterministic search should have caught them; noise does neither.
    for a in range(corrections.shape[1]):
        c = corrections[:, a]
        if abs(c.mean()) > 3 * c.std() / np.sqrt(len(c)) + 1e-3:
            return None
        if np.std(found.commands[:, a]) > 0 and abs(np.corrcoef(c, found.commands[:, a])[0, 1]) > 0.2:
            return None
    # Robust spread (median absolute correction): rows where the command barely moves the robot
    # (a joint on its limit, a foot in the air) give huge, meaningless corrections. Commands near
    # their limit are left out, since the actuator clips their noise.
    limit = np.max(np.abs(found.commands), axis=0, keepdims=True)
    inside = np.abs(found.commands) < 0.8 * np.maximum(limit, 1e-12)
    values = np.abs(corrections[inside])
    if values.size < 20:
        return None
    std = float(1.4826 * np.median(values))
    n = values.size
    half = 1.96 * 1.25 * std / np.sqrt(2 * n)  # the median's standard error is ~1.25x the RMS's
    return NoiseEstimate(std=std, interval=(max(0.0, std - half), std + half), share=found.share)
