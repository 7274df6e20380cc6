"""Model effects: changes to the compiled MuJoCo model, applied once at construction.

Most effects edit fields of a compiled ``mujoco.MjModel`` in place, cheap enough to build many
candidate models during gap diagnosis (``geom_size`` and ``body_offset`` too: they leave mass and
inertia alone); ``limb_size`` changes geometry with its mass and so edits the ``mujoco.MjSpec``
before compilation. :func:`compile_model` runs both stages and then recomputes
the compiler's derived constants (``mj_setConst``) so masses, inertias and invweights stay
consistent.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import numpy as np

from offdyn_bench.effects.base import Effect, Interval, OneOf
from offdyn_bench.errors import OffdynError, UnknownNameError

if TYPE_CHECKING:
    import mujoco
else:
    class _LazyMujoco:
        """MuJoCo, imported on first use. Declaring effects (``import offdyn_bench`` builds and
        registers the task grid) needs no physics engine, and importing MuJoCo costs a command
        line's start-up about a tenth of a second (it loads its GLFW library)."""

        def __getattr__(self, name: str) -> Any:
            import mujoco as module

            globals()["mujoco"] = module  # later look-ups find the module itself
            return getattr(module, name)

    mujoco = _LazyMujoco()


# --- name resolution on a compiled model ------------------------------------------------------

def _names(model: mujoco.MjModel, objtype: mujoco.mjtObj, count: int) -> list[str]:
    return [mujoco.mj_id2name(model, objtype, i) or "" for i in range(count)]


def body_ids(model: mujoco.MjModel, target: str | None) -> np.ndarray:
    """Bodies a target names; ``None`` is every body except the world."""
    if target is None:
        return np.arange(1, model.nbody)
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, target)
    if i < 0:
        raise UnknownNameError("body", target, [n for n in _names(model, mujoco.mjtObj.mjOBJ_BODY, model.nbody) if n])
    return np.array([i])


def geom_ids(model: mujoco.MjModel, target: str | None) -> np.ndarray:
    """Geoms a target names: a geom name, or a body name meaning all that body's geoms."""
    if target is None:
        return np.arange(model.ngeom)
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, target)
    if i >= 0:
        return np.array([i])
    b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, target)
    if b >= 0:
        return np.flatnonzero(model.geom_bodyid == b)
    valid = _names(model, mujoco.mjtObj.mjOBJ_GEOM, model.ngeom) + _names(model, mujoco.mjtObj.mjOBJ_BODY, model.nbody)
    raise UnknownNameError("geom or body", target, [n for n in valid if n])


def actuated_joint_ids(model: mujoco.MjModel) -> np.ndarray:
    joints = [model.actuator_trnid[a, 0] for a in range(model.nu)
              if int(model.actuator_trntype[a]) == int(mujoco.mjtTrn.mjTRN_JOINT)]
    return np.array(sorted(set(int(j) for j in joints)), dtype=int)


def joint_ids(model: mujoco.MjModel, target: str | None) -> np.ndarray:
    """Joints a target names; ``None`` is every actuated joint (root joints excluded)."""
    if target is None:
        return actuated_joint_ids(model)
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, target)
    if i < 0:
        raise UnknownNameError("joint", target, [n for n in _names(model, mujoco.mjtObj.mjOBJ_JOINT, model.njnt) if n])
    return np.array([i])


_JOINT_DOFS = {"mjJNT_FREE": 6, "mjJNT_BALL": 3, "mjJNT_SLIDE": 1, "mjJNT_HINGE": 1}


def dof_ids(model: mujoco.MjModel, target: str | None) -> np.ndarray:
    dofs: list[int] = []
    for j in joint_ids(model, target):
        start = model.jnt_dofadr[j]
        dofs.extend(range(start, start + _JOINT_DOFS[mujoco.mjtJoint(model.jnt_type[j]).name]))
    return np.array(dofs, dtype=int)


def actuator_name(model: mujoco.MjModel, actuator: int) -> str:
    """An actuator's name, or the name of the joint it drives when it has none (Hopper's motors)."""
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, actuator)
    if name:
        return name
    if int(model.actuator_trntype[actuator]) == int(mujoco.mjtTrn.mjTRN_JOINT):
        return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, model.actuator_trnid[actuator, 0]) or str(actuator)
    return str(actuator)


