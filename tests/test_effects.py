"""The effect vocabulary: serialization, validation, and what each channel effect does."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest

from offdyn_bench.effects import (
    EFFECT_KINDS,
    ActionBias,
    ActionDeadzone,
    ActionDelay,
    ActionGain,
    ActionNoise,
    ActionSaturation,
    Effect,
    Friction,
    Gravity,
    JointRange,
    LimbSize,
    Mass,
    ObsDelay,
    compile_model,
    effects_from_dicts,
)
from offdyn_bench.envs import ENV_CLASSES
from offdyn_bench.errors import InvalidParameterError, OffdynError, UnknownNameError

# One valid example of every kind, with a target wherever the kind takes one.
EXAMPLES: dict[str, dict] = {
    "gravity": {"scale": 0.5},
    "friction": {"target": "foot_geom", "scale": 0.3},
    "mass": {"target": "thigh", "scale": 1.5},
    "damping": {"target": "leg_joint", "value": 2.0},
    "frictionloss": {"target": "foot_joint", "value": 0.7},
    "armature": {"target": "thigh_joint", "value": 0.2},
    "gear": {"target": "thigh_joint", "scale": 0.7},
    "joint_range": {"target": "foot_joint", "scale": 0.5},
    "limb_size": {"target": "leg", "scale": 0.8},
    "contact_solref": {"timeconst": 0.04, "dampratio": 0.8},
    "contact_solimp": {"dmin": 0.7, "dmax": 0.9, "width": 0.002},
    "friction_cone": {"cone": "elliptic"},
    "integrator": {"integrator": "implicitfast"},
    "noslip": {"iterations": 3},
    "action_noise": {"target": "leg_joint", "std": 0.2},
    "action_deadzone": {"target": "thigh_joint", "threshold": 0.1},
    "action_bias": {"value": 0.05},
    "action_gain": {"target": "foot_joint", "scale": -1.0},
    "action_saturation": {"limit": 0.5},
    "action_delay": {"steps": 2},
    "obs_noise": {"target": 3, "std": 0.01},
    "obs_bias": {"target": 0, "value": 0.1},
    "obs_delay": {"steps": 1},
}


def test_every_kind_has_an_example():
    assert set(EXAMPLES) == set(EFFECT_KINDS)


@pytest.mark.parametrize("kind", sorted(EXAMPLES))
def test_json_round_trip(kind):
    effect = Effect.from_dict({"kind": kind, **EXAMPLES[kind]})
    text = json.dumps(effect.to_dict())
    again = Effect.from_dict(json.loads(text))
    assert again == effect
    assert again.kind == kind
    assert hash(again) == hash(effect)  # frozen: usable as a dict key
    assert again.to_dict() == json.loads(text)


@pytest.mark.parametrize("kind", sorted(EXAMPLES))
def test_every_kind_builds_a_hopper(kind):
    from offdyn_bench.envs import make_robot_env

    env = make_robot_env("Hopper", [{"kind": kind, **EXAMPLES[kind]}])
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.action_space.sample())


def test_effects_are_frozen():
    effect = Gravity(scale=0.5)
    with pytest.raises(AttributeError):
        effect.scale = 2.0  # type: ignore[misc]


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        ({"kind": "friction", "scale": -1.0}, "invalid scale=-1.0; expected a number in [0, inf]"),
        ({"kind": "action_delay", "steps": -1}, "invalid steps=-1; expected an integer number of control steps >= 0"),
        ({"kind": "action_delay", "steps": 1.5}, "invalid steps=1.5"),
        ({"kind": "gravity", "scale": float("nan")}, "expected a finite number"),
        ({"kind": "gravity", "scale": 1.0, "target": "torso"}, "expected None: this effect acts on the whole model"),
        ({"kind": "joint_range", "scale": 1.5, "target": "thigh_joint"}, "expected a number in (0, 1]"),
        ({"kind": "contact_solimp", "dmin": 0.95, "dmax": 0.9, "width": 0.001}, "dmin <= dmax"),
        ({"kind": "friction_cone", "cone": "round"}, "one of ['elliptic', 'pyramidal']"),
        ({"kind": "obs_bias", "target": -2, "value": 0.1}, "a non-negative observation index"),
        ({"kind": "limb_size", "scale": 0.5}, "the name of the body to scale"),
    ],
)
def test_invalid_parameters_are_named(data, fragment):
    with pytest.raises(InvalidParameterError) as info:
        Effect.from_dict(data)
    assert f"effect {data['kind']!r}" in str(info.value)
    assert fragment in str(info.value)


def test_unknown_kind_lists_close_matches():
    with pytest.raises(UnknownNameError, match="unknown effect kind 'gravty'; closest valid names: 'gravity'"):
        Effect.from_dict({"kind": "gravty", "scale": 1.0})


def test_unknown_and_missing_parameters():
    with pytest.raises(UnknownNameError, match="parameter of effect 'gravity' 'scael'.*'scale'"):
        Effect.from_dict({"kind": "gravity", "scael": 1.0})
    with pytest.raises(OffdynError, match="missing parameter"):
        Effect.from_dict({"kind": "gravity"})
    with pytest.raises(OffdynError, match="expected a list of effects"):
        effects_from_dicts({"kind": "gravity", "scale": 1.0})


def test_unknown_target_names_the_closest_body():
    with pytest.raises(UnknownNameError, match="unknown body 'thihg'; closest valid names: 'thigh'"):
        ENV_CLASSES["Hopper"](model_effects=[Mass(target="thihg", scale=2.0)])
    with pytest.raises(UnknownNameError, match="actuator .* 'knee'"):
        from offdyn_bench.envs import make_robot_env

        make_robot_env("Hopper", [ActionDeadzone(target="knee", threshold=0.1)])


def test_joint_range_rejects_unlimited_joint():
    with pytest.raises(OffdynError, match="joint 'rootx' has no range to shrink"):
        ENV_CLASSES["Hopper"](model_effects=[JointRange(target="rootx", scale=0.5)])


def test_observation_target_out_of_range():
    from offdyn_bench.envs import make_robot_env

    with pytest.raises(OffdynError, match="observation index 11 is out of range; the observation has 11"):
        make_robot_env("Hopper", [{"kind": "obs_bias", "target": 11, "value": 0.1}])


# --- channel transforms (vectorized forms used by diagnosis) ---------------------------------

def test_deadzone_zeroes_small_commands_and_passes_large_ones_unchanged():
    x = np.array([[0.05, -0.1, 0.3], [-0.5, 0.09, -0.11]])
    mask = np.array([True, True, False])
    out = ActionDeadzone(threshold=0.1).transform(x, mask, None)
    np.testing.assert_array_equal(out, [[0.0, 0.0, 0.3], [-0.5, 0.0, -0.11]])


def test_delay_transform_shifts_by_exactly_k():
    x = np.arange(12, dtype=float).reshape(6, 2)
    out = ActionDelay(steps=2).transform(x, np.array([True, False]), None)
    np.testing.assert_array_equal(out[:, 0], [0, 0, 0, 2, 4, 6])
    np.testing.assert_array_equal(out[:, 1], x[:, 1])
    obs = ObsDelay(steps=1).transform(x, np.array([True, True]), None)
    np.testing.assert_array_equal(obs[1:], x[:-1])
    np.testing.assert_array_equal(obs[0], x[0])  # before any history: the first observation


def test_bias_gain_saturation_noise():
    x = np.array([[0.2, -0.8]])
    all_dims = np.array([True, True])
    np.testing.assert_allclose(ActionBias(value=0.1).transform(x, all_dims, None), [[0.3, -0.7]])
    np.testing.assert_allclose(ActionGain(scale=-0.5).transform(x, all_dims, None), [[-0.1, 0.4]])
    np.testing.assert_allclose(ActionSaturation(limit=0.5).transform(x, all_dims, None), [[0.2, -0.5]])
    rng = np.random.default_rng(0)
    noisy = ActionNoise(std=0.3).transform(np.zeros((20000, 2)), np.array([True, False]), rng)
    assert abs(noisy[:, 0].std() - 0.3) < 0.01
    assert np.all(noisy[:, 1] == 0.0)
    with pytest.raises(OffdynError, match="needs a random generator"):
        ActionNoise(std=0.3).transform(x, all_dims, None)


# --- model effects on compiled models --------------------------------------------------------

def _hopper_xml() -> str:
    return ENV_CLASSES["Hopper"]().fullpath


def test_limb_size_scales_mass_with_volume_and_keeps_the_child_attached():
    base = compile_model(_hopper_xml())
    scaled = compile_model(_hopper_xml(), [LimbSize(target="thigh", scale=0.5)])
    thigh = mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_BODY, "thigh")
    # A capsule scaled uniformly by s has s^3 the volume, so s^3 the mass at the same density.
    assert scaled.body_mass[thigh] == pytest.approx(base.body_mass[thigh] * 0.125, rel=1e-9)
    data = mujoco.MjData(scaled)
    mujoco.mj_forward(scaled, data)
    leg_joint = mujoco.mj_name2id(scaled, mujoco.mjtObj.mjOBJ_JOINT, "leg_joint")
    thigh_geom = mujoco.mj_name2id(scaled, mujoco.mjtObj.mjOBJ_GEOM, "thigh_geom")
    half_length = scaled.geom_size[thigh_geom, 1]
    thigh_end = data.geom_xpos[thigh_geom] - data.geom_xmat[thigh_geom].reshape(3, 3)[:, 2] * half_length
    np.testing.assert_allclose(data.xanchor[leg_joint], thigh_end, atol=1e-9)
    other = [b for b in range(base.nbody) if b != thigh]
    np.testing.assert_allclose(scaled.body_mass[other], base.body_mass[other])


def test_limb_size_on_halfcheetah_keeps_other_masses_despite_settotalmass():
    path = ENV_CLASSES["HalfCheetah"]().fullpath
    base = compile_model(path)
    scaled = compile_model(path, [LimbSize(target="fthigh", scale=0.5)])
    fthigh = mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_BODY, "fthigh")
    other = [b for b in range(base.nbody) if b != fthigh]
    np.testing.assert_allclose(scaled.body_mass[other], base.body_mass[other], rtol=1e-9)
    assert scaled.body_mass[fthigh] == pytest.approx(base.body_mass[fthigh] * 0.125, rel=1e-9)


def test_friction_scales_every_geom_so_every_contact_scales():
    base = compile_model(_hopper_xml())
    low = compile_model(_hopper_xml(), [Friction(scale=0.5)])
    np.testing.assert_allclose(low.geom_friction, base.geom_friction * 0.5)


def test_joint_range_shrinks_about_the_reference_pose():
    base = compile_model(_hopper_xml())
    model = compile_model(_hopper_xml(), [JointRange(target="thigh_joint", scale=0.2)])
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "thigh_joint")
    np.testing.assert_allclose(np.degrees(base.jnt_range[j]), [-150.0, 0.0])
    np.testing.assert_allclose(np.degrees(model.jnt_range[j]), [-30.0, 0.0])
