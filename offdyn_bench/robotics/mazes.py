"""AntMaze maps and their layout shifts, as data.

A map is a tuple of rows, one character per cell, read as in Gymnasium-Robotics' ``maps.py``:
``1`` a wall block, ``0`` free floor, ``r`` the start cell, ``g`` the goal cell. Row 0 is the
top of the maze (largest ``y``), column 0 its left (smallest ``x``); a cell is 4 m wide.

The source maps are Gymnasium-Robotics' ``U_MAZE``, ``MEDIUM_MAZE`` and ``LARGE_MAZE`` with D4RL's
evaluation start and goal cells marked (D4RL's ``antmaze-*-v2`` evaluation mazes): the walls are
the vanilla ones, but start and goal are fixed, where the unmarked vanilla maps draw both from
every free cell. A fixed goal is what makes a layout shift a shift of the *same* task.

A layout keeps the maze's size, its outer wall, its start and its goal, and moves inner walls. Each
layout closes every shortest route of the source maze, so a policy that learned the source route
walks into a wall in the target: ``blocked`` walls one corridor cell of that route; ``l-wall``,
``z-wall`` and ``u-wall`` drop an L-, Z- or U-shaped group of blocks across it; the rest are named
where they are defined. :func:`shortest_path_length` measures what each changes.
"""

from __future__ import annotations

import collections
import dataclasses
from collections.abc import Mapping, Sequence
from types import MappingProxyType

from offdyn_bench.effects.layout import MazeLayout
from offdyn_bench.errors import OffdynError, UnknownNameError

WALL, FREE, START, GOAL = "1", "0", "r", "g"
CELL_CHARACTERS = frozenset(WALL + FREE + START + GOAL)
MazeMap = tuple[str, ...]
Cell = tuple[int, int]


@dataclasses.dataclass(frozen=True)
class Maze:
    """One maze size: its source map, its layouts and the Gymnasium-Robotics env it mirrors."""

    name: str
    source_map: MazeMap
    layouts: Mapping[str, MazeMap]
    vanilla_env_id: str
    """The sparse-reward Gymnasium-Robotics id with the same walls (its dense twin ends in ``Dense``)."""
    episode_steps: int
    """As Gymnasium-Robotics registers the vanilla env."""

    def vanilla_id(self, reward_type: str) -> str:
        """The Gymnasium-Robotics id with these walls and ``reward_type``: ``AntMaze_MediumDense-v5``."""
        return self.vanilla_env_id.replace("-v5", "Dense-v5") if reward_type == "dense" else self.vanilla_env_id

    def layout(self, name: str) -> MazeMap:
        if name not in self.layouts:
            raise UnknownNameError(f"layout of the {self.name} maze", name, self.layouts)
        return self.layouts[name]


def walls_of(maze_map: Sequence[str]) -> MazeMap:
    """The map with start and goal marks turned into free floor: what the physics sees."""
    return tuple(row.replace(START, FREE).replace(GOAL, FREE) for row in maze_map)


def cells_marked(maze_map: Sequence[str], mark: str) -> list[Cell]:
    return [(i, j) for i, row in enumerate(maze_map) for j, c in enumerate(row) if c == mark]


def check_map(maze_map: Sequence[str], what: str = "maze map") -> MazeMap:
    """``maze_map`` as a tuple of rows if it is a rectangular map closed by an outer wall, else
    an :class:`OffdynError` that says what is wrong."""
    if isinstance(maze_map, str) or not isinstance(maze_map, Sequence) or not maze_map:
        raise OffdynError(f"{what}: expected a non-empty list of rows (strings of '1', '0', 'r', 'g'), "
                          f"got {maze_map!r:.80}")
    rows = tuple(maze_map)
    if not all(isinstance(row, str) for row in rows):
        raise OffdynError(f"{what}: every row must be a string of '1', '0', 'r', 'g'")
    width = len(rows[0])
    if len(rows) < 3 or width < 3 or any(len(row) != width for row in rows):
        raise OffdynError(f"{what}: expected a rectangle of at least 3x3 cells, got rows of lengths "
                          f"{[len(row) for row in rows]}")
    bad = sorted({c for row in rows for c in row} - CELL_CHARACTERS)
    if bad:
        raise OffdynError(f"{what}: unknown cell character(s) {bad}; expected '1' (wall), '0' (free), "
                          "'r' (start) or 'g' (goal)")
    border = rows[0] + rows[-1] + "".join(row[0] + row[-1] for row in rows)
    if set(border) != {WALL}:
        raise OffdynError(f"{what}: the outer wall must be closed (every border cell '1')")
    return rows


