"""The DART targets: same spaces and MJCF as MuJoCo, physics that agree where they should and
differ where the engines do, replayable states, and clear errors."""

from __future__ import annotations

import pickle

import gymnasium
import mujoco
import numpy as np
import pytest

import offdyn_bench
from offdyn_bench.datasets.policies import load_policy
from offdyn_bench.engines import COLLISION_DETECTORS, build_dart_world, make_dart_env
from offdyn_bench.envs import make_robot_env
from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.tasks import TASKS

ROBOTS = ("Hopper", "Walker2d")
POLICIES = {"Hopper": "assets/policies/sac-source/hopper-nominal.safetensors",
            "Walker2d": "assets/policies/sac-source/walker2d-nominal.safetensors"}


def _lowest_point(env: gymnasium.Env) -> float:
    """Height of the lowest point of the robot's capsules (from the mirrored MuJoCo pose)."""
    model, data = env.unwrapped.model, env.unwrapped.data
    mujoco.mj_kinematics(model, data)
    heights = []
    for g in range(model.ngeom):
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
            axis_z = data.geom_xmat[g].reshape(3, 3)[2, 2]
            heights.append(data.geom_xpos[g][2] - model.geom_size[g][1] * abs(axis_z) - model.geom_size[g][0])
    return min(heights)


@pytest.mark.parametrize("robot", ROBOTS)
def test_registered_pair_has_mujoco_source_and_dart_target_with_identical_spaces(robot):
    pair = TASKS[f"{robot.lower()}-dart"]
    assert pair.env_id("target") == f"offdyn/{robot}-dart-target-v0"
    assert (pair.engine("source"), pair.engine("target")) == ("mujoco", "dart")
    source, target = pair.make("source"), pair.make("target")
    reference = gymnasium.make(f"{robot}-v5")
    assert type(target.unwrapped).__name__ == f"Dart{robot}Env"
    for env in (source, target):
        assert env.observation_space == reference.observation_space
        assert env.action_space == reference.action_space
        assert env.unwrapped.dt == reference.unwrapped.dt
        assert env.unwrapped.frame_skip == reference.unwrapped.frame_skip
        assert env.spec.max_episode_steps == reference.spec.max_episode_steps
    # The same MJCF file: DART's world steps with MuJoCo's timestep and gravity.
    world = target.unwrapped.dart.world
    assert world.getTimeStep() == reference.unwrapped.model.opt.timestep
    np.testing.assert_array_equal(world.getGravity(), reference.unwrapped.model.opt.gravity)


@pytest.mark.parametrize("robot", ROBOTS)
def test_reset_matches_mujoco_exactly_including_reset_noise(robot):
    dart, mujoco_env = make_dart_env(robot), make_robot_env(robot)
    for seed in (0, 7):
        obs_dart, info_dart = dart.reset(seed=seed)
        obs_mujoco, _ = mujoco_env.reset(seed=seed)
        np.testing.assert_array_equal(obs_dart, obs_mujoco)
        np.testing.assert_array_equal(info_dart["state"][1:], np.concatenate([mujoco_env.unwrapped.data.qpos,
                                                                              mujoco_env.unwrapped.data.qvel]))


@pytest.mark.parametrize("robot", ROBOTS)
def test_a_thousand_random_steps_stay_finite_and_reward_terms_add_up(robot):
    env = gymnasium.make(f"offdyn/{robot}-dart-target-v0")
    env.action_space.seed(0)
    env.reset(seed=0)
    for _ in range(1000):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert np.isfinite(obs).all() and np.isfinite(info["state"]).all()
        assert reward == pytest.approx(info["reward_forward"] + info["reward_ctrl"] + info["reward_survive"])
        if terminated or truncated:
            env.reset()


