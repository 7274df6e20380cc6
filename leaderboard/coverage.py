"""How much of a sweep's grid the published reference runs hold, and what the rest would take.

The reference results are a grid (``examples/sweeps/reference-lite.yaml``: the reference methods
x the core suite x 5 seeds at ``lite``), published run by run as sweeps finish them, over many
sessions and machines (:mod:`leaderboard.reference_runs`). ``offdyn-bench leaderboard coverage
SPEC`` says how far it got: per task (and dataset) and method, how many of the spec's seeds have a
published record of exactly the spec's run, and for the runs still missing, the trainings they
need and the CPU those would take at the median of the method's published CPU trainings on the
same robot, or on any robot where it has none on that one (their own counts, in
``<budget>/compute.json``; a GPU training's CPU time is its host thread's). Per robot, because a
training's cost is mostly its robot's: observations, network inputs and simulation steps differ
(an Ant DAP training took about 31 minutes of CPU, a Hopper one about 22).

A run counts as published when the records the sweep would write for it are in the published
tree (``<budget>/<method>/<task>/<seed label>/``, the sweep's own layout; RL on source's source
side too) and are that run: its method, task, seeds, steps and episode count, the dataset it trains
on, its track, and the settings its train command changed from the method's defaults against the
spec's ``overrides`` (execution-only ones such as ``cuda_graph`` aside). A published record of
another run in that folder (another dataset, say) is listed, not counted. A hand-edited record is
refused, as everywhere the published runs are read.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import statistics
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from baselines.run_folder import TrainingCompute
from leaderboard.reference_runs import (REFERENCE_RUNS_DIR, published_record_files, read_published_compute,
                                       read_published_record, require_published_root)
from leaderboard.submission import SubmissionError
from offdyn_bench.machine_speed import REFERENCE_WORKLOAD, reference_update_seconds
from offdyn_bench.protocol.claims import NO_DATASET, dataset_label
from offdyn_bench.sweep.driver import format_duration
from offdyn_bench.sweep.runs import Run, expand
from offdyn_bench.sweep.spec import SweepSpec
from offdyn_bench.tasks import TASKS

Row = tuple[str, str | None]
"""A table row: the task, and the dataset tag of a ``datasets`` sweep's runs (None otherwise)."""


@dataclasses.dataclass(frozen=True)
class RobotPrice:
    """What a method's missing trainings on one robot are priced at."""

    robot: str
    trainings_to_go: int
    median_training_cpu_s: float | None
    """The median CPU time of the method's published trainings on this robot; None where it has
    none counted on it (the method's median over every robot prices them then)."""
    trainings_counted: int


@dataclasses.dataclass(frozen=True)
class MethodCost:
    """What a method's missing runs need."""

    method: str
    seeds_to_go: int
    trainings_to_go: int
    """Distinct trainings behind the missing runs: RL on source trains once per source and seed, so
    runs that score one policy on several tasks count it once."""
    median_training_cpu_s: float | None
    """The median CPU time of the method's published trainings at the budget (any robot), from
    ``compute.json``; None when none counted its compute."""
    trainings_counted: int
    """How many published trainings that median is over."""
    unpriced_because: str = ""
    """Why there is no median (empty where there is one)."""
    robots: tuple[RobotPrice, ...] = ()
    """The missing trainings per robot, each priced at the robot's own median where the method has
    one there; empty prices every training at the method's median."""

    def price_of(self, robot: RobotPrice) -> float | None:
        """The CPU seconds one of ``robot``'s missing trainings is priced at."""
        return robot.median_training_cpu_s if robot.median_training_cpu_s is not None else self.median_training_cpu_s

    @property
    def cpu_to_go_s(self) -> float | None:
        if self.trainings_to_go == 0:
            return 0.0
        if self.median_training_cpu_s is None:
            return None
        if not self.robots:
            return self.trainings_to_go * self.median_training_cpu_s
        return sum(robot.trainings_to_go * (self.price_of(robot) or 0.0) for robot in self.robots)


@dataclasses.dataclass(frozen=True)
class MachineSpeed:
    """This machine's speed now against that of the machines the priced trainings ran on, in the
    reference workload's time per update (:mod:`offdyn_bench.machine_speed`)."""

    trainings_measured: int
    """How many of the trainings the prices count measured it (those trained since it exists)."""
    trainings_counted: int
    published_update_s: float
    """The median over those trainings of their machine's time per update, averaged over their CPU."""
    here_update_s: float

    @property
    def ratio(self) -> float:
        """How many times the CPU seconds a training would take here (above 1: slower here)."""
        return self.here_update_s / self.published_update_s


