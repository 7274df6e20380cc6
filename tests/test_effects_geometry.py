"""Limits, limit softness, body offsets and geom sizes: what each does to the physics.

Each effect is checked by what it means on a small model built for it (a joint driven into its
stop by a constant torque, a block resting on its foot, two bodies that touch only once a geom
grows), and on Hopper's model through both ``compile_model`` and ``apply_model_effects``.
"""

from __future__ import annotations

import copy

import mujoco
import numpy as np
import pytest

from offdyn_bench.effects import (
    BodyOffset,
    Effect,
    GeomSize,
    JointLimit,
    JointLimitSoftness,
    JointRange,
    apply_model_effects,
    compile_model,
)
from offdyn_bench.envs import ENV_CLASSES
from offdyn_bench.errors import OffdynError, UnknownNameError

# A rod on a hinge limited to +-30 deg and a carriage on a slide limited to +-0.1 m, each with a
# motor and damping so that a constant command settles it against a stop. No gravity.
ARM_XML = """
<mujoco>
  <option gravity="0 0 0" timestep="0.002"/>
  <worldbody>
    <body name="arm">
      <joint name="hinge" type="hinge" axis="0 1 0" range="-30 30" limited="true" damping="1"/>
      <geom name="rod" type="capsule" fromto="0 0 0 0.5 0 0" size="0.02" mass="1"/>
    </body>
    <body name="carriage" pos="0 1 0">
      <joint name="slide" type="slide" axis="1 0 0" range="-0.1 0.1" limited="true" damping="10"/>
      <geom name="cart" type="box" size="0.05 0.05 0.05" mass="1"/>
    </body>
    <body name="wheel" pos="0 2 0">
      <joint name="spin" type="hinge" axis="0 1 0" damping="1"/>
      <geom type="cylinder" size="0.1 0.02" mass="1"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="hinge"/>
    <motor joint="slide"/>
    <motor joint="spin"/>
  </actuator>
</mujoco>
"""
HINGE_TORQUE, SLIDE_FORCE = 2.0, 5.0


def _arm() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(ARM_XML)


def _with(model: mujoco.MjModel, effects: list) -> mujoco.MjModel:
    edited = copy.copy(model)
    apply_model_effects(edited, effects)
    return edited