def actuator_ids(model: mujoco.MjModel, target: str | None) -> np.ndarray:
    """Actuators a target names: an actuator name or the name of the joint it drives."""
    if target is None:
        return np.arange(model.nu)
    names = [actuator_name(model, a) for a in range(model.nu)]
    found = [a for a in range(model.nu)
             if names[a] == target or mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) == target]
    if not found:
        raise UnknownNameError("actuator (or the joint it drives)", target, names)
    return np.array(found)


# --- the effects ----------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True, kw_only=True)
class ModelEffect(Effect):
    """An effect on the compiled model. ``fields`` lists the MjModel fields it changes."""

    family: ClassVar[Literal["model"]] = "model"
    fields: ClassVar[tuple[str, ...]] = ()
    needs_spec: ClassVar[bool] = False

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        """Edit the compiled model in place (call :func:`finalize_model` afterwards)."""
        raise NotImplementedError

    def apply_to_spec(self, spec: mujoco.MjSpec) -> None:
        raise NotImplementedError

    def check_target(self, model: mujoco.MjModel) -> None:
        """Raise :class:`UnknownNameError` if the target does not exist in ``model``."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Gravity(ModelEffect):
    """Scale the gravity vector (``opt.gravity``)."""

    kind: ClassVar[str] = "gravity"
    target_type: ClassVar = "global"
    value_field: ClassVar[str] = "scale"
    fields: ClassVar = ("opt.gravity",)
    ranges: ClassVar = {"scale": Interval(0.0, 10.0, unit="x nominal")}
    scale: float

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        model.opt.gravity[:] = model.opt.gravity * self.scale


@dataclasses.dataclass(frozen=True, kw_only=True)
class Friction(ModelEffect):
    """Scale the friction coefficients (sliding, torsional, rolling) of geoms.

    MuJoCo takes the larger friction of the two geoms in a contact, so ``target=None`` scales
    every geom (and every explicit contact pair): only then is every contact scaled exactly.
    A target may be a geom name or a body name (all that body's geoms).
    """

    kind: ClassVar[str] = "friction"
    target_type: ClassVar = "geom_or_body"
    value_field: ClassVar[str] = "scale"
    fields: ClassVar = ("geom_friction", "pair_friction")
    ranges: ClassVar = {"scale": Interval(0.0, 10.0, unit="x nominal")}
    scale: float

    def check_target(self, model: mujoco.MjModel) -> None:
        geom_ids(model, self.target)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        ids = geom_ids(model, self.target)
        model.geom_friction[ids] *= self.scale
        if self.target is None and model.npair:
            model.pair_friction[:] *= self.scale


@dataclasses.dataclass(frozen=True, kw_only=True)
class Mass(ModelEffect):
    """Scale the mass of a body (or all bodies) and its rotational inertia with it."""

    kind: ClassVar[str] = "mass"
    target_type: ClassVar = "body"
    value_field: ClassVar[str] = "scale"
    fields: ClassVar = ("body_mass", "body_inertia")
    ranges: ClassVar = {"scale": Interval(0.01, 100.0, unit="x nominal")}
    scale: float

    def check_target(self, model: mujoco.MjModel) -> None:
        body_ids(model, self.target)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        ids = body_ids(model, self.target)
        model.body_mass[ids] *= self.scale
        model.body_inertia[ids] *= self.scale


@dataclasses.dataclass(frozen=True, kw_only=True)
class _JointScalar(ModelEffect):
    """Set a per-dof joint property to an absolute value (SI units)."""

    target_type: ClassVar = "joint"
    value_field: ClassVar[str] = "value"
    model_field: ClassVar[str]
    value: float

    def check_target(self, model: mujoco.MjModel) -> None:
        joint_ids(model, self.target)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        getattr(model, self.model_field)[dof_ids(model, self.target)] = self.value


@dataclasses.dataclass(frozen=True, kw_only=True)
class Damping(_JointScalar):
    """Set viscous joint damping (N m s/rad or N s/m). ``target=None``: every actuated joint."""

    kind: ClassVar[str] = "damping"
    model_field: ClassVar[str] = "dof_damping"
    fields: ClassVar = ("dof_damping",)
    ranges: ClassVar = {"value": Interval(0.0, 1e4, unit="N m s/rad (N s/m)")}


@dataclasses.dataclass(frozen=True, kw_only=True)
class FrictionLoss(_JointScalar):
    """Set dry (Coulomb) joint friction (N m or N). ``target=None``: every actuated joint."""

    kind: ClassVar[str] = "frictionloss"
    model_field: ClassVar[str] = "dof_frictionloss"
    fields: ClassVar = ("dof_frictionloss",)
    ranges: ClassVar = {"value": Interval(0.0, 1e4, unit="N m (N)")}


@dataclasses.dataclass(frozen=True, kw_only=True)
class Armature(_JointScalar):
    """Set the rotor inertia added to a joint (kg m^2). ``target=None``: every actuated joint."""

    kind: ClassVar[str] = "armature"
    model_field: ClassVar[str] = "dof_armature"
    fields: ClassVar = ("dof_armature",)
    ranges: ClassVar = {"value": Interval(0.0, 1e3, unit="kg m^2 (kg)")}


@dataclasses.dataclass(frozen=True, kw_only=True)
class Gear(ModelEffect):
    """Scale an actuator's gear (its torque per unit of control): a weaker or stronger motor."""

    kind: ClassVar[str] = "gear"
    target_type: ClassVar = "actuator"
    value_field: ClassVar[str] = "scale"
    fields: ClassVar = ("actuator_gear",)
    ranges: ClassVar = {"scale": Interval(0.0, 100.0, low_open=True, unit="x nominal")}
    scale: float

    def check_target(self, model: mujoco.MjModel) -> None:
        actuator_ids(model, self.target)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        model.actuator_gear[actuator_ids(model, self.target)] *= self.scale


def _limited_joint(model: mujoco.MjModel, kind: str, name: str, *, hinge_or_slide: bool) -> int:
    """The id of the named joint, refused (naming it) when it has no limits to act on."""
    j = int(joint_ids(model, name)[0])
    if not model.jnt_limited[j]:
        raise OffdynError(f"effect {kind!r}: joint {name!r} is not limited, so it has no range to change")
    if hinge_or_slide and int(model.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE),
                                                         int(mujoco.mjtJoint.mjJNT_SLIDE)):
        raise OffdynError(f"effect {kind!r}: joint {name!r} is not a hinge or slide joint")
    return j


