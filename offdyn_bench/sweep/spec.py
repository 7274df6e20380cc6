"""A sweep spec: the file ``offdyn-bench sweep`` reads (YAML or JSON), checked key by key.

Every problem is one line naming the file, the key and what was expected; nothing about the
methods, tasks or tracks is looked up here (that needs the algorithm registry, which imports
torch): :mod:`offdyn_bench.sweep.runs` does it when it expands the spec into runs.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from offdyn_bench.errors import OffdynError
from offdyn_bench.json_values import is_finite_number, is_integer
from offdyn_bench.protocol.definition import TRACKS

CORE = "core"
"""``tasks: core`` stands for the protocol's core suite."""
DEFAULT_MAX_RETRIES = 2


class SpecError(OffdynError):
    """A sweep spec that cannot be run as written."""


@dataclasses.dataclass(frozen=True)
class TrainingOptions:
    """``offdyn-bench train`` options that do not change what a run is scored on."""

    eval_every: int | None = None
    """Steps between in-training target evaluations (the trainer's default: steps / 20)."""
    eval_episodes: int | None = None
    """Target episodes per in-training evaluation (the trainer's default: 10)."""
    checkpoint_every: int | None = None
    """Steps between checkpoints (the trainer's default: steps / 10): what a killed run loses at most."""


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """What to run (methods x tasks x seeds, one track, one budget) and how (retries, resources)."""

    source: str
    """Where the spec came from (its path), for messages."""
    methods: tuple[str, ...]
    tasks: tuple[str, ...] | str
    """Task names, or :data:`CORE` for the protocol's core suite."""
    seeds: tuple[int, ...]
    track: str
    budget: str | None
    """``lite`` or ``full`` (a protocol budget); None when ``steps`` is given instead."""
    steps: int | None
    """Explicit training steps (tiny test sweeps); the evaluations then say they are no protocol result."""
    out: Path
    seeds_per_run: int = 1
    """Consecutive seeds trained together in one run (``--n-seeds``): 1 isolates every seed; more
    trains several seeds at the cost of one on a GPU."""
    device: str = "cpu"
    dataset: str | None = None
    """``--dataset`` for methods that need target data (default: the track's official dataset)."""
    datasets: tuple[str, ...] = ()
    """Target dataset qualities (``medium``, ``medium-replay``, ...): each method that needs target
    data runs once per quality on every task, on that task's dataset of it (the H2O paper's Table 1
    grid); the run's folder names the dataset (``medium-replay-v0.seed-0``). Empty: one dataset."""
    evaluation_episodes: int = 20
    training: TrainingOptions = TrainingOptions()
    overrides: Mapping[str, Mapping[str, str]] = dataclasses.field(default_factory=dict)
    """Per method, ``--set key=value`` overrides of its config."""
    max_retries: int = DEFAULT_MAX_RETRIES
    """Attempts after the first one before a run is reported as failed."""
    cpus_per_run: float = 1.0
    gpus_per_run: float = 0.0
    ray_address: str | None = None
    """Ray cluster to join (``auto``, ``ray://host:10001``, ...); None starts a local Ray instance."""

    def to_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["out"] = str(self.out)
        data["overrides"] = {method: dict(values) for method, values in self.overrides.items()}
        return json.loads(json.dumps(data))  # JSON-ready: tuples become lists


_KEYS = ("methods", "tasks", "seeds", "track", "budget", "steps", "out", "seeds_per_run", "device", "dataset",
         "datasets", "evaluation_episodes", "training", "overrides", "max_retries", "cpus_per_run", "gpus_per_run",
         "ray_address")
_REQUIRED = ("methods", "tasks", "seeds", "track", "out")
_TRAINING_KEYS = tuple(field.name for field in dataclasses.fields(TrainingOptions))
_MAX_SEEDS = 1000


