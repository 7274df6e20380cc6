"""Physical meaning of the shifts, the physics state in info, and exact restarts."""

from __future__ import annotations

import gymnasium
import mujoco
import numpy as np
import pytest

import offdyn_bench  # noqa: F401  (registers the ids)
from offdyn_bench.envs import make_robot_env, set_full_state


def _drop_height(env: gymnasium.Env, steps: int) -> float:
    """Lift the robot into the air at rest and return how far it falls in ``steps`` steps."""
    env.reset(seed=0)
    base = env.unwrapped
    qpos = base.init_qpos.copy()
    qpos[1] += 2.0  # rootz: well clear of the floor
    base.set_state(qpos, np.zeros(base.model.nv))
    z0 = base.data.qpos[1]
    for _ in range(steps):
        env.step(np.zeros(env.action_space.shape))
    return float(z0 - base.data.qpos[1])


def test_half_gravity_hopper_falls_half_as_far():
    nominal = _drop_height(gymnasium.make("offdyn/Hopper-gravity-0.5-source-v0"), 20)
    shifted = _drop_height(gymnasium.make("offdyn/Hopper-gravity-0.5-target-v0"), 20)
    t = 20 * gymnasium.make("offdyn/Hopper-gravity-0.5-source-v0").unwrapped.dt
    assert nominal == pytest.approx(0.5 * 9.81 * t**2, rel=0.02)  # free fall, no contact
    assert shifted / nominal == pytest.approx(0.5, rel=0.01)


def test_friction_shift_scales_every_active_contact():
    """MuJoCo uses the larger friction of two geoms; scaling all geoms scales every contact."""

    def contact_friction(env_id: str) -> np.ndarray:
        env = gymnasium.make(env_id)
        env.reset(seed=0)
        for _ in range(30):  # let the foot settle on the floor
            env.step(np.zeros(env.action_space.shape))
        data = env.unwrapped.data
        assert data.ncon > 0
        return np.array([data.contact[i].friction for i in range(data.ncon)])

    nominal = contact_friction("offdyn/Hopper-friction-0.5-source-v0")
    shifted = contact_friction("offdyn/Hopper-friction-0.5-target-v0")
    n = min(len(nominal), len(shifted))
    np.testing.assert_allclose(shifted[:n], 0.5 * nominal[:n])


def test_dead_zone_passes_no_torque_for_small_commands():
    env = make_robot_env("Hopper", [{"kind": "action_deadzone", "target": "leg_joint", "threshold": 0.2}])
    env.reset(seed=0)
    data = env.unwrapped.data
    env.step(np.array([0.15, 0.15, -0.15]))
    np.testing.assert_allclose(data.actuator_force, [0.15, 0.0, -0.15])  # motor force = gain * ctrl
    env.step(np.array([0.5, 0.5, 0.5]))
    np.testing.assert_allclose(data.actuator_force, 0.5)  # large commands pass unchanged


@pytest.mark.parametrize("k", [1, 3])
def test_action_delay_shifts_the_applied_sequence_by_exactly_k(k):
    env = make_robot_env("Hopper", [{"kind": "action_delay", "steps": k}])
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    commanded = rng.uniform(-1, 1, size=(12, 3))
    applied = []
    for action in commanded:
        env.step(action)
        applied.append(env.unwrapped.data.ctrl.copy())
    applied = np.array(applied)
    np.testing.assert_allclose(applied[k:], commanded[:-k])
    np.testing.assert_allclose(applied[:k], 0.0)


def test_observation_delay_returns_the_observation_k_steps_back():
    plain = make_robot_env("Hopper")
    delayed = make_robot_env("Hopper", [{"kind": "obs_delay", "steps": 2}])
    obs_plain = [plain.reset(seed=4)[0]]
    obs_delayed = [delayed.reset(seed=4)[0]]
    actions = np.random.default_rng(0).uniform(-1, 1, size=(8, 3))
    for action in actions:
        obs_plain.append(plain.step(action)[0])
        obs_delayed.append(delayed.step(action)[0])
    np.testing.assert_allclose(obs_delayed[2:], obs_plain[:-2], rtol=1e-6)
    np.testing.assert_allclose(obs_delayed[1], obs_plain[0], rtol=1e-6)


