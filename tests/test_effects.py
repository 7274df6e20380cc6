"""The effect vocabulary: serialization, validation, and what each channel effect does."""

from __future__ import annotations

import copy
import dataclasses
import json
import pathlib

import hypothesis
import hypothesis.strategies as st
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
from offdyn_bench.effects.base import OneOf
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
    "joint_limit": {"target": "thigh_joint", "side": "lower", "shift": -0.3},
    "joint_limit_solref": {"target": "foot_joint", "timeconst": 0.05, "dampratio": 0.7},
    "body_offset": {"target": "foot", "axis": "x", "offset": 0.05},
    "geom_size": {"target": "foot_geom", "scale": 1.5},
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
    "maze_layout": {"walls": ["11111", "10001", "11101", "10001", "11111"]},
}
# Kinds that act on maze models only (their blocks); tests/robotics builds them on AntMaze, and
# test_a_maze_effect_refuses_a_model_without_a_maze checks the error on Hopper.
MAZE_KINDS = {"maze_layout"}
HOPPER_KINDS = sorted(set(EXAMPLES) - MAZE_KINDS)


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


@pytest.mark.parametrize("kind", HOPPER_KINDS)
def test_every_kind_builds_a_hopper(kind):
    from offdyn_bench.envs import make_robot_env

    env = make_robot_env("Hopper", [{"kind": kind, **EXAMPLES[kind]}])
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.action_space.sample())


@pytest.mark.parametrize("kind", sorted(MAZE_KINDS))
def test_a_maze_effect_refuses_a_model_without_a_maze(kind):
    from offdyn_bench.envs import make_robot_env

    with pytest.raises(OffdynError, match="acts on maze models"):
        make_robot_env("Hopper", [{"kind": kind, **EXAMPLES[kind]}])


def test_effects_are_frozen():
    effect = Gravity(scale=0.5)
    with pytest.raises(AttributeError):
        effect.scale = 2.0  # type: ignore[misc]


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        ({"kind": "friction", "scale": -1.0}, "invalid scale=-1.0; expected a number in [0, 10]"),
        ({"kind": "action_delay", "steps": -1}, "invalid steps=-1; expected an integer in [0, 1000]"),
        ({"kind": "action_delay", "steps": 1.5}, "invalid steps=1.5; expected an integer in [0, 1000]"),
        ({"kind": "gravity", "scale": float("nan")}, "invalid scale=nan; expected a number in [0, 10]"),
        ({"kind": "gravity", "scale": "0.5"}, "invalid scale='0.5'; expected a number in [0, 10]"),
        ({"kind": "gravity", "scale": True}, "invalid scale=True; expected a number in [0, 10]"),
        # Absurd but finite values: each used to crash or allocate far downstream.
        ({"kind": "obs_delay", "steps": 10**9}, "invalid steps=1000000000; expected an integer in [0, 1000]"),
        ({"kind": "action_delay", "steps": 10**18}, "expected an integer in [0, 1000]"),
        ({"kind": "noslip", "iterations": 10**12}, "invalid iterations=1000000000000; expected an integer in [0, 1000]"),
        ({"kind": "gravity", "scale": 1e300}, "invalid scale=1e+300; expected a number in [0, 10]"),
        ({"kind": "damping", "value": 1e5}, "expected a number in [0, 10000]"),
        ({"kind": "friction_cone", "cone": ["elliptic"]}, "invalid cone=('elliptic',); expected one of"),
        ({"kind": "gravity", "scale": 1.0, "target": "torso"}, "expected None: this effect acts on the whole model"),
        ({"kind": "joint_range", "scale": 10.5, "target": "thigh_joint"}, "invalid scale=10.5; expected a number in (0, 10]"),
        ({"kind": "joint_range", "scale": 0.0, "target": "thigh_joint"}, "expected a number in (0, 10]"),
        ({"kind": "joint_limit", "side": "left", "shift": 0.1, "target": "thigh_joint"},
         "invalid side='left'; expected one of ['lower', 'upper']"),
        ({"kind": "joint_limit", "side": "upper", "shift": 7.0, "target": "thigh_joint"},
         "invalid shift=7.0; expected a number in [-6.28319, 6.28319]"),
        ({"kind": "joint_limit", "side": "upper", "shift": 0.1}, "the name of the joint whose limit moves"),
        ({"kind": "joint_limit_solref", "timeconst": 0.0}, "invalid timeconst=0.0; expected a number in (0, 1]"),
        ({"kind": "joint_limit_solref", "timeconst": 0.02, "dampratio": -1}, "invalid dampratio=-1"),
        ({"kind": "body_offset", "axis": "w", "offset": 0.1, "target": "foot"},
         "invalid axis='w'; expected one of ['x', 'y', 'z']"),
        ({"kind": "body_offset", "axis": "z", "offset": 1.5, "target": "foot"}, "expected a number in [-1, 1]"),
        ({"kind": "body_offset", "axis": "z", "offset": 0.1}, "the name of the body to move"),
        ({"kind": "geom_size", "scale": 0.0}, "invalid scale=0.0; expected a number in [0.01, 10]"),
        ({"kind": "geom_size", "scale": 11}, "expected a number in [0.01, 10]"),
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
    with pytest.raises(OffdynError, match="effect 'joint_range': joint 'rootx' is not limited, so it has no range"):
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


