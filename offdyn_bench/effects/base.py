"""The effect base class and the registry of effect kinds.

An effect is everything that makes one system differ from another: a frozen, JSON-serializable
dataclass with a stable ``kind``, an optional ``target`` (a MuJoCo name, an observation index, or
``None`` for all) and validated parameters. The same effects define task targets, build candidate
models during gap diagnosis and describe a calibrated simulator.
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

from offdyn_bench.errors import InvalidParameterError, OffdynError, UnknownNameError

EffectFamily = Literal["model", "channel"]
TargetType = Literal["global", "body", "geom_or_body", "joint", "actuator", "observation"]

EFFECT_KINDS: dict[str, type[Effect]] = {}


@dataclasses.dataclass(frozen=True)
class Interval:
    """The plausible values of a numeric parameter; anything outside is refused at construction.

    The bounds are finite on purpose: a parameter of 1e9 steps or a scale of 1e300 is never an
    experiment, only an allocation or an overflow waiting to happen somewhere downstream.
    """

    low: float
    high: float
    low_open: bool = False
    high_open: bool = False
    integer: bool = False
    unit: str = ""

    def __str__(self) -> str:
        return f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"

    def describe(self) -> str:
        """``a number in [0, 10]`` / ``an integer in [0, 1000]``: the end of an error message."""
        return f"{'an integer' if self.integer else 'a number'} in {self}"

    def document(self) -> str:
        """``[0, 10] (x nominal)``: the range as the docs print it."""
        return f"{self}{f' {self.unit}' if self.unit else ''}"

    def normalize(self, value: object) -> int | float | None:
        """``value`` as a plain Python number if it lies in the range, else ``None``."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return None
        if self.integer:
            if not isinstance(value, numbers.Integral):
                return None
            number: int | float = int(value)
        else:
            # Python ints compare exactly with float bounds, however large; numpy scalars become
            # plain numbers so the effect stays JSON-serializable.
            number = value if isinstance(value, int) else float(value)
        too_low = number <= self.low if self.low_open else not number >= self.low  # NaN fails both
        too_high = number >= self.high if self.high_open else not number <= self.high
        return None if too_low or too_high else number


@dataclasses.dataclass(frozen=True)
class OneOf:
    """A parameter that takes one of a few names."""

    options: tuple[str, ...]

    def describe(self) -> str:
        return f"one of {sorted(self.options)}"

    def document(self) -> str:
        return " / ".join(f"`{o}`" for o in self.options)

    def normalize(self, value: object) -> str | None:
        return value if isinstance(value, str) and value in self.options else None


ParameterRange = Interval | OneOf


