"""The layout shift of maze tasks: which cells of a maze are walls.

A maze model built by :mod:`offdyn_bench.robotics.antmaze` has one box geom per cell, named
``block_<row>_<col>`` as Gymnasium-Robotics names its walls. A wall cell's block stands on the
floor; a free cell's block waits below it with its contacts off (``contype = conaffinity = 0``),
out of reach of anything above the floor and skipped by collision detection. All layouts of one
maze therefore compile to models of one structure, and a layout shift moves blocks up or down and
turns their contacts on or off: the model diff names exactly the cells that changed
(``geom_pos[block_3_3]``).
"""

from __future__ import annotations

import dataclasses
import re
from typing import TYPE_CHECKING, ClassVar

from offdyn_bench.effects.model import ModelEffect
from offdyn_bench.errors import OffdynError

if TYPE_CHECKING:
    import mujoco

BLOCK_NAME = re.compile(r"^block_(\d+)_(\d+)$")
MAX_CELLS_PER_SIDE = 64  # the largest Gymnasium-Robotics maze has 12; beyond this a map is a mistake


def block_name(row: int, col: int) -> str:
    return f"block_{row}_{col}"


def raised_z(half_height: float) -> float:
    """The centre height of a block standing on the floor (z = 0)."""
    return half_height


def contact_bits(wall: bool) -> int:
    """``contype`` and ``conaffinity`` of a block: 1 on the floor (as Gymnasium-Robotics' walls), 0
    below it. Off, a lowered block costs no collision checks: with them on, the large maze's 46
    lowered blocks cost about 9% of a step; off, about 3% (``benchmarks/env_step_rate.py``)."""
    return 1 if wall else 0


def lowered_z(half_height: float) -> float:
    """The centre height of a block waiting below the floor: its top a block's height under it,
    so no contact margin reaches it from above."""
    return -3.0 * half_height


@dataclasses.dataclass(frozen=True)
class WallRows:
    """The allowed values of a wall map: rows of ``1`` (wall) and ``0`` (free), all of one length,
    closed by an outer wall."""

    def describe(self) -> str:
        return (f"a list of 3 to {MAX_CELLS_PER_SIDE} equal-length strings of '1' (wall) and '0' (free) "
                "with every border cell '1'")

    def document(self) -> str:
        return "rows of 1 (wall) and 0 (free), the border all walls"

    def normalize(self, value: object) -> tuple[str, ...] | None:
        if isinstance(value, str) or not isinstance(value, (list, tuple)):
            return None
        rows = tuple(value)
        if not 3 <= len(rows) <= MAX_CELLS_PER_SIDE or not all(isinstance(r, str) for r in rows):
            return None
        width = len(rows[0])
        if not 3 <= width <= MAX_CELLS_PER_SIDE or any(len(r) != width or set(r) - {"0", "1"} for r in rows):
            return None
        border = rows[0] + rows[-1] + "".join(r[0] + r[-1] for r in rows)
        return rows if set(border) == {"1"} else None


@dataclasses.dataclass(frozen=True, kw_only=True)
class MazeLayout(ModelEffect):
    """Set which cells of a maze are walls: the layout shift of the AntMaze tasks.

    ``walls`` is the whole map, one string per row from the top, ``1`` a wall and ``0`` free
    floor; it must be the size of the model's maze. Each block geom ``block_<row>_<col>`` is
    raised onto the floor where the map has a wall and lowered below it, contacts off, where the
    map is free.
    Only maze models (offdyn_bench.robotics.antmaze) have these blocks.
    """

    kind: ClassVar[str] = "maze_layout"
    target_type: ClassVar = "global"
    value_field: ClassVar[str] = "walls"
    needs_spec: ClassVar[bool] = True
    # The compiler's collision tree of the world body covers the blocks with contacts on: it follows.
    fields: ClassVar = ("geom_pos", "geom_contype", "geom_conaffinity", "body_bvhnum", "bvh_child", "bvh_depth",
                        "bvh_nodeid")
    ranges: ClassVar = {"walls": WallRows()}
    walls: tuple[str, ...]

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.walls), len(self.walls[0])

    def check_target(self, model: mujoco.MjModel) -> None:
        names = [model.geom(i).name for i in range(model.ngeom)]
        self._check_maze_shape(names)

    def _check_maze_shape(self, geom_names: list[str]) -> None:
        cells = [tuple(int(x) for x in m.groups()) for n in geom_names if (m := BLOCK_NAME.match(n))]
        if not cells:
            raise OffdynError(f"effect {self.kind!r} acts on maze models (geoms named block_<row>_<col>, "
                              "as offdyn_bench.robotics.antmaze builds them); this model has none")
        shape = (max(c[0] for c in cells) + 1, max(c[1] for c in cells) + 1)
        if len(cells) != shape[0] * shape[1]:
            raise OffdynError(f"effect {self.kind!r}: the model's maze has {len(cells)} blocks, not one per cell "
                              f"of its {shape[0]}x{shape[1]} grid; build it with offdyn_bench.robotics.antmaze")
        if shape != self.shape:
            raise OffdynError(f"effect {self.kind!r}: walls is a {self.shape[0]}x{self.shape[1]} map but the "
                              f"model's maze is {shape[0]}x{shape[1]} cells; expected a map of the maze's size")

    def apply_to_spec(self, spec: mujoco.MjSpec) -> None:
        geoms = {g.name: g for g in spec.worldbody.geoms if BLOCK_NAME.match(g.name)}
        self._check_maze_shape(list(geoms))
        for i, row in enumerate(self.walls):
            for j, cell in enumerate(row):
                geom = geoms[block_name(i, j)]
                half_height = float(geom.size[2])
                pos = list(geom.pos)
                pos[2] = raised_z(half_height) if cell == "1" else lowered_z(half_height)
                geom.pos = pos
                geom.contype = geom.conaffinity = contact_bits(cell == "1")

    def describe(self) -> str:
        return f"{self.kind}({self.shape[0]}x{self.shape[1]} cells: {' / '.join(self.walls)})"
