"""The effect base class and the registry of effect kinds.

An effect is everything that makes one system differ from another: a frozen, JSON-serializable
dataclass with a stable ``kind``, an optional ``target`` (a MuJoCo name, an observation index, or
``None`` for all) and validated parameters. The same effects define task targets, build candidate
models during gap diagnosis and describe a calibrated simulator.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

from offdyn_bench.errors import InvalidParameterError, OffdynError, UnknownNameError

EffectFamily = Literal["model", "channel"]
TargetType = Literal["global", "body", "geom_or_body", "joint", "actuator", "observation"]

EFFECT_KINDS: dict[str, type[Effect]] = {}


@dataclasses.dataclass(frozen=True, kw_only=True)
class Effect:
    """Base of every effect. Subclasses declare ``kind`` and their parameters as fields.

    ``value_field`` names the parameter reported as the effect's ``value`` (a scale, a threshold,
    a number of steps): gap diagnosis fits and reports that one.
    """

    kind: ClassVar[str]
    family: ClassVar[EffectFamily]
    target_type: ClassVar[TargetType]
    value_field: ClassVar[str]

    target: str | int | None = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        kind = cls.__dict__.get("kind")
        if kind is None:  # an abstract family class
            return
        if kind in EFFECT_KINDS:
            raise RuntimeError(f"effect kind {kind!r} registered twice")
        EFFECT_KINDS[kind] = cls

    def __post_init__(self) -> None:
        if self.target is not None:
            if self.target_type == "global":
                self._invalid("target", self.target, "None: this effect acts on the whole model")
            if self.target_type == "observation":
                if isinstance(self.target, bool) or not isinstance(self.target, int) or self.target < 0:
                    self._invalid("target", self.target, "a non-negative observation index or None")
            elif not isinstance(self.target, str) or not self.target:
                self._invalid("target", self.target, f"a {self.target_type.replace('_', ' ')} name or None")
        self.validate()

    # --- parameters -------------------------------------------------------------------------
    def validate(self) -> None:
        """Check the parameters; raise :class:`InvalidParameterError` naming the bad one."""

    @property
    def primary_value(self) -> Any:
        """The parameter named by ``value_field``: what diagnosis reports as ``value``."""
        return getattr(self, self.value_field)

    def parameters(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "target"}

    def _invalid(self, parameter: str, value: object, expected: str) -> None:
        raise InvalidParameterError(f"effect {self.kind!r}", parameter, value, expected)

    def _require_finite(self, name: str, *, low: float | None = None, high: float | None = None,
                        low_open: bool = False, high_open: bool = False) -> None:
        value = getattr(self, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self._invalid(name, value, "a finite number")
        too_low = low is not None and (value <= low if low_open else value < low)
        too_high = high is not None and (value >= high if high_open else value > high)
        if too_low or too_high:
            left = "(" if low_open else "["
            right = ")" if high_open else "]"
            lo = "-inf" if low is None else f"{low:g}"
            hi = "inf" if high is None else f"{high:g}"
            self._invalid(name, value, f"a number in {left}{lo}, {hi}{right}")

    def _require_steps(self, name: str) -> None:
        value = getattr(self, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            self._invalid(name, value, "an integer number of control steps >= 0")

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
            raise OffdynError(f"an effect must be a mapping with a 'kind' key, got {data!r}")
        kind = data["kind"]
        cls = EFFECT_KINDS.get(kind)
        if cls is None:
            raise UnknownNameError("effect kind", kind, EFFECT_KINDS)
        names = {f.name: f for f in dataclasses.fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key == "kind":
                continue
            if key not in names:
                raise UnknownNameError(f"parameter of effect {kind!r}", key, names)
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
