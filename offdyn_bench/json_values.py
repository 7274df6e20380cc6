"""What counts as an integer or a number in a value read from JSON, YAML, ``--set`` or a settings object.

``bool`` is a subclass of ``int``, so ``isinstance(True, int)`` holds and a file's ``true`` would pass
for ``1`` (and ``false`` for a seed of 0). Every check of a decoded value goes through these instead.
"""

from __future__ import annotations

import math
from typing import TypeGuard


def is_integer(value: object) -> TypeGuard[int]:
    """A Python ``int`` that is not a ``bool``."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: object) -> TypeGuard[int | float]:
    """An ``int`` or ``float`` that is not a ``bool`` (``inf`` and ``nan`` included)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def is_finite_number(value: object) -> TypeGuard[int | float]:
    """A number that is neither infinite nor ``nan``."""
    return is_number(value) and math.isfinite(value)
