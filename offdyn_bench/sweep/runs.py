"""A sweep spec expanded into runs: one per method x task x group of seeds, each with its folder,
its log and the exact ``offdyn-bench train`` and ``evaluate`` commands it executes.

Everything the protocol or the algorithm registry refuses (an unknown method, task or setting, a
method on a track it does not fit, a method that needs a target dataset its task lacks) is found
here, all of it in one error, before any run starts.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from offdyn_bench.sweep.spec import CORE, SpecError, SweepSpec

RUNS_DIR, LOGS_DIR = "runs", "logs"
EVALUATION_FILE, RESULT_FILE, CONFIG_FILE = "evaluation.json", "result.json", "config.json"
SOURCE_EVALUATION_FILE = "evaluation-source.json"
"""A source-only run's evaluation in its task's source: the other half of the task's gap (PROTOCOL.md §6)."""


@dataclasses.dataclass(frozen=True)
class Run:
    """One training run and its evaluation: what the sweep hands to a worker."""

    method: str
    task: str
    seeds: tuple[int, ...]
    folder: Path
    """The run folder (``train --out``); ``evaluate`` writes its ``evaluation.json`` there."""
    log: Path
    """stdout and stderr of every attempt, appended."""
    train_args: tuple[str, ...]
    """Arguments of ``offdyn-bench`` for training (``train ...``)."""
    evaluate_args: tuple[str, ...]
    """Arguments of ``offdyn-bench`` for the evaluation (``evaluate ...``)."""
    steps: int
    evaluation_episodes: int
    official_dataset: str | None = None
    """The manifest dataset the run trains on, which the sweep installs before any run starts: the
    track's official one, or a ``datasets`` quality's (None: no dataset, or the spec's ``dataset``)."""
    official_source_dataset: str | None = None
    """On the offline-source tracks, the task's official source dataset the run trains on."""
    settings: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    """What ``train`` records in ``config.json`` that decides the result (algo, task, steps,
    seeds, dataset, the full method config): a folder holding other settings is another run."""
    shared_training: Path | None = None
    """The run folder this run's policy is trained in when that is another run's (a source-only
    method on a task whose source an earlier task of the sweep has: ``train_args`` and
    ``settings`` are then that run's, and ``evaluate`` scores its policy on this run's task into
    ``folder``); None: the run trains in ``folder``."""
    dataset_tag: str | None = None
    """The target dataset a run of a ``datasets`` sweep trains on (``medium-replay-v0``), named in
    its folder and id; None for the other runs."""
    source_evaluate_args: tuple[str, ...] = ()
    """For a source-only method (sac-source), the arguments of ``offdyn-bench`` that score the same
    policy in the task's source (``evaluate --side source``, into ``evaluation-source.json``): with
    the target record this is the task's source-target gap (``protocol gap``). Empty for the others."""

    @property
    def training_folder(self) -> Path:
        """Where ``train`` writes this run's policy: its own folder, or the shared one."""
        return self.shared_training if self.shared_training is not None else self.folder

    @property
    def run_id(self) -> str:
        """``method/task/seed-S`` (or ``seeds-S-E``, ``medium-v0.seed-S``): the run's name in the
        state file and its folder."""
        return f"{self.method}/{self.task}/{run_label(self.seeds, self.dataset_tag)}"


def seed_label(seeds: Sequence[int]) -> str:
    return f"seed-{seeds[0]}" if len(seeds) == 1 else f"seeds-{seeds[0]}-{seeds[-1]}"


def run_label(seeds: Sequence[int], dataset_tag: str | None = None) -> str:
    """A run folder's name: its seeds, after the dataset it trained on where a sweep runs several."""
    return seed_label(seeds) if dataset_tag is None else f"{dataset_tag}.{seed_label(seeds)}"


def dataset_tag(dataset_id: str) -> str:
    """``offdyn/halfcheetah-h2o-gravity-2p0/medium-replay-v0`` -> ``medium-replay-v0``."""
    return dataset_id.rsplit("/", 1)[-1]


def task_names(spec: SweepSpec) -> tuple[str, ...]:
    from offdyn_bench.protocol import CORE_SUITE

    return tuple(CORE_SUITE) if spec.tasks == CORE else tuple(spec.tasks)  # type: ignore[arg-type]