def test_joint_noise_is_seeded_from_the_env():
    def applied(seed: int) -> np.ndarray:
        env = gymnasium.make("offdyn/Hopper-joint-noise-0.5-target-v0")
        env.reset(seed=seed)
        out = []
        for _ in range(20):
            _, _, _, _, info = env.step(np.zeros(3))
            out.append(info["applied_action"])
        return np.array(out)

    np.testing.assert_array_equal(applied(7), applied(7))
    assert not np.allclose(applied(7), applied(8))
    assert np.std(applied(7)) == pytest.approx(0.5, rel=0.3)


def test_kinematic_shift_stops_the_joint_at_the_new_limit():
    env = gymnasium.make("offdyn/Hopper-kinematic-thigh-hard-target-v0")
    env.reset(seed=0)
    base = env.unwrapped
    qpos = base.init_qpos.copy()
    qpos[1] += 1.0  # in the air so the thigh swings freely
    base.set_state(qpos, np.zeros(base.model.nv))
    thigh = base.model.joint("thigh_joint")
    for _ in range(40):
        env.step(np.array([-1.0, 0.0, 0.0]))  # drive the thigh towards its lower limit
    angle = float(base.data.qpos[thigh.qposadr[0]])
    assert np.degrees(angle) > -30.0 - 2.0  # soft limits allow a little penetration
    assert np.degrees(angle) < -20.0  # and the joint did reach the new limit region


def test_info_carries_the_full_physics_state_before_and_after():
    env = gymnasium.make("offdyn/Hopper-gravity-0.5-target-v0")
    _, info = env.reset(seed=0)
    model = env.unwrapped.model
    size = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    assert info["state"].shape == (size,)
    previous = info["state"]
    for _ in range(5):
        _, _, _, _, info = env.step(env.action_space.sample())
        np.testing.assert_array_equal(info["prev_state"], previous)
        previous = info["state"]
    # time, then qpos: the state vector is MuJoCo's own layout.
    np.testing.assert_array_equal(info["state"][1: 1 + model.nq], env.unwrapped.data.qpos)


@pytest.mark.parametrize("env_effects", [
    [],
    [{"kind": "action_delay", "steps": 2}, {"kind": "obs_delay", "steps": 1}],
    [{"kind": "gravity", "scale": 2.0}, {"kind": "action_delay", "steps": 1, "target": "foot_joint"}],
])
def test_restart_from_a_recorded_state_is_exact(env_effects):
    """A simulator restored from info['state'] continues exactly like the original, buffers included."""
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(30, 3))
    env = make_robot_env("Hopper", env_effects)
    env.reset(seed=1)
    states, observations = [], []
    for action in actions:
        obs, _, _, _, info = env.step(action)
        states.append(info["prev_state"])
        observations.append(obs)
    fresh = make_robot_env("Hopper", env_effects)
    fresh.reset(seed=99)
    set_full_state(fresh, states[10])
    for t in range(10, 30):
        obs, _, _, _, info = fresh.step(actions[t])
        # The constraint solver's warm start is not part of the physics state: agreement is to
        # round-off, not bit for bit.
        if not any(e["kind"] == "obs_delay" for e in env_effects):
            np.testing.assert_allclose(obs, observations[t], rtol=1e-9, atol=1e-12)
        if t + 1 < 30:
            np.testing.assert_allclose(info["state"], states[t + 1], rtol=1e-9, atol=1e-12)


def test_set_full_state_rejects_a_wrong_size():
    env = make_robot_env("Hopper")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"expected a physics state of shape \(13,\), got \(12,\)"):
        set_full_state(env, np.zeros(12))


