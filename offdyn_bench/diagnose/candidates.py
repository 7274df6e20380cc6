"""The candidate library: the effect vocabulary instantiated everywhere it applies on a model.

Every candidate is one effect with one free value (its ``field``, by default the effect's
``value_field``; the effect's other parameters are held at ``fixed``), the value that means "no
change" (``nominal``), bounds, a probe step for screening, and how its value is searched:
``smooth`` (least squares), ``threshold`` (grids: a dead zone or a saturation changes the
prediction in jumps), ``integer`` (enumeration: delays in control steps) or ``categorical``
(enumeration of named alternatives: the integrator, the friction cone).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any, Literal

import mujoco
import numpy as np

from offdyn_bench.diagnose.source import SourceSimulator
from offdyn_bench.effects import EFFECT_KINDS, Effect
from offdyn_bench.effects.base import Interval
from offdyn_bench.effects.model import (
    CONES,
    INTEGRATORS,
    actuated_joint_ids,
    actuator_name,
    dof_ids,
)

Search = Literal["smooth", "threshold", "integer", "categorical"]

# Between candidates that explain the data equally well, the earlier kind is reported: a weaker
# motor (gear) and a command gain below one are the same physics while commands stay in range.
KIND_PRIORITY = ("gravity", "friction", "mass", "gear", "damping", "frictionloss", "armature",
                 "joint_range", "joint_limit", "joint_limit_solref", "contact_solref", "contact_solimp",
                 "body_offset", "geom_size", "limb_size", "integrator", "friction_cone",
                 "action_delay", "action_deadzone", "action_saturation", "action_bias", "action_gain",
                 "obs_bias", "obs_delay")

# Fixed parameters that make two candidates of one kind and target different effects (both may be
# added); the others (a dampratio, solimp's width) only complete the effect.
DISTINGUISHING = ("side", "axis")


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One effect kind on one target, with one free value."""

    kind: str
    target: str | int | None
    nominal: float
    low: float
    high: float
    probe: float
    search: Search
    trials: tuple[float, ...] = ()  # values the screen also tries directly (a smooth one's are extra)
    fixed: tuple[tuple[str, Any], ...] = ()  # the effect's other parameters
    choices: tuple[str, ...] = ()  # a categorical candidate's values; its value is an index

    @property
    def field(self) -> str:
        return EFFECT_KINDS[self.kind].value_field

    @property
    def qualifier(self) -> str:
        parts = [f"{k}={v}" for k, v in self.fixed if k in DISTINGUISHING]
        return f"({', '.join(parts)})" if parts else ""

    @property
    def label(self) -> str:
        where = "all" if self.target is None else (
            f"obs[{self.target}]" if isinstance(self.target, int) else str(self.target))
        return f"{self.kind}{self.qualifier} on {where}"

    @property
    def priority(self) -> int:
        return KIND_PRIORITY.index(self.kind) if self.kind in KIND_PRIORITY else len(KIND_PRIORITY)

    def parameter_value(self, value: float) -> float | int | str:
        """The effect parameter a searched value stands for (an index names a choice)."""
        if self.search == "categorical":
            return self.choices[int(round(value))]
        return int(round(value)) if self.search == "integer" else float(value)

    def effect(self, value: float) -> Effect:
        cls = EFFECT_KINDS[self.kind]
        parameters = {**dict(self.fixed), self.field: self.parameter_value(value)}
        return cls(target=self.target, **parameters)  # type: ignore[call-arg]

    def matches(self, effect: Effect) -> bool:
        """Whether ``effect`` is this candidate's effect at some value."""
        if effect.kind != self.kind or effect.target != self.target:
            return False
        return all(getattr(effect, k, None) == v for k, v in self.fixed if k in DISTINGUISHING)

    def clip(self, value: float) -> float:
        return float(np.clip(value, self.low, self.high))

    def on_bound(self, value: float) -> bool:
        width = self.high - self.low
        return self.search in ("smooth", "threshold") and (value - self.low < 1e-3 * width
                                                          or self.high - value < 1e-3 * width)


def _joint_name(model: mujoco.MjModel, joint: int) -> str:
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, joint) or ""


def _max_torque(model: mujoco.MjModel, joints: np.ndarray) -> float:
    """The largest generalized force the actuators can put on ``joints`` (sets the scale of
    friction-like candidates)."""
    torque = 0.0
    for a in range(model.nu):
        if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT and model.actuator_trnid[a, 0] in joints:
            limit = np.max(np.abs(model.actuator_ctrlrange[a])) if model.actuator_ctrllimited[a] else 1.0
            torque = max(torque, float(abs(model.actuator_gear[a, 0]) * limit))
    return torque or 1.0