def _limited_joints(model: mujoco.MjModel, kind: str, target: str | None, *, hinge_or_slide: bool) -> np.ndarray:
    """A named limited joint, or (``None``) every limited actuated joint."""
    if target is not None:
        return np.array([_limited_joint(model, kind, target, hinge_or_slide=hinge_or_slide)])
    return np.array([j for j in actuated_joint_ids(model) if model.jnt_limited[j]], dtype=int)


@dataclasses.dataclass(frozen=True, kw_only=True)
class JointRange(ModelEffect):
    """Scale a joint's range by ``scale`` about its reference position: the kinematic shift.

    Below 1 the range shrinks, above 1 it widens; limits are in rad (hinge) or m (slide). The
    range scales about the joint's reference position (``qpos0``, clipped into the range), so the
    nominal pose stays reachable: Hopper's thigh range [-150, 0] deg becomes [-30, 0] deg at scale
    0.2 and [-300, 0] deg at scale 2. ``target=None`` scales every limited actuated joint.
    """

    kind: ClassVar[str] = "joint_range"
    target_type: ClassVar = "joint"
    value_field: ClassVar[str] = "scale"
    fields: ClassVar = ("jnt_range",)
    ranges: ClassVar = {"scale": Interval(0.0, 10.0, low_open=True, unit="x nominal")}
    scale: float

    def check_target(self, model: mujoco.MjModel) -> None:
        _limited_joints(model, self.kind, self.target, hinge_or_slide=True)  # type: ignore[arg-type]

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        for j in _limited_joints(model, self.kind, self.target, hinge_or_slide=True):  # type: ignore[arg-type]
            low, high = model.jnt_range[j]
            ref = float(np.clip(model.qpos0[model.jnt_qposadr[j]], low, high))
            model.jnt_range[j] = [ref + self.scale * (low - ref), ref + self.scale * (high - ref)]


