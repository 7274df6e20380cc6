"""``offdyn-bench leaderboard submit``: one submission from the ``evaluation.json`` files of a runs folder.

``offdyn-bench evaluate`` writes an ``evaluation.json`` into every run folder it scores; ``train``
writes the learning curve next to it (``metrics.jsonl``). This module gathers one evaluation per
core-suite task, checks that they were measured alike (protocol, track, budget, versions, method)
and returns the submission document, validated.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from leaderboard.submission import (
    SUBMISSION_FORMAT,
    SUBMISSION_FORMAT_VERSION,
    Submission,
    SubmissionError,
    parse_json_strict,
    validate_submission,
)
from offdyn_bench.errors import OffdynError

EVALUATION_FILE = "evaluation.json"
METRICS_FILE = "metrics.jsonl"
EVALUATION_FORMAT = "offdyn-bench/evaluation"
EVALUATION_FORMAT_VERSION = 1
_REQUIRED_EVALUATION_KEYS = ("protocol_version", "task", "task_version", "target_env_id", "track", "budget",
                             "method", "episode_seeds", "seeds", "versions")
_SHARED_FIELDS = ("protocol_version", "track", "budget", "method", "versions")
"""Fields every evaluation of one submission must agree on."""


def read_evaluation_strict(path: Path) -> dict[str, Any]:
    """The ``offdyn-bench evaluate`` record at ``path``, parsed as strictly as a submission (NaN and
    duplicate keys refused; ``offdyn_bench.evaluate.read_evaluation`` is the lenient reader)."""
    try:
        document = parse_json_strict(path.read_bytes(), source=str(path))
    except OSError as error:
        raise SubmissionError(f"cannot read {path}: {error.strerror}") from None
    if not isinstance(document, dict) or document.get("format") != EVALUATION_FORMAT:
        raise SubmissionError(f"{path}: not an offdyn-bench evaluation (expected \"format\": "
                              f"\"{EVALUATION_FORMAT}\", as `offdyn-bench evaluate` writes)")
    if document.get("format_version") != EVALUATION_FORMAT_VERSION:
        raise SubmissionError(f"{path}: evaluation format_version {document.get('format_version')!r}; this "
                              f"suite reads version {EVALUATION_FORMAT_VERSION}")
    missing = [key for key in _REQUIRED_EVALUATION_KEYS if key not in document]
    if missing:
        raise SubmissionError(f"{path}: evaluation lacks {', '.join(missing)}; re-run `offdyn-bench evaluate`")
    return document


def read_learning_curve(path: Path, seed_count: int | None) -> list[dict[str, Any]]:
    """The ``step``/``target_return`` pairs of a ``metrics.jsonl`` (baselines/train.py writes them);
    ``seed_count``: the per-seed values every line must hold (None: as many as the first line)."""
    curve = []
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise SubmissionError(f"cannot read {path}: {error}") from None
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        record = parse_json_strict(line, source=f"{path}:{number}")
        if not isinstance(record, dict) or "step" not in record or "target_return" not in record:
            raise SubmissionError(f"{path}:{number}: expected an object with \"step\" and \"target_return\" "
                                  "(the metrics.jsonl of `offdyn-bench train`)")
        returns = record["target_return"]
        if seed_count is None and isinstance(returns, list):
            seed_count = len(returns)
        if not isinstance(returns, list) or len(returns) != seed_count:
            raise SubmissionError(f"{path}:{number}: target_return has "
                                  f"{len(returns) if isinstance(returns, list) else 'no'} per-seed values; the "
                                  f"evaluation next to it has {seed_count} seeds (pass --no-learning-curves to "
                                  "submit without curves)")
        curve.append({"step": record["step"], "target_return": returns})
    return curve


def merged_learning_curve(paths: Sequence[Path], seed_counts: Sequence[int | None]) -> list[dict[str, Any]] | None:
    """The learning curves of several runs' ``metrics.jsonl`` (``seed_counts`` seeds each), their
    seeds side by side in the given order; None when a run has no curve or the runs were evaluated
    at different steps (their curves cannot be put side by side)."""
    if not all(path.is_file() for path in paths):
        return None
    curves = [read_learning_curve(path, count) for path, count in zip(paths, seed_counts, strict=True)]
    if len({tuple(point["step"] for point in curve) for curve in curves}) != 1:
        return None
    return [{"step": point["step"], "target_return": [x for curve in curves for x in curve[index]["target_return"]]}
            for index, point in enumerate(curves[0])]


def _describe_difference(field: str, values: Mapping[Path, Any]) -> str:
    by_value: dict[str, list[Path]] = {}
    for path, value in values.items():
        by_value.setdefault(repr(value), []).append(path)
    parts = [f"{value} in {paths[0]}" + (f" and {len(paths) - 1} more" if len(paths) > 1 else "")
             for value, paths in sorted(by_value.items())]
    return f"the evaluations disagree on {field}: " + "; ".join(parts) + \
        "; a submission gathers evaluations made alike (one suite install, one track, one budget, one method)"


def _dataset_reference(provenance: Any) -> dict[str, str] | None:
    """The submission's view of a run's dataset provenance: the Minari id and the data's sha256."""
    if not isinstance(provenance, dict):
        return None
    ident = provenance.get("id") or provenance.get("dataset_id")
    return {"id": ident, "sha256": provenance.get("sha256")}


