"""The reference methods' runs, published in the repository record by record as a sweep finishes them.

A leaderboard submission needs every core-suite task, and the reference methods' lite runs take
days of CPU. Until a method's submission is complete, and afterwards as the evidence behind it and
behind PROTOCOL.md's tables, the raw evaluation records of its finished runs are kept under
``leaderboard/reference-runs/<budget>/<method>/<task>/<seed label>/`` as ``evaluation.json`` (the
target) and ``evaluation-source.json`` (RL on source's other side), with the learning curve of the
run that trained the policy (``metrics.jsonl``: the target return every evaluation interval, the
evidence a budget is chosen from). That is a sweep's own layout
(``<out>/runs/...``), so every command that reads a sweep reads them unchanged: ``protocol gap``,
``protocol score``, ``protocol claims`` and ``protocol reference oracle``.

Publishing copies the records byte for byte (their sha256 stays the evaluation's) and only records
that score under the protocol: complete, finite, at a protocol budget, in the folder that names
their method, task, seeds and side. Everything is checked before anything is written, and a
published record is never replaced by different bytes unless asked: published numbers do not
change silently. A training seed is published once (per method, task, side and target dataset),
whichever seed folder it comes in: every reader refuses a seed given twice.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from baselines.limits import FINITE
from baselines.run_folder import TrainingCompute, read_training_compute
from leaderboard.assemble import METRICS_FILE, read_evaluation_strict, read_learning_curve
from leaderboard.store import write_file_atomic
from leaderboard.submission import SubmissionError
from offdyn_bench.errors import OffdynError
from offdyn_bench.json_values import is_integer
from offdyn_bench.protocol.claims import NO_DATASET, dataset_label
from offdyn_bench.sweep.runs import EVALUATION_FILE, SOURCE_EVALUATION_FILE, dataset_tag, seed_label

if TYPE_CHECKING:
    from offdyn_bench.protocol.claims import ClaimCheck

REFERENCE_RUNS_DIR = Path(__file__).resolve().parent / "reference-runs"
RECORD_FILES = {EVALUATION_FILE: "target", SOURCE_EVALUATION_FILE: "source"}
"""A run folder's record files and the side each holds (the sweep's names)."""


@dataclasses.dataclass(frozen=True)
class PublishReport:
    written: tuple[Path, ...]
    """Records (and learning curves) new to the destination, or replaced (``replace=True``)."""
    unchanged: tuple[Path, ...]
    """Records (and learning curves) the destination already holds, byte for byte."""
    unfinished: tuple[Path, ...]
    """Run folders of the sweep without a target record yet (training or never started)."""
    compute: tuple[Path, ...] = ()
    """The ``compute.json`` files updated with the published runs' compute (from the sweep's state)."""
    reproduced: tuple[Path, ...] = ()
    """Published records (and curves) the sweep reproduced: other bytes, but only where the run
    ran (its folder, the commands naming it) and, in a curve, its timings differ. The published
    bytes are kept."""


def check_reference_record(path: Path, record: dict[str, Any], method: str, task: str, label: str,
                           side: str) -> None:
    """Raise :class:`SubmissionError` unless ``record`` (read from ``path``) is a complete protocol
    evaluation of ``method`` on ``task``, seeds ``label``, on ``side``."""
    from offdyn_bench.evaluate import SOURCE_SIDE_NOTE
    from offdyn_bench.protocol import EVAL_EPISODES, get_budget

    def fail(what: str) -> SubmissionError:
        return SubmissionError(f"{path}: {what}")

    if record.get("method") != method or record.get("task") != task:
        raise fail(f"holds {record.get('method')!r} on {record.get('task')!r}, but its folder names {method!r} on "
                   f"{task!r}; publish a sweep's runs folder as it is")
    if record.get("side", "target") != side:
        raise fail(f"side {record.get('side')!r}; the file name says {side!r}")
    budget = record.get("budget")
    try:
        get_budget(str(budget))
    except OffdynError:
        raise fail(f"budget {budget!r}; only runs at a protocol budget (lite, full) are reference runs") from None
    # A source-side record is no protocol result by design; it must depart in nothing else.
    notes = [note for note in record.get("notes") or [] if not (side == "source" and note == SOURCE_SIDE_NOTE)]
    if notes or (side == "target" and record.get("protocol_conformant") is not True):
        raise fail(f"not a protocol evaluation ({'; '.join(map(str, notes)) or 'not marked conformant'})")
    seeds = record.get("seeds")
    if not isinstance(seeds, list) or not seeds or not all(isinstance(s, dict) for s in seeds):
        raise fail("no per-seed returns")
    # A folder is ``seed-N``, or ``<dataset tag>.seed-N`` where a sweep ran several datasets.
    tag, _, seeds_named = label.rpartition(".")
    numbers = [s.get("seed") for s in seeds]
    if not all(isinstance(n, int) for n in numbers) or seed_label(sorted(numbers)) != seeds_named:
        raise fail(f"seeds {numbers}; its folder {label!r} names others")
    used = dataset_label(record)
    if tag and (used == NO_DATASET or dataset_tag(used) != tag):
        trained = "on no target dataset" if used == NO_DATASET else f"on dataset {used!r}"
        raise fail(f"trained {trained}; its folder {label!r} names {tag!r}")
    for entry in seeds:
        returns = entry.get("returns")
        if not isinstance(returns, list) or len(returns) < EVAL_EPISODES:
            raise fail(f"seed {entry['seed']}: {len(returns) if isinstance(returns, list) else 'no'} episodes; "
                       f"the protocol scores at least {EVAL_EPISODES}")
        if not all(FINITE.accepts(x) for x in returns):
            raise fail(f"seed {entry['seed']}: a return that is not a finite number")


def check_reference_curve(path: Path, record: dict[str, Any]) -> list[dict[str, Any]]:
    """The learning curve at ``path`` (``step``/``target_return`` points), read once; raise
    :class:`SubmissionError` unless it is the whole curve of the training whose final policy
    ``record`` scores: one finite per-seed target return per evaluation, at strictly increasing
    steps that end at the record's training steps."""
    curve = read_learning_curve(path, len(record["seeds"]))
    steps = [point["step"] for point in curve]
    if not curve or not all(is_integer(step) and step > 0 for step in steps):
        raise SubmissionError(f"{path}: {'no evaluation' if not curve else 'a step that is not a positive integer'}; "
                              "expected the metrics.jsonl `offdyn-bench train` wrote")
    for earlier, later in zip(steps, steps[1:]):
        if later <= earlier:
            raise SubmissionError(f"{path}: step {later} follows step {earlier}; expected one line per evaluation, "
                                  "in order")
    if steps[-1] != record.get("steps"):
        raise SubmissionError(f"{path}: the curve ends at step {steps[-1]}, but the evaluation beside it scores the "
                              f"policy of step {record.get('steps')}; publish the curve of the training it scores")
    for point in curve:
        returns = point["target_return"]
        if not all(FINITE.accepts(x) for x in returns):
            raise SubmissionError(f"{path}: step {point['step']}: a target return that is not a finite number")
    return curve


