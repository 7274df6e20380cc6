"""Users bring their own simulators: any Gymnasium MuJoCo env id works as the source."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

from offdyn_bench.diagnose import DiagnosisSettings, Transitions, diagnose
from offdyn_bench.effects import Gear, apply_model_effects


def _record_swimmer_with_weaker_motors(steps_per_episode: int = 100, episodes: int = 8) -> dict[str, np.ndarray]:
    env = gymnasium.make("Swimmer-v5")
    inner = env.unwrapped
    apply_model_effects(inner.model, [Gear(target=None, scale=0.6)])  # the "real" swimmer, unknown to the tool
    rng = np.random.default_rng(0)
    columns: dict[str, list] = {k: [] for k in ("observations", "actions", "next_observations", "terminations",
                                                "truncations", "qpos", "qvel")}
    for episode in range(episodes):
        obs, _ = env.reset(seed=episode)
        for t in range(steps_per_episode):
            qpos, qvel = inner.data.qpos.copy(), inner.data.qvel.copy()
            action = rng.uniform(-1, 1, 2)
            next_obs, _, terminated, truncated, _ = env.step(action)
            row = (obs, action, next_obs, terminated, truncated or t == steps_per_episode - 1, qpos, qvel)
            for key, value in zip(columns, row):
                columns[key].append(value)
            obs = next_obs
    return {k: np.asarray(v) for k, v in columns.items()}


def test_a_gymnasium_env_outside_the_suite() -> None:
    result = diagnose("Swimmer-v5", Transitions(**_record_swimmer_with_weaker_motors()),
                      DiagnosisSettings(screen_rows=300, fit_rows=500))
    assert [(e["kind"], e["target"]) for e in result.effects_added] == [("gear", None)]
    assert result.effects_added[0]["value"] == pytest.approx(0.6, rel=0.01)
    assert not result.unexplained_residual
    calibrated = result.calibrated_env
    assert calibrated["builder"] == "apply to env.unwrapped.model"
    assert calibrated["effects"] == [{"kind": "gear", "target": None, "scale": pytest.approx(0.6, rel=0.01)}]