def shortest_path_length(maze_map: Sequence[str], start: Cell, goal: Cell) -> int | None:
    """Cells moved (4-connected) from ``start`` to ``goal`` on the free cells; ``None`` if walled off."""
    rows = walls_of(maze_map)
    if rows[start[0]][start[1]] == WALL or rows[goal[0]][goal[1]] == WALL:
        return None
    distance = {start: 0}
    queue = collections.deque([start])
    while queue:
        i, j = cell = queue.popleft()
        if cell == goal:
            return distance[cell]
        for n in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
            if rows[n[0]][n[1]] != WALL and n not in distance:
                distance[n] = distance[cell] + 1
                queue.append(n)
    return None


def shortest_route_cells(maze_map: Sequence[str], start: Cell, goal: Cell) -> frozenset[Cell]:
    """Every cell that lies on some shortest route from ``start`` to ``goal``."""
    total = shortest_path_length(maze_map, start, goal)
    if total is None:
        return frozenset()
    rows = walls_of(maze_map)
    free = [(i, j) for i, row in enumerate(rows) for j, c in enumerate(row) if c != WALL]
    return frozenset(c for c in free
                     if (a := shortest_path_length(maze_map, start, c)) is not None
                     and (b := shortest_path_length(maze_map, c, goal)) is not None and a + b == total)


# --- the mazes ----------------------------------------------------------------------------------
# Layouts are written out whole (data, not edits): what the target's walls are is read off the page.

SMALL = Maze(
    name="small",
    vanilla_env_id="AntMaze_UMaze-v5",
    episode_steps=700,
    source_map=("11111",
                "1r001",
                "11101",
                "1g001",
                "11111"),
    # Three free cells a side leave no room for an L, Z or U corridor: the small maze's layouts
    # move its one inner wall instead, each across the source's U-turn.
    layouts=MappingProxyType({
        "blocked": ("11111",     # the top corridor walled at its end, the inner wall opened on the left
                    "1r011",
                    "10101",
                    "1g001",
                    "11111"),
        "left-gap": ("11111",    # the inner wall slid right: the gap is on the start's side
                     "1r001",
                     "10111",
                     "1g001",
                     "11111"),
        "middle-gap": ("11111",  # the gap in the middle of the inner wall
                       "1r001",
                       "11011",
                       "1g001",
                       "11111"),
        "l-wall": ("11111",      # an L-shaped wall across the top corridor
                   "1r101",
                   "10111",
                   "1g001",
                   "11111"),
        "z-wall": ("11111",      # a Z-shaped wall across both corridors
                   "1r101",
                   "10111",
                   "1g011",
                   "11111"),
        "split": ("11111",       # a wall down the middle: start and goal on its left
                  "1r101",
                  "10101",
                  "1g101",
                  "11111"),
    }),
)

MEDIUM = Maze(
    name="medium",
    vanilla_env_id="AntMaze_Medium-v5",
    episode_steps=1000,
    source_map=("11111111",
                "1r011001",
                "10010001",
                "11000111",
                "10010001",
                "10100101",
                "100010g1",
                "11111111"),
    layouts=MappingProxyType({
        "blocked": ("11111111",        # the corridor in row 3 walled: the detour loops round the left
                    "1r011001",
                    "10010001",
                    "11010111",
                    "10010001",
                    "10100101",
                    "100010g1",
                    "11111111"),
        "blocked-goal": ("11111111",   # the last corridor to the goal walled, a new one opened below it
                         "1r011001",
                         "10010001",
                         "11000111",
                         "10010101",
                         "10100001",
                         "100010g1",
                         "11111111"),
        "blocked-twice": ("11111111",  # both of the above
                          "1r011001",
                          "10010001",
                          "11010111",
                          "10010101",
                          "10100001",
                          "100010g1",
                          "11111111"),
        "l-shape": ("11111111",        # one corridor: right along the top, then down
                    "1r000001",
                    "11111101",
                    "11111101",
                    "11111101",
                    "11111101",
                    "111111g1",
                    "11111111"),
        "z-shape": ("11111111",        # right, down the middle, right
                    "1r001111",
                    "11101111",
                    "11101111",
                    "11101111",
                    "11101111",
                    "111000g1",
                    "11111111"),
        "u-shape": ("11111111",        # down the left, along the bottom, and a dead-end arm up the right
                    "1r111101",
                    "10111101",
                    "10111101",
                    "10111101",
                    "10111101",
                    "100000g1",
                    "11111111"),
    }),
)

