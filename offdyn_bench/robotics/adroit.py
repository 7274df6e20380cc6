"""Adroit hand tasks (pen, door, relocate, hammer) and the hand parts their shifts act on.

The envs are Gymnasium-Robotics' ``AdroitHand*-v1`` classes
(:mod:`offdyn_bench.robotics.adroit_envs`), MuJoCo envs on their own MJCF files, so the suite's
model effects apply to them as to the locomotion robots. The two shift families use the existing
effect vocabulary:

* ``broken-joint``: ``joint_range`` shrinks one finger joint's range about its rest pose (a joint
  that no longer bends fully): easy x0.8, medium x0.5, hard x0.2.
* ``shrink-finger``: ``limb_size`` scales every segment of one finger (proximal, middle and
  distal phalanx, each about its own joint, the next following its end): easy x0.8, medium x0.5,
  hard x0.2. Mass follows volume.

Which part each task's shift acts on is data (:data:`ADROIT_TASKS`), chosen so that a competent
policy meets the change: measured with :mod:`offdyn_bench.robotics.probes` (README, "AntMaze and
Adroit"; tests/robotics).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType

from offdyn_bench.effects import Effect, JointRange, LimbSize
from offdyn_bench.errors import InvalidParameterError, UnknownNameError

LEVEL_SCALES: Mapping[str, float] = MappingProxyType({"easy": 0.8, "medium": 0.5, "hard": 0.2})


@dataclasses.dataclass(frozen=True)
class Finger:
    """One finger of the Adroit (Shadow) hand: its joints from the palm out, and its segments."""

    name: str
    joints: tuple[str, ...]
    segments: tuple[str, ...]


# Joint and body names of the Adroit MJCF (identical in the four task files).
FINGERS: Mapping[str, Finger] = MappingProxyType({f.name: f for f in (
    Finger("index", ("FFJ3", "FFJ2", "FFJ1", "FFJ0"), ("ffproximal", "ffmiddle", "ffdistal")),
    Finger("middle", ("MFJ3", "MFJ2", "MFJ1", "MFJ0"), ("mfproximal", "mfmiddle", "mfdistal")),
    Finger("ring", ("RFJ3", "RFJ2", "RFJ1", "RFJ0"), ("rfproximal", "rfmiddle", "rfdistal")),
    Finger("little", ("LFJ3", "LFJ2", "LFJ1", "LFJ0"), ("lfproximal", "lfmiddle", "lfdistal")),
    Finger("thumb", ("THJ4", "THJ3", "THJ2", "THJ1", "THJ0"), ("thproximal", "thmiddle", "thdistal")),
)})


@dataclasses.dataclass(frozen=True)
class AdroitTask:
    """An Adroit task: its robot name in the suite, the Gymnasium-Robotics env, and its shifts' parts."""

    robot: str
    env_class: str
    vanilla_env_id: str
    broken_joint: tuple[str, str]
    """(part name in task ids, MuJoCo joint) of the ``broken-joint`` shift."""
    shrunk_finger: str
    """The finger (a key of :data:`FINGERS`) of the ``shrink-finger`` shift."""
    why: str
    """What the shrunk finger does in the task (the ``shrink-finger`` pairs' descriptions say it)."""


_MODULE = "offdyn_bench.robotics.adroit_envs"  # imported when an env is built, not with the task grid
# The broken joint is the thumb's proximal flexion THJ3 in all four tasks: of the nine thumb and
# index joints a pinch uses, it is the one the others cannot make up for (measured with
# offdyn_bench.robotics.probes.pinch_gap: THJ3 x0.5 opens the closest thumb-index pinch from 13 to
# 17 mm, x0.2 to 33 mm; THJ4, THJ1, FFJ2 or FFJ3 at x0.2 leave it within 0.2 mm). The shrunk finger
# is the one the task's contact leans on.
ADROIT_TASKS: Mapping[str, AdroitTask] = MappingProxyType({t.robot: t for t in (
    AdroitTask("AdroitPen", f"{_MODULE}:AdroitHandPenEnv", "AdroitHandPen-v1", ("thumb-flex", "THJ3"), "index",
               "the pen turns between thumb and index finger"),
    AdroitTask("AdroitDoor", f"{_MODULE}:AdroitHandDoorEnv", "AdroitHandDoor-v1", ("thumb-flex", "THJ3"), "index",
               "the index finger hooks the handle to turn the latch"),
    AdroitTask("AdroitRelocate", f"{_MODULE}:AdroitHandRelocateEnv", "AdroitHandRelocate-v1",
               ("thumb-flex", "THJ3"), "thumb", "the ball is held between thumb and fingers"),
    AdroitTask("AdroitHammer", f"{_MODULE}:AdroitHandHammerEnv", "AdroitHandHammer-v1",
               ("thumb-flex", "THJ3"), "thumb", "the handle is held in a power grasp closed by the thumb"),
)})
ADROIT_EPISODE_STEPS = 200  # as Gymnasium-Robotics registers the v1 envs


def get_adroit_task(robot: str) -> AdroitTask:
    if robot not in ADROIT_TASKS:
        raise UnknownNameError("Adroit task", robot, ADROIT_TASKS)
    return ADROIT_TASKS[robot]


def _scale(level: str) -> float:
    if level not in LEVEL_SCALES:
        raise InvalidParameterError("Adroit shift", "level", level, f"one of {list(LEVEL_SCALES)}")
    return LEVEL_SCALES[level]


def broken_joint(joint: str, level: str) -> tuple[Effect, ...]:
    """The effects of a broken ``joint`` (a MuJoCo joint name of the hand) at ``level``."""
    known = {j for f in FINGERS.values() for j in f.joints}
    if joint not in known:
        raise UnknownNameError("finger joint of the Adroit hand", joint, known)
    return (JointRange(target=joint, scale=_scale(level)),)


def shrunk_finger(finger: str, level: str) -> tuple[Effect, ...]:
    """The effects of ``finger`` (``index``, ``thumb``, ...) shrunk at ``level``: every segment scaled."""
    if finger not in FINGERS:
        raise UnknownNameError("finger of the Adroit hand", finger, FINGERS)
    scale = _scale(level)
    return tuple(LimbSize(target=segment, scale=scale) for segment in FINGERS[finger].segments)


def adroit_pairs() -> list[tuple[str, str, str, str, tuple[Effect, ...], str]]:
    """(robot, shift, part, level, target effects, description) of every Adroit pair."""
    out = []
    for task in ADROIT_TASKS.values():
        part, joint = task.broken_joint
        for level, scale in LEVEL_SCALES.items():
            description = (f"target {joint} (the thumb's proximal flexion) range x{scale:g}: the thumb "
                           "closes less far onto the fingers")
            out.append((task.robot, "broken-joint", part, level, broken_joint(joint, level), description))
        for level, scale in LEVEL_SCALES.items():
            segments = ", ".join(FINGERS[task.shrunk_finger].segments)
            out.append((task.robot, "shrink-finger", task.shrunk_finger, level, shrunk_finger(task.shrunk_finger, level),
                        f"target {task.shrunk_finger} finger ({segments}) size x{scale:g} ({task.why})"))
    return out