@dataclasses.dataclass(frozen=True)
class Coverage:
    spec_source: str
    budget: str
    published_dir: Path
    methods: tuple[str, ...]
    wanted: Mapping[tuple[str, str, str | None], tuple[int, ...]]
    """(method, task, dataset tag) -> the spec's seeds there."""
    published: Mapping[tuple[str, str, str | None], tuple[int, ...]]
    """(method, task, dataset tag) -> the seeds whose run is published."""
    others: tuple[tuple[Path, str], ...]
    """Published records at a spec run's place that are another run, with what differs."""
    costs: tuple[MethodCost, ...]
    skippable: frozenset[str] = frozenset()
    """Run ids (``Run.run_id``) a sweep of the spec can skip (``sweep --skip-published``): every
    seed result of the run is published as that run, and where other runs of the spec score the
    policy it trains, theirs are too (a missing one still needs it trained)."""
    partly_published: Mapping[str, tuple[int, ...]] = dataclasses.field(default_factory=dict)
    """Run id -> its seeds published already, for the runs of several seeds that have some but not
    all of them published (a lease's ``seeds-0-4`` where a CPU session published ``seed-0``): such a
    run could not be published (a seed is published once), so ``sweep --skip-published`` refuses it."""
    speed: MachineSpeed | None = None
    """None where no priced training measured its machine's speed."""

    @property
    def rows(self) -> tuple[Row, ...]:
        """The table's rows, in the spec's task (and dataset) order."""
        return tuple(dict.fromkeys((task, tag) for _, task, tag in self.wanted))

    @property
    def seeds_wanted(self) -> int:
        return sum(len(seeds) for seeds in self.wanted.values())

    @property
    def seeds_published(self) -> int:
        return sum(len(seeds) for seeds in self.published.values())


def reference_coverage(spec: SweepSpec, root: Path = REFERENCE_RUNS_DIR, *,
                       measure_update_s: Callable[[], float] = reference_update_seconds) -> Coverage:
    """The spec's runs against the reference runs published under ``root`` at the spec's budget,
    seed by seed: a seed counts when a published record of that seed is the spec's run, whichever
    seeds its run trained beside it (``seed-3``, or ``seeds-0-4`` from a GPU sweep). Where priced
    trainings measured their machine's speed, ``measure_update_s`` measures this one's (a tenth
    of a second) for :attr:`Coverage.speed`."""
    if spec.budget is None:
        raise SubmissionError(f"{spec.source}: sets steps, not a protocol budget; reference runs are published "
                              "per budget (lite, full): give the spec a budget")
    require_published_root(root)
    budget_dir = root / spec.budget
    runs = expand(spec)
    wanted: dict[tuple[str, str, str | None], list[int]] = {}
    published: dict[tuple[str, str, str | None], list[int]] = {}
    others: dict[Path, str] = {}
    missing: list[Run] = []
    partly: dict[str, tuple[int, ...]] = {}
    complete_ids: set[str] = set()
    read: dict[tuple[str, str, str | None], dict[tuple[int, str], tuple[Path, dict[str, Any]]]] = {}
    for run in runs:
        key = (run.method, run.task, run.dataset_tag)
        wanted.setdefault(key, []).extend(run.seeds)
        if key not in read:  # each published folder is read once, not once per seed group
            read[key] = _published_records(budget_dir, run)
        records = read[key]
        complete = True
        seeds_published = []
        for seed in run.seeds:
            found = [records[seed, side] for side in _sides(run) if (seed, side) in records]
            differs = {path: why for path, record in found if (why := _difference(spec, run, record))}
            others.update(differs)
            if len(found) == len(_sides(run)) and not differs:
                published.setdefault(key, []).append(seed)
                seeds_published.append(seed)
            else:
                complete = False
        if not complete:
            missing.append(run)
            if seeds_published:
                partly[run.run_id] = tuple(seeds_published)
        else:
            complete_ids.add(run.run_id)
    # A training that a missing run scores is needed, published or not.
    needed_trainings = {run.training_folder for run in missing}
    skippable = frozenset(run.run_id for run in runs
                          if run.run_id in complete_ids and run.folder not in needed_trainings)
    counted: dict[str, dict[str | None, list[float]]] = {}  # method -> robot -> CPU seconds
    priced = published_trainings(budget_dir, spec.seeds_per_run) if spec.device == "cpu" else {}
    for run_id, training in priced.items():
        method, task, _ = run_id.split("/")
        counted.setdefault(method, {}).setdefault(_robot_of(task), []).append(training.cpu_time_s)
    of_spec = [training for run_id, training in priced.items() if run_id.split("/")[0] in spec.methods]
    measured = [speed for training in of_spec if (speed := training.reference_update_s) is not None]
    speed = None
    if measured and missing:  # it speaks to the prices of what is missing
        here = measure_update_s()
        if here > 0:
            speed = MachineSpeed(len(measured), len(of_spec), statistics.median(measured), here)
    costs = []
    for method in spec.methods:
        lacking = [run for run in missing if run.method == method]
        # RL on source's tasks that share a source share its training, and its robot.
        trainings = {run.training_folder: _robot_of(run.task) for run in lacking}
        on_robot = counted.get(method, {})
        times = [cpu for robot_times in on_robot.values() for cpu in robot_times]
        why = ""
        if spec.device != "cpu":
            why = f"the spec trains on {spec.device}, and the published compute is CPU time"
        elif not times:
            why = f"no published training of it ({spec.seeds_per_run} seed(s) per run) counted its compute"
        seeds_to_go = sum(len(seeds) - len(published.get(key, ())) for key, seeds in wanted.items() if key[0] == method)
        robots = []
        for robot in sorted(set(trainings.values()), key=lambda name: (name is None, name or "")):
            own = on_robot.get(robot, []) if robot is not None else []
            robots.append(RobotPrice(robot or "unknown robot", sum(1 for r in trainings.values() if r == robot),
                                     statistics.median(own) if own else None, len(own)))
        costs.append(MethodCost(method, seeds_to_go, len(trainings),
                                statistics.median(times) if times else None, len(times), why, tuple(robots)))
    return Coverage(spec.source, spec.budget, budget_dir, tuple(spec.methods),
                    {key: tuple(sorted(seeds)) for key, seeds in wanted.items()},
                    {key: tuple(sorted(published.get(key, ()))) for key in wanted},
                    tuple(sorted(others.items())), tuple(costs), skippable, partly, speed)