@dataclasses.dataclass(frozen=True, kw_only=True)
class JointLimit(ModelEffect):
    """Move one limit of a hinge or slide joint by ``shift`` (rad or m); the other stays put.

    Two models of one robot often disagree on a single stop (a knee that bends further, a hip
    whose upper stop sits elsewhere), which no scaling about the reference pose describes.
    ``side`` picks the limit, ``lower`` or ``upper``; a positive ``shift`` moves it towards larger
    joint positions, so a negative shift of the lower limit (or a positive one of the upper)
    widens the range. The target is required and must be a limited hinge or slide joint. A shift
    that would put the lower limit at or above the upper one is refused, naming both limits.
    """

    kind: ClassVar[str] = "joint_limit"
    target_type: ClassVar = "joint"
    value_field: ClassVar[str] = "shift"
    fields: ClassVar = ("jnt_range",)
    ranges: ClassVar = {"side": OneOf(("lower", "upper")),
                        "shift": Interval(-2 * math.pi, 2 * math.pi, unit="rad (m)")}
    side: str
    shift: float

    def validate(self) -> None:
        if self.target is None:
            self._invalid("target", None, "the name of the joint whose limit moves")

    def _shifted(self, model: mujoco.MjModel) -> tuple[int, np.ndarray]:
        """The joint's id and its range with the limit moved; refused if the range would close."""
        j = _limited_joint(model, self.kind, str(self.target), hinge_or_slide=True)
        old = model.jnt_range[j].copy()
        new = old.copy()
        new[0 if self.side == "lower" else 1] += self.shift
        if not new[0] < new[1]:
            raise OffdynError(
                f"effect {self.kind!r}: moving the {self.side} limit of joint {self.target!r} by {self.shift:g} "
                f"gives lower={new[0]:g} >= upper={new[1]:g} (the range is [{old[0]:g}, {old[1]:g}]); "
                "the lower limit must stay below the upper one")
        return j, new

    def check_target(self, model: mujoco.MjModel) -> None:
        self._shifted(model)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        j, new = self._shifted(model)
        model.jnt_range[j] = new


@dataclasses.dataclass(frozen=True, kw_only=True)
class JointLimitSoftness(ModelEffect):
    """Set how soft a joint's limits are: ``jnt_solref = (timeconst, dampratio)``.

    A limit is a spring-damper constraint: ``timeconst`` (s) is how fast a violation is pushed
    back, ``dampratio`` its damping relative to critical (1: critically damped). A larger time
    constant is a softer stop: under the same torque the joint goes further past its limit.
    MuJoCo treats a time constant below twice ``opt.timestep`` as twice the time step (its
    ``refsafe`` default). ``target`` is a limited joint; ``None`` is every limited actuated joint.
    The limits' impedance (``jnt_solimp``) is left as it is.
    """

    kind: ClassVar[str] = "joint_limit_solref"
    target_type: ClassVar = "joint"
    value_field: ClassVar[str] = "timeconst"
    fields: ClassVar = ("jnt_solref",)
    ranges: ClassVar = {"timeconst": Interval(0.0, 1.0, low_open=True, unit="s"),
                        "dampratio": Interval(0.0, 10.0, low_open=True)}
    timeconst: float
    dampratio: float = 1.0

    def check_target(self, model: mujoco.MjModel) -> None:
        _limited_joints(model, self.kind, self.target, hinge_or_slide=False)  # type: ignore[arg-type]

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        joints = _limited_joints(model, self.kind, self.target, hinge_or_slide=False)  # type: ignore[arg-type]
        model.jnt_solref[joints] = [self.timeconst, self.dampratio]


_AXES = {"x": 0, "y": 1, "z": 2}


@dataclasses.dataclass(frozen=True, kw_only=True)
class BodyOffset(ModelEffect):
    """Move a body, and everything attached below it, by ``offset`` metres along an axis of its
    parent's frame.

    This edits ``body_pos``, the body's position in its parent's frame: the body's joints, geoms,
    sites and child bodies move with it, while the parent's own geoms stay where they are. So it
    changes where a child joint attaches (a limb length as the kinematics see it: a shin that
    reaches further) while the parent's collision shape is unchanged; to change both, use
    ``limb_size``. Mass and inertia are unchanged. The target is required: a body other than the
    world, and not one on a free joint (its position is the joint's state, not a fixed offset).
    """

    kind: ClassVar[str] = "body_offset"
    target_type: ClassVar = "body"
    value_field: ClassVar[str] = "offset"
    fields: ClassVar = ("body_pos",)
    ranges: ClassVar = {"axis": OneOf(tuple(_AXES)), "offset": Interval(-1.0, 1.0, unit="m")}
    axis: str
    offset: float

    def validate(self) -> None:
        if self.target is None:
            self._invalid("target", None, "the name of the body to move")

    def _body(self, model: mujoco.MjModel) -> int:
        b = int(body_ids(model, str(self.target))[0])
        if b == 0:
            raise OffdynError(f"effect {self.kind!r}: {self.target!r} is the world body, "
                              "which has no parent to move against")
        first_joint = model.body_jntadr[b]
        if first_joint >= 0 and int(model.jnt_type[first_joint]) == int(mujoco.mjtJoint.mjJNT_FREE):
            raise OffdynError(f"effect {self.kind!r}: body {self.target!r} moves on a free joint, so its position "
                              "is the joint's state, not an offset from its parent")
        return b

    def check_target(self, model: mujoco.MjModel) -> None:
        self._body(model)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        model.body_pos[self._body(model), _AXES[self.axis]] += self.offset


