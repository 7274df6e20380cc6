"""Version 1 of the joint-noise pairs: the control cost is charged on the commanded action.

Version 0's target charges Gymnasium's control cost on the noisy action that reached the motors,
so the reward shifts with the dynamics. Version 1 charges the policy's own action on both sides:
the same trajectory, the same physics, one reward function.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

from offdyn_bench.effects import ActionNoise, Gravity
from offdyn_bench.envs import CommandedControlCost, make_robot_env
from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.tasks import TASKS, TaskPair, get_task

JOINT_NOISE_V1 = sorted(name for name, pair in TASKS.items() if pair.shift == "joint-noise" and pair.version == 1)


def _control_weight(env: gymnasium.Env) -> float:
    return float(env.unwrapped.control_cost(np.ones(1)))  # weight x 1^2


def _steps(env: gymnasium.Env, actions: np.ndarray, seed: int) -> tuple[list, list, list, list]:
    obs, _ = env.reset(seed=seed)
    observations, rewards, infos, applied = [obs], [], [], []
    for action in actions:
        obs, reward, terminated, truncated, info = env.step(action)
        observations.append(obs)
        rewards.append(reward)
        infos.append(info)
        applied.append(np.array(info["applied_action"], dtype=float))
        if terminated or truncated:
            break
    return observations, rewards, infos, applied


def test_every_locomotion_robot_has_version_1_of_each_joint_noise_level():
    assert JOINT_NOISE_V1 == sorted(f"{robot}-joint-noise-{std}-v1" for robot in ("ant", "halfcheetah", "hopper",
                                                                                 "walker2d")
                                    for std in ("0.1", "0.5", "1.0"))
    for name in JOINT_NOISE_V1:
        new, old = TASKS[name], TASKS[name.removesuffix("-v1")]
        assert (new.version, old.version) == (1, 0)
        assert (new.control_cost_on, old.control_cost_on) == ("commanded", "applied")
        assert new.target_effects == old.target_effects and new.source_effects == old.source_effects
        assert new.env_id("target") == old.env_id("target").removesuffix("-v0") + "-v1"
        # The nominal source is the one every pair of the robot shares: RL on source trains once.
        assert new.source_key == old.source_key
        assert "control_cost_on" not in new.env_kwargs("source")
        assert new.env_kwargs("target")["control_cost_on"] == "commanded"


def test_version_names_resolve_and_both_versions_are_registered():
    assert get_task("ant-joint-noise-0.5-v1") is TASKS["ant-joint-noise-0.5-v1"]
    assert get_task("Ant-Joint-Noise-0.5-V1") is TASKS["ant-joint-noise-0.5-v1"]
    assert get_task("ant-joint-noise-0.5-v0") is TASKS["ant-joint-noise-0.5"]
    assert get_task("hopper-gravity-0.5-v0") is TASKS["hopper-gravity-0.5"]
    assert get_task("offdyn/Ant-joint-noise-0.5-target-v1") is TASKS["ant-joint-noise-0.5-v1"]
    assert get_task("offdyn/Ant-joint-noise-0.5-target-v0") is TASKS["ant-joint-noise-0.5"]
    for version in (0, 1):
        assert f"offdyn/Ant-joint-noise-0.5-target-v{version}" in gymnasium.registry
    with pytest.raises(UnknownNameError, match="unknown task 'ant-joint-noise-0.5-v2'"):
        get_task("ant-joint-noise-0.5-v2")
    with pytest.raises(UnknownNameError, match="unknown task 'hopper-gravity-0.5-v1'"):
        get_task("hopper-gravity-0.5-v1")


def test_version_1_round_trips_as_data_and_version_0_keeps_its_definition():
    pair = TASKS["walker2d-joint-noise-1.0-v1"]
    data = pair.to_dict()
    assert data["control_cost_on"] == "commanded" and data["version"] == 1
    assert data["name"] == "walker2d-joint-noise-1.0-v1"
    assert TaskPair.from_dict(data) == pair
    # Version 0's definition (what dataset recipes hash) has no new key.
    assert "control_cost_on" not in TASKS["walker2d-joint-noise-1.0"].to_dict()


@pytest.mark.parametrize("name", JOINT_NOISE_V1)
def test_version_1_runs_version_0s_trajectory_and_charges_only_the_command(name):
    """Same seed, same commands: the same states and noise; the reward differs by exactly the
    cost of the noise, and the control term is the commanded action's, as in the source."""
    new, old = TASKS[name], TASKS[name.removesuffix("-v1")]
    env_new, env_old, source = new.make("target"), old.make("target"), new.make("source")
    actions = np.random.default_rng(5).uniform(-1, 1, size=(40, env_new.action_space.shape[0]))
    obs_new, rewards_new, infos_new, applied_new = _steps(env_new, actions, seed=11)
    obs_old, rewards_old, infos_old, applied_old = _steps(env_old, actions, seed=11)
    assert len(rewards_new) == len(rewards_old) > 0
    np.testing.assert_array_equal(np.array(obs_new), np.array(obs_old))
    np.testing.assert_array_equal(np.array(applied_new), np.array(applied_old))
    weight = _control_weight(env_new)
    for t, (action, applied) in enumerate(zip(actions, applied_new)):
        commanded_cost, applied_cost = weight * np.sum(action ** 2), weight * np.sum(applied ** 2)
        assert not np.allclose(applied, action)  # the noise is there
        assert infos_new[t]["reward_ctrl"] == pytest.approx(-commanded_cost, rel=1e-12)
        assert infos_new[t]["reward_ctrl_applied"] == pytest.approx(-applied_cost, rel=1e-12)
        assert infos_old[t]["reward_ctrl"] == pytest.approx(-applied_cost, rel=1e-12)
        assert rewards_new[t] - rewards_old[t] == pytest.approx(applied_cost - commanded_cost, rel=1e-9, abs=1e-9)
    # The source charges the same command the same: one reward function on both sides.
    source.reset(seed=11)
    _, _, _, _, source_info = source.step(actions[0])
    assert source_info["reward_ctrl"] == pytest.approx(infos_new[0]["reward_ctrl"], rel=1e-12)


