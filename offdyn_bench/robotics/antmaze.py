"""AntMaze: Gymnasium's Ant in a maze, a goal to reach, the maze's layout as the shift.

The task is Gymnasium-Robotics' ``AntMaze_*-v5`` (``gymnasium_robotics.envs.maze.ant_maze_v5``):
the same Ant model, the same 4 m cells and 2 m high wall blocks, the same goal and start noise,
the same rewards, observations and episode lengths. It is written here as one MuJoCo env (a
subclass of Gymnasium's ``AntEnv``), where Gymnasium-Robotics wraps an ``AntEnv`` in another
env, so that the suite's model effects and physics state in ``info`` apply to it as to every
other robot (``offdyn_bench.envs`` subclasses it like the locomotion envs).

One difference in the model: every cell of the map has a block (``block_<row>_<col>``), free
cells' blocks below the floor with their contacts off. A layout shift (the ``maze_layout``
effect) raises and lowers blocks, so every layout of a maze compiles to a model of the same
bodies and geoms.

### Observation (a dict, as Gymnasium-Robotics)

| key | shape | what |
|---|---|---|
| ``observation`` | (105,) | the Ant's observation without its x, y: torso z and orientation, joint angles, velocities, contact forces |
| ``achieved_goal`` | (2,) | the torso's x, y (m) |
| ``desired_goal`` | (2,) | the goal's x, y (m) |

### Rewards

``sparse``: 1 when the torso is within 0.45 m of the goal, else 0. ``dense``: ``exp(-distance)``.
The task is continuing (Gymnasium-Robotics' default): an episode ends only at its time limit, and
``info["success"]`` says whether the goal is reached. ``info`` also carries the Ant's reward terms.

### Starting state

The Ant starts upright in the start cell (``r``), the goal is in the goal cell (``g``), each moved
by a uniform offset of up to a quarter cell (1 m) in x and y, drawn from the env's seed in the
order Gymnasium-Robotics draws them: with the same map and seed both envs start the same.
``options={"goal_cell": (i, j), "reset_cell": (i, j)}`` places them in other free cells.

### Version history

* v0: the small (``U_MAZE``), medium and large mazes of Gymnasium-Robotics 1.4.2 with D4RL's
  evaluation start and goal cells; sparse and dense rewards.
"""

from __future__ import annotations

import os
import pathlib
import tempfile
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar
from xml.etree import ElementTree

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.envs.mujoco.ant_v5 import AntEnv
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv
from gymnasium.utils import EzPickle

from offdyn_bench.effects.layout import (
    BLOCK_NAME,
    block_name,
    contact_bits,
    lowered_z,
    raised_z,
)
from offdyn_bench.errors import OffdynError
from offdyn_bench.robotics.mazes import (
    GOAL,
    LARGE,
    MEDIUM,
    SMALL,
    START,
    WALL,
    Cell,
    Maze,
    cells_marked,
    check_map,
    shortest_path_length,
)

ANT_XML = pathlib.Path(gymnasium.envs.mujoco.ant_v5.__file__).parent / "assets" / "ant.xml"
CELL_SIZE = 4.0  # m: Gymnasium-Robotics' maze_size_scaling for AntMaze
WALL_HEIGHT = 0.5  # in cells: Gymnasium-Robotics' maze_height (2 m walls)
GOAL_RADIUS = 0.45  # m: within it the goal is reached
POSITION_NOISE = 0.25  # in cells: the start and goal offsets' range


def maze_xml(maze_map: Sequence[str]) -> str:
    """The Ant's MJCF with one block per cell of ``maze_map`` (walls raised, free cells' blocks
    lowered) and the goal's ``target`` site, placed as Gymnasium-Robotics places its walls."""
    tree = ElementTree.parse(ANT_XML)
    worldbody = tree.find(".//worldbody")
    assert worldbody is not None
    rows, cols = len(maze_map), len(maze_map[0])
    half = 0.5 * CELL_SIZE
    half_height = WALL_HEIGHT / 2 * CELL_SIZE
    for i, row in enumerate(maze_map):
        for j, cell in enumerate(row):
            x, y = cell_center(i, j, rows, cols)
            wall = cell == WALL
            z = raised_z(half_height) if wall else lowered_z(half_height)
            bits = str(contact_bits(wall))
            ElementTree.SubElement(worldbody, "geom", name=block_name(i, j), pos=f"{x} {y} {z}",
                                   size=f"{half} {half} {half_height}", type="box", material="",
                                   contype=bits, conaffinity=bits, rgba="0.7 0.5 0.3 1.0")
    ElementTree.SubElement(worldbody, "site", name="target", pos=f"0 0 {half_height}",
                           size=f"{0.2 * CELL_SIZE}", rgba="1 0 0 0.7", type="sphere")
    return ElementTree.tostring(tree.getroot(), encoding="unicode")


