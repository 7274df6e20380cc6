"""A leaderboard submission: strict parsing, the published schema and the protocol's rules.

One function, :func:`validate_submission`, decides what the leaderboard accepts; the CLI, the store
test and the server all call it. A submission carries raw returns only: the schema forbids any
other field, so a submitted score can never reach the board (scores are recomputed in
``leaderboard.scores``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from offdyn_bench.errors import OffdynError

SCHEMA_PATH = Path(__file__).resolve().parent / "schema" / "submission-v1.json"
SUBMISSION_FORMAT = "offdyn-bench/submission"
SUBMISSION_FORMAT_VERSION = 1
MAX_SUBMISSION_BYTES = 8 * 1024 * 1024
"""Largest submission file or request body: 100 seeds x 1000 episodes of every core task and
full learning curves fit well below it."""

_MAX_MESSAGE_CHARS = 300


class SubmissionError(OffdynError):
    """A submission (or the run folders it is assembled from) the leaderboard does not accept."""


@dataclasses.dataclass(frozen=True)
class CurvePoint:
    step: int
    target_return: tuple[float, ...]
    """Mean in-training target return of each training seed, in the task's seed order."""


@dataclasses.dataclass(frozen=True)
class TaskResult:
    task: str
    seeds: tuple[int, ...]
    returns: np.ndarray
    """Target returns, shape ``(len(seeds), EVAL_EPISODES)``."""
    learning_curve: tuple[CurvePoint, ...]


@dataclasses.dataclass(frozen=True)
class Submission:
    method: str
    description: str
    code_url: str | None
    commit: str | None
    track: str
    budget: str
    protocol_version: str
    versions: Mapping[str, str | None]
    tasks: Mapping[str, TaskResult]
    document: Mapping[str, Any]
    """The validated JSON document, exactly what the store writes (canonically formatted)."""

    @property
    def key(self) -> tuple[str, str, str]:
        """What makes a submission unique on the board: one entry per method, track and budget."""
        return (self.method, self.track, self.budget)

    @property
    def file_name(self) -> str:
        return submission_file_name(self.method, self.track, self.budget)


def submission_file_name(method: str, track: str, budget: str) -> str:
    """``<method>__<track>__<budget>.json``. Only call with validated names: the schema keeps the
    method name to ``[a-z0-9][a-z0-9._+-]*``, so the result cannot leave the store directory."""
    return f"{method}__{track}__{budget}.json"


@functools.cache
def submission_schema() -> dict[str, Any]:
    """The published JSON Schema (draft 2020-12) of format version 1."""
    return json.loads(SCHEMA_PATH.read_text())


def _reject_constant(source: str, name: str) -> Any:
    raise SubmissionError(f"{source}: {name} is not valid JSON; every return must be a finite number")


