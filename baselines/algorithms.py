"""The algorithm registry: CLI name -> default config, builder, and what it needs.

Also turns ``key=value`` overrides (``sac.batch_size=64``, ``target_data=online``) into a config,
with errors that name the closest valid fields, and checks every value against its limits
(:mod:`baselines.limits`) so a bad value fails before a run writes anything.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any

from baselines import cql, dap, dara, darc, h2o, h2o_offline_source, matl, online_sac
from baselines.method import Method, MethodContext
from baselines.limits import config_problems
from offdyn_bench.errors import InvalidParameterError, OffdynError, UnknownNameError
from offdyn_bench.json_values import is_integer, is_number


@dataclasses.dataclass(frozen=True)
class Algorithm:
    name: str
    description: str
    default_config: Callable[[], Any]
    build: Callable[[Any, MethodContext], Method]
    needs_dataset: bool
    track: str
    """"reference" (SAC on source or target) or one of the protocol's tracks (``offline-target``,
    ``online-target``, ``offline-source-offline-target``, ``offline-source-online-target``)."""
    needs_source_dataset: bool = False
    """Trains on a fixed source dataset instead of the source simulator (the offline-source tracks)."""
    source_only: bool = False
    """Training reads nothing of the target: the in-training target evaluations draw from streams of
    their own, so runs with the same seeds and config on tasks that share a source simulator
    (:attr:`offdyn_bench.tasks.TaskPair.source_key`) train the same policy, bit for bit. ``evaluate``
    then scores one such run on every task of its source, and a sweep trains it once."""


ALGORITHMS: Mapping[str, Algorithm] = MappingProxyType({a.name: a for a in [
    Algorithm("sac-source", "RL on source: SAC in the source simulator (behaviour policy for datasets)",
              online_sac.Config, online_sac.build_source, needs_dataset=False, track="reference", source_only=True),
    Algorithm("sac-target", "RL on target: SAC in the target (the oracle for normalized scores)",
              online_sac.Config, online_sac.build_target, needs_dataset=False, track="reference"),
    Algorithm("cql", "CQL on the target dataset only (offline)",
              cql.Config, cql.build, needs_dataset=True, track="offline-target"),
    Algorithm("darc", "DARC with the fixed target dataset (offline-target)",
              darc.Config, darc.build, needs_dataset=True, track="offline-target"),
    Algorithm("darc-online", "DARC with the paper's settings, one target step per ten source steps (online-target)",
              lambda: darc.Config(target_data="online"), darc.build, needs_dataset=False, track="online-target"),
    Algorithm("h2o", "H2O: dynamics-aware hybrid offline (target dataset) and online (source) RL",
              h2o.Config, h2o.build, needs_dataset=True, track="offline-target"),
    Algorithm("dap", "DAP: dual action policy",
              dap.Config, dap.build, needs_dataset=True, track="offline-target"),
    Algorithm("dap-u", "DAP+U: DAP with uncertainty-based robust action resampling",
              dap.dap_u_config, dap.build, needs_dataset=True, track="offline-target"),
    Algorithm("matl", "MATL: simulator and robot TRPO agents aligned by a discriminator (online-target)",
              matl.default_config("matl"), matl.BUILDERS["matl"], needs_dataset=False, track="online-target"),
    Algorithm("matl-u", "MATL-U: MATL with the robot's auxiliary reward only (unilateral alignment)",
              matl.default_config("matl-u"), matl.BUILDERS["matl-u"], needs_dataset=False, track="online-target"),
    Algorithm("matl-f", "MATL-F: MATL starting from a fully trained simulator policy (--set init_run=DIR)",
              matl.default_config("matl-f"), matl.BUILDERS["matl-f"], needs_dataset=False, track="online-target"),
    Algorithm("independent", "TRPO on the robot alone with its target steps (MATL's reference point)",
              matl.default_config("independent"), matl.BUILDERS["independent"], needs_dataset=False,
              track="online-target"),
    Algorithm("direct-transfer", "TRPO in the source, deployed in the target (MATL's reference point)",
              matl.default_config("direct-transfer"), matl.BUILDERS["direct-transfer"], needs_dataset=False,
              track="online-target"),
    Algorithm("fine-tuning", "TRPO fine-tuning of a trained simulator policy on the robot (--set init_run=DIR)",
              matl.default_config("fine-tuning"), matl.BUILDERS["fine-tuning"], needs_dataset=False,
              track="online-target"),
    Algorithm("dara", "DARA: DARC's classifier reward correction on the source dataset, then CQL on source + "
                      "target datasets (offline-source-offline-target)",
              dara.Config, dara.build, needs_dataset=True, track="offline-source-offline-target",
              needs_source_dataset=True),
    Algorithm("h2o-offline-source", "H2O with the source dataset offline and one target step per ten updates "
                                    "(offline-source-online-target)",
              h2o_offline_source.Config, h2o_offline_source.build, needs_dataset=False,
              track="offline-source-online-target", needs_source_dataset=True),
]})


def get_algorithm(name: str) -> Algorithm:
    if name not in ALGORITHMS:
        raise UnknownNameError("algorithm", name, ALGORITHMS)
    return ALGORITHMS[name]


def config_to_dict(config: Any) -> dict[str, Any]:
    """A JSON-ready dict (tuples become lists)."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


