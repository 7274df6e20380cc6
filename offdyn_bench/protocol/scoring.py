"""From raw evaluation records to normalized scores and aggregates.

Scores are always recomputed from raw per-episode returns: a training seed's score is the
normalized mean of its episodes' returns, and a method's score matrix is ``(seeds, tasks)``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, TypeVar

import numpy as np

from offdyn_bench.protocol.definition import ProtocolError
from offdyn_bench.protocol.references import normalize, reference_pair

Key = TypeVar("Key", bound=tuple[str, ...])


@dataclasses.dataclass(frozen=True)
class MethodScores:
    """One method's results on a set of tasks at one budget."""

    method: str
    tasks: tuple[str, ...]
    seeds: tuple[int, ...]
    raw: np.ndarray
    """Per-seed mean target return, ``(seeds, tasks)``."""
    normalized: np.ndarray | None
    """``raw`` normalized per task against the references; None when a task lacks them."""
    missing_references: tuple[str, ...]


def seed_means(record: Mapping[str, Any]) -> dict[int, float]:
    """A record's per-seed mean return (the unit the statistics resample)."""
    out = {}
    for entry in record["seeds"]:
        returns = np.asarray(entry["returns"], dtype=np.float64)
        if returns.size == 0 or not np.all(np.isfinite(returns)):
            raise ProtocolError(f"{record.get('method')} on {record.get('task')}: seed {entry['seed']} has no "
                                "returns or non-finite ones")
        out[int(entry["seed"])] = float(returns.mean())
    return out


def merge_seed_means(into: dict[int, float], record: Mapping[str, Any], method: str, where: str) -> None:
    """Add ``record``'s per-seed mean returns to ``into`` (one method, task, ...: ``where``): a
    task's seeds may come in several records, but a seed already there is refused."""
    means = seed_means(record)
    twice = sorted(set(means) & set(into))
    if twice:
        raise ProtocolError(f"{method}: training seed(s) {twice} {where} are in two evaluations; pass each "
                            "seed's evaluation once")
    into.update(means)


def group_seed_means(records: Sequence[Mapping[str, Any]], key_of: Callable[[Mapping[str, Any], str], Key],
                     where_of: Callable[[Key], str]) -> dict[Key, dict[int, float]]:
    """Check each evaluation record and merge its per-seed means under ``key_of(record, where)``
    (a tuple whose first item is the method; ``key_of`` may refuse a record, naming ``where``),
    with :func:`merge_seed_means`: a seed twice under one key is refused, said with ``where_of(key)``."""
    from offdyn_bench.evaluate import check_evaluation_record

    out: dict[Key, dict[int, float]] = {}
    for i, record in enumerate(records):
        where = f"evaluation {i + 1}" if not isinstance(record, Mapping) else \
            f"the evaluation of {record.get('method')!r} on {record.get('task')!r}"
        check_evaluation_record(record, where)
        key = key_of(record, where)
        merge_seed_means(out.setdefault(key, {}), record, key[0], where_of(key))
    return out


def single_budget(records: Iterable[Mapping[str, Any]], purpose: str) -> str:
    """The one budget of ``records`` (``"None"`` when unset); mixed budgets are refused."""
    budgets = sorted({str(r.get("budget")) for r in records})
    if len(budgets) > 1:
        raise ProtocolError(f"the evaluations mix budgets {budgets}; {purpose} one budget at a time")
    return budgets[0]


def method_scores(method: str, records: Iterable[Mapping[str, Any]], budget: str | None,
                  tasks: Sequence[str] | None = None,
                  reference_file: str | None = None,
                  references: Mapping[str, tuple[float, float]] | None = None) -> MethodScores:
    """Collect ``method``'s records into score matrices, normalized against the reference file at
    ``budget``, or against explicit ``references`` (task -> (J_random, J_oracle)), e.g. a demo's
    own oracle run at a budget of its own. A task's seeds may come in several records (one run
    folder per seed, as a sweep makes them); a seed in two of them is refused."""
    by_task: dict[str, dict[int, float]] = {}
    for record in records:
        if record.get("side", "target") != "target":
            # Scored against the target's references, source returns would pass for target ones.
            raise ProtocolError(f"{method} on {record['task']}: a {record.get('side')}-side evaluation (the "
                                "source-target gap); scores are of target returns: pass target-side records, and "
                                "give both sides to `offdyn-bench protocol gap`")
        merge_seed_means(by_task.setdefault(record["task"], {}), record, method, f"of task {record['task']!r}")
    tasks = tuple(tasks) if tasks is not None else tuple(sorted(by_task))
    absent = [t for t in tasks if t not in by_task]
    if absent:
        raise ProtocolError(f"{method}: no evaluation of {', '.join(absent)}")
    seeds = tuple(sorted(by_task[tasks[0]]))
    for task in tasks:
        if tuple(sorted(by_task[task])) != seeds:
            raise ProtocolError(f"{method}: task {task!r} has seeds {sorted(by_task[task])}, task {tasks[0]!r} "
                                f"has {list(seeds)}; every task needs the same training seeds")
    raw = np.array([[by_task[t][s] for t in tasks] for s in seeds], dtype=np.float64)
    missing = []
    normalized = np.empty_like(raw)
    for j, task in enumerate(tasks):
        if references is not None:
            if task not in references:
                missing.append(task)
                continue
            j_random, j_oracle = references[task]
        elif budget is None:
            missing.append(task)
            continue
        else:
            try:
                j_random, j_oracle = reference_pair(task, budget, reference_file)
            except ProtocolError:
                missing.append(task)
                continue
        normalized[:, j] = normalize(raw[:, j], j_random, j_oracle)
    return MethodScores(method, tasks, seeds, raw, None if missing else normalized, tuple(missing))
