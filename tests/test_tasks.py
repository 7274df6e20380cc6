"""The task grid and every registered id: env checker, determinism, pickling, spaces, shift-diff."""

from __future__ import annotations

import functools
import pickle
import re
import subprocess
import sys
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import offdyn_bench
from offdyn_bench.effects import ModelEffect
from offdyn_bench.envs import ENV_CLASSES
from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.model_diff import DERIVED_FIELDS, model_differences
from offdyn_bench.tasks import SIDES, TASKS, TaskPair, get_task, register_tasks

ALL_IDS = [pair.env_id(side) for pair in TASKS.values() for side in SIDES]
ID_PATTERN = re.compile(r"^offdyn/((Ant|HalfCheetah|Hopper|Walker2d|InvertedPendulum)-[a-z0-9-]+(-[a-z0-9]+)?-"
                        r"[a-z0-9.]+|WheelLegged-(standstill|movestraight)|(Hopper|Walker2d)-dart"
                        r"|AntMaze(Small|Medium|Large)(Dense)?-layout-[a-z0-9-]+"
                        r"|Adroit(Pen|Door|Relocate|Hammer)-(broken-joint|shrink-finger)-[a-z-]+-(easy|medium|hard))"
                        r"-(source|target)-v\d+$")


def _rollout(env: gymnasium.Env, seed: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    # Flattened: AntMaze observations are dicts (observation, achieved_goal, desired_goal).
    flat = functools.partial(gymnasium.spaces.flatten, env.observation_space)
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    observations, rewards = [flat(obs)], []
    for _ in range(steps):
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        observations.append(flat(obs))
        rewards.append(reward)
        if terminated or truncated:
            break
    return np.array(observations), np.array(rewards)


def test_grid_covers_every_robot_family_and_level():
    names = set(TASKS)
    for robot in ("ant", "halfcheetah", "hopper", "walker2d"):
        for family in ("gravity", "friction"):
            for level in ("0.1", "0.5", "2.0", "5.0"):
                assert f"{robot}-{family}-{level}" in names
        for std in ("0.1", "0.5", "1.0"):
            assert f"{robot}-joint-noise-{std}" in names
        for family in ("kinematic", "morph"):
            parts = {p.part for p in TASKS.values() if p.robot.lower() == robot and p.shift == family}
            assert len(parts) == 2
            for part in parts:
                for level in ("easy", "medium", "hard"):
                    assert f"{robot}-{family}-{part}-{level}" in names
    for robot in ("halfcheetah", "walker2d"):
        for name in ("h2o-gravity-2.0", "h2o-friction-0.3", "h2o-joint-noise-1.0"):
            pair = TASKS[f"{robot}-{name}"]
            # H2O's setting: the simulator carries the shift, the target is the nominal system.
            assert pair.source_effects and not pair.target_effects


def test_ids_follow_the_naming_scheme():
    assert "offdyn/Hopper-gravity-0.5-target-v0" in ALL_IDS
    assert "offdyn/Walker2d-kinematic-foot-hard-source-v0" in ALL_IDS
    for env_id in ALL_IDS:
        assert ID_PATTERN.match(env_id), env_id
        assert env_id in gymnasium.registry
        assert isinstance(gymnasium.registry[env_id].entry_point, str)


def test_specs_serialize_to_json_and_back():
    for env_id in ALL_IDS:
        spec = gymnasium.registry[env_id]
        again = gymnasium.envs.registration.EnvSpec.from_json(spec.to_json())
        assert again.kwargs == spec.kwargs


def test_make_in_a_fresh_interpreter():
    code = ("import gymnasium; env = gymnasium.make('offdyn_bench:offdyn/Hopper-gravity-0.5-target-v0'); "
            "print(env.unwrapped.model.opt.gravity[2])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert float(out.stdout.strip()) == pytest.approx(-9.81 * 0.5)


def test_registration_is_idempotent_and_refuses_conflicts():
    register_tasks()
    pair = TASKS["hopper-gravity-0.5"]
    clash = TaskPair(robot="Hopper", shift="gravity", level="0.5", source_effects=(),
                     target_effects=(offdyn_bench.effects.Gravity(scale=0.7),))
    with pytest.raises(OffdynError, match="already registered with other dynamics"):
        register_tasks([clash])
    assert gymnasium.registry[pair.env_id("target")].kwargs == pair.env_kwargs("target")


def test_task_pair_round_trips_as_data():
    for pair in TASKS.values():
        assert TaskPair.from_dict(pair.to_dict()) == pair


def test_unknown_task_lists_close_matches():
    with pytest.raises(UnknownNameError, match="closest valid names: 'hopper-gravity-0.5'"):
        get_task("hoper-gravity-0.5")
    with pytest.raises(UnknownNameError, match="unknown task env id"):
        get_task("offdyn/Hopper-gravity-0.3-target-v0")
    with pytest.raises(UnknownNameError, match="unknown side 'real'"):
        TASKS["hopper-gravity-0.5"].env_id("real")  # type: ignore[arg-type]
    assert get_task("offdyn/Hopper-gravity-0.5-target-v0") is TASKS["hopper-gravity-0.5"]
    assert get_task("Hopper-Gravity-0.5") is TASKS["hopper-gravity-0.5"]


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_env_checker_determinism_and_pickle(env_id):
    env = gymnasium.make(env_id)
    with warnings.catch_warnings():
        # MuJoCo envs have unbounded observation boxes; Gymnasium warns about its own envs too.
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value.*")
        check_env(env.unwrapped, skip_render_check=True)

    first = _rollout(gymnasium.make(env_id), seed=3, steps=30)
    second = _rollout(gymnasium.make(env_id), seed=3, steps=30)
    np.testing.assert_array_equal(first[0], second[0])
    np.testing.assert_array_equal(first[1], second[1])

    # Pickling rebuilds the same dynamics (effects travel with the env) and the same trajectory.
    restored = pickle.loads(pickle.dumps(gymnasium.make(env_id)))
    assert restored.unwrapped.model_effects == gymnasium.make(env_id).unwrapped.model_effects
    third = _rollout(restored, seed=3, steps=30)
    np.testing.assert_array_equal(first[0], third[0])


@pytest.mark.parametrize("name", sorted(TASKS))
def test_source_and_target_share_spaces(name):
    pair = TASKS[name]
    source, target = pair.make("source"), pair.make("target")
    assert source.observation_space == target.observation_space
    assert source.action_space == target.action_space


@pytest.mark.parametrize("name", sorted(TASKS))
def test_target_differs_from_base_only_where_its_effects_declare(name):
    """The shift-diff test: compiled fields change only as the effects say, by the declared amount."""
    pair = TASKS[name]
    base = ENV_CLASSES[pair.robot]().unwrapped.model
    for side in SIDES:
        effects = pair.effects(side)
        compiled = pair.make(side).unwrapped.model
        differences = {d.field: d for d in model_differences(base, compiled)}
        declared = {f for e in effects if isinstance(e, ModelEffect) for f in e.fields}
        undeclared = set(differences) - declared - DERIVED_FIELDS
        assert not undeclared, f"{pair.env_id(side)} changes undeclared fields {sorted(undeclared)}"
        for effect in effects:
            if effect.kind == "gravity":
                np.testing.assert_allclose(compiled.opt.gravity, base.opt.gravity * effect.scale)
            elif effect.kind == "friction" and effect.target is None:
                np.testing.assert_allclose(compiled.geom_friction, base.geom_friction * effect.scale)
            elif effect.kind == "friction":
                friction = differences["geom_friction"]
                assert friction.after == pytest.approx(friction.before * effect.scale)
                body = compiled.body(effect.target).id
                assert set(friction.rows) == {compiled.geom(g).name for g in range(compiled.ngeom)
                                              if compiled.geom_bodyid[g] == body}
            elif effect.kind == "frictionloss":
                assert differences["dof_frictionloss"].rows == (effect.target,)
                assert differences["dof_frictionloss"].after[0] == pytest.approx(effect.value)
            elif effect.kind == "joint_range":
                ratio = np.ptp(differences["jnt_range"].after) / np.ptp(differences["jnt_range"].before)
                assert ratio == pytest.approx(effect.scale)
                assert differences["jnt_range"].rows == (effect.target,)
            elif effect.kind == "limb_size":
                mass = differences["body_mass"]
                # Several limb_size effects (a shrunk Adroit finger: one per segment) change only their bodies.
                assert set(mass.rows) <= {e.target for e in effects if e.kind == "limb_size"}
                row = mass.rows.index(effect.target)
                assert mass.after[row, 0] / mass.before[row, 0] == pytest.approx(effect.scale**3)
            elif effect.kind == "maze_layout":
                # Exactly the blocks of the cells whose wall changed move (up onto or down under the floor).
                blocks = {compiled.geom(g).name: g for g in range(compiled.ngeom)
                          if compiled.geom(g).name.startswith("block_")}
                changed = {name for name, g in blocks.items()
                           if (base.geom_pos[g, 2] > 0) != (effect.walls[int(name.split("_")[1])][int(name.split("_")[2])] == "1")}
                assert changed and set(differences["geom_pos"].rows) == changed
            elif effect.kind == "action_noise":
                assert not differences  # a channel effect leaves the model alone
            elif effect.family == "channel":
                assert not declared or differences  # the model changes only through its model effects
            elif effect.kind == "contact_solref":
                expected = [effect.timeconst, effect.dampratio]
                np.testing.assert_allclose(compiled.geom_solref, [expected] * compiled.ngeom)
                assert differences["geom_solref"]
            elif effect.kind == "contact_solimp":
                expected = [effect.dmin, effect.dmax, effect.width, effect.midpoint, effect.power]
                np.testing.assert_allclose(compiled.geom_solimp, [expected] * compiled.ngeom)
                assert differences["geom_solimp"]
            elif effect.kind in ("friction_cone", "integrator", "noslip"):
                field = effect.fields[0]
                assert field in differences, f"{pair.env_id(side)}: {effect.kind} left {field} unchanged"
            else:
                pytest.fail(f"no check for effect kind {effect.kind!r}")