def cell_center(i: int, j: int, rows: int, cols: int) -> tuple[float, float]:
    """The x, y (m) of cell (row ``i``, column ``j``): the maze is centred on the origin."""
    return (j + 0.5) * CELL_SIZE - cols / 2 * CELL_SIZE, rows / 2 * CELL_SIZE - (i + 0.5) * CELL_SIZE


class AntMazeEnv(AntEnv):
    """Gymnasium's Ant in a maze (see the module docstring). Subclasses fix the maze and reward."""

    maze: ClassVar[Maze]
    reward_type: ClassVar[str]
    vanilla_env_id: ClassVar[str]

    def __init__(self, render_mode: str | None = None, continuing_task: bool = True, reset_target: bool = False,
                 **kwargs: Any) -> None:
        self.maze_map = check_map(self.maze.source_map, f"the {self.maze.name} maze")
        self.start_cells: list[Cell] = cells_marked(self.maze_map, START)
        self.goal_cells: list[Cell] = cells_marked(self.maze_map, GOAL)
        self.continuing_task = continuing_task
        self.reset_target = reset_target
        self.goal = np.zeros(2)
        self.reset_pos = np.zeros(2)
        # MujocoEnv reads a file: the generated MJCF lives on disk only while the model compiles.
        handle, xml_path = tempfile.mkstemp(prefix=f"offdyn-antmaze-{self.maze.name}-", suffix=".xml")
        try:
            with os.fdopen(handle, "w") as f:
                f.write(maze_xml(self.maze_map))
            AntEnv.__init__(self, xml_file=xml_path, exclude_current_positions_from_observation=False,
                            reset_noise_scale=0.0, render_mode=render_mode, **kwargs)
        finally:
            os.remove(xml_path)
        EzPickle.__init__(self, render_mode=render_mode, continuing_task=continuing_task,
                          reset_target=reset_target, **kwargs)
        ant_size = self.observation_space.shape[0]
        self.observation_space = spaces.Dict({
            "observation": spaces.Box(-np.inf, np.inf, shape=(ant_size - 2,), dtype=np.float64),
            "achieved_goal": spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float64),
            "desired_goal": spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float64),
        })
        self._target_site = self.model.site("target").id
        self.walls = self.compiled_walls()
        self._check_layout()

    # --- the maze as compiled --------------------------------------------------------------
    def compiled_walls(self) -> tuple[str, ...]:
        """The wall map the compiled model has (layout effects applied): ``1`` where a block stands."""
        grid = [["0"] * len(self.maze_map[0]) for _ in self.maze_map]
        for g in range(self.model.ngeom):
            match = BLOCK_NAME.match(self.model.geom(g).name)
            if match and self.model.geom_pos[g, 2] > 0:
                grid[int(match.group(1))][int(match.group(2))] = WALL
        return tuple("".join(row) for row in grid)

    def _check_layout(self) -> None:
        for start in self.start_cells:
            for goal in self.goal_cells:
                if shortest_path_length(self.walls, start, goal) is None:
                    raise OffdynError(
                        f"the {self.maze.name} maze's layout walls the goal cell {goal} off from the start cell "
                        f"{start} (or covers one of them); a layout must leave a way from start to goal. "
                        f"Walls: {' / '.join(self.walls)}")

    def cell_xy(self, cell: Sequence[int]) -> np.ndarray:
        return np.array(cell_center(int(cell[0]), int(cell[1]), len(self.maze_map), len(self.maze_map[0])))

    def _free_cell(self, cell: object, what: str) -> Cell:
        rows, cols = len(self.walls), len(self.walls[0])
        try:
            i, j = (int(c) for c in cell)  # type: ignore[union-attr]
        except (TypeError, ValueError):
            raise OffdynError(f"reset option {what}: expected a (row, column) pair, got {cell!r}") from None
        if not (0 <= i < rows and 0 <= j < cols) or self.walls[i][j] == WALL:
            raise OffdynError(f"reset option {what}={cell!r}: expected a free cell of the {rows}x{cols} maze "
                              f"(walls: {' / '.join(self.walls)})")
        return i, j

    # --- Gymnasium API ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: Mapping[str, Any] | None = None):
        gymnasium.Env.reset(self, seed=seed)
        options = options or {}
        # The draws in Gymnasium-Robotics' order (MazeEnv.reset): goal cell, goal offset, start cell(s), start offset.
        if options.get("goal_cell") is not None:
            goal = self.cell_xy(self._free_cell(options["goal_cell"], "goal_cell"))
        else:
            goal = self.cell_xy(self.goal_cells[self.np_random.integers(low=0, high=len(self.goal_cells))])
        self.goal = self._add_position_noise(goal)
        if options.get("reset_cell") is not None:
            start = self.cell_xy(self._free_cell(options["reset_cell"], "reset_cell"))
        else:
            if all(np.linalg.norm(self.cell_xy(c) - self.goal) <= 0.5 * CELL_SIZE for c in self.start_cells):
                raise OffdynError("reset option goal_cell: the goal lies in the start cell; give reset_cell too")
            start = self.goal.copy()
            while np.linalg.norm(start - self.goal) <= 0.5 * CELL_SIZE:
                start = self.cell_xy(self.start_cells[self.np_random.integers(low=0, high=len(self.start_cells))])
        self.reset_pos = self._add_position_noise(start)
        self._place_target_site()
        self.init_qpos[:2] = self.reset_pos
        obs, info = MujocoEnv.reset(self)  # already seeded above: the draws above stay the only ones
        info["success"] = bool(np.linalg.norm(obs["achieved_goal"] - self.goal) <= GOAL_RADIUS)
        return obs, info

    def reset_model(self) -> dict[str, np.ndarray]:
        # Gymnasium-Robotics resets its Ant with no noise; this draws nothing from the env's generator.
        self.set_state(self.init_qpos, self.init_qvel)
        return self._get_obs()

    def step(self, action: np.ndarray):
        obs, _, _, _, info = AntEnv.step(self, action)
        achieved = obs["achieved_goal"]
        reward = self.compute_reward(achieved, self.goal, info)
        terminated = self.compute_terminated(achieved, self.goal, info)
        info["success"] = bool(np.linalg.norm(achieved - self.goal) <= GOAL_RADIUS)
        self._update_goal(achieved)
        return obs, reward, terminated, False, info

    def _get_obs(self) -> dict[str, np.ndarray]:
        ant = AntEnv._get_obs(self)
        return {"observation": ant[2:], "achieved_goal": ant[:2], "desired_goal": self.goal.copy()}

    # --- goal-conditioned API (as Gymnasium-Robotics' GoalEnv) ------------------------------
    def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> Any:
        distance = np.linalg.norm(achieved_goal - desired_goal, axis=-1)
        if self.reward_type == "dense":
            return np.exp(-distance)
        return (distance <= GOAL_RADIUS).astype(np.float64)

    def compute_terminated(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> bool:
        return not self.continuing_task and bool(np.linalg.norm(achieved_goal - desired_goal) <= GOAL_RADIUS)

    def compute_truncated(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> bool:
        return False

    def _update_goal(self, achieved_goal: np.ndarray) -> None:
        if not (self.continuing_task and self.reset_target and np.linalg.norm(achieved_goal - self.goal) <= GOAL_RADIUS):
            return
        while np.linalg.norm(achieved_goal - self.goal) <= GOAL_RADIUS:
            goal = self.cell_xy(self.goal_cells[self.np_random.integers(low=0, high=len(self.goal_cells))])
            self.goal = self._add_position_noise(goal)
        self._place_target_site()

    def _add_position_noise(self, xy: np.ndarray) -> np.ndarray:
        noise = POSITION_NOISE * CELL_SIZE
        xy = xy.copy()
        xy[0] += self.np_random.uniform(low=-noise, high=noise)
        xy[1] += self.np_random.uniform(low=-noise, high=noise)
        return xy

    def _place_target_site(self) -> None:
        self.model.site_pos[self._target_site] = [*self.goal, WALL_HEIGHT / 2 * CELL_SIZE]


def _maze_env(maze: Maze, reward_type: str) -> type[AntMazeEnv]:
    suffix = "Dense" if reward_type == "dense" else ""
    name = f"AntMaze{maze.name.capitalize()}{suffix}Env"
    vanilla = maze.vanilla_id(reward_type)
    cls = type(name, (AntMazeEnv,), {
        "maze": maze, "reward_type": reward_type, "vanilla_env_id": vanilla, "__module__": __name__,
        "__doc__": f"The {maze.name} AntMaze, {reward_type} reward: {vanilla} with D4RL's start and goal cells.",
    })
    return cls


# Module-level classes (robots.py names them; instances pickle by reference).
AntMazeSmallEnv = _maze_env(SMALL, "sparse")
AntMazeSmallDenseEnv = _maze_env(SMALL, "dense")
AntMazeMediumEnv = _maze_env(MEDIUM, "sparse")
AntMazeMediumDenseEnv = _maze_env(MEDIUM, "dense")
AntMazeLargeEnv = _maze_env(LARGE, "sparse")
AntMazeLargeDenseEnv = _maze_env(LARGE, "dense")
ANTMAZE_ENV_CLASSES: Mapping[str, type[AntMazeEnv]] = {
    cls.__name__.removesuffix("Env"): cls
    for cls in (AntMazeSmallEnv, AntMazeSmallDenseEnv, AntMazeMediumEnv, AntMazeMediumDenseEnv,
                AntMazeLargeEnv, AntMazeLargeDenseEnv)
}
