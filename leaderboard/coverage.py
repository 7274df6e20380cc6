"""How much of a sweep's grid the published reference runs hold, and what the rest would take.

The reference results are a grid (``examples/sweeps/reference-lite.yaml``: the reference methods
x the core suite x 5 seeds at ``lite``), published run by run as sweeps finish them, over many
sessions and machines (:mod:`leaderboard.reference_runs`). ``offdyn-bench leaderboard coverage
SPEC`` says how far it got: per task (and dataset) and method, how many of the spec's seeds have a
published record of exactly the spec's run, and for the runs still missing, the trainings they
need and the CPU those would take at the median of the method's published trainings (their own
counts, in ``<budget>/compute.json``).

A run counts as published when the records the sweep would write for it are in the published
tree (``<budget>/<method>/<task>/<seed label>/``, the sweep's own layout; RL on source's source
side too) and are that run: its method, task, seeds, steps and episode count, the dataset it trains
on and its track. A published record of another run in that folder (another dataset, say) is
listed, not counted. A hand-edited record is refused, as everywhere the published runs are read.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path

from baselines.run_folder import TrainingCompute
from leaderboard.assemble import read_evaluation_strict
from leaderboard.reference_runs import (REFERENCE_RUNS_DIR, RECORD_FILES, check_reference_record,
                                       read_published_compute)
from leaderboard.submission import SubmissionError
from offdyn_bench.protocol.claims import NO_DATASET, dataset_label
from offdyn_bench.sweep.driver import format_duration
from offdyn_bench.sweep.runs import Run, evaluation_path, expand, run_label
from offdyn_bench.sweep.spec import SweepSpec

Row = tuple[str, str | None]
"""A table row: the task, and the dataset tag of a ``datasets`` sweep's runs (None otherwise)."""


@dataclasses.dataclass(frozen=True)
class MethodCost:
    """What a method's missing runs need."""

    method: str
    runs_to_go: int
    trainings_to_go: int
    """Distinct trainings behind the missing runs: RL on source trains once per source and seed, so
    runs that score one policy on several tasks count it once."""
    median_training_cpu_s: float | None
    """The median CPU time of the method's published trainings at the budget (any task), from
    ``compute.json``; None when none counted its compute."""
    trainings_counted: int
    """How many published trainings that median is over."""

    @property
    def cpu_to_go_s(self) -> float | None:
        if self.trainings_to_go == 0:
            return 0.0
        return None if self.median_training_cpu_s is None else self.trainings_to_go * self.median_training_cpu_s


@dataclasses.dataclass(frozen=True)
class Coverage:
    spec_source: str
    budget: str
    published_dir: Path
    methods: tuple[str, ...]
    rows: tuple[Row, ...]
    wanted: Mapping[tuple[str, str, str | None], tuple[int, ...]]
    """(method, task, dataset tag) -> the spec's seeds there."""
    published: Mapping[tuple[str, str, str | None], tuple[int, ...]]
    """(method, task, dataset tag) -> the seeds whose run is published."""
    others: tuple[tuple[Path, str], ...]
    """Published records at a spec run's place that are another run, with what differs."""
    costs: tuple[MethodCost, ...]

    @property
    def runs_total(self) -> int:
        return sum(len(seeds) for seeds in self.wanted.values())

    @property
    def runs_published(self) -> int:
        return sum(len(seeds) for seeds in self.published.values())


def reference_coverage(spec: SweepSpec, root: Path = REFERENCE_RUNS_DIR) -> Coverage:
    """The spec's runs against the reference runs published under ``root`` at the spec's budget."""
    if spec.budget is None:
        raise SubmissionError(f"{spec.source}: sets steps, not a protocol budget; reference runs are published "
                              "per budget (lite, full): give the spec a budget")
    if not root.is_dir():
        raise SubmissionError(f"{root}: not a folder; expected published reference runs "
                              "(<budget>/<method>/<task>/<seeds>/evaluation.json, as publish-runs writes them)")
    budget_dir = root / spec.budget
    runs = expand(spec)
    wanted: dict[tuple[str, str, str | None], list[int]] = {}
    published: dict[tuple[str, str, str | None], list[int]] = {}
    others: list[tuple[Path, str]] = []
    missing: list[Run] = []
    for run in runs:
        key = (run.method, run.task, run.dataset_tag)
        wanted.setdefault(key, []).extend(run.seeds)
        published.setdefault(key, [])
        difference = _published_difference(spec, run, budget_dir)
        if difference is None:
            published[key].extend(run.seeds)
            continue
        missing.append(run)
        if difference:
            others.append(difference)
    counted = _published_training_cpu(budget_dir)
    costs = []
    for method in spec.methods:
        lacking = [run for run in missing if run.method == method]
        trainings = {run.training_folder for run in lacking}
        times = counted.get(method, [])
        costs.append(MethodCost(method, len(lacking), len(trainings),
                                statistics.median(times) if times else None, len(times)))
    rows = tuple(dict.fromkeys((task, tag) for _, task, tag in wanted))
    return Coverage(spec.source, spec.budget, budget_dir, tuple(spec.methods), rows,
                    {key: tuple(sorted(seeds)) for key, seeds in wanted.items()},
                    {key: tuple(sorted(seeds)) for key, seeds in published.items()},
                    tuple(others), tuple(costs))