def publish_reference_runs(sweep_out: Path, dest: Path = REFERENCE_RUNS_DIR, *, methods: Sequence[str] = (),
                           replace: bool = False) -> PublishReport:
    """Copy the finished runs' records of the sweep in ``sweep_out`` (its ``runs/`` folder) into
    ``dest/<budget>/...``; ``methods``: only these (default every method there)."""
    runs = sweep_out / "runs"
    if not runs.is_dir():
        raise SubmissionError(f"{sweep_out}: no runs/ folder; expected the out folder of `offdyn-bench sweep`")
    _check_destination(dest)
    folders = sorted(path for path in runs.glob("*/*/*") if path.is_dir())
    if methods:
        present = {folder.parts[-3] for folder in folders}
        unknown = [method for method in methods if method not in present]
        if unknown:
            raise SubmissionError(f"{sweep_out}: no runs of {', '.join(unknown)}; it has runs of "
                                  f"{', '.join(sorted(present)) or 'no method'}")
        folders = [folder for folder in folders if folder.parts[-3] in methods]
    plan: list[tuple[Path, Path, bytes]] = []
    records: list[tuple[Path, Path, dict[str, Any]]] = []  # (source, destination, record) of each record file
    unfinished = []
    trained: dict[str, TrainingCompute] = {}
    for folder in folders:
        method, task, label = folder.parts[-3:]
        if not (folder / EVALUATION_FILE).exists():
            unfinished.append(folder)
            continue
        for name, side in RECORD_FILES.items():
            path = folder / name
            if not path.exists():
                continue
            record = read_evaluation_strict(path)
            check_reference_record(path, record, method, task, label, side)
            if side == "target":
                spent = read_training_compute(folder)
                if spent is not None:
                    trained[f"{method}/{task}/{label}"] = spent
            if side == "target" and (folder / METRICS_FILE).exists():
                # The curve first: the folder's evaluation, written last, marks it complete.
                curve_path = folder / METRICS_FILE
                check_reference_curve(curve_path, record)
                plan.append((curve_path, dest / str(record["budget"]) / method / task / label / METRICS_FILE,
                             curve_path.read_bytes()))
            plan.append((path, dest / str(record["budget"]) / method / task / label / name, path.read_bytes()))
            records.append((path, plan[-1][1], record))
    if not plan:
        raise SubmissionError(f"{sweep_out}: no finished run to publish ({len(unfinished)} unfinished)")
    _refuse_seeds_published_twice(records, dest)
    written, unchanged, reproduced, conflicts = [], [], [], []
    for source, target, data in plan:
        if target.exists():
            published = target.read_bytes()
            if published == data:
                unchanged.append(target)
                continue
            if not replace and _reproduces(published, data, curve=target.name == METRICS_FILE):
                reproduced.append(target)
                continue
            if not replace:
                conflicts.append(f"{target} (from {source})")
                continue
        written.append(target)
    if conflicts:
        raise SubmissionError(f"{len(conflicts)} published record(s) differ from the sweep's: {conflicts[0]}"
                              + (f" and {len(conflicts) - 1} more" if len(conflicts) > 1 else "")
                              + "; published numbers change only with --replace")
    # The compute files are prepared before anything is written: a bad state file changes nothing.
    compute = _compute_documents(_sweep_state(sweep_out) or {}, trained, [target for _, target, _ in plan])
    data_of = {target: data for _, target, data in plan}
    try:
        for target in written:
            write_file_atomic(target, data_of[target])
        for path, document in compute.items():
            write_file_atomic(path, (json.dumps(document, indent=1) + "\n").encode())
    except OSError as error:
        # Each file is whole or absent (atomic renames); publishing again finishes the job.
        raise SubmissionError(f"{dest}: writing failed ({error.strerror or error}: {error.filename}); every "
                              "file written is complete, and publishing again writes the rest") from None
    return PublishReport(tuple(written), tuple(unchanged), tuple(unfinished), tuple(compute), tuple(reproduced))