def load_spec(path: str | Path, *, out: Path | None = None) -> SweepSpec:
    """Read and check the spec file at ``path`` (``.json``: JSON; anything else: YAML). ``out``
    replaces the spec's output root. Relative paths in the spec are taken from the current folder."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise SpecError(f"cannot read sweep spec {str(path)!r}: {error.strerror or error}") from None
    except UnicodeDecodeError:
        raise SpecError(f"sweep spec {str(path)!r} is not text; expected a YAML or JSON file") from None
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise SpecError(f"{path}: not valid JSON (line {error.lineno}, column {error.colno}: {error.msg})") from None
    else:
        import yaml

        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as error:
            mark = getattr(error, "problem_mark", None)
            where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
            problem = getattr(error, "problem", None) or str(error).splitlines()[0]
            raise SpecError(f"{path}: not valid YAML ({where}{problem})") from None
    return parse_spec(data, source=str(path), out=out)


def parse_spec(data: Any, *, source: str = "sweep spec", out: Path | None = None) -> SweepSpec:
    """Check a spec given as data (the parsed file) and return it."""
    if not isinstance(data, dict):
        raise SpecError(f"{source}: expected a mapping of keys ({', '.join(_REQUIRED)}, ...), "
                        f"got {type(data).__name__}")
    unknown = [key for key in data if key not in _KEYS]
    if unknown:
        import difflib

        close = difflib.get_close_matches(str(unknown[0]), _KEYS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise SpecError(f"{source}: unknown key {unknown[0]!r}{hint}; valid keys: {', '.join(_KEYS)}")
    if out is not None:
        data = {**data, "out": str(out)}
    missing = [key for key in _REQUIRED if data.get(key) is None]
    if missing:
        raise SpecError(f"{source}: missing key {missing[0]!r}; a spec names {', '.join(_REQUIRED)} and one of "
                        "budget (lite|full) or steps")

    def fail(key: str, expected: str) -> SpecError:
        return SpecError(f"{source}: {key}: got {_show(data_at(key))}; expected {expected}")

    def data_at(key: str) -> Any:
        value: Any = data
        for part in key.split("."):
            value = value.get(part) if isinstance(value, dict) else None
        return value

    def distinct_names(key: str, expected: str, each: str) -> list[str]:
        """``key``'s value as a list of distinct non-empty names (one name alone is a list of one)."""
        names = data[key]
        if isinstance(names, str):
            names = [names]
        if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
            raise fail(key, expected)
        if len(set(names)) != len(names):
            raise fail(key, f"each {each} once")
        return names

    methods = distinct_names("methods", "a non-empty list of method names, e.g. [sac-source, dap]", "method")
    tasks = data["tasks"]
    if tasks != CORE:
        tasks = distinct_names("tasks", f"{CORE!r} (the protocol's core suite) or a non-empty list of task names",
                               "task")

    seeds_value = data["seeds"]
    if is_integer(seeds_value):
        if not 1 <= seeds_value <= _MAX_SEEDS:
            raise fail("seeds", f"a count in [1, {_MAX_SEEDS}] (seeds 0..count-1) or a list of seeds")
        seeds = tuple(range(seeds_value))
    elif isinstance(seeds_value, list) and seeds_value and all(is_integer(s) and s >= 0 for s in seeds_value):
        if len(set(seeds_value)) != len(seeds_value):
            raise fail("seeds", "distinct seeds")
        if len(seeds_value) > _MAX_SEEDS:
            raise fail("seeds", f"at most {_MAX_SEEDS} seeds")
        seeds = tuple(sorted(seeds_value))
    else:
        raise fail("seeds", "a count >= 1 (seeds 0..count-1) or a non-empty list of non-negative integers")

    track = data["track"]
    if not isinstance(track, str):
        raise fail("track", "a track name: " + ", ".join(TRACKS))

    budget, steps = data.get("budget"), data.get("steps")
    if (budget is None) == (steps is None):
        raise SpecError(f"{source}: give exactly one of budget (lite|full, the protocol's) and steps "
                        "(explicit training steps, e.g. for a tiny test sweep)")
    if budget is not None and not isinstance(budget, str):
        raise fail("budget", "a protocol budget name: lite or full")
    if steps is not None and not (is_integer(steps) and steps >= 1):
        raise fail("steps", "an integer >= 1")

    out_value = data["out"]
    if not isinstance(out_value, str) or not out_value:
        raise fail("out", "a folder path (the sweep's output root)")

    seeds_per_run = _int_key(data, "seeds_per_run", 1, 1, _MAX_SEEDS, fail)
    device = data.get("device", "cpu")
    if not isinstance(device, str) or not device:
        raise fail("device", "cpu, cuda, cuda:N or auto")
    dataset = data.get("dataset")
    if dataset is not None and (not isinstance(dataset, str) or not dataset):
        raise fail("dataset", "a dataset for methods that need target data: collect:random:N, an .npz path or a "
                              "Minari id (leave it out for the track's official dataset)")
    if dataset is not None:
        dataset = _absolute_dataset(dataset)
    datasets = data.get("datasets")
    if datasets is not None:
        datasets = distinct_names("datasets", "a non-empty list of dataset qualities, e.g. [medium, medium-replay, "
                                              "medium-expert]", "quality")
        if dataset is not None:
            raise SpecError(f"{source}: give at most one of dataset (one dataset for every run) and datasets "
                            "(a run per dataset quality)")
    evaluation_episodes = _int_key(data, "evaluation_episodes", 20, 1, 1000, fail)

    training_data = data.get("training") or {}
    if not isinstance(training_data, dict):
        raise fail("training", f"a mapping with any of {', '.join(_TRAINING_KEYS)}")
    for key in training_data:
        if key not in _TRAINING_KEYS:
            raise SpecError(f"{source}: training: unknown key {key!r}; valid keys: {', '.join(_TRAINING_KEYS)}")
    training = TrainingOptions(**{key: _int_key(training_data, key, None, 1, 10**9,
                                                lambda k, e: fail(f"training.{k}", e))
                                  for key in _TRAINING_KEYS})

    overrides_data = data.get("overrides") or {}
    if not isinstance(overrides_data, dict):
        raise fail("overrides", "a mapping from method to {setting: value}, e.g. {dap: {sac.batch_size: 128}}")
    overrides: dict[str, dict[str, str]] = {}
    for method, values in overrides_data.items():
        if method not in methods:
            raise SpecError(f"{source}: overrides: {method!r} is not one of the sweep's methods "
                            f"({', '.join(methods)})")
        if not isinstance(values, dict) or not all(isinstance(k, str) and k for k in values):
            raise fail(f"overrides.{method}", "a mapping from setting to value, e.g. {sac.batch_size: 128}")
        overrides[method] = {key: _setting_text(value) for key, value in values.items()}

    max_retries = _int_key(data, "max_retries", DEFAULT_MAX_RETRIES, 0, 100, fail)
    cpus_per_run = _number_key(data, "cpus_per_run", 1.0, False, fail)
    gpus_per_run = _number_key(data, "gpus_per_run", 0.0, True, fail)
    ray_address = data.get("ray_address")
    if ray_address is not None and (not isinstance(ray_address, str) or not ray_address):
        raise fail("ray_address", "a Ray address (auto, host:port or ray://host:10001), or nothing for a local "
                                  "Ray instance")
    if gpus_per_run > 0 and device == "cpu":
        raise SpecError(f"{source}: gpus_per_run is {gpus_per_run:g} but device is 'cpu'; set device: cuda "
                        "(or auto), or gpus_per_run: 0")

    return SweepSpec(source=source, methods=tuple(methods), tasks=CORE if tasks == CORE else tuple(tasks),
                     # Absolute: the runs' commands execute in other processes, and under Ray in other
                     # working folders (on a cluster, out must be on a filesystem every node shares).
                     seeds=seeds, track=track, budget=budget, steps=steps, out=Path(out_value).absolute(),
                     seeds_per_run=seeds_per_run, device=device, dataset=dataset,
                     datasets=tuple(datasets or ()),
                     evaluation_episodes=evaluation_episodes, training=training, overrides=overrides,
                     max_retries=max_retries, cpus_per_run=cpus_per_run, gpus_per_run=gpus_per_run,
                     ray_address=ray_address)