def _settle(model: mujoco.MjModel, ctrl: list[float], seconds: float = 1.5) -> np.ndarray:
    data = mujoco.MjData(model)
    data.ctrl[:] = ctrl
    for _ in range(round(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
    return data.qpos.copy()


def _id(model: mujoco.MjModel, objtype: mujoco.mjtObj, name: str) -> int:
    i = mujoco.mj_name2id(model, objtype, name)
    assert i >= 0, name
    return i


def _hopper_xml() -> str:
    return ENV_CLASSES["Hopper"]().fullpath


# --- joint ranges and limits ------------------------------------------------------------------

def test_the_arm_stops_at_its_nominal_limits():
    """The reference the other limit tests compare against: the stops hold within a milliradian."""
    hinge, slide = _settle(_arm(), [HINGE_TORQUE, SLIDE_FORCE, 0])[:2]
    assert hinge == pytest.approx(np.radians(30), abs=1e-3)
    assert slide == pytest.approx(0.1, abs=1e-3)


def test_a_widened_range_lets_the_joint_past_the_old_limit_to_the_new_one():
    wide = _with(_arm(), [JointRange(target="hinge", scale=2.0)])
    np.testing.assert_allclose(np.degrees(wide.jnt_range[0]), [-60.0, 60.0])
    up = _settle(wide, [HINGE_TORQUE, 0, 0])[0]
    down = _settle(wide, [-HINGE_TORQUE, 0, 0])[0]
    assert up == pytest.approx(np.radians(60), abs=1e-3)
    assert down == pytest.approx(-np.radians(60), abs=1e-3)


def test_a_moved_upper_limit_moves_only_that_stop():
    base = _arm()
    moved = _with(base, [JointLimit(target="hinge", side="upper", shift=0.5)])
    np.testing.assert_allclose(moved.jnt_range[0], base.jnt_range[0] + [0.0, 0.5])
    assert _settle(moved, [HINGE_TORQUE, 0, 0])[0] == pytest.approx(np.radians(30) + 0.5, abs=1e-3)
    assert _settle(moved, [-HINGE_TORQUE, 0, 0])[0] == pytest.approx(-np.radians(30), abs=1e-3)


def test_a_moved_lower_limit_of_a_slide_joint_is_in_metres():
    moved = _with(_arm(), [JointLimit(target="slide", side="lower", shift=-0.05)])
    assert _settle(moved, [0, -SLIDE_FORCE, 0])[1] == pytest.approx(-0.15, abs=1e-3)
    assert _settle(moved, [0, SLIDE_FORCE, 0])[1] == pytest.approx(0.1, abs=1e-3)
    narrowed = _with(_arm(), [JointLimit(target="slide", side="lower", shift=0.15)])
    assert _settle(narrowed, [0, -SLIDE_FORCE, 0])[1] == pytest.approx(0.05, abs=1e-3)


def test_a_limit_moved_past_the_other_is_refused_and_nothing_is_written():
    base = _arm()
    model = copy.copy(base)
    with pytest.raises(OffdynError, match=r"effect 'joint_limit': moving the lower limit of joint 'hinge' by 1.2 "
                                          r"gives lower=0.676\d* >= upper=0.523\d* \(the range is \[-0.523\d*, 0.523\d*\]\)"):
        apply_model_effects(model, [JointLimit(target="hinge", side="lower", shift=1.2)])
    np.testing.assert_array_equal(model.jnt_range, base.jnt_range)
    with pytest.raises(OffdynError, match="upper limit of joint 'slide'.*must stay below"):
        apply_model_effects(model, [JointLimit(target="slide", side="upper", shift=-0.2)])  # equal limits
    np.testing.assert_array_equal(model.jnt_range, base.jnt_range)


def test_a_failure_after_earlier_effects_acted_restores_every_field():
    """The shift fits the nominal range (checked up front) but not the one joint_range leaves."""
    base = compile_model(_hopper_xml())
    model = copy.copy(base)
    effects = [JointRange(target="thigh_joint", scale=0.2), BodyOffset(target="foot", axis="z", offset=-0.1),
               JointLimit(target="thigh_joint", side="lower", shift=2.0)]
    with pytest.raises(OffdynError, match="lower limit of joint 'thigh_joint'"):
        apply_model_effects(model, effects)
    np.testing.assert_array_equal(model.jnt_range, base.jnt_range)
    np.testing.assert_array_equal(model.body_pos, base.body_pos)
    with pytest.raises(OffdynError, match="lower limit of joint 'thigh_joint'"):
        compile_model(_hopper_xml(), effects)


@pytest.mark.parametrize("effect", [JointLimit(target="spin", side="upper", shift=0.1),
                                    JointRange(target="spin", scale=2.0),
                                    JointLimitSoftness(target="spin", timeconst=0.1)])
def test_limit_effects_refuse_an_unlimited_joint(effect):
    with pytest.raises(OffdynError, match=f"effect '{effect.kind}': joint 'spin' is not limited"):
        apply_model_effects(copy.copy(_arm()), [effect])


def test_joint_limit_names_the_closest_joints():
    with pytest.raises(UnknownNameError, match="unknown joint 'thigh'; closest valid names: 'thigh_joint'"):
        compile_model(_hopper_xml(), [JointLimit(target="thigh", side="upper", shift=0.1)])


# --- joint-limit softness ---------------------------------------------------------------------

def test_a_softer_limit_lets_the_joint_go_further_past_it_under_the_same_torque():
    base = _arm()
    limit = base.jnt_range[0, 1]
    stiff = _settle(base, [HINGE_TORQUE, 0, 0], seconds=3.0)[0] - limit
    soft_model = _with(base, [JointLimitSoftness(target="hinge", timeconst=0.2)])
    soft = _settle(soft_model, [HINGE_TORQUE, 0, 0], seconds=3.0)[0] - limit
    # At rest the limit's spring carries the torque; its stiffness goes as 1/timeconst^2, so ten
    # times the time constant is (nearly: the impedance varies with depth) a hundred times deeper.
    assert 0 < stiff < 1e-3
    assert soft > 50 * stiff
    assert soft > 0.03
    np.testing.assert_allclose(soft_model.jnt_solref[0], [0.2, 1.0])


def test_limit_softness_without_target_sets_every_limited_actuated_joint():
    base = compile_model(_hopper_xml())
    model = compile_model(_hopper_xml(), [JointLimitSoftness(timeconst=0.08, dampratio=0.5)])
    limited = [_id(base, mujoco.mjtObj.mjOBJ_JOINT, n) for n in ("thigh_joint", "leg_joint", "foot_joint")]
    roots = [_id(base, mujoco.mjtObj.mjOBJ_JOINT, n) for n in ("rootx", "rootz", "rooty")]
    np.testing.assert_allclose(model.jnt_solref[limited], [[0.08, 0.5]] * 3)
    np.testing.assert_array_equal(model.jnt_solref[roots], base.jnt_solref[roots])
    assert not np.allclose(base.jnt_solref[limited], model.jnt_solref[limited])


# --- body offsets ------------------------------------------------------------------------------

# A two-link arm hanging from a shoulder whose frame is turned 90 deg about y, with a hand.
LINKS_XML = """
<mujoco>
  <worldbody>
    <body name="upper" pos="0 0 1" euler="0 90 0">
      <joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom name="upper_geom" type="capsule" fromto="0 0 0 0 0 -0.4" size="0.03"/>
      <body name="lower" pos="0 0 -0.4">
        <joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom name="lower_geom" type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03"/>
        <body name="hand" pos="0 0 -0.3">
          <geom name="hand_geom" type="sphere" size="0.04"/>
        </body>
      </body>
    </body>
    <body name="floating" pos="2 0 1">
      <freejoint/>
      <geom type="sphere" size="0.1"/>
    </body>
  </worldbody>
</mujoco>
"""


def _pose(model: mujoco.MjModel, qpos: dict[str, float]) -> mujoco.MjData:
    data = mujoco.MjData(model)
    for name, value in qpos.items():
        data.qpos[model.jnt_qposadr[_id(model, mujoco.mjtObj.mjOBJ_JOINT, name)]] = value
    mujoco.mj_forward(model, data)
    return data


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_a_body_offset_moves_the_body_and_all_below_it_in_the_parents_turned_frame(axis):
    base = mujoco.MjModel.from_xml_string(LINKS_XML)
    moved = _with(base, [BodyOffset(target="lower", axis=axis, offset=-0.1)])
    pose = {"shoulder": 0.7, "elbow": -0.4}
    before, after = _pose(base, pose), _pose(moved, pose)
    upper, lower, hand = (_id(base, mujoco.mjtObj.mjOBJ_BODY, n) for n in ("upper", "lower", "hand"))
    step = before.xmat[upper].reshape(3, 3)[:, "xyz".index(axis)] * -0.1  # the parent's axis, in the world
    for body in (lower, hand):
        np.testing.assert_allclose(after.xpos[body] - before.xpos[body], step, atol=1e-12)
    upper_geom = _id(base, mujoco.mjtObj.mjOBJ_GEOM, "upper_geom")
    np.testing.assert_allclose(after.geom_xpos[upper_geom], before.geom_xpos[upper_geom], atol=1e-12)
    np.testing.assert_allclose(moved.body_mass, base.body_mass)
    np.testing.assert_allclose(moved.body_inertia, base.body_inertia)


def test_a_body_offset_along_the_limb_changes_the_reach():
    base = mujoco.MjModel.from_xml_string(LINKS_XML)
    longer = _with(base, [BodyOffset(target="lower", axis="z", offset=-0.1)])  # the upper link's length axis
    hand = _id(base, mujoco.mjtObj.mjOBJ_BODY, "hand")
    shoulder = _id(base, mujoco.mjtObj.mjOBJ_JOINT, "shoulder")

    def reach(model: mujoco.MjModel) -> float:
        data = _pose(model, {"elbow": 0.0})
        return float(np.linalg.norm(data.xpos[hand] - data.xanchor[shoulder]))

    assert reach(base) == pytest.approx(0.7, abs=1e-12)
    assert reach(longer) == pytest.approx(0.8, abs=1e-12)


def test_a_hopper_foot_offset_lengthens_the_shin_and_moves_the_foot_geom_with_it():
    base = compile_model(_hopper_xml())
    effect = BodyOffset(target="foot", axis="z", offset=-0.1)
    compiled = compile_model(_hopper_xml(), [effect])
    applied = _with(base, [effect])
    np.testing.assert_array_equal(compiled.body_pos, applied.body_pos)
    leg_joint, foot_joint = (_id(base, mujoco.mjtObj.mjOBJ_JOINT, n) for n in ("leg_joint", "foot_joint"))
    foot_geom, leg_geom = (_id(base, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("foot_geom", "leg_geom"))
    before, after = _pose(base, {}), _pose(compiled, {})

    def shin(data: mujoco.MjData) -> float:
        return float(np.linalg.norm(data.xanchor[foot_joint] - data.xanchor[leg_joint]))

    assert shin(before) == pytest.approx(0.5)
    assert shin(after) == pytest.approx(0.6)
    np.testing.assert_allclose(after.geom_xpos[foot_geom] - before.geom_xpos[foot_geom], [0, 0, -0.1], atol=1e-12)
    np.testing.assert_allclose(after.geom_xpos[leg_geom], before.geom_xpos[leg_geom], atol=1e-12)


def test_a_body_offset_refuses_the_world_a_free_body_and_unknown_names():
    model = mujoco.MjModel.from_xml_string(LINKS_XML)
    with pytest.raises(OffdynError, match="'world' is the world body, which has no parent to move against"):
        apply_model_effects(copy.copy(model), [BodyOffset(target="world", axis="x", offset=0.1)])
    with pytest.raises(OffdynError, match="body 'floating' moves on a free joint"):
        apply_model_effects(copy.copy(model), [BodyOffset(target="floating", axis="x", offset=0.1)])
    with pytest.raises(UnknownNameError, match="unknown body 'lowr'; closest valid names: 'lower'"):
        apply_model_effects(copy.copy(model), [BodyOffset(target="lowr", axis="x", offset=0.1)])


# --- geom sizes --------------------------------------------------------------------------------

# A block on a slide joint that rests on a sphere foot; the block's own box does not collide.
STAND_XML = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="block" pos="0 0 0.5">
      <joint name="lift" type="slide" axis="0 0 1" damping="20"/>
      <geom name="box" type="box" size="0.1 0.1 0.1" contype="0" conaffinity="0"/>
      <geom name="foot" type="sphere" pos="0 0 -0.2" size="0.05"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("scale", [0.5, 2.0, 3.0])
def test_a_bigger_foot_lifts_the_resting_body_by_the_change_of_radius_at_the_same_mass(scale):
    base = mujoco.MjModel.from_xml_string(STAND_XML)
    resized = _with(base, [GeomSize(target="foot", scale=scale)])
    rest_before = _settle(base, [], seconds=1.0)[0]
    rest_after = _settle(resized, [], seconds=1.0)[0]
    # The same weight on the same contact settings sinks the foot equally deep.
    assert rest_after - rest_before == pytest.approx((scale - 1) * 0.05, abs=1e-6)
    np.testing.assert_array_equal(resized.body_mass, base.body_mass)
    np.testing.assert_array_equal(resized.body_inertia, base.body_inertia)
    np.testing.assert_array_equal(resized.geom_pos, base.geom_pos)


# Two bodies of two spheres each: mid-phase collision (body bounding-volume trees) decides
# whether their geoms are even compared.
PAIR_XML = """
<mujoco>
  <option gravity="0 0 0"/>
  <worldbody>
    <body name="a">
      <joint type="slide" axis="1 0 0"/>
      <geom name="a1" type="sphere" size="0.1"/>
      <geom name="a2" type="sphere" pos="0 0 0.5" size="0.1"/>
    </body>
    <body name="b" pos="0.5 0 0">
      <joint type="slide" axis="1 0 0"/>
      <geom name="b1" type="sphere" size="0.1"/>
      <geom name="b2" type="sphere" pos="0 0 0.5" size="0.1"/>
    </body>
  </worldbody>
</mujoco>
"""


def _contacts(model: mujoco.MjModel) -> int:
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return int(data.ncon)


def test_a_grown_geom_touches_what_it_now_reaches_through_every_collision_phase():
    base = mujoco.MjModel.from_xml_string(PAIR_XML)
    assert _contacts(base) == 0
    assert _contacts(_with(base, [GeomSize(target="a", scale=3.0)])) == 0  # 0.3 + 0.1 < 0.5 apart
    assert _contacts(_with(base, [GeomSize(target="a", scale=4.5)])) == 2  # 0.45 + 0.1 > 0.5
    # Scaling only the sizes and the geoms' own bounds misses both contacts: the bodies' trees
    # still cull with the old boxes. This is what the effect's tree refit is for.
    naive = copy.copy(base)
    naive.geom_size[:2] *= 4.5
    naive.geom_rbound[:2] *= 4.5
    naive.geom_aabb[:2] *= 4.5
    assert _contacts(naive) == 0


# One body with three differently shaped, placed and turned geoms, and an explicit inertial
# frame, so the compiler's own bounds for larger geoms can be compared with the effect's.
SHAPES_XML = """
<mujoco>
  <worldbody>
    <body name="shapes" pos="0 0 1" euler="10 20 30">
      <joint type="hinge" axis="1 0 0"/>
      <inertial pos="0.05 -0.02 0.1" quat="0.9 0.1 0.3 0.2" mass="2" diaginertia="0.1 0.2 0.3"/>
      <geom name="box" type="box" pos="0.2 0 0" euler="0 0 40" size="0.1 0.05 0.02"/>
      <geom name="capsule" type="capsule" fromto="-0.3 0 0 -0.1 0.2 0.1" size="0.03"/>
      <geom name="ellipsoid" type="ellipsoid" pos="0 0.3 -0.1" euler="30 0 0" size="0.05 0.08 0.12"/>
      <geom name="cylinder" type="cylinder" pos="0 -0.3 0.2" size="0.04 0.1"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_geom_size_matches_what_the_compiler_builds_for_the_larger_geoms():
    scale = 1.7
    edited = _with(mujoco.MjModel.from_xml_string(SHAPES_XML), [GeomSize(target="shapes", scale=scale)])
    spec = mujoco.MjSpec.from_string(SHAPES_XML)
    for geom in spec.geoms:
        if np.isnan(geom.fromto[0]):
            geom.size = np.asarray(geom.size) * scale
        else:  # a capsule from-to grows about its midpoint
            start, end = np.asarray(geom.fromto[:3]), np.asarray(geom.fromto[3:])
            middle = (start + end) / 2
            geom.fromto = np.concatenate([middle + scale * (start - middle), middle + scale * (end - middle)])
            geom.size = np.asarray(geom.size) * scale
    compiled = spec.compile()
    np.testing.assert_allclose(edited.geom_size, compiled.geom_size, atol=1e-12)
    np.testing.assert_allclose(edited.geom_rbound, compiled.geom_rbound, atol=1e-12)
    np.testing.assert_allclose(edited.geom_aabb, compiled.geom_aabb, atol=1e-12)
    np.testing.assert_allclose(edited.bvh_aabb, compiled.bvh_aabb, atol=1e-12)
    np.testing.assert_allclose(edited.geom_pos, compiled.geom_pos, atol=1e-12)


def test_geom_size_on_hopper_through_both_paths_leaves_the_floor_and_the_mass_alone():
    base = compile_model(_hopper_xml())
    compiled = compile_model(_hopper_xml(), [GeomSize(scale=1.5)])
    applied = _with(base, [GeomSize(scale=1.5)])
    floor = _id(base, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    body_geoms = [g for g in range(base.ngeom) if g != floor]
    for model in (compiled, applied):
        np.testing.assert_array_equal(model.geom_size[floor], base.geom_size[floor])
        np.testing.assert_allclose(model.geom_size[body_geoms], base.geom_size[body_geoms] * 1.5)
        np.testing.assert_allclose(model.geom_rbound[body_geoms], base.geom_rbound[body_geoms] * 1.5)
        np.testing.assert_array_equal(model.body_mass, base.body_mass)
        np.testing.assert_array_equal(model.body_inertia, base.body_inertia)
    np.testing.assert_array_equal(compiled.geom_size, applied.geom_size)
    np.testing.assert_array_equal(compiled.bvh_aabb, applied.bvh_aabb)


def test_a_bigger_hopper_foot_touches_the_ground_sooner_when_dropped():
    def first_contact_height(model: mujoco.MjModel) -> float:
        data = mujoco.MjData(model)
        rootz = model.jnt_qposadr[_id(model, mujoco.mjtObj.mjOBJ_JOINT, "rootz")]
        data.qpos[rootz] = model.qpos0[rootz] + 0.3  # the foot starts 0.34 m above the floor
        while data.ncon == 0:
            mujoco.mj_step(model, data)
        return float(data.qpos[rootz])

    base = compile_model(_hopper_xml())
    bigger = compile_model(_hopper_xml(), [GeomSize(target="foot_geom", scale=2.0)])
    foot_radius = base.geom_size[_id(base, mujoco.mjtObj.mjOBJ_GEOM, "foot_geom"), 0]
    # Falling straight down at qpos0: the foot capsule's bottom is its radius below its axis.
    assert first_contact_height(bigger) - first_contact_height(base) == pytest.approx(foot_radius, abs=0.005)


def test_geom_size_refuses_planes_meshes_and_targets_without_a_scalable_geom():
    hopper = compile_model(_hopper_xml())
    with pytest.raises(OffdynError, match="effect 'geom_size': geom 'floor' is a plane, whose size is not a scale"):
        apply_model_effects(copy.copy(hopper), [GeomSize(target="floor", scale=2.0)])
    with pytest.raises(OffdynError, match="'world' has no geom whose size can be scaled"):
        apply_model_effects(copy.copy(hopper), [GeomSize(target="world", scale=2.0)])
    with pytest.raises(UnknownNameError, match="unknown geom or body 'foot_gem'; closest valid names: 'foot_geom'"):
        apply_model_effects(copy.copy(hopper), [GeomSize(target="foot_gem", scale=2.0)])
    mesh_xml = """
    <mujoco>
      <asset><mesh name="tetra" vertex="0 0 0  1 0 0  0 1 0  0 0 1"/></asset>
      <worldbody><body name="rock"><geom name="rock_geom" type="mesh" mesh="tetra"/></body></worldbody>
    </mujoco>"""
    with_mesh = mujoco.MjModel.from_xml_string(mesh_xml)
    for target in ("rock_geom", "rock", None):
        with pytest.raises(OffdynError, match="rock_geom"):
            apply_model_effects(copy.copy(with_mesh), [GeomSize(target=target, scale=2.0)])


# --- serialization of the new kinds ----------------------------------------------------------

@pytest.mark.parametrize("effect", [
    JointLimit(target="hinge", side="upper", shift=-0.25),
    JointLimitSoftness(timeconst=0.03),
    BodyOffset(target="lower", axis="y", offset=0.02),
    GeomSize(target="foot", scale=1.25),
    JointRange(target="hinge", scale=4.0),
])
def test_round_trip_and_description(effect):
    data = effect.to_dict()
    assert Effect.from_dict(data) == effect
    assert data["kind"] == effect.kind
    assert effect.primary_value == data[effect.value_field]
    assert effect.kind in effect.describe()
