"""The robots of the suite: which Gymnasium v5 env each wraps and which of its parts shift.

Data, not code: a robot names its environment class and the joints and bodies that the
kinematic and morphology shift families act on. The task grid is built from this table.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Mapping
from types import MappingProxyType

from offdyn_bench.errors import UnknownNameError
from offdyn_bench.robotics.adroit import ADROIT_EPISODE_STEPS, ADROIT_TASKS
from offdyn_bench.robotics.mazes import MAZES, REWARD_TYPES, antmaze_robot
from offdyn_bench.wheel_legged.pairs import EPISODE_STEPS as WHEEL_LEGGED_EPISODE_STEPS


@dataclasses.dataclass(frozen=True)
class Robot:
    """A robot: its Gymnasium environment class and its shiftable parts.

    ``kinematic_joints`` maps the part name used in task ids to a MuJoCo joint name;
    ``morph_parts`` maps it to a MuJoCo body name.
    """

    name: str
    env_class: str
    max_episode_steps: int
    kinematic_joints: Mapping[str, str] = dataclasses.field(default_factory=dict)
    morph_parts: Mapping[str, str] = dataclasses.field(default_factory=dict)
    reference_env_id: str | None = None
    task_episode_steps: Mapping[str, int] = dataclasses.field(default_factory=dict)
    """For a robot whose env offers several tasks (its ``task`` argument): each task's episode
    length; empty for the locomotion robots, whose task is fixed."""

    def episode_steps(self, task: str | None) -> int:
        if task is None:
            return self.max_episode_steps
        if task not in self.task_episode_steps:
            raise UnknownNameError(f"task of robot {self.name}", task, self.task_episode_steps)
        return self.task_episode_steps[task]

    def load_env_class(self) -> type:
        module, _, attr = self.env_class.partition(":")
        return getattr(importlib.import_module(module), attr)


_ROBOT_LIST = [
    Robot(
        name="Ant",
        env_class="gymnasium.envs.mujoco.ant_v5:AntEnv",
        max_episode_steps=1000,
        kinematic_joints={"hip1": "hip_1", "ankle1": "ankle_1"},
        morph_parts={"leg1": "aux_1", "leg3": "aux_3"},
        reference_env_id="Ant-v5",
    ),
    Robot(
        name="HalfCheetah",
        env_class="gymnasium.envs.mujoco.half_cheetah_v5:HalfCheetahEnv",
        max_episode_steps=1000,
        kinematic_joints={"bthigh": "bthigh", "fthigh": "fthigh"},
        morph_parts={"bthigh": "bthigh", "fthigh": "fthigh"},
        reference_env_id="HalfCheetah-v5",
    ),
    Robot(
        name="Hopper",
        env_class="gymnasium.envs.mujoco.hopper_v5:HopperEnv",
        max_episode_steps=1000,
        kinematic_joints={"thigh": "thigh_joint", "foot": "foot_joint"},
        morph_parts={"thigh": "thigh", "leg": "leg"},
        reference_env_id="Hopper-v5",
    ),
    Robot(
        name="Walker2d",
        env_class="gymnasium.envs.mujoco.walker2d_v5:Walker2dEnv",
        max_episode_steps=1000,
        kinematic_joints={"thigh": "thigh_joint", "foot": "foot_joint"},
        morph_parts={"thigh": "thigh", "leg": "leg"},
        reference_env_id="Walker2d-v5",
    ),
    # Our own MJCF (assets/robots/wheel_legged.xml): H2O's real-robot validation, simulated.
    Robot(
        name="WheelLegged",
        env_class="offdyn_bench.wheel_legged.env:WheelLeggedEnv",
        max_episode_steps=WHEEL_LEGGED_EPISODE_STEPS["standstill"],
        task_episode_steps=WHEEL_LEGGED_EPISODE_STEPS,  # 30 s and 20 s at 200 Hz
    ),
    # A fast robot for learning tests of the baselines; not part of the benchmark grid.
    Robot(
        name="InvertedPendulum",
        env_class="gymnasium.envs.mujoco.inverted_pendulum_v5:InvertedPendulumEnv",
        max_episode_steps=1000,
        reference_env_id="InvertedPendulum-v5",
    ),
]
# Gymnasium-Robotics' families (issue 16): AntMaze per maze size and reward, and the Adroit hand tasks.
_ROBOT_LIST += [
    Robot(name=antmaze_robot(maze.name, reward), max_episode_steps=maze.episode_steps,
          env_class=f"offdyn_bench.robotics.antmaze:{antmaze_robot(maze.name, reward)}Env",
          reference_env_id=maze.vanilla_id(reward))
    for maze in MAZES.values() for reward in REWARD_TYPES
]
_ROBOT_LIST += [Robot(name=task.robot, env_class=task.env_class, max_episode_steps=ADROIT_EPISODE_STEPS,
                      reference_env_id=task.vanilla_env_id) for task in ADROIT_TASKS.values()]

ROBOTS: Mapping[str, Robot] = MappingProxyType({r.name: r for r in _ROBOT_LIST})


def get_robot(name: str) -> Robot:
    if name not in ROBOTS:
        raise UnknownNameError("robot", name, ROBOTS)
    return ROBOTS[name]