LARGE = Maze(
    name="large",
    vanilla_env_id="AntMaze_Large-v5",
    episode_steps=1000,
    source_map=("111111111111",
                "1r0001000001",
                "101101010101",
                "100000010001",
                "101111011101",
                "100101000001",
                "110101010111",
                "100100010g01",
                "111111111111"),
    layouts=MappingProxyType({
        "blocked": ("111111111111",        # the way down the middle walled: the detour runs along the top right
                    "1r0001000001",
                    "101101010101",
                    "100000010001",
                    "101111111101",
                    "100101000001",
                    "110101010111",
                    "100100010g01",
                    "111111111111"),
        "blocked-goal": ("111111111111",   # the corridor in row 5 walled before the goal's column
                         "1r0001000001",
                         "101101010101",
                         "100000010001",
                         "101111011101",
                         "100101010001",
                         "110101010111",
                         "100100010g01",
                         "111111111111"),
        "blocked-twice": ("111111111111",  # both of the above
                          "1r0001000001",
                          "101101010101",
                          "100000010001",
                          "101111111101",
                          "100101010001",
                          "110101010111",
                          "100100010g01",
                          "111111111111"),
        "l-shape": ("111111111111",        # one corridor: right along the top, then down to the goal
                    "1r0000000011",
                    "111111111011",
                    "111111111011",
                    "111111111011",
                    "111111111011",
                    "111111111011",
                    "111111111g11",
                    "111111111111"),
        "z-shape": ("111111111111",        # right, down the middle, right
                    "1r0000111111",
                    "111110111111",
                    "111110111111",
                    "111110111111",
                    "111110111111",
                    "111110111111",
                    "111110000g11",
                    "111111111111"),
        "u-shape": ("111111111111",        # down the left, along the bottom, and a dead-end arm up the right
                    "1r1111111101",
                    "101111111101",
                    "101111111101",
                    "101111111101",
                    "101111111101",
                    "101111111101",
                    "100000000g01",
                    "111111111111"),
    }),
)

MAZES: Mapping[str, Maze] = MappingProxyType({m.name: m for m in (SMALL, MEDIUM, LARGE)})


def get_maze(name: str) -> Maze:
    if name not in MAZES:
        raise UnknownNameError("maze", name, MAZES)
    return MAZES[name]


REWARD_TYPES = ("sparse", "dense")


def antmaze_robot(maze: str, reward_type: str) -> str:
    """The suite's robot name: ``AntMazeMedium`` (sparse, as ``AntMaze_Medium-v5``), ``AntMazeMediumDense``."""
    if reward_type not in REWARD_TYPES:
        raise UnknownNameError("AntMaze reward type", reward_type, REWARD_TYPES)
    return f"AntMaze{get_maze(maze).name.capitalize()}{'Dense' if reward_type == 'dense' else ''}"


def layout_effects(maze: str, layout: str) -> tuple[MazeLayout]:
    """The target effects of ``layout`` in ``maze``: the layout's walls as a ``maze_layout`` effect."""
    return (MazeLayout(walls=walls_of(get_maze(maze).layout(layout))),)


def antmaze_pairs() -> list[tuple[str, str, str, tuple[MazeLayout], str]]:
    """(robot, shift, level, target effects, description) of every AntMaze pair."""
    out = []
    for maze in MAZES.values():
        start, goal = cells_marked(maze.source_map, START)[0], cells_marked(maze.source_map, GOAL)[0]
        before = shortest_path_length(maze.source_map, start, goal)
        for reward_type in REWARD_TYPES:
            for name, layout in maze.layouts.items():
                after = shortest_path_length(layout, start, goal)
                description = (f"target {maze.name} maze, layout {name}: the source route is walled, the shortest "
                               f"route is {after} cells (source: {before}); {reward_type} reward")
                out.append((antmaze_robot(maze.name, reward_type), "layout", name, layout_effects(maze.name, name),
                            description))
    return out
