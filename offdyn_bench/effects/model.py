"""Model effects: changes to the compiled MuJoCo model, applied once at construction.

Most effects edit fields of a compiled ``mujoco.MjModel`` in place (cheap enough to build many
candidate models during gap diagnosis); ``limb_size`` changes geometry and so edits the
``mujoco.MjSpec`` before compilation. :func:`compile_model` runs both stages and then recomputes
the compiler's derived constants (``mj_setConst``) so masses, inertias and invweights stay
consistent.
"""

from __future__ import annotations

import dataclasses
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


@dataclasses.dataclass(frozen=True, kw_only=True)
class JointRange(ModelEffect):
    """Shrink a joint's range by ``scale`` towards its reference position: the kinematic shift.

    The range shrinks about the joint's reference position (``qpos0``, clipped into the range),
    so the nominal pose stays reachable: Hopper's thigh range [-150, 0] deg at scale 0.2 becomes
    [-30, 0] deg. ``target=None`` shrinks every limited actuated joint.
    """

    kind: ClassVar[str] = "joint_range"
    target_type: ClassVar = "joint"
    value_field: ClassVar[str] = "scale"
    fields: ClassVar = ("jnt_range",)
    ranges: ClassVar = {"scale": Interval(0.0, 1.0, low_open=True, unit="x nominal")}
    scale: float

    def _joints(self, model: mujoco.MjModel) -> np.ndarray:
        joints = joint_ids(model, self.target)
        if self.target is None:
            return np.array([j for j in joints if model.jnt_limited[j]], dtype=int)
        j = int(joints[0])
        if not model.jnt_limited[j]:
            raise OffdynError(f"effect 'joint_range': joint {self.target!r} has no range to shrink")
        if int(model.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            raise OffdynError(f"effect 'joint_range': joint {self.target!r} is not a hinge or slide joint")
        return joints

    def check_target(self, model: mujoco.MjModel) -> None:
        self._joints(model)

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        for j in self._joints(model):
            low, high = model.jnt_range[j]
            ref = float(np.clip(model.qpos0[model.jnt_qposadr[j]], low, high))
            model.jnt_range[j] = [ref + self.scale * (low - ref), ref + self.scale * (high - ref)]


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


# Names of mujoco.mjtCone / mujoco.mjtIntegrator members, looked up when an effect is applied.
_CONES = {"pyramidal": "mjCONE_PYRAMIDAL", "elliptic": "mjCONE_ELLIPTIC"}
_INTEGRATORS = {"Euler": "mjINT_EULER", "RK4": "mjINT_RK4", "implicit": "mjINT_IMPLICIT",
                "implicitfast": "mjINT_IMPLICITFAST"}


@dataclasses.dataclass(frozen=True, kw_only=True)
class FrictionCone(ModelEffect):
    """Switch the friction cone model: ``pyramidal`` or ``elliptic``."""

    kind: ClassVar[str] = "friction_cone"
    target_type: ClassVar = "global"
    value_field: ClassVar[str] = "cone"
    fields: ClassVar = ("opt.cone",)
    ranges: ClassVar = {"cone": OneOf(tuple(_CONES))}
    cone: str

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        model.opt.cone = getattr(mujoco.mjtCone, _CONES[self.cone])


@dataclasses.dataclass(frozen=True, kw_only=True)
class Integrator(ModelEffect):
    """Switch the numerical integrator: ``Euler``, ``RK4``, ``implicit`` or ``implicitfast``."""

    kind: ClassVar[str] = "integrator"
    target_type: ClassVar = "global"
    value_field: ClassVar[str] = "integrator"
    fields: ClassVar = ("opt.integrator",)
    ranges: ClassVar = {"integrator": OneOf(tuple(_INTEGRATORS))}
    integrator: str

    def apply_to_model(self, model: mujoco.MjModel) -> None:
        model.opt.integrator = getattr(mujoco.mjtIntegrator, _INTEGRATORS[self.integrator])


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


def apply_model_effects(model: mujoco.MjModel, effects: Sequence[ModelEffect]) -> None:
    """Apply field-level model effects to a compiled model in place, then finalize it."""
    for effect in effects:
        if effect.needs_spec:
            raise OffdynError(f"effect {effect.kind!r} changes geometry; build the model with compile_model()")
        effect.check_target(model)
    for effect in effects:
        effect.apply_to_model(model)
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