def seed_groups(seeds: Sequence[int], per_run: int) -> list[tuple[int, ...]]:
    """Consecutive seeds, at most ``per_run`` to a group (``train`` takes ``--seed S --n-seeds K``)."""
    groups: list[list[int]] = []
    for seed in sorted(seeds):
        if groups and len(groups[-1]) < per_run and groups[-1][-1] == seed - 1:
            groups[-1].append(seed)
        else:
            groups.append([seed])
    return [tuple(group) for group in groups]


def steps_of(spec: SweepSpec) -> int:
    from offdyn_bench.protocol import get_budget

    return get_budget(spec.budget).source_steps if spec.budget is not None else int(spec.steps or 0)


def expand(spec: SweepSpec) -> list[Run]:
    """The spec's runs, seed group by seed group (in each, method, task and dataset order), the order
    the driver starts them in; a :class:`SpecError` listing every refusal."""
    from baselines.algorithms import apply_overrides, config_to_dict, get_algorithm
    from offdyn_bench.errors import OffdynError
    from offdyn_bench.protocol import get_budget, get_track, official_dataset, official_source_dataset
    from offdyn_bench.protocol.training import resolve_run
    from offdyn_bench.tasks import get_task

    where = spec.source
    try:
        get_track(spec.track)
    except OffdynError as error:
        raise SpecError(f"{where}: track: {error}") from None
    if spec.budget is not None:
        try:
            get_budget(spec.budget)
        except OffdynError as error:
            raise SpecError(f"{where}: budget: {error}") from None
    needs_dataset: dict[str, bool] = {}
    needs_source_dataset: dict[str, bool] = {}
    source_only: dict[str, bool] = {}
    configs: dict[str, dict[str, Any]] = {}
    target_step_every: dict[str, int | None] = {}
    for method in spec.methods:
        try:
            algorithm = get_algorithm(method)
        except OffdynError as error:
            raise SpecError(f"{where}: methods: {error}") from None
        try:
            config = apply_overrides(algorithm.default_config(), dict(spec.overrides.get(method, {})), method)
        except OffdynError as error:
            raise SpecError(f"{where}: overrides.{method}: {error}") from None
        # The trainer's rule (baselines/train.py): DARC with target_data=online takes no dataset.
        needs_dataset[method] = algorithm.needs_dataset and getattr(config, "target_data", "offline") != "online"
        needs_source_dataset[method] = algorithm.needs_source_dataset
        source_only[method] = algorithm.source_only
        configs[method] = config_to_dict(config)
        # The trainer's rule too: an online method steps the target once per target_step_every steps.
        target_step_every[method] = (int(config.target_step_every)
                                     if getattr(config, "target_data", None) == "online" else None)
    tasks = []
    for task in task_names(spec):
        try:
            tasks.append(get_task(task).name)
        except OffdynError as error:
            raise SpecError(f"{where}: tasks: {error}") from None

    refused = []
    steps = steps_of(spec)
    for method in spec.methods:
        # The trainer's own check (resolve_run): the track must fit the method, and an online
        # method may not take more target steps than the track allows; no dataset is touched.
        try:
            resolve_run(method, tasks[0], steps=steps, track=spec.track, budget=None, dataset=None,
                        needs_dataset=False, target_step_every=target_step_every[method], progress=False,
                        echo=lambda _line: None)
        except OffdynError as error:
            refused.append(str(error))
    if refused:
        raise SpecError(f"{where}: the protocol refuses {len(refused)} method(s) on track {spec.track!r}: "
                        + "; ".join(refused) + "; remove them or run them in a sweep of their own track")
    # Per task, the datasets its data-hungry methods train on, one run each; a None id is the
    # trainer's own choice (the spec's dataset, or the track's official one).
    datasets_of: dict[str, list[str | None]] = {}
    if spec.datasets and any(needs_dataset.values()):
        datasets_of = _quality_datasets(spec, tasks)
    elif spec.dataset is None and any(needs_dataset.values()):
        from offdyn_bench.datasets import read_manifest

        manifest = read_manifest()
        lacking = [f"{method} on {task}" for method in spec.methods if needs_dataset[method] for task in tasks
                   if official_dataset(task, spec.track) not in manifest]
        if lacking:
            raise SpecError(f"{where}: no official {spec.track} dataset for {', '.join(lacking)}; these methods "
                            "need target data: set dataset (e.g. collect:random:5000) or drop those tasks")

    root = spec.out
    runs = []
    for method in spec.methods:
        # A source-only method (sac-source) trains once per source and seed group: later tasks
        # with the same source score the first one's policy (the same bytes training would give).
        trained: dict[tuple[str, tuple[int, ...]], Run] = {}
        for task in tasks:
            choices = datasets_of.get(task, [None]) if needs_dataset[method] else [None]
            for chosen, seeds in itertools.product(choices, seed_groups(spec.seeds, spec.seeds_per_run)):
                tag = dataset_tag(chosen) if chosen is not None else None
                label = run_label(seeds, tag)
                folder = root / RUNS_DIR / method / task / label
                # train_dataset: what --dataset says (None: the trainer's default, the official one);
                # dataset: what the run trains on, as its config.json records it.
                if not needs_dataset[method]:
                    train_dataset = dataset = None
                elif chosen is not None:
                    train_dataset = dataset = chosen
                else:
                    train_dataset = spec.dataset
                    dataset = spec.dataset if spec.dataset is not None else official_dataset(task, spec.track)
                source = official_source_dataset(task, spec.track) if needs_source_dataset[method] else None
                log = root / LOGS_DIR / method / task / f"{label}.log"
                run = Run(method=method, task=task, seeds=seeds, folder=folder, log=log,
                          train_args=tuple(_train_args(spec, method, task, seeds, folder, train_dataset)),
                          evaluate_args=tuple(_evaluate_args(spec, folder)),
                          steps=steps, evaluation_episodes=spec.evaluation_episodes,
                          official_dataset=dataset if spec.dataset is None else None,
                          official_source_dataset=source, dataset_tag=tag,
                          settings={"algo": method, "task": task, "steps": steps, "seeds": list(seeds),
                                    "dataset": dataset, "config": configs[method]}
                          | ({"source_dataset": source} if source is not None else {}))
                if source_only[method]:
                    donor = trained.setdefault((get_task(task).source_key, seeds), run)
                    if donor is not run:
                        run = dataclasses.replace(
                            run, train_args=donor.train_args, settings=donor.settings,
                            shared_training=donor.folder,
                            evaluate_args=tuple(_evaluate_args(spec, donor.folder, task=task,
                                                               out=folder / EVALUATION_FILE)))
                    run = dataclasses.replace(run, source_evaluate_args=tuple(_evaluate_args(
                        spec, donor.folder, task=task, out=folder / SOURCE_EVALUATION_FILE, side="source")))
                runs.append(run)
    # Seed-major: a sweep stopped part-way (a small machine, a lost lease) has the same seeds of
    # every method and task, so its cells compare; within a group the order above stands, so a
    # shared source training still precedes the runs that score it.
    group_order = {group: index for index, group in enumerate(seed_groups(spec.seeds, spec.seeds_per_run))}
    runs.sort(key=lambda run: group_order[run.seeds])
    return runs


