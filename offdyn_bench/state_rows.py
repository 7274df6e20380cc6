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
    can take one without a method call.

    With ``split``, each row also comes with writable views of its first ``split`` numbers and of
    the rest, made in bulk with the block: a state of two parts is then two assignments, cheaper
    than a concatenation into the row."""

    __slots__ = ("free", "size", "split")

    def __init__(self, size: int, split: int | None = None) -> None:
        self.size = size
        self.split = split
        self.free: list[tuple[np.ndarray, ...]] = []

    def __getstate__(self) -> tuple[int, int | None]:
        # The free rows are views of one block: pickled (or deep-copied), each would become an
        # array of its own, and a write into a row would no longer show in its read-only view.
        # A copy starts with none and allocates its own block.
        return self.size, self.split

    def __setstate__(self, state: tuple[int, int | None]) -> None:
        self.size, self.split = state
        self.free = []

    def refill(self) -> list[tuple[np.ndarray, ...]]:
        block = np.empty((BLOCK_ROWS, self.size))
        read_only = block.view()
        read_only.flags.writeable = False
        if self.split is None:
            self.free = list(zip(block, read_only))
        else:
            self.free = list(zip(block, read_only, block[:, :self.split], block[:, self.split:]))
        return self.free