def _refuse_seeds_published_twice(records: Sequence[tuple[Path, Path, dict[str, Any]]], dest: Path) -> None:
    """Refuse a record whose training seed is published, or about to be, in another seed folder of
    the same method, task, side and target dataset (``seed-0`` beside a GPU lease's ``seeds-0-4``):
    every reader of the published runs counts a seed once and refuses one given twice."""
    holder: dict[tuple[str, str, str, str, str, int], Path] = {}

    def claim(path: Path, record: dict[str, Any], side: str, source: Path | None = None) -> None:
        for entry in record["seeds"]:
            key = (str(record["budget"]), str(record["method"]), str(record["task"]), side, dataset_label(record),
                   entry["seed"])
            other = holder.setdefault(key, path)
            if other.parent != path.parent:
                where = f"{path}" + (f" (from {source})" if source is not None else "")
                raise SubmissionError(
                    f"{where} would publish training seed {entry['seed']} of {record['method']} on "
                    f"{record['task']} ({side} side, trained on {dataset_label(record)}), which {other} holds "
                    "already: a seed is published once, or every score would count it twice. Publish the "
                    "sweep's other runs with --method, or take the older folder out of the published tree "
                    "(git rm -r) first if this run is to replace it")

    touched = {(target.relative_to(dest).parts[:3]) for _, target, _ in records}
    for budget, method, task in sorted(touched):
        for path, side in published_record_files(dest / budget / method / task):
            claim(path, read_published_record(dest / budget, path), side)
    for source, target, record in records:
        if not target.exists():  # a published one was claimed above, under its own path
            claim(target, record, RECORD_FILES[target.name], source)


