"""What the protocol decides before a training run starts: its budget, its track, its dataset.

``offdyn-bench train`` calls :func:`resolve_run` first, so a run that breaks the protocol is
refused before anything is written, and a run that names a track or a budget gets the official
datasets (target, and source on the offline-source tracks) and step count without having to spell
them out.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from offdyn_bench.errors import OffdynError
from offdyn_bench.protocol.definition import (
    TRACKS,
    ProtocolError,
    check_method_on_track,
    get_budget,
    get_track,
    official_dataset,
    official_source_dataset,
    track_of_method,
)


@dataclasses.dataclass(frozen=True)
class RunPlan:
    steps: int
    dataset: str | None
    track: str | None
    budget: str | None
    target_step_limit: int | None
    """Target-environment steps per training seed the track allows (None: not limited)."""
    source_dataset: str | None = None
    """The fixed source dataset of an offline-source method (None: the method uses none)."""
    source_interaction_allowed: bool = True
    """False on the offline-source tracks for their own methods: the trainer refuses a method that
    steps the source simulator there."""


def resolve_run(algo: str, task: str, *, steps: int | None, track: str | None, budget: str | None,
                dataset: str | None, needs_dataset: bool, target_step_every: int | None,
                source_dataset: str | None = None, needs_source_dataset: bool = False,
                progress: bool = True, echo: Callable[[str], None] = print) -> RunPlan:
    """Steps from the budget, the method checked against the track, and, for a method that needs
    a target (or source) dataset and got none, the task's official one installed and verified."""
    if budget is not None:
        budget_steps = get_budget(budget).source_steps
        if steps is not None and steps != budget_steps:
            raise ProtocolError(f"--steps {steps} contradicts --budget {budget} ({budget_steps} steps); "
                                "pass one of them")
        steps = budget_steps
    if steps is None:
        raise OffdynError("pass --steps N or --budget lite|full")
    if track is not None:
        check_method_on_track(algo, track)
    else:
        track = track_of_method(algo) if algo in {m for t in TRACKS.values() for m in t.methods} else None
    limit = None
    own_track = track is not None and algo in get_track(track).methods
    if own_track:
        if get_track(track).target_data == "online":
            limit = get_track(track).target_step_budget(steps)
            taken = steps // target_step_every if target_step_every else 0
            if taken > limit:
                raise ProtocolError(f"{algo} would take {taken} target steps per seed; the {track} track allows "
                                    f"{limit} (one per {round(1 / get_track(track).target_steps_per_source_step)} "
                                    + ("source steps)" if get_track(track).source_data == "simulator"
                                       else "gradient updates)"))
        else:
            limit = 0
            if target_step_every:
                raise ProtocolError(f"{algo} steps the target environment; the {track} track allows no target "
                                    "interaction")
    if needs_dataset and dataset is None:
        official = official_dataset(task, track or "offline-target")
        if official is None:
            raise OffdynError(f"{algo} needs a target dataset and track {track!r} has no official one: pass --dataset")
        dataset = _install_official(official, algo, task, "target", "--dataset",
                                    "collect:<sac-source run folder>:20000", track or "offline-target", progress, echo)
    if needs_source_dataset and source_dataset is None:
        official = official_source_dataset(task, track) if track is not None else None
        if official is None:
            raise OffdynError(f"{algo} needs a source dataset and {task} has none on track {track!r}: pass "
                              "--source-dataset, e.g. collect:<sac-source run folder>:60000")
        source_dataset = _install_official(official, algo, task, "source", "--source-dataset",
                                           "collect:<sac-source run folder>:60000", track, progress, echo)
    return RunPlan(steps=steps, dataset=dataset, track=track, budget=budget, target_step_limit=limit,
                   source_dataset=source_dataset,
                   source_interaction_allowed=not (own_track and get_track(track).source_data == "dataset"))


def _install_official(official: str, algo: str, task: str, side: str, flag: str, example: str, track: str,
                      progress: bool, echo: Callable[[str], None]) -> str:
    """Install (or verify) the official ``side`` dataset ``official`` and return its id."""
    from offdyn_bench.datasets import read_manifest
    from offdyn_bench.datasets.ensure import ensure_dataset

    if official not in read_manifest():
        raise OffdynError(f"{algo} needs a {side} dataset and {task} has no official one ({official} is not in "
                          f"the manifest): pass {flag}, e.g. {example}")
    echo(f"using the official {track} {side} dataset of {task}: {official}" if side == "source"
         else f"using the official {track} dataset of {task}: {official}")
    ensure_dataset(official, progress=progress, echo=echo)
    return official