def _uniform(values: np.ndarray) -> bool:
    return bool(len(values)) and bool(np.allclose(values, values[:1]))


def _contact_geoms(model: mujoco.MjModel) -> np.ndarray:
    return np.flatnonzero((model.geom_contype != 0) | (model.geom_conaffinity != 0))


def _named_bodies(model: mujoco.MjModel, ids: Any) -> list[tuple[int, str]]:
    out = []
    for body in ids:
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(body))
        if name:
            out.append((int(body), name))
    return out


def _joint_candidates(model: mujoco.MjModel, joints: np.ndarray,
                      extremes: dict[int, tuple[float, float]] | None) -> list[Candidate]:
    """Per limited hinge or slide joint: its range widened or shrunk, each limit moved on its own,
    and the softness of its limit. ``extremes`` (joint id -> the lowest and highest position in the
    data) adds the natural guesses for a limit: where the recorded motion stops, or beyond where
    it goes past the source's limit."""
    out: list[Candidate] = []
    sliding_or_hinged = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    limited = [j for j in joints.tolist() if model.jnt_limited[j] and int(model.jnt_type[j]) in sliding_or_hinged]
    for j in limited:
        name = _joint_name(model, j)
        if not name:
            continue
        low, high = (float(x) for x in model.jnt_range[j])
        width = high - low
        if width <= 0:
            continue
        out.append(Candidate("joint_range", name, 1.0, 0.2, 3.0, 0.05, "smooth", trials=(0.6, 1.5, 2.0)))
        # A limit only acts on rows that reach it: the screen also tries whole moves, not just a probe.
        moves = (-0.3 * width, -0.1 * width, 0.1 * width, 0.3 * width)
        lower_guess, upper_guess = (), ()
        if extremes is not None and j in extremes:
            seen_low, seen_high = extremes[j]
            margin = 0.01 * width
            lower_guess = (seen_low - margin - low,)
            upper_guess = (seen_high + margin - high,)
        out.append(Candidate("joint_limit", name, 0.0, -width, 0.9 * width, 0.02 * width, "smooth",
                             trials=moves + lower_guess, fixed=(("side", "lower"),)))
        out.append(Candidate("joint_limit", name, 0.0, -0.9 * width, width, 0.02 * width, "smooth",
                             trials=moves + upper_guess, fixed=(("side", "upper"),)))
        timeconst, dampratio = (float(x) for x in model.jnt_solref[j])
        if timeconst > 0:  # a negative solref sets stiffness directly: another parameterization
            out.append(Candidate("joint_limit_solref", name, timeconst, 0.002, 0.3, 0.1 * timeconst, "smooth",
                                 trials=(3 * timeconst,), fixed=(("dampratio", dampratio),)))
    return out


def _contact_candidates(model: mujoco.MjModel) -> list[Candidate]:
    """Friction per body, and the contact softness (solref) and impedance (solimp) of every geom."""
    out: list[Candidate] = []
    geoms = _contact_geoms(model)
    for body, name in _named_bodies(model, sorted(set(model.geom_bodyid[geoms].tolist()))):
        out.append(Candidate("friction", name, 1.0, 0.1, 5.0, 0.1, "smooth", trials=(2.0,)))
    if len(geoms) and _uniform(model.geom_solref[geoms]) and model.geom_solref[geoms[0], 0] > 0:
        timeconst, dampratio = (float(x) for x in model.geom_solref[geoms[0]])
        out.append(Candidate("contact_solref", None, timeconst, max(0.002, 2 * model.opt.timestep), 0.3,
                             0.1 * timeconst, "smooth", trials=(3 * timeconst,), fixed=(("dampratio", dampratio),)))
    if len(geoms) and _uniform(model.geom_solimp[geoms]):
        dmin, dmax, width, midpoint, power = (float(x) for x in model.geom_solimp[geoms[0]])
        out.append(Candidate("contact_solimp", None, dmax, max(dmin, 0.05), 0.999, 0.02, "smooth",
                             trials=(max(dmin, 0.5 * dmax), min(0.99, 0.5 * (1 + dmax))),
                             fixed=(("dmin", dmin), ("width", width), ("midpoint", midpoint), ("power", power))))
    return out