# Geom types whose ``size`` is not a scale of the collision shape: a plane's size only sets how it
# is drawn, a height field's shape lives in its asset, a mesh's and an SDF's in their vertices.
_UNSCALABLE_GEOMS = {"mjGEOM_PLANE": "a plane", "mjGEOM_HFIELD": "a height field",
                     "mjGEOM_MESH": "a mesh", "mjGEOM_SDF": "an SDF"}
_SKIPPED_GEOMS = ("mjGEOM_PLANE", "mjGEOM_HFIELD")  # unbounded ground: never what "every geom" means
_MJ_EPS = 1e-14  # the compiler's mjEPS: flat bounding boxes are inflated by it


def _rotation(quat: np.ndarray) -> np.ndarray:
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, np.asarray(quat, dtype=float))
    return matrix.reshape(3, 3)


def _refit_body_bvh(model: mujoco.MjModel, body: int) -> None:
    """Recompute a body's bounding-volume tree from its geoms' boxes, as the compiler builds it.

    Mid-phase collision between two multi-geom bodies culls with these boxes (in the body's
    inertial frame), so they must grow with the geoms or contacts of a grown geom are missed.
    """
    adr = int(model.body_bvhadr[body])
    if adr < 0:
        return
    to_inertial = _rotation(model.body_iquat[body])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)

    def geom_corners(g: int) -> np.ndarray:
        local = model.geom_aabb[g, :3] + corners * model.geom_aabb[g, 3:]
        in_body = local @ _rotation(model.geom_quat[g]).T + model.geom_pos[g]
        return (in_body - model.body_ipos[body]) @ to_inertial

    def refit(node: int) -> np.ndarray:
        children = [int(c) for c in model.bvh_child[adr + node] if c >= 0]
        if children:
            points = np.concatenate([refit(c) for c in children])
        else:
            points = geom_corners(int(model.bvh_nodeid[adr + node]))
        low, high = points.min(axis=0), points.max(axis=0)
        flat = high - low < _MJ_EPS
        low[flat] -= _MJ_EPS
        high[flat] += _MJ_EPS
        model.bvh_aabb[adr + node] = np.concatenate([(low + high) / 2, (high - low) / 2])
        return np.stack([low, high])

    refit(0)


@dataclasses.dataclass(frozen=True, kw_only=True)
class GeomSize(ModelEffect):
    """Scale the collision shape of geoms uniformly about each geom's centre by ``scale``.

    Every size (radius, half-length, half-extents) scales, so a capsule foot of radius r becomes
    one of radius ``scale`` x r: a resting robot stands higher by the change of radius, and it
    touches the ground at another height. The centre stays put (a capsule given by ``fromto``
    grows at both ends). Mass and inertia are NOT changed: this is collision geometry only (pair
    it with ``mass`` to change the mass; ``limb_size`` scales a limb with its mass). The bounds the
    collision phases cull with (``geom_rbound``, ``geom_aabb``, the body's ``bvh_aabb``) scale
    with it. ``target`` is a geom name, a body name (all that body's geoms except planes and
    height fields) or ``None`` (every geom except planes and height fields). Planes, height
    fields, meshes and SDFs are refused by name: their size is not a scale of their shape.
    """

    kind: ClassVar[str] = "geom_size"
    target_type: ClassVar = "geom_or_body"
    value_field: ClassVar[str] = "scale"
    fields: ClassVar = ("geom_size", "geom_rbound", "geom_aabb", "bvh_aabb")
    # Below a hundredth a 5 cm foot is half a millimetre: no model gap, only a degenerate shape.
    ranges: ClassVar = {"scale": Interval(0.01, 10.0, unit="x nominal")}
    scale: float

    def _geoms(self, model: mujoco.MjModel) -> np.ndarray:
        ids = geom_ids(model, self.target)  # type: ignore[arg-type]
        types = [mujoco.mjtGeom(model.geom_type[g]).name for g in ids]
        named_geom = (self.target is not None
                      and mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, str(self.target)) >= 0)
        if named_geom and types[0] in _UNSCALABLE_GEOMS:
            raise OffdynError(f"effect {self.kind!r}: geom {self.target!r} is {_UNSCALABLE_GEOMS[types[0]]}, "
                              "whose size is not a scale of its collision shape; expected a primitive geom "
                              "(sphere, capsule, ellipsoid, cylinder, box)")
        kept = [g for g, t in zip(ids, types) if t not in _SKIPPED_GEOMS]
        shaped = [g for g in kept if mujoco.mjtGeom(model.geom_type[g]).name in _UNSCALABLE_GEOMS]
        if shaped:
            names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"#{g}" for g in shaped]
            raise OffdynError(f"effect {self.kind!r}: geom(s) {names} are meshes or SDFs, whose shape lives in "
                              "their vertices and cannot be scaled on a compiled model; target the primitive "
                              "geoms by name instead")
        if not kept:
            raise OffdynError(f"effect {self.kind!r}: {self.target!r} has no geom whose size can be scaled "
                              "(planes and height fields are left alone)")
        return np.array(kept, dtype=int)

    def check_target(self, model: mujoco.MjModel) -> None:
        self._geoms(model)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        geoms = self._geoms(model)
        model.geom_size[geoms] *= self.scale
        model.geom_rbound[geoms] *= self.scale
        model.geom_aabb[geoms] *= self.scale  # centre and half-sizes, both in the geom's own frame
        for body in sorted({int(model.geom_bodyid[g]) for g in geoms}):
            _refit_body_bvh(model, body)