def test_extra_effects_extend_a_registered_task():
    env = gymnasium.make("offdyn/Hopper-gravity-0.5-source-v0",
                         extra_effects=[{"kind": "mass", "target": "torso", "scale": 2.0}])
    base = gymnasium.make("offdyn/Hopper-gravity-0.5-source-v0")
    torso = env.unwrapped.model.body("torso").id
    assert env.unwrapped.model.body_mass[torso] == pytest.approx(2 * base.unwrapped.model.body_mass[torso])


def test_prev_state_follows_set_state_between_steps():
    env = make_robot_env("Hopper")
    env.reset(seed=0)
    env.step(np.zeros(3))
    base = env.unwrapped
    qpos = base.init_qpos.copy()
    qpos[1] += 0.5
    base.set_state(qpos, np.zeros(base.model.nv))
    _, _, _, _, info = env.step(np.zeros(3))
    np.testing.assert_array_equal(info["prev_state"][1: 1 + base.model.nq], qpos)
    with pytest.raises(ValueError, match="read-only"):
        info["state"][0] = 1.0


# --- hot path: noise drawn in blocks, states handed out in blocks ------------------------------

def test_noise_drawn_in_blocks_is_exactly_what_per_step_draws_give():
    """The wrapper draws noise for many steps at once; recorded datasets rely on it giving the very
    numbers of one ``rng.normal(0.0, std)`` call per stage and step, in the order of the stages."""
    effects = [{"kind": "action_noise", "std": 0.3},
               {"kind": "obs_noise", "std": 0.2, "target": 4},
               {"kind": "action_noise", "std": 0.1, "target": "foot_joint"},
               {"kind": "obs_noise", "std": 0.05}]
    env = make_robot_env("Hopper", effects, terminate_when_unhealthy=False)
    plain = make_robot_env("Hopper", terminate_when_unhealthy=False)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(300, 3))  # crosses several block ends
    foot = np.arange(3) == 2
    obs4 = np.arange(11) == 4
    for seed in (3, None):
        obs, _ = env.reset(seed=seed)
        expected_obs, _ = plain.reset(seed=seed)
        rng = np.random.default_rng(int(plain.unwrapped.np_random.integers(2**63)))  # as the wrapper seeds
        expected_obs = expected_obs + rng.normal(0.0, 0.2, 11) * obs4 + rng.normal(0.0, 0.05, 11)
        np.testing.assert_array_equal(obs, expected_obs)
        for action in actions:
            command = action + rng.normal(0.0, 0.3, 3) + rng.normal(0.0, 0.1, 3) * foot
            expected_obs = plain.step(command)[0]
            expected_obs = expected_obs + rng.normal(0.0, 0.2, 11) * obs4 + rng.normal(0.0, 0.05, 11)
            obs, _, _, _, info = env.step(action)
            np.testing.assert_array_equal(info["applied_action"], command)
            np.testing.assert_array_equal(obs, expected_obs)


def test_noise_transform_gives_the_values_of_rng_normal():
    from offdyn_bench.effects import ActionNoise

    x = np.array([[-0.0, 0.5, -0.0], [1.0, -2.0, 0.0]] * 50)
    mask = np.array([True, False, True])
    for std in (0.0, 0.4):
        for m in (None, mask):
            noise = np.random.default_rng(1).normal(0.0, std, size=x.shape)
            expected = x + (noise if m is None else noise * m)
            got = ActionNoise(std=std).transform(x, m, np.random.default_rng(1))
            assert got.tobytes() == expected.tobytes()  # bit for bit, signed zeros included


def test_reset_with_a_seed_replays_the_noise_whatever_came_before():
    def applied(history: list[tuple[int | None, int]]) -> np.ndarray:
        env = gymnasium.make("offdyn/Hopper-joint-noise-0.5-target-v0", terminate_when_unhealthy=False)
        for seed, steps in history:
            env.reset(seed=seed)
            out = [env.step(np.zeros(3))[4]["applied_action"] for _ in range(steps)]
        return np.array(out)

    reference = applied([(5, 120)])
    # a block left half used by an earlier episode must not leak into the reseeded one
    np.testing.assert_array_equal(applied([(1, 37), (None, 3), (5, 120)]), reference)
    assert not np.array_equal(applied([(6, 120)]), reference)


