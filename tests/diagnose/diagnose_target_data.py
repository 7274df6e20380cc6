"""Target data from systems with effects nothing declares to the diagnosis."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from offdyn_bench import make_robot_env


def record(effects: Sequence[dict[str, Any]], steps: int, *, robot: str = "Hopper", seed: int = 0,
           with_state: bool = True) -> dict[str, np.ndarray]:
    """Roll a random behaviour policy with smooth and jumpy parts (excites every actuator over its
    whole range) in ``robot`` with ``effects``; return the npz arrays of the diagnosis contract."""
    env = make_robot_env(robot, effects=effects)
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
            action = np.clip(0.6 * smooth + rng.uniform(-0.7, 0.7, size), -1, 1)
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