def _published_difference(spec: SweepSpec, run: Run, budget_dir: Path) -> tuple[Path, str] | tuple[()] | None:
    """None: ``run``'s records are published; ``()``: nothing is published at its place;
    ``(path, what differs)``: a record of another run is."""
    folder = budget_dir / run.method / run.task / run_label(run.seeds, run.dataset_tag)
    at_home = dataclasses.replace(run, folder=folder)
    sides = ["target"] + (["source"] if run.source_evaluate_args else [])
    for side in sides:
        path = evaluation_path(at_home, side)
        if not path.exists():
            return ()
        record = read_evaluation_strict(path)
        # A hand edit (a record in another method's folder, a damaged one) is refused outright.
        check_reference_record(path, record, run.method, run.task, folder.name, RECORD_FILES[path.name])
        differs = []
        if record.get("steps") != run.steps:
            differs.append(f"{record.get('steps')} training steps, the spec's {run.steps}")
        episodes = sorted({len(seed["returns"]) for seed in record["seeds"]})
        if episodes != [run.evaluation_episodes]:
            differs.append(f"{'/'.join(map(str, episodes))} episodes per seed, the spec's {run.evaluation_episodes}")
        trained_on = run.settings.get("dataset") or NO_DATASET
        if dataset_label(record) != trained_on:
            differs.append(f"trained on {dataset_label(record)}, the spec's run on {trained_on}")
        if record.get("track") != spec.track:
            differs.append(f"track {record.get('track')!r}, the spec's {spec.track!r}")
        if differs:
            return path, "; ".join(differs)
    return None


def _published_training_cpu(budget_dir: Path) -> dict[str, list[float]]:
    """Per method, the CPU seconds of each published training that counted its compute whole."""
    times: dict[str, list[float]] = {}
    for run_id, entry in sorted(read_published_compute(budget_dir).items()):
        training = TrainingCompute.parse(entry.get("training"))
        if training is not None and training.complete:
            times.setdefault(run_id.split("/", 1)[0], []).append(training.cpu_time_s)
    return times


def coverage_lines(coverage: Coverage) -> list[str]:
    """The coverage as a table and a summary of what is left, for a terminal or a note."""
    tagged = any(tag is not None for _, tag in coverage.rows)
    headers = ["task"] + (["dataset"] if tagged else []) + list(coverage.methods)
    table = []
    for task, tag in coverage.rows:
        cells = [task] + ([tag or "-"] if tagged else [])
        for method in coverage.methods:
            seeds = coverage.wanted.get((method, task, tag))
            done = coverage.published.get((method, task, tag), ())
            cells.append("" if seeds is None else f"{len(done)}/{len(seeds)}")
        table.append(cells)
    widths = [max(len(row[i]) for row in [headers, *table]) for i in range(len(headers))]
    text_columns = 2 if tagged else 1

    def line(cells: Sequence[str]) -> str:
        return "  ".join(cell.ljust(width) if i < text_columns else cell.rjust(width)
                         for i, (cell, width) in enumerate(zip(cells, widths))).rstrip()

    heading = (f"{coverage.spec_source} at {coverage.budget}, against {coverage.published_dir}: "
               f"{coverage.runs_published} of {coverage.runs_total} run(s) published "
               "(cells: seeds published / the spec's seeds)")
    lines = [heading, line(headers), line(["-" * w for w in widths])]
    lines += [line(cells) for cells in table]
    to_go = [cost for cost in coverage.costs if cost.runs_to_go]
    if not to_go:
        lines.append("every run of the spec is published")
    else:
        runs = sum(cost.runs_to_go for cost in to_go)
        trainings = sum(cost.trainings_to_go for cost in to_go)
        known = [cost.cpu_to_go_s for cost in to_go if cost.cpu_to_go_s is not None]
        unknown = [cost.method for cost in to_go if cost.cpu_to_go_s is None]
        total = f"about {format_duration(sum(known))} of CPU"
        if unknown:
            total += f" for all but {', '.join(unknown)}"
        lines.append(f"to go: {runs} run(s), {trainings} training(s), {total} "
                     "(each method's median training CPU at this budget, from compute.json):")
        for cost in to_go:
            if cost.median_training_cpu_s is None:
                estimate = "not estimated: no published training of it counted its compute"
            else:
                estimate = (f"x {format_duration(cost.median_training_cpu_s)} (median of {cost.trainings_counted}) "
                            f"= {format_duration(cost.cpu_to_go_s or 0.0)}")
            lines.append(f"  {cost.method}: {cost.runs_to_go} run(s), {cost.trainings_to_go} training(s) {estimate}")
    if coverage.others:
        lines.append(f"{len(coverage.others)} published record(s) where the spec's runs belong are other runs "
                     "(not counted):")
        lines += [f"  {path}: {why}" for path, why in coverage.others]
    return lines
