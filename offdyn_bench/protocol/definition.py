"""The fixed evaluation protocol, as data the code enforces. ``PROTOCOL.md`` is its prose.

A change to anything here that changes a score is a new :data:`PROTOCOL_VERSION`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType
from typing import Literal

from offdyn_bench.errors import OffdynError, UnknownNameError

PROTOCOL_VERSION = "1.0"


class ProtocolError(OffdynError):
    """Something the protocol does not allow (a method on the wrong track, a missing reference...)."""


TargetData = Literal["dataset", "online"]
SourceData = Literal["simulator", "dataset"]


@dataclasses.dataclass(frozen=True)
class Track:
    """What a method may touch of the target system."""

    name: str
    description: str
    target_data: TargetData
    """``dataset``: only the task's fixed target dataset; ``online``: target steps within a budget."""
    target_steps_per_source_step: float
    """The target-step budget as a fraction of the step budget (source steps; gradient updates on the
    offline-source tracks); 0 on offline-target tracks."""
    methods: tuple[str, ...]
    """The suite's reference implementations that belong on this track."""
    dataset_quality: str | None
    """Quality of the task's official target dataset on this track (None: the track has none)."""
    source_data: SourceData = "simulator"
    """``simulator``: the source simulator, stepped freely within the budget; ``dataset``: only the
    task's fixed source dataset (no source interaction; steps are gradient updates)."""
    source_dataset_quality: str | None = None
    """Quality of the task's official source dataset (None: the track uses the simulator)."""

    def target_step_budget(self, source_steps: int) -> int:
        return int(source_steps * self.target_steps_per_source_step)


TRACKS: Mapping[str, Track] = MappingProxyType({
    "offline-target": Track(
        name="offline-target",
        description="source simulator plus the task's fixed target dataset; no target interaction",
        target_data="dataset", target_steps_per_source_step=0.0,
        methods=("dap", "dap-u", "h2o", "darc", "cql"), dataset_quality="source-policy"),
    "online-target": Track(
        name="online-target",
        description="source simulator plus one target step per ten source steps, counted by the trainer",
        target_data="online", target_steps_per_source_step=0.1,
        methods=("darc-online", "matl", "matl-u", "matl-f", "independent", "direct-transfer", "fine-tuning"),
        dataset_quality=None),
    # ODRL's (Lyu et al. 2024) offline-source settings: no source simulator, a fixed source dataset.
    "offline-source-offline-target": Track(
        name="offline-source-offline-target",
        description="the task's fixed source dataset plus its fixed target dataset; no interaction with either "
                    "system (steps are gradient updates)",
        target_data="dataset", target_steps_per_source_step=0.0, methods=("dara",),
        dataset_quality="source-policy", source_data="dataset", source_dataset_quality="source"),
    "offline-source-online-target": Track(
        name="offline-source-online-target",
        description="the task's fixed source dataset plus one target step per ten gradient updates, counted by "
                    "the trainer; no source simulator",
        target_data="online", target_steps_per_source_step=0.1, methods=("h2o-offline-source",),
        dataset_quality=None, source_data="dataset", source_dataset_quality="source"),
})

REFERENCE_METHODS: Mapping[str, str] = MappingProxyType({
    "sac-source": "RL on source: SAC in the source simulator only, no target data (the floor a transfer "
                  "method must beat); scored on every track",
    "sac-target": "RL on target: SAC trained in the target with the budget's steps (the oracle of the "
                  "normalized score; it uses target interaction no track allows)",
})
"""Reference points, not entries of a track: scored and shown beside every track, labelled."""


@dataclasses.dataclass(frozen=True)
class Budget:
    name: str
    source_steps: int
    """Source-simulator steps (gradient updates for a method that trains on data only, e.g. CQL, and
    on the offline-source tracks)."""
    description: str


BUDGETS: Mapping[str, Budget] = MappingProxyType({
    "full": Budget("full", 1_000_000, "paper scale: the DAP, H2O and DARC papers train for 1M steps"),
    "lite": Budget("lite", 100_000, "one 256x256 SAC-core run takes about 20-35 minutes on one CPU core "
                                    "(see PROTOCOL.md for the measured learning curves behind the choice)"),
})

EVAL_EPISODES = 20
"""Target episodes per training seed, deterministic actions of the final policy."""
EPISODE_SEEDS: tuple[int, ...] = tuple(range(2_000_000, 2_000_000 + EVAL_EPISODES))
"""Reset seeds of the evaluation episodes: disjoint from the trainer's in-training evaluation
(1,000,000...), the datasets' reference episodes (1,000,000...) and their collection seeds."""
MIN_SEEDS = 5
"""Training seeds per method and task."""

CORE_SUITE: tuple[str, ...] = (
    "hopper-gravity-0.5",
    "hopper-friction-0.5",
    "hopper-kinematic-foot-medium",
    "hopper-morph-thigh-medium",
    "hopper-joint-noise-0.5",
    "walker2d-gravity-2.0",
    "walker2d-morph-leg-medium",
    "walker2d-joint-noise-1.0",
    "halfcheetah-gravity-0.5",
    "halfcheetah-friction-5.0",
    "halfcheetah-kinematic-bthigh-hard",
    "ant-friction-5.0",
    "ant-joint-noise-0.5",
)
"""13 pairs covering every robot and every shift family, each one where the shipped RL-on-source
policy keeps at most about half of its source return in the target (the screening is in
PROTOCOL.md). The H2O settings are not in it: their official target data are the H2O paper's three
datasets (:func:`official_datasets`), and source-policy datasets would need behaviour policies
trained in the shifted simulators, which do not ship."""