def _sides(run: Run) -> tuple[str, ...]:
    """The records a run owes: the target's, and for RL on source its source side's too."""
    return ("target", "source") if run.source_evaluate_args else ("target",)


def _published_records(budget_dir: Path, run: Run) -> dict[tuple[int, str], tuple[Path, dict[str, Any]]]:
    """(seed, side) -> the published record holding it, among the folders of ``run``'s method,
    task and dataset tag (any seed grouping)."""
    found: dict[tuple[int, str], tuple[Path, dict[str, Any]]] = {}
    for path, side in published_record_files(budget_dir / run.method / run.task):
        tag, _, _ = path.parent.name.rpartition(".")
        if (tag or None) != run.dataset_tag:
            continue
        # A hand edit (a record in another method's folder, a damaged one) is refused outright.
        record = read_published_record(budget_dir, path)
        for entry in record["seeds"]:
            found[(entry["seed"], side)] = (path, record)
    return found


def _difference(spec: SweepSpec, run: Run, record: dict[str, Any]) -> str:
    """What makes a published record of ``run``'s method, task and seed another run ('' where nothing does)."""
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
    trained_with = _result_settings(record.get("train_command"))
    wanted = _result_settings(spec.overrides.get(run.method))
    if trained_with is not None and trained_with != wanted:
        differs.append(f"trained with {_settings_text(trained_with)}, the spec's run with {_settings_text(wanted)}")
    return "; ".join(differs)


def _result_settings(source: str | Mapping[str, str] | None) -> dict[str, Any] | None:
    """The settings that decide a run's result, values parsed: from a record's train command (its
    ``--set`` words) or a spec's overrides; execution-only ones (``cuda_graph``) left out. None for
    a train command that cannot be read."""
    from baselines.algorithms import EXECUTION_SETTINGS
    from offdyn_bench.evaluate import train_command_settings

    if isinstance(source, str):
        settings = train_command_settings(source)
    elif source is None:
        settings = {}
    else:
        settings = dict(source)
    if settings is None:
        return None
    return {key: _parsed(value) for key, value in settings.items() if key.split(".")[-1] not in EXECUTION_SETTINGS}


def _parsed(value: str) -> Any:
    try:
        return json.loads(value)
    except json.JSONDecodeError:
        return value


def _settings_text(settings: Mapping[str, Any]) -> str:
    return " ".join(f"--set {key}={value if isinstance(value, str) else json.dumps(value)}"
                    for key, value in sorted(settings.items())) or "the defaults"


def _robot_of(task: str) -> str | None:
    """The robot a task runs (None for a task this version does not know)."""
    pair = TASKS.get(task)
    return None if pair is None else pair.robot


def published_training_cpu(budget_dir: Path, seeds_per_run: int) -> dict[str, float]:
    """Run id (``method/task/label``) -> the CPU seconds of each published CPU training of
    ``seeds_per_run`` seeds that counted its compute whole."""
    return {run_id: training.cpu_time_s for run_id, training in published_trainings(budget_dir, seeds_per_run).items()}


