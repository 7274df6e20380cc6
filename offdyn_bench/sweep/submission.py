"""From a finished sweep to ``offdyn-bench leaderboard submit``.

``leaderboard submit`` takes one ``evaluation.json`` per task holding every training seed. A sweep
trains seeds in separate runs (``seeds_per_run``), so once every run of a method and task is
evaluated, their records are merged into ``<out>/submission/<method>/<task>/evaluation.json``
(with the learning curves of ``metrics.jsonl`` side by side): the per-seed returns, episode seeds
and policy hashes exactly as each run's evaluation wrote them, after checking that the runs were
evaluated alike (task version, protocol, track, budget, steps, dataset, library versions).
"""

from __future__ import annotations

import json
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from baselines.run_folder import write_json_atomic, write_lines_atomic
from offdyn_bench.errors import OffdynError
from offdyn_bench.sweep.runs import EVALUATION_FILE, Run, finished_evaluation, task_names
from offdyn_bench.sweep.spec import SweepSpec

SUBMISSION_DIR = "submission"
METRICS_FILE = "metrics.jsonl"
_SAME_FIELDS = ("format", "format_version", "protocol_version", "task", "task_version", "target_env_id", "side",
                "env_id", "track", "budget", "method", "steps", "dataset", "episode_seeds", "versions")
"""Fields every run of one method and task must agree on to be one evaluation."""


def merge_evaluations(records: Sequence[dict[str, Any]], sources: Sequence[Path]) -> dict[str, Any]:
    """One evaluation record of all seeds of ``records`` (evaluations of runs of one method and
    task, read from ``sources``)."""
    if not records:
        raise OffdynError("no evaluation to merge")
    first = records[0]
    for field in _SAME_FIELDS:
        values = {json.dumps(record.get(field), sort_keys=True) for record in records}
        if len(values) > 1:
            raise OffdynError(f"the evaluations of {first.get('method')} on {first.get('task')} disagree on {field} "
                              f"({', '.join(str(s) for s in sources)}); re-evaluate them in one environment")
    seeds = sorted((seed for record in records for seed in record["seeds"]), key=lambda seed: seed["seed"])
    if len({seed["seed"] for seed in seeds}) != len(seeds):
        raise OffdynError(f"the evaluations of {first.get('method')} on {first.get('task')} hold a training seed "
                          "twice")
    policy_sha256: dict[str, str] = {}
    for record in records:
        policy_sha256.update((record.get("agent") or {}).get("policy_sha256") or {})
    notes = list(dict.fromkeys(note for record in records for note in record.get("notes") or []))
    merged = {field: first.get(field) for field in _SAME_FIELDS}
    merged |= {
        "agent": {"kind": "runs", "path": None, "policy_sha256": dict(sorted(policy_sha256.items(),
                                                                             key=lambda item: int(item[0]))),
                  "runs": [record.get("agent") for record in records]},
        "train_command": "; ".join(str(record.get("train_command")) for record in records),
        "seeds": seeds,
        "protocol_conformant": all(record.get("protocol_conformant") is True for record in records) and not notes,
        "notes": notes,
        "command": "; ".join(str(record.get("command")) for record in records),
        "merged_from": [str(source) for source in sources],
        # Per run, in the order above: where it was evaluated and trained (PROTOCOL §8).
        "machines": [{"evaluation": record.get("machine"), "training": record.get("training_machines")}
                     for record in records],
        # Likewise the code revisions, and when each run trained.
        "provenance": [{"evaluation_source_revision": record.get("source_revision"),
                        "training": record.get("training_provenance")} for record in records],
    }
    return merged


def merged_curve_lines(runs: Sequence[Run]) -> list[str] | None:
    """The learning curves of ``runs`` (in seed order) as one metrics.jsonl, or None when a run
    has none, an unreadable one, or the runs were evaluated at different steps."""
    from leaderboard.assemble import merged_learning_curve
    from leaderboard.submission import SubmissionError

    try:
        curve = merged_learning_curve([run.folder / METRICS_FILE for run in runs], [None] * len(runs))
    except SubmissionError:
        return None
    if curve is None:
        return None
    return [json.dumps({"step": point["step"], "target_return": point["target_return"],
                        "target_return_mean": sum(point["target_return"]) / len(point["target_return"])})
            for point in curve]


def write_submission_folder(spec: SweepSpec, method: str, runs: Sequence[Run]) -> Path:
    """``<out>/submission/<method>/<task>/`` for every task of ``method``'s runs, all evaluated."""
    folder = spec.out / SUBMISSION_DIR / method
    by_task: dict[str, list[Run]] = {}
    for run in runs:
        by_task.setdefault(run.task, []).append(run)
    for task, task_runs in by_task.items():
        task_runs = sorted(task_runs, key=lambda run: run.seeds)
        records = []
        for run in task_runs:
            record = finished_evaluation(run)
            if record is None:
                raise OffdynError(f"{run.folder / EVALUATION_FILE} is missing or incomplete; run the sweep again")
            records.append(record)
        target = folder / task
        target.mkdir(parents=True, exist_ok=True)
        lines = merged_curve_lines(task_runs)
        if lines is not None:
            write_lines_atomic(target / METRICS_FILE, lines)
        else:
            (target / METRICS_FILE).unlink(missing_ok=True)
        # The evaluation last: a folder with it is complete.
        write_json_atomic(target / EVALUATION_FILE,
                          merge_evaluations(records, [run.folder / EVALUATION_FILE for run in task_runs]))
    return folder


def leaderboard_blockers(spec: SweepSpec, merged: dict[str, Any]) -> list[str]:
    """Why the sweep's results cannot be a leaderboard submission (empty: they can)."""
    from offdyn_bench.protocol import CORE_SUITE, EVAL_EPISODES, MIN_SEEDS

    reasons = []
    if spec.budget is None:
        reasons.append(f"trained for {spec.steps} steps, not at a protocol budget (lite or full)")
    if set(task_names(spec)) != set(CORE_SUITE):
        reasons.append("the tasks are not the protocol's core suite (tasks: core)")
    if len(spec.seeds) < MIN_SEEDS:
        reasons.append(f"{len(spec.seeds)} seed(s); the protocol needs at least {MIN_SEEDS}")
    if spec.evaluation_episodes != EVAL_EPISODES:
        reasons.append(f"{spec.evaluation_episodes} evaluation episodes; the protocol evaluates {EVAL_EPISODES}")
    if not reasons and merged.get("protocol_conformant") is False:
        reasons += [str(note) for note in merged.get("notes") or []]
    return reasons


def submit_arguments(spec: SweepSpec, method: str) -> list[str]:
    folder = spec.out / SUBMISSION_DIR / method
    return ["leaderboard", "submit", str(folder), "--method", method, "--track", spec.track,
            "--budget", str(spec.budget), "--out", str(spec.out / SUBMISSION_DIR / f"{method}.json")]


def submit_command(spec: SweepSpec, method: str) -> str:
    return "offdyn-bench " + shlex.join(submit_arguments(spec, method))


def submit(spec: SweepSpec, method: str, description: str) -> Path:
    """Assemble and validate ``method``'s submission with the leaderboard's own function and write
    it to ``<out>/submission/<method>.json``."""
    from leaderboard.assemble import assemble_submission
    from leaderboard.store import write_file_atomic
    from leaderboard.submission import canonical_json

    folder = spec.out / SUBMISSION_DIR / method
    submission = assemble_submission(folder, method=method, description=description, track=spec.track,
                                     budget=spec.budget)
    path = spec.out / SUBMISSION_DIR / f"{method}.json"
    write_file_atomic(path, canonical_json(submission.document))
    return path