def _quality_datasets(spec: SweepSpec, tasks: Sequence[str]) -> dict[str, list[str | None]]:
    """Per task, the Minari id of each of the spec's ``datasets`` qualities; a
    :class:`SpecError` naming every quality a task lacks or the manifest does not list."""
    from offdyn_bench.datasets import read_manifest
    from offdyn_bench.datasets.recipes import QUALITIES, dataset_id, qualities_of
    from offdyn_bench.tasks import get_task

    unknown = [quality for quality in spec.datasets if quality not in QUALITIES]
    if unknown:
        raise SpecError(f"{spec.source}: datasets: unknown quality {unknown[0]!r}; expected qualities from "
                        f"{', '.join(QUALITIES)} (for one dataset by id or file, use dataset)")
    manifest = read_manifest()
    lacking: list[str] = []
    chosen: dict[str, list[str | None]] = {}
    for task in tasks:
        have = qualities_of(get_task(task))
        chosen[task] = []
        for quality in spec.datasets:
            if quality not in have:
                lacking.append(f"{task} has no {quality} dataset (its qualities: {', '.join(have)})")
                continue
            identifier = dataset_id(task, quality)
            if identifier not in manifest:
                lacking.append(f"{identifier} is not in the manifest")
            chosen[task].append(identifier)
    if lacking:
        raise SpecError(f"{spec.source}: datasets: " + "; ".join(lacking))
    return chosen


