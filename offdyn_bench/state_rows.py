"""State vectors for ``info``, handed out as read-only rows of preallocated blocks.

An env's physics states and the channel effects' states with delay buffers are made once per step
and kept by whoever records them. One array is a step's ``state`` and the next step's
``prev_state``, hence read-only. Allocating one array and clearing its ``writeable`` flag per step
costs more than the copy into it, so states are rows of a block allocated ``BLOCK_ROWS`` at a time,
their read-only views made in bulk. A state kept alone keeps its block alive: ``.copy()`` it to
keep it on its own.
"""

from __future__ import annotations

import numpy as np

BLOCK_ROWS = 64


class ReadOnlyRows:
    """Fresh vectors of ``size`` floats: ``(free or refill()).pop()`` gives a (writable row,
    read-only view of it) pair never handed out before. The attribute is public so a hot loop
    can take one without a method call."""

    __slots__ = ("free", "size")

    def __init__(self, size: int) -> None:
        self.size = size
        self.free: list[tuple[np.ndarray, np.ndarray]] = []

    def refill(self) -> list[tuple[np.ndarray, np.ndarray]]:
        block = np.empty((BLOCK_ROWS, self.size))
        read_only = block.view()
        read_only.flags.writeable = False
        self.free = list(zip(block, read_only))
        return self.free