def _no_duplicate_keys(source: str, pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    document: dict[str, Any] = {}
    for key, value in pairs:
        if key in document:
            raise SubmissionError(f"{source}: key {key!r} appears twice in one JSON object; expected unique keys")
        document[key] = value
    return document


def parse_json_strict(data: bytes | str, *, source: str, max_bytes: int = MAX_SUBMISSION_BYTES) -> Any:
    """Parse JSON as the standard defines it: no NaN/Infinity tokens, no repeated keys, bounded size."""
    size = len(data.encode() if isinstance(data, str) else data)
    if size > max_bytes:
        raise SubmissionError(f"{source}: {size} bytes; a submission holds at most {max_bytes} bytes")
    try:
        text = data.decode("utf-8") if isinstance(data, bytes) else data
        return json.loads(text, parse_constant=functools.partial(_reject_constant, source),
                          object_pairs_hook=functools.partial(_no_duplicate_keys, source))
    except UnicodeDecodeError:
        raise SubmissionError(f"{source}: not UTF-8 text; expected a JSON document") from None
    except json.JSONDecodeError as error:
        raise SubmissionError(f"{source}: not valid JSON: {error.msg} at line {error.lineno} "
                              f"column {error.colno}") from None
    except RecursionError:
        raise SubmissionError(f"{source}: JSON nested too deeply; expected a submission document") from None


def read_submission_file(path: Path) -> Submission:
    """Read and validate one submission file."""
    try:
        size = path.stat().st_size
        if size > MAX_SUBMISSION_BYTES:
            raise SubmissionError(f"{path}: {size} bytes; a submission holds at most {MAX_SUBMISSION_BYTES} bytes")
        data = path.read_bytes()
    except OSError as error:
        raise SubmissionError(f"cannot read submission {path}: {error.strerror}") from None
    return validate_submission(parse_json_strict(data, source=str(path)), source=str(path))


def _json_path(parts: Any) -> str:
    text = "$"
    for part in parts:
        text += f"[{part}]" if isinstance(part, int) else f".{part}"
    return text


def _short(message: str) -> str:
    return message if len(message) <= _MAX_MESSAGE_CHARS else message[:_MAX_MESSAGE_CHARS] + "..."


def _first_non_finite(value: Any, path: tuple[Any, ...] = ()) -> tuple[tuple[Any, ...], float] | None:
    # Python's json (and a caller building the dict in Python) accepts NaN and infinities; the
    # schema's minimum/maximum do not catch NaN (every comparison with it is false).
    if isinstance(value, float) and not math.isfinite(value):
        return path, value
    if isinstance(value, dict):
        items: Any = value.items()
    elif isinstance(value, list):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = _first_non_finite(item, (*path, key))
        if found is not None:
            return found
    return None


def _check_schema(document: Any, source: str) -> None:
    import jsonschema

    validator = jsonschema.Draft202012Validator(submission_schema())
    error = jsonschema.exceptions.best_match(validator.iter_errors(document))
    if error is None:
        return
    where = _json_path(error.absolute_path)
    message = error.message
    # jsonschema quotes the offending value in full; a long one would bury what was wrong.
    shown = repr(error.instance)
    if len(shown) > 60:
        message = message.replace(shown, shown[:40] + "...")
    if error.validator == "pattern" and "description" in error.schema:
        message += f"; expected: {error.schema['description']}"
    if error.validator == "additionalProperties" and "score" in message.lower():
        message += "; a submission carries raw returns only, the leaderboard computes every score itself"
    raise SubmissionError(_short(f"{source}: {where}: {message} (schema {SCHEMA_PATH.name})"))


def validate_submission(document: Any, *, source: str = "submission") -> Submission:
    """Check ``document`` against the schema and the protocol; return it as a :class:`Submission`.

    Raises :class:`SubmissionError` with one line that names the offending field and what was
    expected. Reads the protocol (core suite, seeds, episodes) at call time.
    """
    from offdyn_bench import protocol
    from offdyn_bench.tasks import TASKS
    from offdyn_bench.versions import PINNED_MUJOCO

    if not isinstance(document, dict):
        raise SubmissionError(f"{source}: expected a JSON object (a submission), got {type(document).__name__}")
    non_finite = _first_non_finite(document)
    if non_finite is not None:
        where, value = non_finite
        raise SubmissionError(f"{source}: {_json_path(where)} is {value}; every return must be a finite number")
    _check_schema(document, source)

    if document["protocol_version"] != protocol.PROTOCOL_VERSION:
        raise SubmissionError(f"{source}: protocol_version {document['protocol_version']!r}; this leaderboard "
                              f"scores protocol {protocol.PROTOCOL_VERSION!r} (re-evaluate with the current suite)")
    for field, known in (("track", protocol.TRACKS), ("budget", protocol.BUDGETS)):
        if document[field] not in known:
            raise SubmissionError(f"{source}: unknown {field} {document[field]!r}; expected one of "
                                  + ", ".join(repr(k) for k in sorted(known)))
    mujoco_version = document["versions"]["mujoco"]
    if mujoco_version != PINNED_MUJOCO:
        raise SubmissionError(f"{source}: measured with MuJoCo {mujoco_version}; the protocol pins MuJoCo "
                              f"{PINNED_MUJOCO} (returns from another version are not comparable)")

    core = tuple(protocol.CORE_SUITE)
    submitted = document["tasks"]
    unknown = sorted(set(submitted) - set(core))
    if unknown:
        raise SubmissionError(f"{source}: task {unknown[0]!r} is not in the core suite of protocol "
                              f"{protocol.PROTOCOL_VERSION}; expected exactly: {', '.join(core)}")
    missing = [task for task in core if task not in submitted]
    if missing:
        raise SubmissionError(f"{source}: missing core-suite task(s) {', '.join(missing)}; a submission holds "
                              f"every task of the core suite ({len(core)} tasks)")

    results: dict[str, TaskResult] = {}
    first_seeds: tuple[str, tuple[int, ...]] | None = None
    for task in core:
        entry = submitted[task]
        where = f"{source}: $.tasks.{task}"
        pair = TASKS.get(task)
        if pair is not None:
            if entry["task_version"] != pair.version:
                raise SubmissionError(f"{where}.task_version is {entry['task_version']}; the suite's {task} is "
                                      f"version {pair.version}")
            if entry["target_env_id"] != pair.env_id("target"):
                raise SubmissionError(f"{where}.target_env_id is {entry['target_env_id']!r}; expected "
                                      f"{pair.env_id('target')!r}")
        if tuple(entry["episode_seeds"]) != tuple(protocol.EPISODE_SEEDS):
            raise SubmissionError(f"{where}.episode_seeds differ from the protocol's {len(protocol.EPISODE_SEEDS)} "
                                  f"episode seeds {protocol.EPISODE_SEEDS[0]}..{protocol.EPISODE_SEEDS[-1]}")
        seeds = tuple(int(s["seed"]) for s in entry["seeds"])
        if len(seeds) < protocol.MIN_SEEDS:
            raise SubmissionError(f"{where} has {len(seeds)} training seed(s); the protocol asks for at least "
                                  f"{protocol.MIN_SEEDS}")
        if len(set(seeds)) != len(seeds):
            raise SubmissionError(f"{where}.seeds repeats a seed ({sorted(seeds)}); expected distinct training seeds")
        if first_seeds is None:
            first_seeds = (task, seeds)
        elif seeds != first_seeds[1]:
            raise SubmissionError(f"{where}.seeds are {list(seeds)}; every task must list the same training "
                                  f"seeds in the same order ({first_seeds[0]} has {list(first_seeds[1])})")
        for index, seed_entry in enumerate(entry["seeds"]):
            count = len(seed_entry["returns"])
            if count != protocol.EVAL_EPISODES:
                raise SubmissionError(f"{where}.seeds[{index}] (seed {seed_entry['seed']}) has {count} returns; "
                                      f"the protocol evaluates exactly {protocol.EVAL_EPISODES} episodes per seed")
        curve = tuple(CurvePoint(int(p["step"]), tuple(float(x) for x in p["target_return"]))
                      for p in entry.get("learning_curve", ()))
        for index, point in enumerate(curve):
            if len(point.target_return) != len(seeds):
                raise SubmissionError(f"{where}.learning_curve[{index}] has {len(point.target_return)} values; "
                                      f"expected one per training seed ({len(seeds)})")
            if index and point.step <= curve[index - 1].step:
                raise SubmissionError(f"{where}.learning_curve[{index}].step {point.step} does not increase; "
                                      "expected points in training-step order")
        returns = np.array([s["returns"] for s in entry["seeds"]], dtype=np.float64)
        results[task] = TaskResult(task=task, seeds=seeds, returns=returns, learning_curve=curve)

    method = document["method"]
    return Submission(method=method["name"], description=method["description"],
                      code_url=method.get("code_url"), commit=method.get("commit"),
                      track=document["track"], budget=document["budget"],
                      protocol_version=document["protocol_version"], versions=dict(document["versions"]),
                      tasks=results, document=document)


def canonical_json(document: Mapping[str, Any]) -> bytes:
    """The bytes the store keeps: sorted keys, one indentation, no NaN (same document, same bytes)."""
    return (json.dumps(document, indent=1, sort_keys=True, allow_nan=False, ensure_ascii=False) + "\n").encode()