def _train_args(spec: SweepSpec, method: str, task: str, seeds: tuple[int, ...], folder: Path,
                dataset: str | None) -> list[str]:
    args = ["train", method, "--task", task, "--track", spec.track]
    args += ["--budget", spec.budget] if spec.budget is not None else ["--steps", str(spec.steps)]
    args += ["--seed", str(seeds[0]), "--n-seeds", str(len(seeds)), "--device", spec.device,
             "--threads", str(max(1, int(spec.cpus_per_run))), "--no-progress"]
    if dataset is not None:
        args += ["--dataset", dataset]
    for option, value in (("--eval-every", spec.training.eval_every),
                          ("--eval-episodes", spec.training.eval_episodes),
                          ("--checkpoint-every", spec.training.checkpoint_every)):
        if value is not None:
            args += [option, str(value)]
    for key, value in spec.overrides.get(method, {}).items():
        args += ["--set", f"{key}={value}"]
    return args + ["--out", str(folder)]


def _evaluate_args(spec: SweepSpec, folder: Path, *, task: str | None = None, out: Path | None = None,
                   side: str = "target") -> list[str]:
    # --track also for the reference methods (sac-source, sac-target): their records then name the
    # track they are submitted beside, like every other run of the sweep.
    args = ["evaluate", "--agent", str(folder), "--track", spec.track, "--episodes", str(spec.evaluation_episodes),
            "--no-progress"]
    return (args + (["--task", task] if task is not None else []) + (["--side", side] if side != "target" else [])
            + (["--out", str(out)] if out is not None else []))


def official_datasets(runs: Sequence[Run]) -> list[str]:
    """Official datasets the runs train on, each once: the sweep installs them before any run
    starts, so concurrent runs never install one dataset at the same time."""
    return list(dict.fromkeys(dataset for run in runs for dataset in (run.official_dataset, run.official_source_dataset)
                              if dataset is not None))


def evaluation_path(run: Run, side: str = "target") -> Path:
    """The record of ``run`` on ``side``: ``evaluation.json`` (target) or ``evaluation-source.json``."""
    return run.folder / (EVALUATION_FILE if side == "target" else SOURCE_EVALUATION_FILE)


def run_finished(run: Run) -> bool:
    """Whether every evaluation the run owes is complete: the target's, and for a source-only
    method the source side's too."""
    return finished_evaluation(run) is not None and (
        not run.source_evaluate_args or finished_evaluation(run, side="source") is not None)


def mean_return(evaluation: dict[str, Any]) -> float:
    """The mean return over every seed's episodes of a record :func:`finished_evaluation` accepted."""
    returns = [float(x) for seed in evaluation["seeds"] for x in seed["returns"]]
    return sum(returns) / len(returns)


def finished_evaluation(run: Run, side: str = "target") -> dict[str, Any] | None:
    """The run's ``evaluation.json`` (``side="source"``: ``evaluation-source.json``) when it is a
    complete evaluation of exactly this run (its method, task, seeds, steps and episode count, on
    that side); otherwise None."""
    path = evaluation_path(run, side)
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(record, dict) or record.get("format") != "offdyn-bench/evaluation":
        return None
    seeds = record.get("seeds")
    if not isinstance(seeds, list) or not all(isinstance(s, dict) for s in seeds):
        return None
    same = (record.get("method") == run.method and record.get("task") == run.task
            and record.get("steps") == run.steps and record.get("side", "target") == side
            and sorted(s.get("seed") for s in seeds) == list(run.seeds)  # type: ignore[type-var]
            and all(isinstance(s.get("returns"), list) and len(s["returns"]) == run.evaluation_episodes
                    for s in seeds))
    return record if same else None


def settings_conflict(run: Run) -> str | None:
    """Why ``run.training_folder`` holds another run than ``run`` (its ``config.json`` records
    other settings: ``differs in: steps, config.sac.batch_size``), or None (no run there, or this one)."""
    path = run.training_folder / CONFIG_FILE
    if not path.exists():
        return None
    try:
        stored = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        return f"{path} cannot be read ({error})"
    if not isinstance(stored, dict):
        return f"{path} is not a training run's config.json"
    differs = []
    for key, expected in run.settings.items():
        differs += _differences(key, stored.get(key), expected)
    return f"differs in: {', '.join(differs)}" if differs else None


def _differences(key: str, stored: Any, expected: Any) -> list[str]:
    if isinstance(stored, dict) and isinstance(expected, dict):
        return [difference for name in sorted(set(stored) | set(expected))
                for difference in _differences(f"{key}.{name}", stored.get(name), expected.get(name))]
    return [] if json.dumps(stored, sort_keys=True) == json.dumps(expected, sort_keys=True) else [key]