def test_the_zero_command_pays_no_control_cost_under_noise():
    """PROTOCOL §9's finding: Ant's version 0 target charges about 1.0 per step for noise at std
    0.5 that nobody commanded, as much as the Ant earns for staying up. Version 1 charges nothing."""
    for name, expected_cost in (("ant-joint-noise-0.5", 8 * 0.5 * 0.5 ** 2), ("ant-joint-noise-0.5-v1", 0.0)):
        env = get_task(name).make("target")
        env.reset(seed=2000000)
        terms = []
        for _ in range(30):
            *_, terminated, truncated, info = env.step(np.zeros(8))
            terms.append(-info["reward_ctrl"])
            if terminated or truncated:
                break
        assert np.mean(terms) == pytest.approx(expected_cost, rel=0.25, abs=1e-12), name


def test_commanded_cost_without_action_effects_changes_nothing():
    plain = make_robot_env("Hopper", [Gravity(scale=0.5)])
    charged = make_robot_env("Hopper", [Gravity(scale=0.5)], control_cost_on="commanded")
    assert isinstance(charged, CommandedControlCost)
    action = np.full(3, 0.3)
    plain.reset(seed=4)
    charged.reset(seed=4)
    for _ in range(5):
        a, b = plain.step(action), charged.step(action)
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1] == pytest.approx(b[1], rel=1e-12)


def test_commanded_cost_refuses_robots_without_a_control_cost_and_unknown_values():
    with pytest.raises(OffdynError, match="InvertedPendulumWithEffects has no control_cost\\(action\\) with a _ctrl_cost_weight"):
        make_robot_env("InvertedPendulum", [ActionNoise(std=0.1)], control_cost_on="commanded")
    with pytest.raises(UnknownNameError, match="unknown control_cost_on 'motor'; valid names: 'applied', 'commanded'"):
        make_robot_env("Hopper", [ActionNoise(std=0.1)], control_cost_on="motor")  # type: ignore[arg-type]
    with pytest.raises(UnknownNameError, match="unknown control_cost_on"):
        TaskPair(robot="Hopper", shift="joint-noise", level="0.1", source_effects=(),
                 target_effects=(ActionNoise(std=0.1),), control_cost_on="motor")  # type: ignore[arg-type]