def test_the_per_step_dead_zone_gives_the_transforms_bits_for_any_array_like_command():
    """The wrapper's per-step dead zone (Python floats) is ``transform`` on one command: the same
    float64 bits (signed zeros, the threshold itself, NaN and infinities included), a new array,
    the caller's command unchanged, whatever it came as."""
    torch = pytest.importorskip("torch")
    values = [0.1, -0.1, 0.1000001, -0.0999999, -0.0, 0.0, np.nan, -np.inf, np.inf, 5e-324, -3.0, 0.25]
    masks = [None, np.array([i % 3 != 1 for i in range(len(values))]), np.zeros(len(values), dtype=bool)]
    for threshold in (0.1, 0.0):
        effect = ActionDeadzone(threshold=threshold)
        for mask in masks:
            step = effect.per_step(mask, len(values))
            for command in (np.array(values), np.array(values, dtype=np.float32), values, tuple(values),
                            torch.tensor(values, dtype=torch.float64), torch.tensor(values, dtype=torch.float32),
                            np.arange(-6, 6), np.arange(-6, 6) % 2 == 0):
                expected = effect.transform(np.asarray(command, dtype=float), mask, None)
                before = np.asarray(command, dtype=float).copy()
                got = step(command)
                assert type(got) is np.ndarray and got.dtype == np.float64 and got is not command
                assert got.tobytes() == expected.tobytes(), (threshold, mask, command)
                np.testing.assert_array_equal(np.asarray(command, dtype=float), before)
    assert ActionDeadzone(threshold=0.1).per_step(None, ActionDeadzone.PER_STEP_MAX_SIZE + 1) is None


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


def test_joint_range_scales_about_the_reference_pose():
    base = compile_model(_hopper_xml())
    model = compile_model(_hopper_xml(), [JointRange(target="thigh_joint", scale=0.2)])
    wider = compile_model(_hopper_xml(), [JointRange(target="foot_joint", scale=2.0)])
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "thigh_joint")
    np.testing.assert_allclose(np.degrees(base.jnt_range[j]), [-150.0, 0.0])
    np.testing.assert_allclose(np.degrees(model.jnt_range[j]), [-30.0, 0.0])
    foot = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "foot_joint")
    np.testing.assert_allclose(np.degrees(base.jnt_range[foot]), [-45.0, 45.0])
    np.testing.assert_allclose(np.degrees(wider.jnt_range[foot]), [-90.0, 90.0])


def _model_values(model: mujoco.MjModel) -> dict[str, object]:
    """Every array field of a compiled model and every field of its options, by effect field name."""
    values: dict[str, object] = {}
    for owner, prefix in ((model, ""), (model.opt, "opt.")):
        for name in dir(owner):
            value = getattr(owner, name)
            if not name.startswith("_") and isinstance(value, (np.ndarray, int, float)):
                values[prefix + name] = np.array(value, copy=True)
    return values


@pytest.mark.parametrize("kind", sorted(k for k, cls in EFFECT_KINDS.items()
                                        if cls.family == "model" and not cls.needs_spec))
def test_a_model_effect_changes_only_the_fields_it_declares(kind):
    """``fields`` is what apply_model_effects restores when a later effect fails: it must be complete."""
    base = compile_model(_hopper_xml())
    effect = Effect.from_dict({"kind": kind, **EXAMPLES[kind]})
    model = copy.copy(base)
    effect.apply_to_model(model)
    before, after = _model_values(base), _model_values(model)
    changed = {name for name in before if not np.array_equal(before[name], after[name], equal_nan=True)}
    assert changed, f"{kind} changed nothing on Hopper"
    assert changed <= set(effect.fields), changed - set(effect.fields)


# --- parameter ranges: every parameter has one, and nothing outside it is ever built --------

def test_every_parameter_of_every_kind_has_a_documented_range():
    for kind, cls in EFFECT_KINDS.items():
        parameters = {f.name for f in dataclasses.fields(cls)} - {"target"}
        assert set(cls.ranges) == parameters, kind
        for name, allowed in cls.ranges.items():
            assert f"``{name}`` in {allowed.document()}" in cls.__doc__, kind


