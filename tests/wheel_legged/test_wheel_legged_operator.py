"""The human operator: its LQR, its imperfections, its determinism, and the data it records."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

import offdyn_bench  # noqa: F401  (registers the ids)
from offdyn_bench.errors import InvalidParameterError, UnknownNameError
from offdyn_bench.wheel_legged.operator import (
    BalancingController,
    HumanOperator,
    OperatorSettings,
    linearized_control_step,
    lqr_gain,
)


def _drive(env_id: str, operator: HumanOperator, seed: int, steps: int) -> dict[str, np.ndarray | bool]:
    env = gymnasium.make(env_id)
    obs, _ = env.reset(seed=seed)
    operator.start_episode(seed)
    actions, tilts, velocities, xs, terminated = [], [], [], [], False
    for _ in range(steps):
        action = operator(obs)
        obs, _, terminated, truncated, info = env.step(action.astype(np.float32))
        actions.append(action[0])
        tilts.append(info["tilt"])
        velocities.append(info["x_velocity"])
        xs.append(info["x_position"])
        if terminated or truncated:
            break
    return {"actions": np.array(actions), "tilt": np.array(tilts), "velocity": np.array(velocities),
            "x": np.array(xs), "terminated": terminated}


def test_linearization_is_an_unstable_pendulum_that_the_lqr_stabilizes():
    a, b = linearized_control_step()
    assert np.max(np.abs(np.linalg.eigvals(a))) > 1.01  # open loop: it falls
    assert b[2, 0] < 0  # forward wheel torque pushes the body backwards (reaction)
    for task, keep in (("standstill", [0, 1, 2, 3]), ("movestraight", [0, 2, 3])):
        closed = a[np.ix_(keep, keep)] - b[keep] @ lqr_gain(task)[None]
        assert np.max(np.abs(np.linalg.eigvals(closed))) < 1.0


def test_operator_is_reproducible_and_seeded_per_episode():
    first = _drive("offdyn/WheelLegged-standstill-target-v0", HumanOperator("standstill", seed=7), 2, 500)
    second = _drive("offdyn/WheelLegged-standstill-target-v0", HumanOperator("standstill", seed=7), 2, 500)
    np.testing.assert_array_equal(first["actions"], second["actions"])
    # The same operator object, restarted: the episode's commands again, whatever ran before.
    operator = HumanOperator("standstill", seed=7)
    _drive("offdyn/WheelLegged-standstill-target-v0", operator, 9, 300)
    again = _drive("offdyn/WheelLegged-standstill-target-v0", operator, 2, 500)
    np.testing.assert_array_equal(first["actions"], again["actions"])
    other = _drive("offdyn/WheelLegged-standstill-target-v0", HumanOperator("standstill", seed=8), 2, 500)
    assert not np.array_equal(first["actions"], other["actions"])


@pytest.mark.parametrize("task", ["standstill", "movestraight"])
def test_operator_keeps_the_real_robot_near_balance_but_imperfectly(task):
    steps = {"standstill": 6000, "movestraight": 4000}[task]
    env_id = f"offdyn/WheelLegged-{task}-target-v0"
    human = _drive(env_id, HumanOperator(task, seed=0), seed=1, steps=steps)
    assert not human["terminated"] and len(human["actions"]) == steps
    assert np.mean(np.abs(human["tilt"]) < 0.05) > 0.99  # mostly near the balanced state
    # Human-like: it wanders more than the clean controller does in the same system.
    clean = BalancingController(task)
    env = gymnasium.make(env_id)
    obs, _ = env.reset(seed=1)
    clean_x, clean_actions = [], []
    for _ in range(steps):
        action = clean(obs)
        obs, _, _, _, info = env.step(action.astype(np.float32))
        clean_x.append(info["x_position"])
        clean_actions.append(action[0])
    assert np.std(human["actions"]) > np.std(clean_actions)
    if task == "standstill":
        assert np.max(np.abs(human["x"])) > 2 * np.max(np.abs(clean_x))
        assert np.max(np.abs(human["x"])) < 0.5
    else:
        assert np.mean(human["velocity"][400:]) == pytest.approx(0.2, abs=0.05)


def test_operator_corrects_after_its_reaction_delay():
    """Noticing the robot 0.1 m off, the person re-centres the set-point 50 steps later."""
    settings = OperatorSettings(command_noise_std=0.0, trim_std=0.0, setpoint_drift=0.0,
                                random_correction_rate_hz=0.0, reaction_delay_steps=50)
    operator = HumanOperator("standstill", seed=0, settings=settings)
    operator.start_episode(0)
    operator.reference[1] = 0.3  # the set-point the stick drifted to
    far = np.array([0.0, 0.3, 0.0, 0.0])  # the robot went there
    for _ in range(50):
        operator(far)
        assert operator.reference[1] == 0.3
    operator(far)
    assert operator.reference[1] == 0.0


def test_clean_controller_is_the_operator_without_imperfections():
    settings = OperatorSettings(loop_delay_steps=0, command_noise_std=0.0, trim_std=0.0, setpoint_drift=0.0,
                                random_correction_rate_hz=0.0)
    operator = HumanOperator("movestraight", seed=0, settings=settings)
    clean = BalancingController("movestraight")
    rng = np.random.default_rng(0)
    for _ in range(20):
        obs = rng.normal(0, 0.05, 3)
        np.testing.assert_array_equal(operator(obs), clean(obs))


def test_bad_operator_input_is_a_clear_error():
    with pytest.raises(UnknownNameError, match="unknown wheel-legged task 'hop'"):
        lqr_gain("hop")
    with pytest.raises(InvalidParameterError, match="reaction_delay_steps"):
        OperatorSettings(reaction_delay_steps=-1)
    with pytest.raises(InvalidParameterError, match="trim_time_constant_s"):
        OperatorSettings(trim_time_constant_s=0.0)