def _geometry_candidates(source: SourceSimulator) -> list[Candidate]:
    """Body positions (where a child attaches: limb lengths as the kinematics see them), collision
    geom sizes, and whole limbs rescaled (geometry and mass, compiled per candidate)."""
    model = source.base_model
    out: list[Candidate] = []
    children = [b for b in range(1, model.nbody) if model.body_parentid[b] != 0]
    for body, name in _named_bodies(model, children):
        reach = max(0.05, 0.5 * float(np.linalg.norm(model.body_pos[body])))
        for axis in "xyz":
            out.append(Candidate("body_offset", name, 0.0, -reach, reach, 0.005, "smooth",
                                 trials=(-0.2 * reach, 0.2 * reach), fixed=(("axis", axis),)))
    planes = {int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD)}
    sized = [g for g in _contact_geoms(model) if int(model.geom_type[g]) not in planes]
    for body, name in _named_bodies(model, sorted(set(model.geom_bodyid[sized].tolist()))):
        if body == 0:
            continue
        out.append(Candidate("geom_size", name, 1.0, 0.3, 3.0, 0.05, "smooth", trials=(1.5,)))
        if source.compiles_from_spec:
            out.append(Candidate("limb_size", name, 1.0, 0.5, 2.0, 0.05, "smooth"))
    return out


def _solver_candidates(model: mujoco.MjModel) -> list[Candidate]:
    """Numerical choices of the engine: the integrator and the friction cone."""
    out: list[Candidate] = []
    for kind, field, enum, names in (("integrator", "integrator", mujoco.mjtIntegrator, INTEGRATORS),
                                     ("friction_cone", "cone", mujoco.mjtCone, CONES)):
        current = int(getattr(model.opt, field))
        choices = tuple(label for label, member in names.items() if hasattr(enum, member))
        nominal = next((i for i, label in enumerate(choices) if int(getattr(enum, names[label])) == current), None)
        if nominal is None or len(choices) < 2:
            continue
        out.append(Candidate(kind, None, float(nominal), 0.0, float(len(choices) - 1), 1.0, "categorical",
                             trials=tuple(float(i) for i in range(len(choices)) if i != nominal), choices=choices))
    return out


def candidate_library(source: SourceSimulator, *, obs_bias_dims: Iterable[int] | None = None,
                      obs_delay_dims: Iterable[int] | None = None,
                      qpos: np.ndarray | None = None, commands: np.ndarray | None = None) -> list[Candidate]:
    """Every candidate the vocabulary allows on ``source``'s model and observation.

    ``obs_bias_dims`` / ``obs_delay_dims``: the observation dimensions where the data allow that
    observation effect (``None``: every dimension read off the state). ``qpos``: the recorded
    positions, which suggest where a joint's limits lie. ``commands``: the recorded commands
    (rows x actuators), which suggest where a dead zone can be seen at all.
    """
    model = source.base_model
    out: list[Candidate] = [
        Candidate("gravity", None, 1.0, 0.2, 3.0, 0.05, "smooth"),
        Candidate("friction", None, 1.0, 0.1, 5.0, 0.1, "smooth"),
    ]
    for body in [None, *range(1, model.nbody)]:
        name = None if body is None else mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body)
        if body is not None and not name:
            continue
        out.append(Candidate("mass", name, 1.0, 0.2, 5.0, 0.05, "smooth"))

    joints = actuated_joint_ids(model)
    field_of = {"damping": model.dof_damping, "frictionloss": model.dof_frictionloss, "armature": model.dof_armature}
    for joint in [None, *joints.tolist()]:
        name = None if joint is None else _joint_name(model, joint)
        if joint is not None and not name:
            continue
        dofs = dof_ids(model, name)
        torque = _max_torque(model, joints if joint is None else np.array([joint]))
        for kind, values in field_of.items():
            current = values[dofs]
            if not np.allclose(current, current[0]):
                continue  # "all joints" sets one value; it is no null hypothesis when they differ
            nominal = float(current[0])
            trials: tuple[float, ...] = ()
            if kind == "armature":
                high, probe = 10.0 * nominal + 1.0, 0.1 * nominal + 0.01
            else:
                high, probe = nominal + 0.5 * torque, 0.1 * nominal + 0.01 * torque
            if kind == "frictionloss":
                # Dry friction sticks or slips: a small probe says little about a large value.
                trials = (nominal + 5 * probe, nominal + 15 * probe)
            out.append(Candidate(kind, name, nominal, 0.0, high, probe, "smooth", trials))
    extremes = None
    if qpos is not None and len(qpos):
        address = model.jnt_qposadr
        extremes = {int(j): (float(np.min(qpos[:, address[j]])), float(np.max(qpos[:, address[j]])))
                    for j in joints.tolist()}
    out += _joint_candidates(model, joints, extremes)
    out += _contact_candidates(model)
    out += _geometry_candidates(source)
    out += _solver_candidates(model)

    for actuator in [None, *range(model.nu)]:
        name = None if actuator is None else actuator_name(model, actuator)
        ids = np.arange(model.nu) if actuator is None else np.array([actuator])
        limited = model.actuator_ctrllimited[ids].astype(bool)
        limit = float(np.max(np.abs(model.actuator_ctrlrange[ids]))) if limited.all() else 1.0
        deadzone_trials = _deadzone_trials(limit, None if commands is None else commands[:, ids])
        out += [
            Candidate("gear", name, 1.0, 0.1, 3.0, 0.05, "smooth"),
            Candidate("action_gain", name, 1.0, 0.1, 3.0, 0.05, "smooth"),
            Candidate("action_bias", name, 0.0, -0.5 * limit, 0.5 * limit, 0.05 * limit, "smooth"),
            Candidate("action_deadzone", name, 0.0, 0.0, 0.9 * limit, 0.0, "threshold", trials=deadzone_trials),
            Candidate("action_saturation", name, limit, 0.05 * limit, limit, 0.0, "threshold",
                      trials=(0.8 * limit, 0.5 * limit, 0.25 * limit)),
            Candidate("action_delay", name, 0, 1, 3, 1, "integer", trials=(1.0, 2.0)),
        ]

    mapped = source.observation_map.mapped.tolist()
    bias = set(mapped if obs_bias_dims is None else obs_bias_dims)
    delay = set(mapped if obs_delay_dims is None else obs_delay_dims)
    for i in mapped:
        if i in bias:
            out.append(Candidate("obs_bias", int(i), 0.0, -1e3, 1e3, 0.01, "smooth"))
        if i in delay:
            out.append(Candidate("obs_delay", int(i), 0, 1, 2, 1, "integer", trials=(1.0,)))
    # Kinds the installed vocabulary lacks are skipped, never guessed at.
    known = [c for c in out if c.kind in EFFECT_KINDS]
    return [c for c in map(_within_effect_range, known) if c is not None]


