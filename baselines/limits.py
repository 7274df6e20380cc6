"""Valid values of config fields, checked before a run writes anything.

Each method's ``Config`` dataclass lists its limits in a ``LIMITS`` class variable (field name ->
:class:`Limit`); :func:`config_problems` walks a config, nested groups included (``sac.batch_size``),
and returns one message per bad value, e.g. ``sac.batch_size=-3: expected an integer >= 1``. A
config may add checks between fields in a ``cross_checks()`` method returning more messages.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from typing import Any

from offdyn_bench.json_values import is_finite_number, is_integer


@dataclasses.dataclass(frozen=True)
class Limit:
    """A check of one value and what a good value looks like (for the message)."""

    accepts: Callable[[Any], bool]
    expected: str


def integer(minimum: int) -> Limit:
    return Limit(lambda v: is_integer(v) and v >= minimum, f"an integer >= {minimum}")


def number(low: float | None = None, high: float | None = None, *, low_open: bool = False) -> Limit:
    """A finite number in ``[low, high]`` (``(low, high]`` with ``low_open``); None: unbounded."""
    def accepts(v: Any) -> bool:
        if not is_finite_number(v):
            return False
        above = low is None or (v > low if low_open else v >= low)
        return above and (high is None or v <= high)

    if low is not None and high is not None:
        expected = f"a number in {'(' if low_open else '['}{low:g}, {high:g}]"
    elif low is not None:
        expected = f"a number {'>' if low_open else '>='} {low:g}"
    elif high is not None:
        expected = f"a number <= {high:g}"
    else:
        expected = "a finite number"
    return Limit(accepts, expected)


def optional(limit: Limit) -> Limit:
    return Limit(lambda v: v is None or limit.accepts(v), f"null or {limit.expected}")


def one_of(*choices: str) -> Limit:
    return Limit(lambda v: v in choices, "one of " + ", ".join(repr(c) for c in choices))


def layer_sizes(allow_empty: bool) -> Limit:
    return Limit(lambda v: isinstance(v, (tuple, list)) and (allow_empty or len(v) > 0)
                 and all(is_integer(x) and x >= 1 for x in v),
                 f"a {'' if allow_empty else 'non-empty '}list of integers >= 1, e.g. [256, 256]")


def ordered_pair(low: float, *, low_open: bool) -> Limit:
    """``[a, b]`` with ``low < a <= b`` (``low <= a`` unless ``low_open``)."""
    first = number(low, low_open=low_open)
    return Limit(lambda v: isinstance(v, (tuple, list)) and len(v) == 2 and all(first.accepts(x) for x in v)
                 and v[0] <= v[1], f"a pair [low, high] of numbers with {'' if low_open else '='}"
                 f"{low:g} {'<' if low_open else '<='} low <= high")


POSITIVE = number(0.0, low_open=True)
NON_NEGATIVE = number(0.0)
FINITE = number()


def config_problems(config: Any, prefix: str = "") -> list[str]:
    """One message per field of ``config`` (and its nested config groups) outside its limits."""
    problems = []
    limits: dict[str, Limit] = getattr(type(config), "LIMITS", {})
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        key = prefix + field.name
        if dataclasses.is_dataclass(value):
            problems += config_problems(value, key + ".")
        elif field.name in limits and not limits[field.name].accepts(value):
            problems.append(f"{key}={json.dumps(value)}: expected {limits[field.name].expected}")
    cross_checks = getattr(config, "cross_checks", None)
    if cross_checks is not None and not problems:
        problems += [prefix + message for message in cross_checks()]
    return problems