@dataclasses.dataclass(frozen=True, kw_only=True)
class LimbSize(ModelEffect):
    """Scale a limb uniformly about its joint: the morphology shift.

    The body's geoms (lengths, radii and positions) scale by ``scale`` about the body's first
    joint, and each child body moves rigidly so that it stays attached at the scaled point: what
    hangs below follows the limb's new end. Mass and inertia follow from the new volume (the
    model's density); a model that rescales its total mass (HalfCheetah's ``settotalmass``) keeps
    the other bodies' masses unchanged.
    """

    kind: ClassVar[str] = "limb_size"
    target_type: ClassVar = "body"
    value_field: ClassVar[str] = "scale"
    needs_spec: ClassVar[bool] = True
    fields: ClassVar = ("body_pos", "body_ipos", "body_iquat", "body_mass", "body_inertia",
                        "geom_size", "geom_pos", "geom_quat", "geom_aabb", "geom_rbound",
                        "site_pos", "site_size", "cam_pos", "body_sameframe", "geom_sameframe")
    # Mass follows volume (scale^3): x5 already makes a limb 125 times heavier,
    # and inertia scale^5, so below x0.05 a limb's inertia falls under what MuJoCo accepts.
    ranges: ClassVar = {"scale": Interval(0.05, 5.0, unit="x nominal")}
    scale: float

    def validate(self) -> None:
        if self.target is None:
            self._invalid("target", None, "the name of the body to scale")

    def check_target(self, model: mujoco.MjModel) -> None:
        body_ids(model, self.target)

    def apply_to_spec(self, spec: mujoco.MjSpec) -> None:
        body = spec.body(str(self.target))
        if body is None:
            raise UnknownNameError("body", self.target, [b.name for b in spec.bodies if b.name])
        s = self.scale
        anchor = np.array(body.joints[0].pos) if body.joints else np.zeros(3)

        def about_anchor(p: np.ndarray) -> np.ndarray:
            return anchor + s * (np.asarray(p) - anchor)

        for geom in body.geoms:
            if not np.isnan(geom.fromto[0]):
                geom.fromto = np.concatenate([about_anchor(geom.fromto[:3]), about_anchor(geom.fromto[3:])])
            else:
                geom.pos = about_anchor(geom.pos)
            geom.size = np.asarray(geom.size) * s
        for site in body.sites:
            site.pos = about_anchor(site.pos)
            site.size = np.asarray(site.size) * s
        for child in body.bodies:
            rotation = np.zeros(9)
            mujoco.mju_quat2Mat(rotation, np.asarray(child.quat, dtype=float))
            joint_offset = np.array(child.joints[0].pos) if child.joints else np.zeros(3)
            attach = np.asarray(child.pos) + rotation.reshape(3, 3) @ joint_offset
            child.pos = np.asarray(child.pos) + (about_anchor(attach) - attach)
        if body.explicitinertial:
            body.ipos = about_anchor(body.ipos)
            body.mass = body.mass * s**3
            body.inertia = np.asarray(body.inertia) * s**5


