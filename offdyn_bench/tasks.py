"""Source/target task pairs as data, and the benchmark grid built from a few comprehensions.

A :class:`TaskPair` is a robot, the effects of its source (the simulator a policy trains in) and
of its target (the "real" system), and a version. Each pair registers two Gymnasium ids::

    offdyn/<Robot>-<shift>[-<part>]-<level>-{source,target}-v<version>

and is known to the CLI by its lower-case name, e.g. ``hopper-gravity-0.5``. Released versions
are frozen: a change of dynamics (or of the reward) is a new version, registered beside the old
one. Version 0 is the bare name; a later version's name ends in ``-v<N>``
(``ant-joint-noise-0.5-v1``), so that every name means one fixed pair and records, datasets and
reference scores made for one version are never read as another's.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from collections.abc import Iterable, Mapping
from types import MappingProxyType
from typing import Any, Literal

import gymnasium

from offdyn_bench.effects import (
    CONTROL_COST_ON,
    ActionBias,
    ActionGain,
    ActionDelay,
    ActionNoise,
    ContactSolimp,
    ContactSolref,
    ControlCostOn,
    Effect,
    Friction,
    FrictionCone,
    Gravity,
    Integrator,
    NoSlip,
    JointRange,
    LimbSize,
    effects_from_dicts,
)
from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.robotics.adroit import adroit_pairs
from offdyn_bench.robotics.mazes import antmaze_pairs
from offdyn_bench.robots import ROBOTS, get_robot
from offdyn_bench.wheel_legged.pairs import ROBOT as WHEEL_LEGGED
from offdyn_bench.wheel_legged.pairs import TASK_NAMES as WHEEL_LEGGED_TASKS
from offdyn_bench.wheel_legged.pairs import real_robot_effects

Side = Literal["source", "target"]
SIDES: tuple[Side, ...] = ("source", "target")
ENTRY_POINT = "offdyn_bench.envs:make_robot_env"
# The physics engine a side runs on -> its entry point. DART (dartpy) is imported only when built.
ENGINE_ENTRY_POINTS = {"mujoco": ENTRY_POINT, "dart": "offdyn_bench.engines.dart_env:make_dart_env"}


@dataclasses.dataclass(frozen=True)
class TaskPair:
    """A source/target pair. ``shift``, ``part`` and ``level`` only name it; the effects define it."""

    robot: str
    shift: str
    level: str
    source_effects: tuple[Effect, ...]
    target_effects: tuple[Effect, ...]
    part: str | None = None
    version: int = 0
    description: str = ""
    task: str | None = None
    """The robot's task where its env offers several (``WheelLegged``: ``standstill`` or
    ``movestraight``), passed to the env; ``None`` for robots with one task."""
    target_engine: str = "mujoco"
    """The physics engine of the target (a key of ``ENGINE_ENTRY_POINTS``); sources run on MuJoCo."""
    control_cost_on: ControlCostOn = "applied"
    """Which action the robot's control cost is charged on where action-channel effects change
    it: ``applied`` (what reached the motors; Gymnasium's own reward, version 0 of the joint-noise
    pairs) or ``commanded`` (the policy's action, so that only the dynamics differ between the
    sides; :class:`offdyn_bench.envs.CommandedControlCost`)."""

    def __post_init__(self) -> None:
        if self.control_cost_on not in CONTROL_COST_ON:
            raise UnknownNameError("control_cost_on", self.control_cost_on, CONTROL_COST_ON)
        if self.version < 0:
            raise OffdynError(f"task version must be >= 0, got {self.version}")

    @property
    def pair_id(self) -> str:
        """``Hopper-gravity-0.5``, ``Walker2d-kinematic-foot-hard``; no level: ``WheelLegged-standstill``."""
        parts = [self.robot, self.shift] + ([self.part] if self.part else []) + ([self.level] if self.level else [])
        return "-".join(parts)

    @property
    def name(self) -> str:
        """The CLI name: ``hopper-gravity-0.5``; a later version carries it: ``ant-joint-noise-0.5-v1``."""
        return self.pair_id.lower() + (f"-v{self.version}" if self.version else "")

    def env_id(self, side: Side) -> str:
        _check_side(side)
        return f"offdyn/{self.pair_id}-{side}-v{self.version}"

    @property
    def source_key(self) -> str:
        """What the source simulator is built from (engine, robot, effects, robot task), as canonical
        JSON: pairs with equal keys have the same source, whatever their targets."""
        return json.dumps({"engine": self.engine("source"), **self.env_kwargs("source")}, sort_keys=True)

    def effects(self, side: Side) -> tuple[Effect, ...]:
        _check_side(side)
        return self.source_effects if side == "source" else self.target_effects

    def env_kwargs(self, side: Side) -> dict[str, Any]:
        kwargs: dict[str, Any] = {"robot": self.robot, "effects": [e.to_dict() for e in self.effects(side)]}
        if self.task is not None:
            kwargs["task"] = self.task
        # Only a side whose action channel is changed charges differently; a side without such
        # effects keeps the plain kwargs, so a nominal source stays the one every pair shares.
        changes_action = any(getattr(e, "channel", None) == "action" for e in self.effects(side))
        if self.control_cost_on != "applied" and changes_action:
            kwargs["control_cost_on"] = self.control_cost_on
        return kwargs

    def engine(self, side: Side) -> str:
        _check_side(side)
        return self.target_engine if side == "target" else "mujoco"

    def entry_point(self, side: Side) -> str:
        engine = self.engine(side)
        if engine not in ENGINE_ENTRY_POINTS:
            raise UnknownNameError("physics engine", engine, ENGINE_ENTRY_POINTS)
        return ENGINE_ENTRY_POINTS[engine]

    def make(self, side: Side, **kwargs: Any) -> gymnasium.Env:
        """``gymnasium.make`` of this pair's ``side`` id (registered on import)."""
        with warnings.catch_warnings():
            # Gymnasium calls a version with a later one beside it out of date; here the version
            # was chosen by name (protocol 1.0 pins version 0 of the joint-noise pairs).
            warnings.filterwarnings("ignore", message=".*is out of date. You should consider upgrading",
                                    category=DeprecationWarning)
            return gymnasium.make(self.env_id(side), **kwargs)

    def to_dict(self) -> dict[str, Any]:
        # "task" only where set: the definitions (and dataset recipes' hashes) of other pairs stay as they were.
        engine = {"target_engine": self.target_engine} if self.target_engine != "mujoco" else {}
        cost = {"control_cost_on": self.control_cost_on} if self.control_cost_on != "applied" else {}
        return ({"task": self.task} if self.task is not None else {}) | engine | cost | {
            "name": self.name,
            "robot": self.robot,
            "shift": self.shift,
            "part": self.part,
            "level": self.level,
            "version": self.version,
            "source_env_id": self.env_id("source"),
            "target_env_id": self.env_id("target"),
            "source_effects": [e.to_dict() for e in self.source_effects],
            "target_effects": [e.to_dict() for e in self.target_effects],
            "description": self.description,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TaskPair:
        return cls(robot=data["robot"], shift=data["shift"], part=data.get("part"), level=data["level"],
                   version=int(data.get("version", 0)), description=data.get("description", ""),
                   task=data.get("task"), target_engine=data.get("target_engine", "mujoco"),
                   control_cost_on=data.get("control_cost_on", "applied"),
                   source_effects=effects_from_dicts(data["source_effects"]),
                   target_effects=effects_from_dicts(data["target_effects"]))


def _check_side(side: str) -> None:
    if side not in SIDES:
        raise UnknownNameError("side", side, SIDES)


# --- the grid -------------------------------------------------------------------------------

LOCOMOTION_ROBOTS = ("Ant", "HalfCheetah", "Hopper", "Walker2d")
SCALE_LEVELS = (0.1, 0.5, 2.0, 5.0)
DIFFICULTY_SCALES = {"easy": 0.8, "medium": 0.5, "hard": 0.2}
JOINT_NOISE_STDS = (0.1, 0.5, 1.0)


def _level(x: float) -> str:
    return f"{x:g}" if x != int(x) else f"{x:.1f}"


def _shifted(robot: str, shift: str, level: str, target: Iterable[Effect], part: str | None = None,
             description: str = "") -> TaskPair:
    """The usual pair: a nominal source simulator and a shifted target."""
    return TaskPair(robot=robot, shift=shift, part=part, level=level, source_effects=(),
                    target_effects=tuple(target), description=description)


def _h2o(robot: str, shift: str, level: str, source: Iterable[Effect], description: str) -> TaskPair:
    """The H2O paper's setting: the *simulator* carries the shift, the target is nominal."""
    return TaskPair(robot=robot, shift=shift, level=level, source_effects=tuple(source),
                    target_effects=(), description=description)


# Engine-style swaps: robot -> the integrator its model does *not* use (Hopper and Walker2d ask for
# RK4; HalfCheetah uses Euler, where implicitfast would change nothing: its only velocity force,
# joint damping, is already implicit in MuJoCo's Euler).
ENGINE_SWAP_ROBOTS = {"Hopper": "Euler", "Walker2d": "Euler", "HalfCheetah": "RK4"}


def _contact_solver_swaps(other_integrator: str) -> list[tuple[str, str, list[Effect], str]]:
    """(shift, level, target effects, description) of the MuJoCo contact/solver swaps."""
    return [
        ("contact", "soft", [ContactSolref(timeconst=0.08)],
         "target contacts 4x softer: solref time constant 0.08 s on every geom (models: 0.02 s)"),
        ("contact", "stiff", [ContactSolimp(dmin=0.99, dmax=0.99, width=0.001)],
         "target contacts stiffer: solimp impedance 0.99 from 1 mm penetration on every geom"),
        ("cone", "elliptic", [FrictionCone(cone="elliptic")],
         "target friction cone elliptic (models: pyramidal)"),
        ("integrator", other_integrator.lower(), [Integrator(integrator=other_integrator)],
         f"target integrator {other_integrator} (the model asks for another one)"),
        ("noslip", "10", [NoSlip(iterations=10)], "target no-slip solver on: 10 iterations (models: off)"),
    ]


def _grid() -> list[TaskPair]:
    pairs: list[TaskPair] = []
    for robot in LOCOMOTION_ROBOTS:
        r = ROBOTS[robot]
        pairs += [_shifted(robot, "gravity", _level(s), [Gravity(scale=s)],
                           description=f"target gravity x{s:g}") for s in SCALE_LEVELS]
        pairs += [_shifted(robot, "friction", _level(s), [Friction(scale=s)],
                           description=f"target friction x{s:g} on every geom") for s in SCALE_LEVELS]
        pairs += [_shifted(robot, "kinematic", level, [JointRange(target=joint, scale=s)], part=part,
                           description=f"target {joint} range x{s:g}")
                  for part, joint in r.kinematic_joints.items() for level, s in DIFFICULTY_SCALES.items()]
        pairs += [_shifted(robot, "morph", level, [LimbSize(target=body, scale=s)], part=part,
                           description=f"target {body} limb size x{s:g}")
                  for part, body in r.morph_parts.items() for level, s in DIFFICULTY_SCALES.items()]
        pairs += [_shifted(robot, "joint-noise", _level(std), [ActionNoise(std=std)],
                           description=f"target action noise N(0, {std:g}^2) on every actuator")
                  for std in JOINT_NOISE_STDS]
        # Version 1 charges the control cost on the commanded action (protocol 1.1's decision 4):
        # version 0's target also charged the noise, a reward shift that on the Ant outweighs
        # the dynamics shift. Both stay registered; records and datasets name their version.
        pairs += [dataclasses.replace(
            _shifted(robot, "joint-noise", _level(std), [ActionNoise(std=std)],
                     description=f"target action noise N(0, {std:g}^2) on every actuator; control cost "
                                 "charged on the commanded action"),
            version=1, control_cost_on="commanded") for std in JOINT_NOISE_STDS]
    for robot in ("HalfCheetah", "Walker2d"):
        pairs += [
            _h2o(robot, "h2o-gravity", "2.0", [Gravity(scale=2.0)], "H2O setting: simulator gravity x2"),
            _h2o(robot, "h2o-friction", "0.3", [Friction(scale=0.3)], "H2O setting: simulator friction x0.3"),
            _h2o(robot, "h2o-joint-noise", "1.0", [ActionNoise(std=1.0)],
                 "H2O setting: simulator action noise N(0, 1)"),
        ]
    # Engine swaps (issue 13): the same robot on another contact/solver model of MuJoCo ...
    for robot, other_integrator in ENGINE_SWAP_ROBOTS.items():
        pairs += [_shifted(robot, shift, level, effects, description=description)
                  for shift, level, effects, description in _contact_solver_swaps(other_integrator)]
    # ... and on another engine: DART runs the same MJCF (the engine is the shift; see offdyn_bench.engines).
    pairs += [TaskPair(robot=robot, shift="dart", level="", source_effects=(), target_effects=(), target_engine="dart",
                       description="MuJoCo source -> the same MJCF simulated by DART (hard LCP contacts, hard joint "
                                   "limits, semi-implicit Euler; see offdyn_bench.engines.dart_env)")
              for robot in ("Hopper", "Walker2d")]
    # Fast pairs for the baselines' learning tests (issue 3); InvertedPendulum is not one of the
    # benchmark's locomotion robots, but learns in minutes. A shorter cart rail in the target
    # (slider range x0.2: +-0.2 m) stops a source policy that lets the cart drift (DARC's kind of
    # shift: some source transitions are impossible in the target); stronger gravity (x3) makes the
    # pole fall faster than a source policy reacts. Issue 9's learning benchmark needs pairs where RL
    # on source fails in the target on most seeds (measured: baselines/results/README.md): a
    # one-step command delay, and the short rail with a constant motor offset.
    pairs += [
        _shifted("InvertedPendulum", "kinematic", "hard", [JointRange(target="slider", scale=0.2)],
                 part="slider", description="target slider (cart rail) range x0.2"),
        _shifted("InvertedPendulum", "gravity", "3.0", [Gravity(scale=3.0)], description="target gravity x3"),
        _shifted("InvertedPendulum", "action-delay", "1", [ActionDelay(steps=1)],
                 description="target commands applied one control step (40 ms) late"),
        _shifted("InvertedPendulum", "rail-offset", "hard",
                 [JointRange(target="slider", scale=0.2), ActionBias(value=1.0)],
                 description="target slider range x0.2 and motor command offset +1.0 (a third of the range)"),
        # The second learning pair: the motor wired the other way round (an action-channel gap
        # only, DAP's kind); every source policy pushes the cart the wrong way.
        _shifted("InvertedPendulum", "reversed-motor", "", [ActionGain(scale=-1.0)],
                 description="target motor wired in reverse (command gain -1)"),
    ]
    # The wheel-legged balancer (issue 12): the clean model against the "real robot", one pair per task.
    pairs += [TaskPair(robot=WHEEL_LEGGED, shift=task, level="", task=task, source_effects=(),
                       target_effects=real_robot_effects(task),
                       description=f"{task}: clean model -> real robot (motor dead zone, drive friction, "
                                   "worn tyre friction, 5 ms sensor latency, sensor noise)")
              for task in WHEEL_LEGGED_TASKS]
    # Gymnasium-Robotics' families (issue 16): AntMaze layouts, Adroit broken joints and shrunk fingers.
    pairs += [_shifted(robot, shift, level, effects, description=description)
              for robot, shift, level, effects, description in antmaze_pairs()]
    pairs += [_shifted(robot, shift, level, effects, part=part, description=description)
              for robot, shift, part, level, effects, description in adroit_pairs()]
    return pairs


def _index(pairs: Iterable[TaskPair]) -> Mapping[str, TaskPair]:
    out: dict[str, TaskPair] = {}
    for pair in pairs:
        get_robot(pair.robot)
        if pair.name in out:
            raise RuntimeError(f"task {pair.name!r} defined twice")
        out[pair.name] = pair
    return MappingProxyType(out)


TASKS: Mapping[str, TaskPair] = _index(_grid())


def get_task(name: str) -> TaskPair:
    """The pair called ``name`` (``hopper-gravity-0.5``); also accepts its env ids."""
    if isinstance(name, str) and name.startswith("offdyn/"):
        for pair in TASKS.values():
            if name in (pair.env_id("source"), pair.env_id("target")):
                return pair
        raise UnknownNameError("task env id", name, [p.env_id(s) for p in TASKS.values() for s in SIDES])
    if name not in TASKS:
        lowered = str(name).lower()
        if lowered in TASKS:
            return TASKS[lowered]
        # Version 0 is the bare name; "<name>-v0" says the same explicitly.
        if lowered.endswith("-v0") and lowered.removesuffix("-v0") in TASKS:
            return TASKS[lowered.removesuffix("-v0")]
        raise UnknownNameError("task", name, TASKS)
    return TASKS[name]


def register_tasks(pairs: Iterable[TaskPair] | None = None) -> list[str]:
    """Register both ids of every pair with Gymnasium (string entry points). Idempotent."""
    ids = []
    for pair in TASKS.values() if pairs is None else pairs:
        robot = get_robot(pair.robot)
        for side in SIDES:
            env_id = pair.env_id(side)
            if env_id in gymnasium.registry:
                existing = gymnasium.registry[env_id]
                if existing.kwargs != pair.env_kwargs(side) or existing.entry_point != pair.entry_point(side):
                    raise OffdynError(f"{env_id} is already registered with other dynamics")
            else:
                gymnasium.register(id=env_id, entry_point=pair.entry_point(side),
                                   max_episode_steps=robot.episode_steps(pair.task), kwargs=pair.env_kwargs(side))
            ids.append(env_id)
    return ids