# Where the screen also tries a dead zone, as quantiles of the recorded command magnitudes: a
# threshold only shows where commands cross it, so data of small commands (a balancing robot near
# upright) need trials among them, not only at fixed fractions of the limit. A saturation keeps
# its fixed trials: one just below the largest commands mimics command noise clipped at the
# actuator's own limit, which the loop must leave to the noise estimate.
DEADZONE_QUANTILES = (0.25, 0.5, 0.75, 0.9)


def _deadzone_trials(limit: float, commands: np.ndarray | None) -> tuple[float, ...]:
    """Screen trials of a dead zone on actuators whose commands are ``commands`` (rows x those
    actuators; ``None``: not known): fixed fractions of the command limit, plus the recorded
    magnitudes' quantiles when the data give them."""
    trials = [0.1 * limit, 0.3 * limit, 0.5 * limit]
    if commands is not None and commands.size:
        magnitudes = np.abs(np.asarray(commands, dtype=float)).ravel()
        magnitudes = magnitudes[np.isfinite(magnitudes)]
        if magnitudes.size:
            trials += [float(q) for q in np.quantile(magnitudes, DEADZONE_QUANTILES) if q > 0]
    return tuple(sorted(set(trials)))


def _within_effect_range(candidate: Candidate) -> Candidate | None:
    """The candidate with its bounds inside the plausible range of its effect's value (a model
    with huge gears would otherwise search damping values no effect accepts); ``None`` when
    nothing of its search interval is left."""
    cls = EFFECT_KINDS[candidate.kind]
    allowed = cls.ranges.get(cls.value_field)
    if not isinstance(allowed, Interval):
        return candidate
    low, high = max(candidate.low, allowed.low), min(candidate.high, allowed.high)
    if (allowed.low_open and low <= allowed.low) or (allowed.high_open and high >= allowed.high):
        return None
    if low > high:
        return None
    if (low, high) == (candidate.low, candidate.high):
        return candidate
    return dataclasses.replace(candidate, low=low, high=high, nominal=float(np.clip(candidate.nominal, low, high)),
                               probe=min(candidate.probe, high - low),
                               trials=tuple(t for t in candidate.trials if low <= t <= high))