@pytest.mark.parametrize("robot", ROBOTS)
def test_dart_mass_matrix_is_mujocos_without_armature(robot):
    """The parser leaves inertias at the identity; after the correction, DART's joint-space
    inertia equals MuJoCo's minus the armature that DART cannot represent (it is emulated)."""
    env = make_dart_env(robot)
    env.reset(seed=0)
    model, data = env.unwrapped.model, env.unwrapped.data
    qpos = model.qpos0 + np.random.default_rng(1).uniform(-0.4, 0.4, model.nq)
    env.unwrapped.set_state(qpos, np.zeros(model.nv))
    mujoco.mj_forward(model, data)
    expected = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, expected)
    dart = env.unwrapped.dart
    mass = np.asarray(dart.robot.getMassMatrix())[np.ix_(dart.dof_indices, dart.dof_indices)]
    np.testing.assert_allclose(mass + np.diag(model.dof_armature), expected, atol=1e-10)
    bias = np.asarray(dart.robot.getCoriolisAndGravityForces())[dart.dof_indices]
    np.testing.assert_allclose(bias, data.qfrc_bias, atol=1e-9)


@pytest.mark.parametrize("robot", ROBOTS)
def test_free_flight_with_torques_agrees_with_mujoco(robot):
    """In the air, away from joint limits, only the integrators differ (RK4 against DART's
    semi-implicit Euler, with armature emulated): one step agrees to a few hundredths."""
    dart, reference = make_dart_env(robot), make_robot_env(robot)
    rng = np.random.default_rng(0)
    model = reference.unwrapped.model
    worst = 0.0
    for seed in range(5):
        dart.reset(seed=seed)
        reference.reset(seed=seed)
        qpos = model.qpos0.copy()
        qpos[1] += 2.0
        low, high = model.jnt_range[3:].T
        qpos[3:] = rng.uniform(low + 0.2, high - 0.2)
        qvel = rng.normal(size=model.nv) * 0.5
        dart.unwrapped.set_state(qpos, qvel)
        reference.unwrapped.set_state(qpos, qvel)
        action = rng.uniform(-1, 1, dart.action_space.shape)
        worst = max(worst, np.abs(dart.step(action)[0] - reference.step(action)[0]).max())
    # Measured: 0.0015 (Hopper), 0.044 (Walker2d); without the armature: 9.5 and 2.2.
    assert worst < {"Hopper": 0.005, "Walker2d": 0.08}[robot]


def test_without_armature_emulation_the_actuated_joints_respond_far_faster():
    emulated, bare = make_dart_env("Hopper"), make_dart_env("Hopper", emulate_armature=False)
    assert not bare.unwrapped.dart.armature_damping.any()
    speeds = []
    for env in (emulated, bare):
        env.reset(seed=0)
        qpos = env.unwrapped.init_qpos.copy()
        qpos[1] += 2.0
        qpos[3:] = [-0.5, -0.5, 0.0]
        env.unwrapped.set_state(qpos, np.zeros(6))
        speeds.append(abs(env.step(np.array([0.0, 0.0, 1.0]))[0][-1]))  # foot joint velocity
    # The foot's own inertia is about 0.1 kg m^2 against MuJoCo's armature of 1: without the
    # armature the same torque spins it up far faster. Measured: 1.4 rad/s against 10 (the
    # observation clips velocities at 10).
    assert speeds[1] > 5 * speeds[0]