ADMISSION_PROBABILITY = 0.9
"""The same-budget test a pair must pass to be in a budget's core suite (PROTOCOL.md §9, decision
1 for version 1.1): its oracle beats RL on source in the target with P(oracle > RL on source) at
least this, over at least :data:`MIN_SEEDS` training seeds on each side, both at that budget, and
the oracle's mean return beats the zero command's (the task's ``zero-command`` reference: an oracle
that doing nothing beats anchors no normalized score).
Version 1.0's suite was screened before the test existed (with a shipped policy, §7); the command
``offdyn-bench protocol admission`` reports how it fares."""

ADMISSION_MAX_SOURCE_SCORE = 50.0
"""The test's third condition (PROTOCOL.md §9, decision 1): RL on source's normalized target score,
100 x (J - J_random) / (J_oracle - J_random), at most this. The issue's "RL on source well below the
oracle", read as §7's screening already reads it ("keeps at most about half"), at the same budget:
RL on source closes at most half of the way from the random policy to the oracle. P alone is not
it: an oracle that beats every RL-on-source seed by a few points passes P."""


def get_track(name: str) -> Track:
    if name not in TRACKS:
        raise UnknownNameError("track", name, TRACKS)
    return TRACKS[name]


def get_budget(name: str) -> Budget:
    if name not in BUDGETS:
        raise UnknownNameError("budget", name, BUDGETS)
    return BUDGETS[name]


def track_of_method(algo: str) -> str | None:
    """The track a reference implementation belongs on (None for the reference points)."""
    for track in TRACKS.values():
        if algo in track.methods:
            return track.name
    if algo in REFERENCE_METHODS:
        return None
    raise UnknownNameError("method", algo, [m for t in TRACKS.values() for m in t.methods] + list(REFERENCE_METHODS))


def check_method_on_track(algo: str, track: str) -> None:
    """Refuse a reference implementation on a track it does not fit."""
    get_track(track)
    home = track_of_method(algo)
    if home is not None and home != track:
        raise ProtocolError(f"{algo} belongs on the {home!r} track ({TRACKS[home].description}), "
                            f"not on {track!r}")


def official_dataset(task: str, track: str) -> str | None:
    """The id of ``task``'s official target dataset on ``track``, the one a run trains on when it
    names none (None: the track uses none). :func:`official_datasets` lists every official one."""
    official = official_datasets(task, track)
    return official[0] if official else None


def official_datasets(task: str, track: str) -> tuple[str, ...]:
    """Every official target dataset of ``task`` on ``track``, the default first (empty: the track
    uses none). One, except on the H2O settings (``*-h2o-*``) on a track with the source simulator:
    the H2O paper's Table 1 trains every method on each of the D4RL-style ``medium``,
    ``medium-replay`` and ``medium-expert`` target datasets and reports each, so each is official
    (``medium`` the default) and a record names the one it trained on. These tasks are outside the
    core suite, so no score of the core suite depends on this."""
    from offdyn_bench.datasets.recipes import H2O_QUALITIES, dataset_id, is_h2o_setting, qualities_of
    from offdyn_bench.tasks import get_task

    chosen = get_track(track)
    quality = chosen.dataset_quality
    if quality is None:
        return ()
    pair = get_task(task)
    if chosen.source_data == "simulator" and is_h2o_setting(pair):
        return tuple(dataset_id(pair, level) for level in H2O_QUALITIES)
    # The wheel-legged robot's target data is its human operator's, as on H2O's real robot; it has
    # no source-policy dataset.
    if quality not in qualities_of(pair) and "human-operator" in qualities_of(pair):
        quality = "human-operator"
    return (dataset_id(pair, quality),)


def official_source_dataset(task: str, track: str) -> str | None:
    """The id of ``task``'s official source dataset on ``track`` (None: the track uses the source
    simulator, or the task has no source dataset, e.g. the wheel-legged robot)."""
    from offdyn_bench.datasets.recipes import dataset_id, qualities_of
    from offdyn_bench.tasks import get_task

    quality = get_track(track).source_dataset_quality
    if quality is None:
        return None
    pair = get_task(task)
    if quality not in qualities_of(pair):
        return None
    return dataset_id(pair, quality)


def summary() -> dict[str, object]:
    """The protocol as JSON-ready data (``offdyn-bench protocol show --json``)."""
    return {
        "protocol_version": PROTOCOL_VERSION,
        "tracks": {name: dataclasses.asdict(track) for name, track in TRACKS.items()},
        "reference_methods": dict(REFERENCE_METHODS),
        "budgets": {name: dataclasses.asdict(budget) for name, budget in BUDGETS.items()},
        "eval_episodes": EVAL_EPISODES,
        "episode_seeds": list(EPISODE_SEEDS),
        "min_seeds": MIN_SEEDS,
        "core_suite": list(CORE_SUITE),
    }