@dataclasses.dataclass(frozen=True, kw_only=True)
class ContactSolref(ModelEffect):
    """Set the contact softness of geoms: ``solref = (timeconst, dampratio)``."""

    kind: ClassVar[str] = "contact_solref"
    target_type: ClassVar = "geom_or_body"
    value_field: ClassVar[str] = "timeconst"
    fields: ClassVar = ("geom_solref", "pair_solref")
    ranges: ClassVar = {"timeconst": Interval(0.0, 1.0, low_open=True, unit="s"),
                        "dampratio": Interval(0.0, 10.0, low_open=True)}
    timeconst: float
    dampratio: float = 1.0

    def check_target(self, model: mujoco.MjModel) -> None:
        geom_ids(model, self.target)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        model.geom_solref[geom_ids(model, self.target)] = [self.timeconst, self.dampratio]
        if self.target is None and model.npair:
            model.pair_solref[:] = [self.timeconst, self.dampratio]


@dataclasses.dataclass(frozen=True, kw_only=True)
class ContactSolimp(ModelEffect):
    """Set the contact impedance of geoms: ``solimp = (dmin, dmax, width, midpoint, power)``."""

    kind: ClassVar[str] = "contact_solimp"
    target_type: ClassVar = "geom_or_body"
    value_field: ClassVar[str] = "dmax"
    fields: ClassVar = ("geom_solimp", "pair_solimp")
    ranges: ClassVar = {"dmin": Interval(0.0, 1.0, high_open=True), "dmax": Interval(0.0, 1.0, high_open=True),
                        "width": Interval(0.0, 1.0, low_open=True, unit="m"), "midpoint": Interval(0.0, 1.0),
                        "power": Interval(1.0, 10.0)}
    dmin: float
    dmax: float
    width: float
    midpoint: float = 0.5
    power: float = 2.0

    def validate(self) -> None:
        if self.dmin > self.dmax:
            self._invalid("dmin", self.dmin, f"dmin <= dmax ({self.dmax})")

    def check_target(self, model: mujoco.MjModel) -> None:
        geom_ids(model, self.target)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        values = [self.dmin, self.dmax, self.width, self.midpoint, self.power]
        model.geom_solimp[geom_ids(model, self.target)] = values
        if self.target is None and model.npair:
            model.pair_solimp[:] = values


# The effects' names for MuJoCo's cones and integrators: members of mujoco.mjtCone /
# mujoco.mjtIntegrator, looked up when an effect is applied (and by diagnosis's candidates).
CONES = {"pyramidal": "mjCONE_PYRAMIDAL", "elliptic": "mjCONE_ELLIPTIC"}
INTEGRATORS = {"Euler": "mjINT_EULER", "RK4": "mjINT_RK4", "implicit": "mjINT_IMPLICIT",
                "implicitfast": "mjINT_IMPLICITFAST"}


@dataclasses.dataclass(frozen=True, kw_only=True)
class FrictionCone(ModelEffect):
    """Switch the friction cone model: ``pyramidal`` or ``elliptic``."""

    kind: ClassVar[str] = "friction_cone"
    target_type: ClassVar = "global"
    value_field: ClassVar[str] = "cone"
    fields: ClassVar = ("opt.cone",)
    ranges: ClassVar = {"cone": OneOf(tuple(CONES))}
    cone: str

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        model.opt.cone = getattr(mujoco.mjtCone, CONES[self.cone])


@dataclasses.dataclass(frozen=True, kw_only=True)
class Integrator(ModelEffect):
    """Switch the numerical integrator: ``Euler``, ``RK4``, ``implicit`` or ``implicitfast``."""

    kind: ClassVar[str] = "integrator"
    target_type: ClassVar = "global"
    value_field: ClassVar[str] = "integrator"
    fields: ClassVar = ("opt.integrator",)
    ranges: ClassVar = {"integrator": OneOf(tuple(INTEGRATORS))}
    integrator: str

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        model.opt.integrator = getattr(mujoco.mjtIntegrator, INTEGRATORS[self.integrator])


@dataclasses.dataclass(frozen=True, kw_only=True)
class NoSlip(ModelEffect):
    """Set the number of no-slip solver iterations (0 disables the no-slip solver)."""

    kind: ClassVar[str] = "noslip"
    target_type: ClassVar = "global"
    value_field: ClassVar[str] = "iterations"
    fields: ClassVar = ("opt.noslip_iterations",)
    ranges: ClassVar = {"iterations": Interval(0, 1000, integer=True)}
    iterations: int

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        model.opt.noslip_iterations = self.iterations