# Where a run ran, not what it measured: a record's own command and its training's (both name the
# run's folder), the machines of its evaluation and training, the code revisions and dates they ran
# at, and the agent's folder; a curve line's timings.
_RECORD_LOCATION_FIELDS = ("command", "train_command", "machine", "training_machines", "source_revision",
                           "training_provenance")
_CURVE_TIMING_FIELDS = ("wall_time_s", "cpu_time_s")


def _reproduces(published: bytes, new: bytes, *, curve: bool) -> bool:
    """Whether ``new`` is the same measurement as ``published``, run elsewhere: equal once the
    fields that only say where (and, for a curve, how fast) it ran are left out. Every number,
    policy hash, seed and version must be the same."""
    try:
        if curve:
            old_lines, new_lines = published.decode().splitlines(), new.decode().splitlines()
            return len(old_lines) == len(new_lines) and all(
                _without(json.loads(a), _CURVE_TIMING_FIELDS) == _without(json.loads(b), _CURVE_TIMING_FIELDS)
                for a, b in zip(old_lines, new_lines))
        return _record_without_location(json.loads(published)) == _record_without_location(json.loads(new))
    except (UnicodeDecodeError, ValueError, TypeError):
        return False


def _without(document: Any, fields: Sequence[str]) -> Any:
    if not isinstance(document, dict):
        return document
    return {key: value for key, value in document.items() if key not in fields}


def _record_without_location(record: Any) -> Any:
    record = _without(record, _RECORD_LOCATION_FIELDS)
    if isinstance(record, dict) and isinstance(record.get("agent"), dict):
        record = record | {"agent": _without(record["agent"], ("path",))}
    return record


COMPUTE_FILE = "compute.json"
_ATTEMPT_FIELDS = ("attempt", "ok", "stage", "started_at", "wall_time_s", "cpu_time_s", "host")


def _check_destination(dest: Path) -> None:
    """Refuse a destination that cannot hold folders, before anything is read or written."""
    existing = next((path for path in (dest, *dest.parents) if path.exists()), None)
    if existing is not None and not existing.is_dir():
        raise SubmissionError(f"--to {dest}: {existing} is a file; expected a folder (or a path to create one)")
    if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        raise SubmissionError(f"--to {dest}: {existing} is not writable by this user")


def _sweep_state(sweep_out: Path) -> dict[str, Any] | None:
    """The run records of the sweep's state file (``sweep.json``); None where there is none (runs
    made without a sweep)."""
    state_path = sweep_out / "sweep.json"
    if not state_path.exists():
        return None
    try:
        runs = json.loads(state_path.read_text())["runs"]
        if not isinstance(runs, dict):
            raise TypeError("its runs are not a mapping")
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as error:
        raise SubmissionError(f"{state_path}: not a sweep state file ({error!s}); nothing was published") from None
    return runs


