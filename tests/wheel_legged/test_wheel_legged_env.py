"""The wheel-legged balancer: its physics, tasks, rewards, the real-robot target and the state contract."""

from __future__ import annotations

import gymnasium
import mujoco
import numpy as np
import pytest

import offdyn_bench  # noqa: F401  (registers the ids)
from offdyn_bench.envs import make_robot_env, set_full_state
from offdyn_bench.errors import UnknownNameError
from offdyn_bench.tasks import get_task
from offdyn_bench.wheel_legged.env import FALL_TILT, WheelLeggedEnv
from offdyn_bench.wheel_legged.operator import BalancingController
from offdyn_bench.wheel_legged.pairs import MOTOR_DEADZONE

IDS = {(task, side): f"offdyn/WheelLegged-{task}-{side}-v0"
       for task in ("standstill", "movestraight") for side in ("source", "target")}


def _episode(env_id: str, policy, seed: int = 0) -> dict[str, np.ndarray | int | bool | float]:
    env = gymnasium.make(env_id)
    obs, _ = env.reset(seed=seed)
    tilts, velocities, xs, total, steps, terminated = [], [], [], 0.0, 0, False
    while True:
        obs, reward, terminated, truncated, info = env.step(policy(obs).astype(np.float32))
        tilts.append(info["tilt"])
        velocities.append(info["x_velocity"])
        xs.append(info["x_position"])
        total += reward
        steps += 1
        if terminated or truncated:
            break
    return {"steps": steps, "terminated": terminated, "return": total, "tilt": np.array(tilts),
            "velocity": np.array(velocities), "x": np.array(xs)}


def test_model_has_the_documented_physical_numbers():
    env = WheelLeggedEnv()
    model = env.model
    assert env.dt == pytest.approx(1 / 200)  # 200 Hz control
    assert model.body_subtreemass[model.body("chassis").id] == pytest.approx(3.6)
    assert model.geom_size[model.geom("left_wheel").id, 0] == pytest.approx(0.065)
    assert model.actuator_gear[0, 0] == pytest.approx(3.0)  # two motors of 1.5 N m, summed
    np.testing.assert_array_equal(model.actuator_ctrlrange[0], [-1.0, 1.0])
    assert env.action_space.shape == (1,)


def test_observation_is_tilt_displacement_tilt_rate_velocity():
    for task, names in (("standstill", (2, 0, 6, 4)), ("movestraight", (2, 6, 4))):
        env = WheelLeggedEnv(task=task)
        env.reset(seed=0)
        env.set_state(np.array([0.3, 0.0, 0.1, 2.0]), np.array([0.2, 0.0, -0.4, 5.0]))
        state = np.concatenate([env.data.qpos, env.data.qvel])
        np.testing.assert_array_equal(env._get_obs(), state[list(names)])


def test_uncontrolled_robot_falls_within_about_a_second():
    for seed in range(10):
        result = _episode(IDS["standstill", "source"], lambda obs: np.zeros(1), seed=seed)
        assert result["terminated"]
        assert result["steps"] * 0.005 <= 1.25, f"seed {seed}: still up after {result['steps'] * 0.005:.2f} s"
        assert abs(result["tilt"][-1]) > FALL_TILT


@pytest.mark.parametrize("task", ["standstill", "movestraight"])
def test_clean_controller_balances_for_a_whole_episode_in_source_and_target(task):
    source = _episode(IDS[task, "source"], BalancingController(task))
    target = _episode(IDS[task, "target"], BalancingController(task))
    full = {"standstill": 6000, "movestraight": 4000}[task]
    assert source["steps"] == full and not source["terminated"]
    assert target["steps"] == full and not target["terminated"]
    # Measurably worse on the real robot: the dead zone, friction and latency make it wobble.
    rms = {k: float(np.sqrt(np.mean(r["tilt"] ** 2))) for k, r in (("source", source), ("target", target))}
    assert rms["target"] > 1.2 * rms["source"]
    assert target["return"] < source["return"]
    if task == "standstill":
        assert np.max(np.abs(source["x"])) < 0.02
    else:
        assert np.mean(source["velocity"][400:]) == pytest.approx(0.2, abs=0.01)


def test_target_dead_zone_passes_no_torque_for_small_commands():
    env = gymnasium.make(IDS["standstill", "target"])
    env.reset(seed=0)
    data = env.unwrapped.data
    _, _, _, _, info = env.step(np.array([0.9 * MOTOR_DEADZONE], dtype=np.float32))
    assert data.actuator_force[0] == 0.0 and data.qfrc_actuator[3] == 0.0
    assert info["applied_action"][0] == 0.0
    _, _, _, _, info = env.step(np.array([-0.9 * MOTOR_DEADZONE], dtype=np.float32))
    assert data.actuator_force[0] == 0.0
    command = np.float32(2 * MOTOR_DEADZONE)
    env.step(np.array([command]))
    assert data.actuator_force[0] == pytest.approx(float(command))  # passes unchanged above it
    assert data.qfrc_actuator[3] == pytest.approx(3.0 * float(command))  # gear 3 N m on the wheel axle
    source = gymnasium.make(IDS["standstill", "source"])
    source.reset(seed=0)
    source.step(np.array([0.9 * MOTOR_DEADZONE], dtype=np.float32))
    assert source.unwrapped.data.actuator_force[0] == pytest.approx(float(np.float32(0.9 * MOTOR_DEADZONE)))