def _show(value: Any) -> str:
    text = json.dumps(value) if isinstance(value, (dict, list, str, int, float, bool, type(None))) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _int_key(data: Mapping[str, Any], key: str, default: int | None, low: int, high: int, fail: Any) -> Any:
    value = data.get(key)
    if value is None:
        return default
    if not is_integer(value) or not low <= value <= high:
        raise fail(key, f"an integer in [{low}, {high}]")
    return value


def _number_key(data: Mapping[str, Any], key: str, default: float, zero_ok: bool, fail: Any) -> float:
    value = data.get(key)
    if value is None:
        return default
    if not is_finite_number(value) or value < 0 or (value == 0 and not zero_ok):
        raise fail(key, "a number >= 0" if zero_ok else "a number > 0 (CPUs a run needs, e.g. 1 or 0.5)")
    return float(value)


def _setting_text(value: Any) -> str:
    """A spec value as the text ``--set key=value`` takes (the trainer parses it as JSON)."""
    return value if isinstance(value, str) else json.dumps(value)


def _absolute_dataset(dataset: str) -> str:
    """``dataset`` with its file or run folder made absolute (``collect:<run folder>:N``, an
    ``.npz`` path), like ``out``: runs execute in other working folders under Ray."""
    prefix = "collect:"
    if dataset.startswith(prefix):
        source, sep, size = dataset[len(prefix):].rpartition(":")
        if sep and source and source != "random":
            return f"{prefix}{Path(source).absolute()}:{size}"
        return dataset
    return str(Path(dataset).absolute()) if dataset.endswith(".npz") else dataset