def _compute_documents(runs: dict[str, Any], trained: dict[str, TrainingCompute],
                       published: Sequence[Path]) -> dict[Path, dict[str, Any]]:
    """Per budget folder, its ``compute.json`` updated with the published runs: per run (keyed
    ``method/task/seeds``), the compute its attempts took as the sweep's state file holds it, and
    under ``training`` what the training itself counted over all its attempts (carried in its
    checkpoints, so resumes lose nothing). A run that scores another run's policy (RL on source on
    a second task) shows its evaluations only; the training is the other run's."""
    by_budget: dict[Path, dict[str, Any]] = {}
    for target in published:
        budget_dir = target.parents[3]
        run_id = "/".join(target.parent.relative_to(budget_dir).parts)
        record = runs.get(run_id)
        entry: dict[str, Any] = {}
        # Found finished (its records restored or made by an earlier sweep whose state is gone), a
        # run has no attempts in this state: the sweep measured nothing, and zeros would be false.
        if (isinstance(record, dict) and record.get("status") == "done"
                and (record.get("attempts") or record.get("history"))):
            history = [{key: attempt.get(key) for key in _ATTEMPT_FIELDS}
                       for attempt in record.get("history") or [] if isinstance(attempt, dict)]
            entry = {"attempts_started": record.get("attempts"), "wall_time_s": record.get("wall_time_s"),
                     "cpu_time_s": record.get("cpu_time_s"), "recorded_attempts": history}
        if run_id in trained:
            entry["training"] = trained[run_id].to_dict()
        if entry:
            by_budget.setdefault(budget_dir, {})[run_id] = entry
    documents = {}
    for budget_dir, entries in sorted(by_budget.items()):
        path = budget_dir / COMPUTE_FILE
        stored = read_published_compute(budget_dir)
        documents[path] = {
            "format": "offdyn-bench/reference-compute", "format_version": 1,
            "note": "Per run, from the sweep's state file: wall and CPU time summed over the attempts it recorded "
                    "(an attempt cut short by a killed sweep has no outcome and is not counted). `training`, "
                    "where present: the training's own count over all its attempts, each up to the checkpoint "
                    "the next resumed from (carried in the checkpoints); `complete` is false when an attempt "
                    "before the count began is missing.",
            # A run's entry is updated, not replaced: a training count found later keeps the sweep's.
            "runs": dict(sorted((stored | {run_id: stored.get(run_id, {}) | entry
                                           for run_id, entry in entries.items()}).items()))}
    return documents


def read_published_compute(budget_dir: Path) -> dict[str, dict[str, Any]]:
    """The per-run entries of ``budget_dir``'s ``compute.json`` (empty where there is none yet)."""
    path = budget_dir / COMPUTE_FILE
    if not path.exists():
        return {}
    try:
        runs = json.loads(path.read_text())["runs"]
        if not isinstance(runs, dict) or not all(isinstance(entry, dict) for entry in runs.values()):
            raise TypeError("its runs are not a mapping of run entries")
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as error:
        raise SubmissionError(f"{path}: unreadable ({error}); move it away to record compute anew") from None
    return runs


@dataclasses.dataclass(frozen=True)
class ReferenceProgress:
    """One task's published reference runs at one budget: RL on source on both sides (its gap,
    against the oracle reference) and the oracle runs (RL on target)."""

    task: str
    rl_on_source: Any | None
    """The task's :class:`offdyn_bench.protocol.gap.TaskGap` for ``sac-source``; None: no runs yet."""
    oracle_seed_means: tuple[float, ...]
    """Per published ``sac-target`` seed, its mean target return."""
    in_core_suite: bool = True
    """False for a candidate: a pair outside the core suite whose runs are published to test it."""

    @property
    def admission(self) -> Any | None:
        """The core suite's same-budget test on the published runs
        (:class:`offdyn_bench.protocol.gap.Admission`); None without RL-on-source runs."""
        from offdyn_bench.protocol.gap import admit

        return admit(self.rl_on_source) if self.rl_on_source is not None else None