# --- building a model -----------------------------------------------------------------------

def _keep_body_masses_when_resized(spec: mujoco.MjSpec) -> None:
    """Replace ``settotalmass`` by the density factor it implies, so resizing one limb leaves
    the other bodies' masses alone instead of renormalizing all of them."""
    total = spec.compiler.settotalmass
    if total <= 0:
        return
    spec.compiler.settotalmass = -1
    raw = _compile(spec)
    factor = total / float(np.sum(raw.body_mass))
    for geom in spec.geoms:
        if np.isnan(geom.mass):
            geom.density = geom.density * factor
        else:
            geom.mass = geom.mass * factor
    for body in spec.bodies:
        if body.explicitinertial:
            body.mass = body.mass * factor
            body.inertia = np.asarray(body.inertia) * factor


def split_effects(effects: Iterable[Effect]) -> tuple[list[ModelEffect], list[Effect]]:
    model_effects: list[ModelEffect] = []
    channel_effects: list[Effect] = []
    for effect in effects:
        (model_effects if isinstance(effect, ModelEffect) else channel_effects).append(effect)
    return model_effects, channel_effects


def finalize_model(model: mujoco.MjModel) -> None:
    """Recompute the compiler's derived constants after fields were edited."""
    mujoco.mj_setConst(model, mujoco.MjData(model))


def _field_owner(model: mujoco.MjModel, field: str) -> tuple[Any, str]:
    """``("opt.gravity")`` -> ``(model.opt, "gravity")``; ``"jnt_range"`` -> ``(model, "jnt_range")``."""
    return (model.opt, field[len("opt."):]) if field.startswith("opt.") else (model, field)


def _save_fields(model: mujoco.MjModel, fields: Iterable[str]) -> dict[str, Any]:
    saved: dict[str, Any] = {}
    for field in fields:
        value = getattr(*_field_owner(model, field))
        saved[field] = value.copy() if isinstance(value, np.ndarray) else value
    return saved


def _restore_fields(model: mujoco.MjModel, saved: dict[str, Any]) -> None:
    for field, value in saved.items():
        owner, name = _field_owner(model, field)
        current = getattr(owner, name)
        if isinstance(current, np.ndarray):
            current[...] = value
        else:
            setattr(owner, name, value)


def apply_model_effects(model: mujoco.MjModel, effects: Sequence[ModelEffect]) -> None:
    """Apply field-level model effects to a compiled model in place, then finalize it.

    Targets are checked before anything is written; an effect that fails only once the effects
    before it have acted (a limit moved past a range that an earlier effect narrowed) restores
    every field the effects declare, so a failed call leaves the model as it was.
    """
    for effect in effects:
        if effect.needs_spec:
            raise OffdynError(f"effect {effect.kind!r} changes geometry; build the model with compile_model()")
        effect.check_target(model)
    saved = _save_fields(model, dict.fromkeys(f for effect in effects for f in effect.fields))
    try:
        for effect in effects:
            effect.apply_to_model(model)
    except BaseException:
        _restore_fields(model, saved)
        raise
    if effects:
        finalize_model(model)


def _compile(spec: mujoco.MjSpec) -> mujoco.MjModel:
    # HalfCheetah's MJCF uses the deprecated ``settotalmass``; the warning is Gymnasium's to fix.
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*settotalmass.*")
        try:
            return spec.compile()
        except ValueError as error:  # MuJoCo's compiler refuses the model (e.g. a massless body)
            raise OffdynError(f"MuJoCo cannot compile the model with these effects: {error}") from None


def compile_model(xml_path: str, effects: Sequence[ModelEffect] = ()) -> mujoco.MjModel:
    """Compile the MJCF file at ``xml_path`` with model effects applied, in the given order."""
    spec = mujoco.MjSpec.from_file(xml_path)
    spec_effects = [e for e in effects if e.needs_spec]
    if spec_effects:
        base = _compile(spec)
        for effect in spec_effects:
            effect.check_target(base)
        _keep_body_masses_when_resized(spec)
        for effect in spec_effects:
            effect.apply_to_spec(spec)
    model = _compile(spec)
    apply_model_effects(model, [e for e in effects if not e.needs_spec])
    return model