def test_target_tyres_slip_where_the_source_grips():
    """Friction x0.4 on the wheels: half torque (23 N at the tyre, 35 N on it) spins them in the target only."""

    def slip(env_id: str) -> float:
        env = gymnasium.make(env_id)
        env.reset(seed=0)
        base = env.unwrapped
        for _ in range(4):
            env.step(np.full(1, 0.5, dtype=np.float32))
        radius = base.model.geom_size[base.model.geom("left_wheel").id, 0]
        rolling = (base.data.qvel[3] + base.data.qvel[2]) * radius  # the tyre's surface speed
        return float(abs(rolling - base.data.qvel[0]))

    assert slip(IDS["standstill", "source"]) < 0.02
    assert slip(IDS["standstill", "target"]) > 0.1


def test_reward_terms_add_up_and_stay_positive():
    for task, offset in (("standstill", 30.0), ("movestraight", 15.0)):
        env = gymnasium.make(IDS[task, "target"])
        env.reset(seed=1)
        rng = np.random.default_rng(0)
        for _ in range(300):
            _, reward, terminated, _, info = env.step(rng.uniform(-1, 1, 1).astype(np.float32))
            terms = sum(v for k, v in info.items() if k.startswith("reward_"))
            assert reward == pytest.approx(offset + terms)
            assert reward >= 1.0
            if terminated:
                break


def test_reward_is_highest_upright_at_rest_at_the_origin():
    env = WheelLeggedEnv(task="standstill")
    env.reset(seed=0)
    env.set_state(env.init_qpos, env.init_qvel)
    _, upright, _, _, _ = env.step(np.zeros(1))
    env.set_state(env.init_qpos + np.array([0.2, 0, 0.1, 0]), env.init_qvel)
    _, away, _, _, _ = env.step(np.zeros(1))
    assert upright == pytest.approx(30.0, abs=0.05)
    assert away < upright - 3.0


def test_info_state_restarts_the_target_exactly():
    """The contract datasets and diagnosis rely on: set_full_state(state[t]) + action[t] gives state[t+1]."""
    env = gymnasium.make(IDS["standstill", "target"])
    _, info = env.reset(seed=5)
    controller = BalancingController("standstill")
    states, actions = [info["state"].copy()], []
    obs = None
    for t in range(60):
        action = controller(obs).astype(np.float32) if obs is not None else np.zeros(1, np.float32)
        obs, _, _, _, info = env.step(action)
        np.testing.assert_array_equal(info["prev_state"], states[-1])
        states.append(info["state"].copy())
        actions.append(action)
    # physics (time, qpos, qvel, act...) plus the one-step observation delay buffer
    physics = mujoco.mj_stateSize(env.unwrapped.model, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    assert states[0].size == physics + 4
    replay = gymnasium.make(IDS["standstill", "target"])
    replay.reset(seed=123)
    for t in (0, 17, 59):
        set_full_state(replay, states[t])
        _, _, _, _, info = replay.step(actions[t])
        np.testing.assert_allclose(info["state"], states[t + 1], rtol=0, atol=1e-12)


def test_bad_task_and_action_are_clear_errors():
    with pytest.raises(UnknownNameError, match="unknown wheel-legged task 'standstil'.*'standstill'"):
        WheelLeggedEnv(task="standstil")  # type: ignore[arg-type]
    env = WheelLeggedEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"expected an action of shape \(1,\)"):
        env.step(np.zeros(2))


def test_pairs_are_named_by_task_and_pass_the_task_to_the_env():
    pair = get_task("wheellegged-movestraight")
    assert pair.env_id("target") == "offdyn/WheelLegged-movestraight-target-v0"
    assert pair.to_dict()["task"] == "movestraight"
    assert gymnasium.spec(pair.env_id("source")).max_episode_steps == 4000
    assert gymnasium.spec(IDS["standstill", "source"]).max_episode_steps == 6000
    env = make_robot_env("WheelLegged", task="movestraight")
    assert env.unwrapped.task == "movestraight"
    kinds = {e.kind for e in pair.target_effects}
    assert {"action_deadzone", "frictionloss", "friction", "obs_delay", "obs_noise"} <= kinds
    assert not pair.source_effects


def test_tasks_show_prints_both_sides_and_the_model_diff():
    from typer.testing import CliRunner

    from offdyn_bench.cli import app

    result = CliRunner().invoke(app, ["tasks", "show", "wheellegged-standstill"])
    assert result.exit_code == 0, result.output
    assert "source: offdyn/WheelLegged-standstill-source-v0" in result.output
    assert "action_deadzone(threshold=0.05) on wheel_motors" in result.output
    assert "dof_frictionloss[wheel_axle]: 0 -> 0.04" in result.output
    assert "geom_friction[left_wheel]: [0.9 0.005 0.0001] -> [0.36 0.002 4e-05]  (x0.4)" in result.output
    listed = CliRunner().invoke(app, ["tasks", "list", "--robot", "wheellegged"])
    assert listed.exit_code == 0, listed.output
    assert "wheellegged-standstill" in listed.output and "wheellegged-movestraight" in listed.output