def test_states_stay_distinct_read_only_and_unchanged_across_state_blocks():
    env = make_robot_env("Hopper", terminate_when_unhealthy=False)
    _, info = env.reset(seed=0)
    kept, copies = [info["state"]], [info["state"].copy()]
    for action in np.random.default_rng(0).uniform(-1, 1, size=(200, 3)):  # > 3 blocks of states
        _, _, _, _, info = env.step(action)
        assert info["prev_state"] is kept[-1]
        kept.append(info["state"])
        copies.append(info["state"].copy())
        np.testing.assert_array_equal(info["state"][1: 1 + env.unwrapped.model.nq], env.unwrapped.data.qpos)
    for state, copy in zip(kept, copies, strict=True):  # no state was overwritten by a later step
        np.testing.assert_array_equal(state, copy)
        assert not state.flags.writeable
    assert len({id(state) for state in kept}) == len(kept)
    assert len({state[0] for state in kept}) == len(kept)  # each at its own time


@pytest.mark.parametrize("robot", ["Hopper", "Walker2d", "HalfCheetah", "Ant", "InvertedPendulum"])
def test_an_env_without_effects_steps_exactly_like_vanilla_gymnasium(robot):
    """The suite's faster do_simulation, dt and state capture change nothing Gymnasium computes:
    the same observations, rewards, terminations and info, bit for bit, and a state that is
    MuJoCo's own mj_getState."""
    vanilla = gymnasium.make(f"{robot}-v5").unwrapped
    suite = make_robot_env(robot)
    assert suite.dt == vanilla.dt
    vanilla_obs, _ = vanilla.reset(seed=3)
    suite_obs, _ = suite.reset(seed=3)
    np.testing.assert_array_equal(suite_obs, vanilla_obs)
    size = mujoco.mj_stateSize(vanilla.model, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    rng = np.random.default_rng(0)
    for t in range(60):
        # float32, float64 and a list; some commands beyond the control range
        action = rng.uniform(-1.5, 1.5, size=suite.action_space.shape)
        action = action.astype(np.float32) if t % 3 == 0 else (action.tolist() if t % 3 == 1 else action)
        expected, actual = vanilla.step(action), suite.step(action)
        np.testing.assert_array_equal(actual[0], expected[0])
        assert actual[1:4] == expected[1:4]
        assert {k: v for k, v in actual[4].items() if k not in ("state", "prev_state")} == expected[4]
        state = np.empty(size)
        mujoco.mj_getState(vanilla.model, vanilla.data, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        np.testing.assert_array_equal(actual[4]["state"], state)
        if expected[2]:
            break
    with pytest.raises(ValueError, match=r"Action dimension mismatch. Expected \(\d+,\), found \(\d+,\)"):
        suite.step(np.zeros(suite.action_space.shape[0] + 1))
    suite.model.opt.timestep *= 2  # dt reads the live model, as Gymnasium's does
    assert suite.dt == pytest.approx(2 * vanilla.dt)


def test_channel_states_chain_and_follow_moves_of_physics_and_buffers():
    """With delay buffers, each step's prev_state is the previous step's state (one array), and
    after a move of the physics (set_state) or of everything (set_full_state) it is what was there."""
    env = make_robot_env("Hopper", [{"kind": "obs_delay", "steps": 2}, {"kind": "action_delay", "steps": 1}])
    _, info = env.reset(seed=0)
    base = env.unwrapped
    nq, physics = base.model.nq, base.state_size
    previous = info["state"]
    assert previous.size == physics + 2 * 11 + 3
    actions = np.random.default_rng(1).uniform(-1, 1, size=(6, 3))
    for action in actions[:3]:
        _, _, _, _, info = env.step(action)
        assert info["prev_state"] is previous
        assert not info["state"].flags.writeable
        previous = info["state"]
    buffers = previous[physics:].copy()
    qpos = base.data.qpos.copy()
    qpos[1] += 0.3
    base.set_state(qpos, np.zeros(base.model.nv))  # physics moved, buffers not
    _, _, _, _, info = env.step(actions[3])
    np.testing.assert_array_equal(info["prev_state"][1: 1 + nq], qpos)
    np.testing.assert_array_equal(info["prev_state"][physics:], buffers)
    older = previous
    set_full_state(env, older)  # everything moved back
    _, _, _, _, info = env.step(actions[4])
    np.testing.assert_array_equal(info["prev_state"], older)
    assert info["prev_state"] is not older  # a vector of its own: the step does not hand back the input
    kept, copies = [], []
    for action in np.random.default_rng(2).uniform(-1, 1, size=(150, 3)):  # > 2 blocks of states
        _, _, terminated, _, info = env.step(action)
        kept.append(info["state"])
        copies.append(info["state"].copy())
        if terminated:
            env.reset(seed=5)
    for state, copy in zip(kept, copies, strict=True):  # no later step wrote over a kept state
        np.testing.assert_array_equal(state, copy)
        assert not state.flags.writeable


def test_wheel_legged_env_keeps_its_own_motor_model():
    """The suite's faster do_simulation replaces only Gymnasium's: the wheel-legged env's own
    (clip to [-1, 1], torque cost on what the motors got) still runs."""
    env = gymnasium.make("offdyn/WheelLegged-standstill-source-v0")
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([2.5]))
    assert env.unwrapped.data.ctrl[0] == 1.0
    assert info["reward_torque"] == -4.0


def test_a_noisy_channel_takes_any_array_like_action_and_applies_the_same_float64_command():
    """The first noise stage may get the caller's action as it came: lists, tuples, float32 or
    integer arrays and other libraries' arrays all give the very same command."""
    torch = pytest.importorskip("torch")
    applied = []
    for action in ([0.25, -0.5, 1.0], (0.25, -0.5, 1.0), np.array([0.25, -0.5, 1.0], dtype=np.float32),
                   np.array([0.25, -0.5, 1.0]), torch.tensor([0.25, -0.5, 1.0])):
        env = make_robot_env("Hopper", [{"kind": "action_noise", "std": 0.1}])
        env.reset(seed=4)
        _, _, _, _, info = env.step(action)
        assert isinstance(info["applied_action"], np.ndarray) and info["applied_action"].dtype == np.float64
        applied.append(info["applied_action"])
    for other in applied[1:]:
        np.testing.assert_array_equal(other, applied[0])


# --- channel fast paths: the same bits as the generic path ----------------------------------------

def _generic_channel(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make ChannelEffects built from now on take its generic path: every memoryless stage through
    its effect's ``transform``, every delay through one shifted buffer."""
    from offdyn_bench.effects import channel

    monkeypatch.setattr(channel.ChannelEffect, "per_step", lambda self, mask, size: None)
    monkeypatch.setattr(channel.ActionDeadzone, "per_step", lambda self, mask, size: None)
    monkeypatch.setattr(channel._Stage, "RING_STEPS", 0)


def _channel_trace(env: gymnasium.Env, actions: list, torch) -> list:
    """Everything a run gives, as bytes: observations, rewards, flags, applied actions, states
    (before and after, and whether prev_state is the previous state itself), across resets,
    set_state and set_full_state; the caller scribbles on what it gets and reuses its action arrays."""
    def exact(x):
        if isinstance(x, np.ndarray):
            return x.dtype.str, x.shape, x.tobytes(), x.flags.writeable
        if isinstance(x, dict):
            return {key: exact(value) for key, value in x.items()}
        return x

    out = []
    obs, info = env.reset(seed=3)
    out.append(("reset", exact(obs), exact(info)))
    states, last = [info["state"]], info["state"]
    for t, action in enumerate(actions):
        if t == 40:
            obs, info = env.reset()
            out.append(("reset", exact(obs), exact(info)))
            last = info["state"]
        if t == 70:
            set_full_state(env, states[20])
            last = None
        if t == 90:
            base = env.unwrapped
            qpos = base.data.qpos.copy()
            qpos[1] += 0.01
            base.set_state(qpos, base.data.qvel.copy())
        if t % 5 == 1:
            action = action.astype(np.float32)
        elif t % 5 == 2:
            action = action.tolist()
        elif t % 5 == 3:
            action = torch.tensor(action)
        obs, reward, terminated, truncated, info = env.step(action)
        out.append((t, exact(obs), reward, terminated, truncated, exact(info), info["prev_state"] is last))
        if isinstance(action, np.ndarray):
            action[:] = 7.0  # the caller reuses its action array: a delay must have kept its own copy
        obs[...] = -3.0  # and writes over its observation: a delay must not hand out what it keeps
        info["applied_action"][...] = 5.0
        states.append(info["state"])
        last = info["state"]
    return out


@pytest.mark.parametrize("effects", [
    [{"kind": "action_deadzone", "threshold": 0.3}, {"kind": "obs_delay", "steps": 1},
     *({"kind": "obs_noise", "target": i, "std": 0.01} for i in range(4))],  # the wheel-legged target's channel
    [{"kind": "action_deadzone", "threshold": 0.4, "target": "foot_joint"}, {"kind": "action_delay", "steps": 2},
     {"kind": "obs_delay", "steps": 3, "target": 2}, {"kind": "obs_bias", "value": 0.1}],
    [{"kind": "action_delay", "steps": 1}, {"kind": "action_deadzone", "threshold": 0.2},
     {"kind": "obs_noise", "std": 0.1}, {"kind": "obs_delay", "steps": 1}],
    [{"kind": "action_noise", "std": 0.2}, {"kind": "action_deadzone", "threshold": 0.2},
     {"kind": "obs_delay", "steps": 0}, {"kind": "obs_delay", "steps": 16}, {"kind": "obs_delay", "steps": 17}],
    [{"kind": "action_delay", "steps": 20, "target": "thigh_joint"}, {"kind": "obs_delay", "steps": 1, "target": 0}],
])
def test_channel_fast_paths_step_exactly_like_the_generic_path(effects, monkeypatch):
    """The per-step dead zone on Python floats and the short delays that keep their inputs (no copy
    per step) give what the effects' transforms and a shifted buffer give, bit for bit: the same
    observations, rewards, applied actions and state vectors, for float32, list and torch actions,
    through resets and restarts from a state."""
    torch = pytest.importorskip("torch")
    actions = list(np.random.default_rng(0).uniform(-1, 1, size=(120, 3)) * np.tile([[1.0], [0.2]], (60, 1)))
    fast = make_robot_env("Hopper", effects, terminate_when_unhealthy=False)
    fast_trace = _channel_trace(fast, [a.copy() for a in actions], torch)
    _generic_channel(monkeypatch)
    generic = make_robot_env("Hopper", effects, terminate_when_unhealthy=False)
    assert fast_trace == _channel_trace(generic, [a.copy() for a in actions], torch)
    ring = [stage.keeps_input for stage in fast._stages]
    assert any(ring) == any(e["kind"].endswith("delay") and 0 < e["steps"] <= 16 for e in effects)
    assert not any(stage.keeps_input for stage in generic._stages)


def test_a_short_delay_keeps_arrays_of_its_own():
    """A one-step observation delay hands out the observation it kept (no copy), so it must keep a
    copy of what the env gave, and a kept state vector must not change when the caller writes
    over the observation it got."""
    env = make_robot_env("Hopper", [{"kind": "obs_delay", "steps": 1}, {"kind": "action_delay", "steps": 1}],
                         terminate_when_unhealthy=False)
    base = env.unwrapped
    obs, info = env.reset(seed=0)
    first = obs.copy()
    action = np.full(3, 0.5)
    obs, _, _, _, info = env.step(action)
    np.testing.assert_array_equal(obs, first)  # one step late: the reset's observation
    kept = info["state"].copy()
    obs[...] = 9.0
    action[...] = -0.25  # the caller's array, reused
    np.testing.assert_array_equal(info["state"], kept)
    _, _, _, _, info = env.step(np.zeros(3))
    np.testing.assert_array_equal(info["applied_action"], 0.5)  # what was sent, not the reused array
    # the buffers follow the physics, action stages first: the command kept, the observation kept
    np.testing.assert_array_equal(info["state"][base.state_size:], np.concatenate([np.zeros(3), base._get_obs()]))


@pytest.mark.parametrize("copier", ["pickle", "deepcopy"])
def test_a_copied_channel_env_steps_exactly_like_the_original(copier):
    """Pickled or deep-copied mid-episode (its per-step functions, kept inputs and blocks of state
    rows with it), an env with channel effects then runs exactly like the original: the rows of a
    block are not split from their read-only views, so every state vector is the state."""
    import copy
    import pickle

    torch = pytest.importorskip("torch")
    effects = [{"kind": "action_deadzone", "threshold": 0.2}, {"kind": "action_delay", "steps": 1},
               {"kind": "obs_delay", "steps": 20, "target": 1}, {"kind": "obs_delay", "steps": 1},
               {"kind": "obs_noise", "std": 0.1, "target": 0}, {"kind": "obs_noise", "std": 0.1, "target": 3}]
    env = make_robot_env("Hopper", effects, terminate_when_unhealthy=False)
    env.reset(seed=0)
    for action in np.random.default_rng(1).uniform(-1, 1, size=(5, 3)):
        env.step(action)
    copied = pickle.loads(pickle.dumps(env)) if copier == "pickle" else copy.deepcopy(env)
    actions = list(np.random.default_rng(2).uniform(-1, 1, size=(80, 3)))
    trace = _channel_trace(copied, [a.copy() for a in actions], torch)
    assert trace == _channel_trace(env, [a.copy() for a in actions], torch)
    for entry in trace:
        if entry[0] != "reset":
            state = np.frombuffer(entry[5]["state"][2])
            assert state[0] > 0.0 and np.isfinite(state).all()  # a state, not a row left unwritten


def test_a_locomotion_run_never_imports_another_robots_package():
    """Env classes are built when a robot is first made: training or pickling a HalfCheetah env
    imports neither Gymnasium-Robotics (the Adroit robots) nor their env module, so a machine
    without that package (a GPU box carrying only what a sweep needs) still trains it."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        import pickle, sys
        import gymnasium
        import baselines.train, offdyn_bench
        from offdyn_bench import envs
        gymnasium.make("offdyn/HalfCheetah-friction-5.0-target-v0").reset(seed=0)
        cls = envs.ENV_CLASSES["HalfCheetah"]
        assert pickle.loads(pickle.dumps(cls)) is cls and cls.__name__ == "HalfCheetahWithEffects"
        assert len(envs.ENV_CLASSES) == len(set(envs.ENV_CLASSES)) > 10
        print(sorted(m for m in ("gymnasium_robotics", "offdyn_bench.robotics.adroit_envs") if m in sys.modules))
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True)
    assert result.stdout.strip().splitlines()[-1] == "[]"
    # An env class is found by its module-level name before anything built it (how unpickling looks).
    lookup = subprocess.run([sys.executable, "-c", "import pickle, offdyn_bench.envs as e; "
                             "print(e.HopperWithEffects.__name__, e.ENV_CLASSES['Hopper'] is e.HopperWithEffects)"],
                            capture_output=True, text=True, timeout=120, check=True)
    assert lookup.stdout.split() == ["HopperWithEffects", "True"]
