"""The candidate library: the effect vocabulary instantiated everywhere it applies on a model.

Every candidate is one effect with one free value (the effect's ``value_field``), the value that
means "no change" (``nominal``), bounds, a probe step for screening, and how its value is searched:
``smooth`` (least squares), ``threshold`` (grids: a dead zone or a saturation changes the
prediction in jumps) or ``integer`` (enumeration: delays in control steps).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import mujoco
import numpy as np

from offdyn_bench.diagnose.source import SourceSimulator
from offdyn_bench.effects import EFFECT_KINDS, Effect
from offdyn_bench.effects.base import Interval
from offdyn_bench.effects.model import actuated_joint_ids, actuator_name, dof_ids

Search = Literal["smooth", "threshold", "integer"]

# Between candidates that explain the data equally well, the earlier kind is reported: a weaker
# motor (gear) and a command gain below one are the same physics while commands stay in range.
KIND_PRIORITY = ("gravity", "friction", "mass", "gear", "damping", "frictionloss", "armature",
                 "action_delay", "action_deadzone", "action_saturation", "action_bias", "action_gain",
                 "obs_bias", "obs_delay")


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

    @property
    def label(self) -> str:
        where = "all" if self.target is None else (
            f"obs[{self.target}]" if isinstance(self.target, int) else str(self.target))
        return f"{self.kind} on {where}"

    @property
    def priority(self) -> int:
        return KIND_PRIORITY.index(self.kind) if self.kind in KIND_PRIORITY else len(KIND_PRIORITY)

    def effect(self, value: float) -> Effect:
        cls = EFFECT_KINDS[self.kind]
        number: float | int = int(round(value)) if self.search == "integer" else float(value)
        return cls(target=self.target, **{cls.value_field: number})  # type: ignore[call-arg]

    def clip(self, value: float) -> float:
        return float(np.clip(value, self.low, self.high))

    def on_bound(self, value: float) -> bool:
        width = self.high - self.low
        return self.search != "integer" and (value - self.low < 1e-3 * width or self.high - value < 1e-3 * width)


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


def candidate_library(source: SourceSimulator, *, with_observation_delay: bool = True) -> list[Candidate]:
    """Every candidate the vocabulary allows on ``source``'s model and observation."""
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

    for actuator in [None, *range(model.nu)]:
        name = None if actuator is None else actuator_name(model, actuator)
        ids = np.arange(model.nu) if actuator is None else np.array([actuator])
        limited = model.actuator_ctrllimited[ids].astype(bool)
        limit = float(np.max(np.abs(model.actuator_ctrlrange[ids]))) if limited.all() else 1.0
        out += [
            Candidate("gear", name, 1.0, 0.1, 3.0, 0.05, "smooth"),
            Candidate("action_gain", name, 1.0, 0.1, 3.0, 0.05, "smooth"),
            Candidate("action_bias", name, 0.0, -0.5 * limit, 0.5 * limit, 0.05 * limit, "smooth"),
            Candidate("action_deadzone", name, 0.0, 0.0, 0.9 * limit, 0.0, "threshold",
                      trials=(0.1 * limit, 0.3 * limit, 0.5 * limit)),
            Candidate("action_saturation", name, limit, 0.05 * limit, limit, 0.0, "threshold",
                      trials=(0.8 * limit, 0.5 * limit, 0.25 * limit)),
            Candidate("action_delay", name, 0, 1, 3, 1, "integer", trials=(1.0, 2.0)),
        ]

    for i in source.observation_map.mapped.tolist():
        out.append(Candidate("obs_bias", int(i), 0.0, -1e3, 1e3, 0.01, "smooth"))
        if with_observation_delay:
            out.append(Candidate("obs_delay", int(i), 0, 1, 2, 1, "integer", trials=(1.0,)))
    return [c for c in map(_within_effect_range, out) if c is not None]


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