def test_the_readme_effects_table_states_every_range():
    readme = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    rows = {line.split("|")[1].strip().strip("`"): line for line in readme.splitlines()
            if line.startswith("| `") and line.split("|")[1].strip().strip("`") in EFFECT_KINDS}
    assert set(rows) == set(EFFECT_KINDS)
    for kind, cls in EFFECT_KINDS.items():
        for name, allowed in cls.ranges.items():
            assert f"`{name}` {allowed.document()}" in rows[kind], (kind, name)


def test_numpy_numbers_become_plain_numbers():
    effect = Effect.from_dict({"kind": "obs_bias", "target": np.int64(2), "value": np.float32(0.25)})
    assert type(effect.target) is int and type(effect.value) is float
    assert json.loads(json.dumps(effect.to_dict())) == {"kind": "obs_bias", "target": 2, "value": 0.25}
    assert ActionDelay(steps=np.int32(3)).steps == 3


def test_the_longest_delay_builds_and_steps():
    from offdyn_bench.envs import make_robot_env

    env = make_robot_env("Hopper", [{"kind": "obs_delay", "steps": 1000}, {"kind": "action_delay", "steps": 1000}])
    obs, _ = env.reset(seed=0)
    first = obs.copy()
    for _ in range(3):
        obs, _, _, _, info = env.step(env.action_space.sample())
    np.testing.assert_array_equal(obs, first)
    np.testing.assert_array_equal(info["applied_action"], 0.0)


_SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(), st.integers(min_value=-10**30, max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.sampled_from(["elliptic", "pyramidal", "RK4", "implicitfast", "thigh", "foot_joint"]),
)
_VALUES = st.recursive(_SCALARS, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
                       max_leaves=6)
_PARAMETER_NAMES = sorted({f.name for cls in EFFECT_KINDS.values() for f in dataclasses.fields(cls)})


@st.composite
def _effect_dicts(draw: st.DrawFn) -> dict:
    kind = draw(st.one_of(st.sampled_from(sorted(EFFECT_KINDS)), _VALUES))
    keys = draw(st.lists(st.one_of(st.sampled_from(_PARAMETER_NAMES), st.text(max_size=8)), max_size=6, unique=True))
    data = {key: draw(_VALUES) for key in keys}
    if draw(st.booleans()):
        data["kind"] = kind
    return data


@hypothesis.settings(max_examples=400, deadline=None)
@hypothesis.given(data=st.one_of(_effect_dicts(), _VALUES))
def test_from_dict_builds_a_valid_effect_or_raises_the_suites_error(data):
    try:
        effect = Effect.from_dict(data)
    except OffdynError as error:
        message = str(error)
        assert "\n" not in message and len(message) < 600
        return
    # Built: every parameter is a plain value inside its range, and the effect round-trips.
    for name, allowed in effect.ranges.items():
        assert allowed.normalize(getattr(effect, name)) == getattr(effect, name)
    assert Effect.from_dict(json.loads(json.dumps(effect.to_dict()))) == effect


def _in_range(allowed) -> st.SearchStrategy:
    if isinstance(allowed, OneOf):
        return st.sampled_from(allowed.options)
    if allowed.integer:
        return st.integers(min_value=int(allowed.low), max_value=min(int(allowed.high), 50))
    return st.floats(min_value=allowed.low, max_value=allowed.high, exclude_min=allowed.low_open,
                     exclude_max=allowed.high_open)


@st.composite
def _valid_hopper_effects(draw: st.DrawFn) -> dict:
    kind = draw(st.sampled_from(HOPPER_KINDS))
    cls = EFFECT_KINDS[kind]
    data = {"kind": kind, "target": EXAMPLES[kind].get("target")}
    data.update({name: draw(_in_range(allowed)) for name, allowed in cls.ranges.items()})
    if kind == "contact_solimp" and data["dmin"] > data["dmax"]:
        data["dmin"], data["dmax"] = data["dmax"], data["dmin"]
    return data


def _closes_the_range(data: dict) -> bool:
    """Whether a ``joint_limit`` example would put its joint's lower limit at or above the upper."""
    if data["kind"] != "joint_limit":
        return False
    model = compile_model(_hopper_xml())
    low, high = model.jnt_range[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, data["target"])]
    return low + data["shift"] >= high if data["side"] == "lower" else high + data["shift"] <= low


@hypothesis.settings(max_examples=40, deadline=None, suppress_health_check=[hypothesis.HealthCheck.too_slow])
@hypothesis.given(data=_valid_hopper_effects())
def test_every_value_in_range_builds_a_hopper_that_steps(data):
    from offdyn_bench.envs import make_robot_env

    if _closes_the_range(data):  # the one in-range value that is not a model: refused, naming the joint
        with pytest.raises(OffdynError, match=f"limit of joint '{data['target']}'.*must stay below"):
            make_robot_env("Hopper", [data])
        return
    env = make_robot_env("Hopper", [data])
    env.reset(seed=0)
    for _ in range(3):
        env.step(env.action_space.sample())