def published_trainings(budget_dir: Path, seeds_per_run: int) -> dict[str, TrainingCompute]:
    """Run id (``method/task/label``) -> the compute of each published CPU training of
    ``seeds_per_run`` seeds that counted its compute whole."""
    times: dict[str, TrainingCompute] = {}
    for run_id, entry in sorted(read_published_compute(budget_dir).items()):
        training = TrainingCompute.parse(entry.get("training"))
        label = run_id.rsplit("/", 1)[-1].rpartition(".")[2]
        seeds = 1 if label.startswith("seed-") else _group_size(label)
        if (training is not None and training.complete and seeds == seeds_per_run
                and not _trained_on_a_gpu(budget_dir, run_id)):
            times[run_id] = training
    return times


def _trained_on_a_gpu(budget_dir: Path, run_id: str) -> bool:
    """Whether a published run's records name a GPU among the machines that trained it. Such a
    run's CPU time is its host thread's (waiting on the device), not what the training costs on a
    CPU, so it prices no CPU run."""
    method, task, label = run_id.split("/")
    for path, _ in published_record_files(budget_dir / method / task, label):
        machines = read_published_record(budget_dir, path).get("training_machines") or []
        if any(isinstance(machine, dict) and machine.get("cuda") for machine in machines):
            return True
    return False


def _group_size(label: str) -> int | None:
    """``seeds-0-4`` -> 5 (None for anything else)."""
    first, _, last = label.removeprefix("seeds-").partition("-")
    return int(last) - int(first) + 1 if first.isdigit() and last.isdigit() else None


def _robot_estimate(cost: MethodCost, robot: RobotPrice) -> str:
    """``Ant: 10 x 31m05s (median of 10 on Ant)``, or where the method has none on the robot,
    ``Ant: 10 x 22m01s (median of 55 on any robot, none on Ant)``."""
    price = format_duration(cost.price_of(robot) or 0.0)
    where = (f"median of {robot.trainings_counted} on {robot.robot}" if robot.median_training_cpu_s is not None
             else f"median of {cost.trainings_counted} on any robot, none on {robot.robot}")
    return f"{robot.robot}: {robot.trainings_to_go} x {price} ({where})"


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
               f"{coverage.seeds_published} of {coverage.seeds_wanted} seed result(s) published "
               "(cells: seeds published / the spec's seeds)")
    lines = [heading, line(headers), line(["-" * w for w in widths])]
    lines += [line(cells) for cells in table]
    to_go = [cost for cost in coverage.costs if cost.seeds_to_go]
    if not to_go:
        lines.append("every run of the spec is published")
    else:
        runs = sum(cost.seeds_to_go for cost in to_go)
        trainings = sum(cost.trainings_to_go for cost in to_go)
        known = [cost.cpu_to_go_s for cost in to_go if cost.cpu_to_go_s is not None]
        unknown = [cost.method for cost in to_go if cost.cpu_to_go_s is None]
        total = "CPU not estimated" if not known else f"about {format_duration(sum(known))} of CPU"
        if known and unknown:
            total += f" for all but {', '.join(unknown)}"
        lines.append(f"to go: {runs} seed result(s), {trainings} training(s), {total} (each training at the "
                     "median CPU of its method's published trainings at this budget on its robot, or on any "
                     "robot where none is on its own; from compute.json):")
        for cost in to_go:
            if cost.median_training_cpu_s is None:
                estimate = f"not estimated: {cost.unpriced_because}"
            else:
                estimate = f"= {format_duration(cost.cpu_to_go_s or 0.0)}"
            lines.append(f"  {cost.method}: {cost.seeds_to_go} seed result(s), {cost.trainings_to_go} training(s) "
                         f"{estimate}")
            if cost.median_training_cpu_s is not None:
                lines += [f"    {_robot_estimate(cost, robot)}" for robot in cost.robots]
        speed = coverage.speed
        if speed is not None:
            lines.append(f"machine speed: {speed.trainings_measured} of the {speed.trainings_counted} priced trainings "
                         f"timed the reference workload ({REFERENCE_WORKLOAD}) on their machine, a median "
                         f"{speed.published_update_s * 1e3:.2f} ms an update; this machine takes "
                         f"{speed.here_update_s * 1e3:.2f} ms now, so a training here would take about "
                         f"{speed.ratio:.2f} times the CPU of one of theirs (PROTOCOL §8)")
        lines.append(f"run only those: offdyn-bench sweep {shlex.quote(coverage.spec_source)} --skip-published")
    if coverage.others:
        lines.append(f"{len(coverage.others)} published record(s) where the spec's runs belong are other runs "
                     "(not counted):")
        lines += [f"  {path}: {why}" for path, why in coverage.others]
    return lines