def _tasks_outside_core_suite(evaluations: Mapping[Path, Mapping[str, Any]]) -> dict[str, list[Path]]:
    """The registered tasks outside the core suite that ``evaluations`` (path: record) score, each
    with its records' paths. A name that is no registered task is not among them: it is an error
    wherever it appears, never something to leave out."""
    from offdyn_bench import protocol
    from offdyn_bench.tasks import TASKS

    outside: dict[str, list[Path]] = {}
    for path, evaluation in evaluations.items():
        task = evaluation.get("task")
        if isinstance(task, str) and task in TASKS and task not in protocol.CORE_SUITE:
            outside.setdefault(task, []).append(path)
    return outside


def assemble_submission(runs_dir: Path, *, method: str, description: str = "", code_url: str | None = None,
                        commit: str | None = None, track: str | None = None, budget: str | None = None,
                        learning_curves: bool = True, merge_seeds: bool = False,
                        core_suite_only: bool = False, echo: Callable[[str], None] | None = None) -> Submission:
    """The validated submission of the ``evaluation.json`` files under ``runs_dir`` (one per task;
    ``merge_seeds``: or one per training seed, as a sweep and ``leaderboard/reference-runs`` keep
    them, each task's merged into one after checking they were evaluated alike).
    ``core_suite_only``: leave out evaluations of registered tasks outside the core suite (a sweep
    that also screened candidate tasks) instead of refusing them, each named to ``echo``."""
    from offdyn_bench import protocol

    if not runs_dir.is_dir():
        raise SubmissionError(f"runs folder {runs_dir} does not exist; expected a folder of evaluated runs")
    paths = sorted(runs_dir.rglob(EVALUATION_FILE))
    if not paths:
        raise SubmissionError(f"no {EVALUATION_FILE} under {runs_dir}; run `offdyn-bench evaluate` on each "
                              "run folder first")
    evaluations = {path: read_evaluation_strict(path) for path in paths}
    if core_suite_only:
        outside = _tasks_outside_core_suite(evaluations)
        for task, task_paths in sorted(outside.items()):
            if echo is not None:
                echo(f"left out {task} ({len(task_paths)} evaluation(s)): not in the core suite")
        evaluations = {path: evaluation for path, evaluation in evaluations.items()
                       if evaluation["task"] not in outside}
        if not evaluations:
            raise SubmissionError(f"no evaluation of a core-suite task under {runs_dir} (only of "
                                  f"{', '.join(sorted(outside))})")

    for path, evaluation in evaluations.items():
        # `evaluate` says itself when a record is no protocol result (the source side, another
        # budget or dataset, fewer episodes): such a record never reaches the board.
        if evaluation.get("side", "target") != "target":
            raise SubmissionError(f"{path} evaluates the {evaluation.get('side')} side; the board takes target "
                                  "evaluations only")
        if evaluation.get("protocol_conformant") is False:
            reasons = "; ".join(str(note) for note in evaluation.get("notes") or []) or "see its notes"
            raise SubmissionError(f"{path} is not a protocol result: {reasons}")

    paths_of: dict[str, list[Path]] = {}
    for path, evaluation in evaluations.items():
        paths_of.setdefault(evaluation["task"], []).append(path)
    for task, task_paths in paths_of.items():
        if len(task_paths) > 1 and not merge_seeds:
            raise SubmissionError(f"two evaluations of {task}: {task_paths[0]} and {task_paths[1]}; keep one per "
                                  "task, or pass --merge-seeds where they are separate training seeds of one "
                                  "method (a sweep's run folders, leaderboard/reference-runs)")
    by_task = {task: task_paths[0] for task, task_paths in paths_of.items()}
    for field in _SHARED_FIELDS:
        values = {path: evaluation[field] for path, evaluation in evaluations.items()}
        if len({repr(v) for v in values.values()}) > 1:
            raise SubmissionError(_describe_difference(field, values))
    first = next(iter(evaluations.values()))
    for option, field in ((track, "track"), (budget, "budget")):
        if field == "track" and first[field] is None:
            # A reference point (sac-source, sac-target) belongs on no track of its own: it is
            # submitted beside the track named here.
            if option is None:
                raise SubmissionError(f"the evaluations under {runs_dir} name no track (a reference method); "
                                      "pass --track with the track they are submitted beside, e.g. "
                                      "--track offline-target")
            continue
        if option is not None and option != first[field]:
            raise SubmissionError(f"--{field} {option} but the evaluations under {runs_dir} were made on "
                                  f"{field} {first[field]!r}")

    core = tuple(protocol.CORE_SUITE)
    extra = sorted(set(by_task) - set(core))
    if extra:
        from offdyn_bench.tasks import TASKS

        registered = any(task in TASKS for task in extra)
        hint = "; pass --core-suite-only to leave out the tasks evaluated beside it" if registered else ""
        raise SubmissionError(f"{by_task[extra[0]]} evaluates {extra[0]}, which is not in the core suite; "
                              f"a submission holds exactly the core suite ({', '.join(core)}){hint}")
    missing = [task for task in core if task not in by_task]
    if missing:
        raise SubmissionError(f"no evaluation of {', '.join(missing)} under {runs_dir} "
                              f"({len(by_task)} of {len(core)} core-suite tasks found); evaluate every core task")

    tasks: dict[str, Any] = {}
    for task in core:
        path = by_task[task]
        evaluation = evaluations[path]
        # One training seed per record (a sweep's layout): in seed order, merged as the sweep merges them.
        task_paths = sorted(paths_of[task], key=lambda p: min((s.get("seed", 0) for s in evaluations[p]["seeds"]
                                                                if isinstance(s, dict)), default=0))
        if len(task_paths) > 1:
            from offdyn_bench.sweep.submission import merge_evaluations

            try:
                evaluation = merge_evaluations([evaluations[p] for p in task_paths], task_paths)
            except OffdynError as error:
                raise SubmissionError(str(error)) from None
        entry: dict[str, Any] = {
            "task_version": evaluation["task_version"],
            "target_env_id": evaluation["target_env_id"],
            "dataset": _dataset_reference(evaluation.get("dataset")),
            "episode_seeds": evaluation["episode_seeds"],
            "seeds": [{"seed": s.get("seed"), "returns": s.get("returns")} if isinstance(s, dict) else s
                      for s in evaluation["seeds"]],
        }
        policy_sha256 = (evaluation.get("agent") or {}).get("policy_sha256")
        if policy_sha256:
            entry["policy_sha256"] = policy_sha256
        if learning_curves:
            # A merged task shows a curve only when every seed's run has one (a run that scores
            # another run's policy, as RL on source does on its second task, has none).
            curve = merged_learning_curve([p.parent / METRICS_FILE for p in task_paths],
                                          [len(evaluations[p]["seeds"]) for p in task_paths])
            if curve is not None:
                entry["learning_curve"] = curve
        tasks[task] = entry

    method_entry: dict[str, Any] = {"name": method, "description": description}
    if code_url is not None:
        method_entry["code_url"] = code_url
    if commit is not None:
        method_entry["commit"] = commit
    document = {
        "format": SUBMISSION_FORMAT,
        "format_version": SUBMISSION_FORMAT_VERSION,
        "protocol_version": first["protocol_version"],
        "method": method_entry,
        "track": first["track"] or track,
        "budget": first["budget"],
        "versions": first["versions"],
        "tasks": tasks,
    }
    return validate_submission(document, source=f"submission assembled from {runs_dir}")