@pytest.mark.parametrize("robot", ROBOTS)
def test_zero_action_trajectories_agree_at_first_and_drift_apart_after_touchdown(robot):
    dart = make_dart_env(robot, terminate_when_unhealthy=False)
    reference = make_robot_env(robot, terminate_when_unhealthy=False)
    dart.reset(seed=0)
    reference.reset(seed=0)
    model = reference.unwrapped.model
    qpos = model.qpos0.copy()
    qpos[1] += 0.05  # 5 cm of free fall before the feet touch the floor
    qpos[3:] = np.tile([-0.1, -0.1, 0.0], (model.nq - 3) // 3)  # joints off their limits
    for env in (dart, reference):
        env.unwrapped.set_state(qpos, np.zeros(model.nv))
    gaps = []
    for _ in range(100):
        for env in (dart, reference):
            env.step(np.zeros(env.action_space.shape))
        gaps.append(np.abs(dart.unwrapped.data.qpos - reference.unwrapped.data.qpos).max())
    gaps = np.array(gaps)
    # Measured: 7.8e-4 over the first ten steps (free fall); past step 50, 2.4 (Hopper), 0.49 (Walker2d).
    assert gaps[:10].max() < 1e-3
    assert gaps[50:].max() > 0.2


def _crouch_and_push(env: gymnasium.Env, seed: int) -> tuple[float, int]:
    """Play a hop open-loop: crouch 15 steps, push 5 steps, then hold still; forward distance of
    the torso after 60 steps, and the number of steps with every capsule 1 cm above the floor."""
    crouch, push = np.array([0.0, 0.75, 0.75]), np.array([-0.25, 0.5, 1.0])
    env.reset(seed=seed)
    x0 = env.unwrapped.data.qpos[0]
    flight = 0
    for t in range(60):
        action = crouch if t < 15 else push if t < 20 else np.zeros(3)
        *_, terminated, _, _ = env.step(action)
        assert not terminated, f"fell at step {t}"
        flight += _lowest_point(env) > 0.01
    return float(env.unwrapped.data.qpos[0] - x0), flight


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_open_loop_hop_moves_the_hopper_forward_in_both_engines(seed):
    distance_mujoco, flight_mujoco = _crouch_and_push(make_robot_env("Hopper"), seed)
    distance_dart, flight_dart = _crouch_and_push(make_dart_env("Hopper"), seed)
    # Measured (seeds 0-2): MuJoCo 0.36-0.38 m with 45 steps of flight, DART 0.25-0.26 m with 4-5
    # (hard contacts stop the foot at once; MuJoCo's soft contact lets it rebound).
    assert distance_mujoco > 0.2 and distance_dart > 0.2
    assert flight_mujoco >= 3 and flight_dart >= 3


@pytest.mark.parametrize("detector", COLLISION_DETECTORS)
def test_capsules_rest_on_the_floor_with_each_supported_detector(detector):
    """FCL replaces capsules by 0.1 m spheres; ODE and Bullet collide the capsules themselves, so
    the resting foot's lowest point sits at the floor (hard contact: within a few millimetres)."""
    env = make_dart_env("Hopper", collision_detector=detector, terminate_when_unhealthy=False)
    env.reset(seed=0)
    for _ in range(100):
        env.step(np.zeros(3))
    assert abs(_lowest_point(env)) < 0.005
    assert env.unwrapped.dart.world.getLastCollisionResult().getNumContacts() > 0


@pytest.mark.parametrize("robot", ROBOTS)
def test_the_source_policy_scores_clearly_above_random_on_dart(robot):
    policy = load_policy(POLICIES[robot])
    env = gymnasium.make(f"offdyn/{robot}-dart-target-v0")

    def average_return(act) -> float:
        returns = []
        for seed in range(3):
            obs, _ = env.reset(seed=seed)
            total, done = 0.0, False
            while not done:
                obs, reward, terminated, truncated, _ = env.step(act(obs))
                total += reward
                done = terminated or truncated
            returns.append(total)
        return float(np.mean(returns))

    env.action_space.seed(0)
    policy_return = average_return(policy)
    random_return = average_return(lambda obs: env.action_space.sample())
    # Measured: Hopper 227 against 80 (MuJoCo source: about 2,000); Walker2d 575 against 11 (about 800).
    assert policy_return > 2 * random_return and policy_return > random_return + 100


def test_info_states_replay_bit_for_bit_with_set_full_state():
    env = gymnasium.make("offdyn/Hopper-dart-target-v0")
    _, info = env.reset(seed=3)
    assert info["state"].shape == (1 + 6 + 6,) and not info["state"].flags.writeable
    rng = np.random.default_rng(0)
    records = []
    previous = info["state"]
    for _ in range(40):
        action = rng.uniform(-1, 1, 3)
        obs, _, terminated, _, info = env.step(action)
        assert info["prev_state"] is previous or np.array_equal(info["prev_state"], previous)
        records.append((info["prev_state"], action, info["state"], obs))
        previous = info["state"]
        if terminated:
            break
    assert records[-1][2][0] == pytest.approx(len(records) * env.unwrapped.dt)  # the clock is in the state
    replay = gymnasium.make("offdyn/Hopper-dart-target-v0")
    replay.reset(seed=99)
    for prev_state, action, state, obs in records[::-1]:  # out of order: nothing carries over between steps
        offdyn_bench.set_full_state(replay, prev_state)
        replayed_obs, *_, replayed_info = replay.step(action)
        np.testing.assert_array_equal(replayed_info["state"], state)
        np.testing.assert_array_equal(replayed_obs, obs)


def test_dart_and_mujoco_states_share_one_layout_and_a_wrong_shape_is_refused():
    """[time, qpos, qvel] is MuJoCo's full-physics state of these models: a DART state restarts the
    MuJoCo source at the same place (what diagnosis does), and the other way round."""
    dart, source = gymnasium.make("offdyn/Hopper-dart-target-v0"), gymnasium.make("offdyn/Hopper-dart-source-v0")
    dart_state = dart.reset(seed=0)[1]["state"]
    for _ in range(5):
        dart_state = dart.step(np.full(3, 0.2))[4]["state"]
    offdyn_bench.set_full_state(source, dart_state)
    np.testing.assert_array_equal(source.unwrapped.current_observation(), dart.unwrapped.current_observation())

    walker_state = gymnasium.make("offdyn/Walker2d-dart-target-v0").reset(seed=0)[1]["state"]
    before = dart.unwrapped.dart.qpos().copy()
    with pytest.raises(OffdynError, match=r"expected a state \[time, qpos \(6\), qvel \(6\)\] of shape \(13,\) "
                                          r"for DartHopperEnv, got \(19,\)"):
        offdyn_bench.set_full_state(dart, walker_state)
    np.testing.assert_array_equal(dart.unwrapped.dart.qpos(), before)  # nothing was written


def test_pickling_rebuilds_the_dart_world_with_its_detector():
    env = make_dart_env("Walker2d", collision_detector="bullet")
    restored = pickle.loads(pickle.dumps(env))
    assert restored.unwrapped.collision_detector == "bullet"
    a, b = env.reset(seed=5)[0], restored.reset(seed=5)[0]
    np.testing.assert_array_equal(a, b)
    action = np.full(6, 0.3)
    np.testing.assert_array_equal(env.step(action)[0], restored.step(action)[0])


def test_channel_effects_wrap_a_dart_env_and_model_effects_are_refused():
    noisy = make_dart_env("Hopper", [{"kind": "action_noise", "std": 0.1}])
    assert noisy.unwrapped.engine == "dart" and noisy is not noisy.unwrapped
    with pytest.raises(OffdynError, match=r"DART envs take channel effects only, got model effects \(gravity\)"):
        make_dart_env("Hopper", [{"kind": "gravity", "scale": 0.5}])
    with pytest.raises(OffdynError, match="model effects"):
        gymnasium.make("offdyn/Hopper-dart-target-v0", extra_effects=[{"kind": "friction", "scale": 2.0}])


def test_unknown_robot_and_detector_are_one_line_errors():
    with pytest.raises(UnknownNameError, match="unknown DART robot 'Ant'; valid names: 'Hopper', 'Walker2d'"):
        make_dart_env("Ant")
    with pytest.raises(OffdynError, match="unknown DART collision detector 'fcl'; expected one of ode, bullet"):
        make_dart_env("Hopper", collision_detector="fcl")


def test_an_mjcf_dart_cannot_simulate_is_refused_before_parsing(tmp_path):
    xml = tmp_path / "ball.xml"
    xml.write_text("<mujoco><worldbody><geom type='plane' size='1 1 .1'/><body name='b' pos='0 0 1'>"
                   "<joint name='j' type='ball'/><geom type='sphere' size='.1'/></body></worldbody></mujoco>")
    model = mujoco.MjModel.from_xml_path(str(xml))
    with pytest.raises(OffdynError, match="joint 'j' is not a hinge or slide joint"):
        build_dart_world(str(xml), model)


def test_actuators_are_mujocos_motors_gear_times_clipped_control():
    env = make_dart_env("Walker2d")
    dart = env.unwrapped.dart
    forces = dart.torques(np.array([2.0, -3.0, 0.5, 0.0, -0.25, 1.0]))
    model = env.unwrapped.model
    expected = model.actuator_gear[:, 0] * np.array([1.0, -1.0, 0.5, 0.0, -0.25, 1.0])  # ctrlrange [-1, 1]
    np.testing.assert_allclose(forces[dart.actuator_dofs], expected)
    assert not np.delete(forces, dart.actuator_dofs).any()  # the root dofs are not actuated


def test_an_engine_pair_cannot_be_registered_again_on_another_engine():
    from offdyn_bench.tasks import TaskPair, register_tasks

    on_mujoco = TaskPair(robot="Hopper", shift="dart", level="", source_effects=(), target_effects=())
    with pytest.raises(OffdynError, match="offdyn/Hopper-dart-target-v0 is already registered with other dynamics"):
        register_tasks([on_mujoco])
    with pytest.raises(UnknownNameError, match="unknown physics engine 'bullet'"):
        TaskPair(robot="Hopper", shift="x", level="", source_effects=(), target_effects=(),
                 target_engine="bullet").entry_point("target")


def _slide_distance(box_friction: float, floor_friction: float) -> float:
    """How far a 1 kg box launched at 3 m/s slides on DART's floor in 0.3 s."""
    import dartpy

    world = dartpy.simulation.World()
    world.setTimeStep(0.001)
    world.getConstraintSolver().setCollisionDetector(dartpy.collision.OdeCollisionDetector())
    bodies = []
    for name, size, friction, joint in (("floor", [100, 100, 1.0], floor_friction, "weld"),
                                        ("box", [0.2, 0.2, 0.2], box_friction, "free")):
        skeleton = dartpy.dynamics.Skeleton(name)
        create = skeleton.createWeldJointAndBodyNodePair if joint == "weld" else skeleton.createFreeJointAndBodyNodePair
        body = create()[1]
        shape = body.createShapeNode(dartpy.dynamics.BoxShape(np.array(size, dtype=float)))
        shape.createCollisionAspect()
        shape.createDynamicsAspect().setFrictionCoeff(friction)
        world.addSkeleton(skeleton)
        bodies.append((skeleton, shape))
    floor_shape = bodies[0][1]
    offset = dartpy.math.Isometry3()
    offset.set_translation([0.0, 0.0, -0.5])
    floor_shape.setRelativeTransform(offset)
    box = bodies[1][0]
    box.setPositions(np.array([0, 0, 0, 0, 0, 0.1]))
    box.setVelocities(np.array([0, 0, 0, 3.0, 0, 0]))
    for _ in range(300):
        world.step()
    return float(box.getPositions()[3])


def test_dart_combines_friction_by_the_smaller_coefficient_which_the_alignment_relies_on():
    """MuJoCo uses the larger friction of two geoms, DART the smaller: each robot shape carries the
    value MuJoCo would use against the floor, and the floor the largest of them."""
    low = _slide_distance(0.1, 0.1)
    assert _slide_distance(0.1, 2.0) == pytest.approx(low) and _slide_distance(2.0, 0.1) == pytest.approx(low)
    assert _slide_distance(2.0, 2.0) < 0.5 * low  # measured: 0.23 m against 0.86 m
    world = make_dart_env("Hopper").unwrapped.dart
    frictions = {shape.getName(): shape.getDynamicsAspect().getFrictionCoeff()
                 for node in world.robot.getBodyNodes() for shape in node.getShapeNodes()}
    assert frictions == {"torso_geom": 1.0, "thigh_geom": 1.0, "leg_geom": 1.0, "foot_geom": 2.0}