def apply_overrides(config: Any, overrides: Mapping[str, str], algo: str) -> Any:
    """Set ``a.b=value`` fields of a (nested) config dataclass; values are parsed as JSON when they
    parse, else taken as strings, then checked against the field's type and limits."""
    for key, raw in overrides.items():
        owner, path = config, key.split(".")
        for part in path[:-1]:
            owner = _field_value(config, owner, part, key, algo)
            if not dataclasses.is_dataclass(owner):
                raise InvalidParameterError(algo, key, raw, f"{part!r} is not a group of settings")
        name = path[-1]
        current = _field_value(config, owner, name, key, algo)
        if dataclasses.is_dataclass(current):
            raise InvalidParameterError(algo, key, raw, "one setting of the group, e.g. " + _setting_names(current, key + ".")[0])
        setattr(owner, name, _parse(raw, current, key, algo))
    check_config(config, algo)
    return config


EXECUTION_SETTINGS = frozenset({"cuda_graph"})
"""Settings that choose how an update runs, not what it computes (a CUDA-graph replay computes the
eager update's numbers, :mod:`baselines.sac`): runs that differ only in these are the same run."""


def overrides_of(algo: str, config: Mapping[str, Any]) -> dict[str, str]:
    """The ``--set key=value`` settings that turn ``algo``'s default config into ``config`` (a
    run's ``config.json`` ``config``): every leaf that differs from this version's default, with
    nested groups flattened (``sac.batch_size``) and values as JSON, so that ``apply_overrides``
    on the default config gives ``config`` back."""
    default = config_to_dict(get_algorithm(algo).default_config())

    def differing(stored: Mapping[str, Any], expected: Mapping[str, Any], prefix: str) -> dict[str, str]:
        found: dict[str, str] = {}
        for name, value in stored.items():
            base = expected.get(name)
            if isinstance(value, Mapping) and isinstance(base, Mapping):
                found |= differing(value, base, f"{prefix}{name}.")
            elif json.dumps(value, sort_keys=True) != json.dumps(base, sort_keys=True) or name not in expected:
                found[prefix + name] = value if isinstance(value, str) else json.dumps(value)
        return found

    return differing(config, default, "")


def check_config(config: Any, algo: str) -> None:
    """Raise one error listing every value of ``config`` outside its limits."""
    problems = config_problems(config)
    if problems:
        raise OffdynError(f"{algo}: invalid setting " + "; invalid setting ".join(problems))


def _setting_names(config: Any, prefix: str = "") -> list[str]:
    """Every settable key of a config, nested groups flattened (``sac.batch_size``)."""
    names = []
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        names += _setting_names(value, f"{prefix}{field.name}.") if dataclasses.is_dataclass(value) \
            else [prefix + field.name]
    return names


def _field_value(root: Any, owner: Any, name: str, key: str, algo: str) -> Any:
    if name not in [f.name for f in dataclasses.fields(owner)]:
        # Suggest among all keys, so "batch_size" finds "sac.batch_size".
        raise UnknownNameError(f"setting of {algo}", key, _setting_names(root))
    return getattr(owner, name)


def _parse(raw: str, current: Any, key: str, algo: str) -> Any:
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    if isinstance(current, bool):
        ok = isinstance(value, bool)
    elif isinstance(current, int):
        ok = is_integer(value)
    elif isinstance(current, float):
        ok = is_number(value)
        value = float(value) if ok else value
    elif isinstance(current, tuple):
        ok = isinstance(value, list)
        value = tuple(value) if ok else value
    elif current is None:
        ok = value is None or isinstance(value, (int, float))
    else:
        ok = isinstance(value, type(current))
    if not ok:
        raise InvalidParameterError(algo, key, raw, f"a value like {json.dumps(current)!s}")
    return value


def config_overrides(data: Mapping[str, Any]) -> dict[str, str]:
    """:func:`config_to_dict` output as ``key=value`` overrides (``sac.batch_size`` -> ``"256"``):
    every value, so a run rebuilt from them cannot drift with a changed default."""
    flat: dict[str, str] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, Mapping):
            for k, v in value.items():
                walk(f"{prefix}{k}.", v)
        else:
            flat[prefix[:-1]] = json.dumps(value)

    walk("", dict(data))
    return flat
