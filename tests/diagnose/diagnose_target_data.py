"""Target data from systems with effects nothing declares to the diagnosis, and the check that a
diagnosis found them."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pytest

from offdyn_bench import make_robot_env
from offdyn_bench.diagnose import Diagnosis


def record(effects: Sequence[dict[str, Any]], steps: int, *, robot: str = "Hopper", seed: int = 0,
           with_state: bool = True, edit_model: Callable[[Any], None] | None = None,
           command_scale: float = 1.0, **env_kwargs: Any) -> dict[str, np.ndarray]:
    """Roll a random behaviour policy with smooth and jumpy parts (excites every actuator over its
    whole range) in ``robot`` with ``effects``; return the npz arrays of the diagnosis contract.
    ``edit_model`` changes the compiled target model in place (an effect outside the vocabulary);
    ``command_scale`` shrinks every command (a gentle behaviour policy, commands in
    ``[-command_scale, command_scale]``); ``env_kwargs`` go to the robot's Gymnasium constructor."""
    env = make_robot_env(robot, effects=effects, **env_kwargs)
    if edit_model is not None:
        edit_model(env.unwrapped.model)
    rng = np.random.default_rng(seed)
    columns: dict[str, list] = {k: [] for k in ("observations", "actions", "next_observations", "terminations",
                                                "truncations", "qpos", "qvel")}
    nq = env.unwrapped.model.nq
    nv = env.unwrapped.model.nv
    size = env.action_space.shape[0]
    episode = 0
    while len(columns["actions"]) < steps:
        obs, _ = env.reset(seed=seed * 10_000 + episode)
        phase = rng.uniform(0, 2 * np.pi, size)
        frequency = rng.uniform(0.05, 0.3, size)
        for t in range(200):
            smooth = np.sin(frequency * t + phase)
            action = command_scale * np.clip(0.6 * smooth + rng.uniform(-0.7, 0.7, size), -1, 1)
            next_obs, _, terminated, truncated, info = env.step(action)
            truncated = truncated or t == 199 or len(columns["actions"]) + 1 >= steps
            columns["observations"].append(obs)
            columns["actions"].append(action)
            columns["next_observations"].append(next_obs)
            columns["terminations"].append(terminated)
            columns["truncations"].append(truncated and not terminated)
            columns["qpos"].append(info["prev_state"][1:1 + nq])
            columns["qvel"].append(info["prev_state"][1 + nq:1 + nq + nv])
            obs = next_obs
            if terminated or truncated:
                break
        episode += 1
    out = {k: np.asarray(v) for k, v in columns.items()}
    if not with_state:
        del out["qpos"], out["qvel"]
    return out


def assert_diagnosed(result: Diagnosis, expected: list[tuple[str, str | int | None, float]]) -> None:
    """The diagnosis named exactly the ``(kind, target)`` pairs expected, fitted each value within
    10%, and brought the held-out error to the noise floor."""
    found = {(e["kind"], e["target"]): e["value"] for e in result.effects_added}
    assert set(found) == {(kind, target) for kind, target, _ in expected}, result.effects_added
    for kind, target, value in expected:
        assert found[(kind, target)] == pytest.approx(value, rel=0.10), (kind, target, found)
    after = result.error_after
    assert not result.unexplained_residual, result.stop_reason
    assert after.heldout_trimmed_nrmse <= 1.1 * result.noise_floor + 1e-3
    assert after.heldout_trimmed_nrmse < 0.1 * result.error_before.heldout_trimmed_nrmse
    # Untrimmed, a held-out command that falls between the recorded ones that located a threshold
    # keeps a little error: no finite sample pins a dead zone down further.
    assert after.heldout_one_step_nrmse < 0.5 * result.error_before.heldout_one_step_nrmse
    assert after.horizon_nrmse < result.error_before.horizon_nrmse