def require_published_root(root: Path) -> None:
    """Refuse a ``root`` of published reference runs that is not a folder."""
    if not root.is_dir():
        raise SubmissionError(f"{root}: not a folder; expected published reference runs "
                              "(<budget>/<method>/<task>/<seeds>/evaluation.json, as publish-runs writes them)")


def _published_budgets(root: Path) -> list[Path]:
    """The budget folders of published reference runs under ``root``, which must be a folder."""
    require_published_root(root)
    return sorted(path for path in root.glob("*") if path.is_dir())


def published_record_files(task_dir: Path, label: str = "*") -> list[tuple[Path, str]]:
    """(path, side) of each record file under a published ``<budget>/<method>/<task>`` folder, seed
    folder by seed folder, or in the one seed folder ``label`` ([] where there is none)."""
    return [(path, RECORD_FILES[path.name]) for path in sorted(task_dir.glob(f"{label}/evaluation*.json"))
            if path.name in RECORD_FILES]


def read_published_record(budget_dir: Path, path: Path) -> dict[str, Any]:
    """A published record, checked again where it is read: a hand edit is refused, not rendered."""
    method, task, label, name = path.relative_to(budget_dir).parts
    record = read_evaluation_strict(path)
    check_reference_record(path, record, method, task, label, RECORD_FILES[name])
    return record


def reference_progress(root: Path = REFERENCE_RUNS_DIR, *, references: Path | None = None
                       ) -> dict[str, list[ReferenceProgress]]:
    """Per budget published under ``root``, a row for every core-suite task (empty where nothing is
    published yet): what the reference submissions will hold, as far as it exists; then a row for
    every other task with published runs, a candidate for the core suite."""
    from offdyn_bench.protocol import CORE_SUITE
    from offdyn_bench.protocol.gap import measure_gaps
    from offdyn_bench.protocol.scoring import seed_means

    progress = {}
    for budget_dir in _published_budgets(root):
        source_records = [read_published_record(budget_dir, path) for path in sorted(budget_dir.glob("sac-source/*/*/evaluation*.json"))
                          if path.name in RECORD_FILES]
        oracle_records = [read_published_record(budget_dir, path)
                          for path in sorted(budget_dir.glob(f"sac-target/*/*/{EVALUATION_FILE}"))]
        # The oracle runs are a candidate's oracle where the reference file records none, as in
        # `protocol admission`: the board's test is the command's, on the same records.
        gaps = {gap.task: gap for gap in measure_gaps(source_records + oracle_records,
                                                      str(references) if references else None)} \
            if source_records else {}
        oracle: dict[str, list[float]] = {}
        for record in oracle_records:
            oracle.setdefault(record["task"], []).extend(seed_means(record).values())
        candidates = sorted((set(gaps) | set(oracle)) - set(CORE_SUITE))
        progress[budget_dir.name] = [ReferenceProgress(task, gaps.get(task), tuple(oracle.get(task, ())),
                                                       in_core_suite=task in CORE_SUITE)
                                     for task in (*CORE_SUITE, *candidates)]
    return progress


def reference_claims(root: Path = REFERENCE_RUNS_DIR) -> dict[str, list[ClaimCheck]]:
    """Per budget published under ``root``, the papers' headline claims checked on its target
    records (:func:`offdyn_bench.protocol.claims.check_claims`, as ``protocol claims`` does): a row
    wherever both methods of a claim have published runs on one task; budgets with none are left out."""
    from offdyn_bench.protocol.claims import check_claims

    claims = {}
    for budget_dir in _published_budgets(root):
        records = [read_published_record(budget_dir, path) for path in sorted(budget_dir.glob(f"*/*/*/{EVALUATION_FILE}"))]
        checks = check_claims(records) if records else []
        if checks:
            claims[budget_dir.name] = checks
    return claims