class _Shown:
    """A value too long to quote whole in a one-line error."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __repr__(self) -> str:
        return self.text


def _shown(value: object) -> object:
    try:
        text = repr(value)
    except ValueError:  # an int beyond Python's digit limit for str()
        return _Shown(f"<an integer of {int(value).bit_length()} bits>")  # type: ignore[call-overload]
    return value if len(text) <= 80 else _Shown(text[:60] + "...")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Effect:
    """Base of every effect. Subclasses declare ``kind`` and their parameters as fields.

    ``value_field`` names the parameter reported as the effect's ``value`` (a scale, a threshold,
    a number of steps): gap diagnosis fits and reports that one. ``ranges`` gives every parameter
    its plausible values; construction refuses anything outside them (and the class docstring
    lists them).
    """

    kind: ClassVar[str]
    family: ClassVar[EffectFamily]
    target_type: ClassVar[TargetType]
    value_field: ClassVar[str]
    ranges: ClassVar[Mapping[str, ParameterRange]] = {}

    target: str | int | None = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        kind = cls.__dict__.get("kind")
        if kind is None:  # an abstract family class
            return
        if kind in EFFECT_KINDS:
            raise RuntimeError(f"effect kind {kind!r} registered twice")
        EFFECT_KINDS[kind] = cls
        if cls.ranges and cls.__doc__:
            listed = "; ".join(f"``{name}`` in {r.document()}" for name, r in cls.ranges.items())
            cls.__doc__ = cls.__doc__.rstrip() + f"\n\n    Parameters: {listed}.\n"

    def __post_init__(self) -> None:
        if self.target is not None:
            if self.target_type == "global":
                self._invalid("target", self.target, "None: this effect acts on the whole model")
            if self.target_type == "observation":
                if (isinstance(self.target, bool) or not isinstance(self.target, numbers.Integral)
                        or self.target < 0):
                    self._invalid("target", self.target, "a non-negative observation index or None")
                object.__setattr__(self, "target", int(self.target))
            elif not isinstance(self.target, str) or not self.target:
                self._invalid("target", self.target, f"a {self.target_type.replace('_', ' ')} name or None")
        for name, allowed in self.ranges.items():
            value = allowed.normalize(getattr(self, name))
            if value is None:
                self._invalid(name, getattr(self, name), allowed.describe())
            object.__setattr__(self, name, value)
        self.validate()

    # --- parameters -------------------------------------------------------------------------
    def validate(self) -> None:
        """Checks beyond each parameter's range (e.g. ``dmin <= dmax``); raise
        :class:`InvalidParameterError` naming the bad parameter."""

    @property
    def primary_value(self) -> Any:
        """The parameter named by ``value_field``: what diagnosis reports as ``value``."""
        return getattr(self, self.value_field)

    def parameters(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "target"}

    def _invalid(self, parameter: str, value: object, expected: str) -> None:
        raise InvalidParameterError(f"effect {self.kind!r}", parameter, _shown(value), expected)

    # --- serialization ----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """``{"kind": ..., "target": ..., <parameters>}``: JSON-serializable, round-trips."""
        out: dict[str, Any] = {"kind": self.kind, "target": self.target}
        for name, value in self.parameters().items():
            out[name] = list(value) if isinstance(value, tuple) else value
        return out

    @staticmethod
    def from_dict(data: Mapping[str, Any] | Effect) -> Effect:
        """Build an effect from its dict form; unknown kinds and parameters are named in the error."""
        if isinstance(data, Effect):
            return data
        if not isinstance(data, Mapping) or "kind" not in data:
            raise OffdynError(f"an effect must be a mapping with a 'kind' key, got {_shown(data)!r}")
        kind = data["kind"]
        cls = EFFECT_KINDS.get(kind) if isinstance(kind, str) else None
        if cls is None:
            raise UnknownNameError("effect kind", _shown(kind), EFFECT_KINDS)
        names = {f.name: f for f in dataclasses.fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key == "kind":
                continue
            if key not in names:
                raise UnknownNameError(f"parameter of effect {kind!r}", _shown(key), names)
            if isinstance(value, list):
                value = tuple(value)
            kwargs[key] = value
        missing = [n for n, f in names.items() if n not in kwargs and f.default is dataclasses.MISSING]
        if missing:
            raise OffdynError(f"effect {kind!r} is missing parameter(s) {missing}")
        return cls(**kwargs)

    def describe(self) -> str:
        """One line a person reads, e.g. ``gear x0.7 on thigh_joint``."""
        where = "all" if self.target is None else (
            f"obs[{self.target}]" if self.target_type == "observation" else str(self.target))
        params = ", ".join(f"{k}={v}" for k, v in self.parameters().items())
        return f"{self.kind}({params}) on {where}"


def effects_from_dicts(items: Any) -> tuple[Effect, ...]:
    """Normalize a sequence of effects or their dict forms."""
    if items is None:
        return ()
    if isinstance(items, (Mapping, Effect, str)):
        raise OffdynError(f"expected a list of effects, got a single {type(items).__name__}")
    return tuple(Effect.from_dict(item) for item in items)


def effects_to_dicts(effects: Any) -> list[dict[str, Any]]:
    return [e.to_dict() for e in effects_from_dicts(effects)]
