"""Dataset ids and recipes: everything needed to regenerate a dataset byte for byte.

A dataset id is ``offdyn/<task slug>/<quality>-v<N>``, the task slug being the task name with
``p`` for the dot (``hopper-gravity-0.5`` -> ``hopper-gravity-0p5``). ``N`` is the dataset's own
version: a new behaviour policy, size or seed is a new version, and the task's version (its
dynamics) is pinned inside the recipe next to a hash of its full definition.

A :class:`Recipe` is data: the task, the behaviour that acts in the target (uniform random
actions, or a policy file pinned by hash), how many transitions, the seeds, the reference-score
protocol and the storage format. Recipes of the default set live in ``assets/datasets.json``;
:func:`default_recipe` makes the recipe of any other task on demand.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib
import re
from collections.abc import Mapping
from typing import Any, Literal

from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.json_values import is_integer
from offdyn_bench.tasks import TASKS, TaskPair, get_task

Quality = Literal["random", "source-policy", "human-operator", "source", "medium", "medium-replay", "medium-expert"]
QUALITIES: tuple[Quality, ...] = ("random", "source-policy", "human-operator", "source", "medium", "medium-replay",
                                  "medium-expert")
"""``random``, ``source-policy``, ``human-operator`` and the :data:`H2O_QUALITIES` are collected in
the task's target; ``source`` in its source (the offline-source tracks' data, see :data:`SKILL_LEVELS`)."""
H2O_QUALITIES: tuple[Quality, ...] = ("medium", "medium-replay", "medium-expert")
"""The target data of the H2O paper's Table 1 (D4RL's levels, made in this suite's target: the
nominal robot), for the H2O settings only (:func:`is_h2o_setting`). All three come from one SAC
run in the target, the oracle's own training (``assets/policies/sac-target``):

* ``medium``: its checkpoint closest to a third of the way from random to the oracle's return
  (``assets/policies/sac-target-medium``), with the usual Gaussian action noise;
* ``medium-replay``: every transition that run stored up to that checkpoint, re-simulated from its
  replay buffer (so it has the full physics state like every dataset) and checked against it;
* ``medium-expert``: equal halves from the medium policy and the oracle, labelled by level.

``scripts/make_h2o_behaviours.py`` trains the run and exports both policies."""
# The wheel-legged robot's target data is a person's, as on H2O's real robot; it has no SAC
# behaviour policy. Every other robot has no human operator.
HUMAN_OPERATOR_ROBOTS = ("WheelLegged",)

NAMESPACE = "offdyn"
REPO_ROOT = pathlib.Path(__file__).resolve().parents[2]
ASSETS_DIR = REPO_ROOT / "assets"
POLICIES_DIR = ASSETS_DIR / "policies"

# Sizes (see the top-level README, "Sizes and why"): DAP's main experiments used tens of thousands of target
# transitions and its size ablation lost little at 15,000 and 10,000; 20,000 keeps us inside that
# range while the default set still builds in minutes on two cores. The random quality has the
# same size so that quality is the only thing that differs between the two.
DEFAULT_TRANSITIONS: Mapping[Quality, int] = {"random": 20_000, "source-policy": 20_000,
                                               # H2O recorded 100,000 human-controlled transitions per task.
                                               "human-operator": 100_000,
                                               # Source data is the plentiful side: each of the three skill
                                               # levels as large as a whole target dataset.
                                               "source": 60_000,
                                               # H2O's Table 1 ran on D4RL's 1M-transition sets; a tenth of
                                               # that keeps the builds in minutes. medium-expert is two
                                               # medium-sized halves, as in D4RL. medium-replay is what the
                                               # run stored up to the medium checkpoint (read from the
                                               # policy's sidecar); this is the size before one exists.
                                               "medium": 100_000, "medium-expert": 200_000,
                                               "medium-replay": 100_000}
SKILL_LEVELS: tuple[tuple[str, float | None], ...] = (("expert", 0.1), ("medium", 0.3), ("random", None))
"""The ``skill-mixture`` behaviour of ``source`` datasets, D4RL-style: equal thirds of the
transitions from the task's sac-source policy with Gaussian action noise of std 0.1 (``expert``:
the ``source-policy`` datasets' own setting) and 0.3 (``medium``: the same policy made clumsy; its
return lands between the expert's and random's on all four robots, where 0.6 put Ant's below
random), then uniform-random actions (``None``). The suite ships one behaviour policy per source dynamics, not
checkpoints at several training stages, so noise sets the skill; the measured return of each level
is in the dataset's metadata. Changing the levels is a new dataset version."""
# Gaussian noise (in action-space units, clipped to the box) on the behaviour policy's
# deterministic action: DAP "samples" its source policy in the target; a fixed-std noise keeps
# that sampling reproducible and independent of how a checkpoint parameterizes its std.
DEFAULT_ACTION_NOISE_STD = 0.1
DEFAULT_SEED = 0
# Reference episodes use their own seeds, disjoint from any data episode's seed.
REFERENCE_SEED = 1_000_000
REFERENCE_EPISODES = 10
DATA_FORMAT = "hdf5"
DATA_FORMATS = ("arrow", "hdf5")

_ID_RE = re.compile(r"^(?P<namespace>[a-z0-9_-]+)/(?P<slug>[a-z0-9_-]+)/(?P<quality>[a-z0-9_-]+?)-v(?P<version>\d+)$")


class RecipeError(OffdynError):
    """A recipe or dataset id that is malformed or does not match the code it would run."""


def task_slug(task_name: str) -> str:
    return task_name.replace(".", "p")


MEDIUM_FRACTION = 1 / 3
"""Where the ``medium`` policy sits between a uniform-random policy (0) and the oracle (1): D4RL's
"about a third of the expert's performance", measured from random so that HalfCheetah's negative
random return does not skew it."""


def is_h2o_setting(pair: TaskPair) -> bool:
    """The H2O paper's pairs: a shifted simulator (the source) and the nominal robot as the real
    system (the target), which the D4RL-style :data:`H2O_QUALITIES` are collected in."""
    return bool(pair.source_effects) and not pair.target_effects and pair.target_engine == "mujoco"


def qualities_of(pair: TaskPair) -> tuple[Quality, ...]:
    """The dataset qualities a pair has: ``random``, ``source-policy`` and ``source`` (and the
    :data:`H2O_QUALITIES` for the H2O settings), or, for the wheel-legged robot, ``random`` and
    ``human-operator``."""
    if pair.robot in HUMAN_OPERATOR_ROBOTS:
        return ("random", "human-operator")
    return ("random", "source-policy", "source") + (H2O_QUALITIES if is_h2o_setting(pair) else ())


def _check_quality(pair: TaskPair, quality: str) -> None:
    if quality not in QUALITIES:
        raise UnknownNameError("dataset quality", quality, QUALITIES)
    if quality not in qualities_of(pair):
        raise RecipeError(f"task {pair.name} has no {quality!r} dataset; its qualities are {list(qualities_of(pair))}")


def dataset_id(task: str | TaskPair, quality: str, version: int = 0) -> str:
    """``dataset_id("hopper-gravity-0.5", "source-policy")`` -> ``offdyn/hopper-gravity-0p5/source-policy-v0``."""
    pair = task if isinstance(task, TaskPair) else get_task(task)
    _check_quality(pair, quality)
    return f"{NAMESPACE}/{task_slug(pair.name)}/{quality}-v{version}"


def parse_dataset_id(dataset_id: str) -> tuple[TaskPair, Quality, int]:
    """The task, quality and dataset version an id names; a clear error for anything else."""
    match = _ID_RE.fullmatch(str(dataset_id))
    if match is None or match["namespace"] != NAMESPACE:
        raise RecipeError(f"malformed dataset id {dataset_id!r}; expected "
                          f"'{NAMESPACE}/<task with p for the dot>/<quality>-v<N>', "
                          f"e.g. '{NAMESPACE}/hopper-gravity-0p5/source-policy-v0'")
    slugs = {task_slug(name): name for name in TASKS}
    if match["slug"] not in slugs:
        raise UnknownNameError("dataset task", match["slug"], slugs)
    pair = TASKS[slugs[match["slug"]]]
    _check_quality(pair, match["quality"])
    return pair, match["quality"], int(match["version"])  # type: ignore[return-value]


def task_sha256(pair: TaskPair) -> str:
    """Hash of a pair's full definition: a recipe refuses to run on changed dynamics."""
    return hashlib.sha256(json.dumps(pair.to_dict(), sort_keys=True).encode()).hexdigest()


def dynamics_label(pair: TaskPair, side: Literal["source", "target"]) -> str:
    """Name of the dynamics a policy was trained in: pairs with a nominal side share it (a side on
    another engine, e.g. DART, is not nominal even without effects)."""
    nominal = not pair.effects(side) and pair.engine(side) == "mujoco"
    return f"{pair.robot.lower()}-nominal" if nominal else f"{pair.name}-{side}"


def sac_policy_path(pair: TaskPair, role: Literal["sac-source", "sac-target", "sac-target-medium"]) -> str:
    """Where a pair's behaviour policy (``sac-source``, DAP's "RL on source"), oracle
    (``sac-target``, "RL on target") or the oracle run's medium checkpoint (``sac-target-medium``,
    the :data:`H2O_QUALITIES`' behaviour) ships, relative to the repo root.

    Files are named by the dynamics they were trained in, so every pair with a nominal source
    shares one behaviour policy, and every pair with a nominal target one oracle. Behaviour
    policies and oracles sit in separate folders: a quick behaviour policy must never stand
    in for an oracle in normalized scores."""
    side: Literal["source", "target"] = "source" if role == "sac-source" else "target"
    return f"assets/policies/{role}/{dynamics_label(pair, side)}.safetensors"


BEHAVIOUR_KINDS = ("uniform-random", "policy", "human-operator", "skill-mixture", "training-replay",
                   "medium-expert")
POLICY_KINDS = ("policy", "skill-mixture", "training-replay", "medium-expert")
"""Behaviour kinds that read a policy file (``Behaviour.policy``)."""
# The kind each quality that has one fixed kind must have (the others take "policy" or "uniform-random").
_QUALITY_KINDS = {"source": "skill-mixture", "medium-replay": "training-replay", "medium-expert": "medium-expert"}


@dataclasses.dataclass(frozen=True)
class Behaviour:
    """What acts while the data is collected (in the target; in the source for ``source`` data).

    ``kind`` is ``uniform-random``, ``policy``, ``human-operator`` (the wheel-legged robot's
    balancing controller steered by an imperfect person, seeded from the recipe:
    ``offdyn_bench/wheel_legged/operator.py``), ``skill-mixture`` (``policy`` at each of
    :data:`SKILL_LEVELS`; ``action_noise_std`` is then the expert level's), ``training-replay``
    (the transitions the training run of ``policy``, a checkpoint, stored up to it; its sidecar
    says how to re-run it) or ``medium-expert`` (equal halves from ``policy`` and the recipe's
    oracle, both with ``action_noise_std``).
    """

    kind: Literal["uniform-random", "policy", "human-operator", "skill-mixture", "training-replay", "medium-expert"]
    policy: str | None = None
    policy_sha256: str | None = None
    action_noise_std: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in BEHAVIOUR_KINDS:
            raise UnknownNameError("behaviour kind", self.kind, BEHAVIOUR_KINDS)
        if self.kind == "human-operator" and self.policy is not None:
            raise RecipeError("a 'human-operator' behaviour is the operator in code; it takes no policy file")
        if self.kind in POLICY_KINDS and not self.policy:
            raise RecipeError(f"a {self.kind!r} behaviour needs the path of its .safetensors file")
        if not self.action_noise_std >= 0:
            raise RecipeError(f"action_noise_std must be >= 0, got {self.action_noise_std!r}")


@dataclasses.dataclass(frozen=True)
class Recipe:
    """Everything a build needs; two builds of one recipe give identical bytes."""

    dataset_id: str
    task: str
    task_version: int
    task_sha256: str
    quality: Quality
    behaviour: Behaviour
    num_transitions: int
    seed: int = DEFAULT_SEED
    collect_in: Literal["target", "source"] = "target"
    reference_episodes: int = REFERENCE_EPISODES
    reference_seed: int = REFERENCE_SEED
    oracle_policy: str | None = None
    oracle_policy_sha256: str | None = None
    data_format: str = DATA_FORMAT

    def __post_init__(self) -> None:
        if self.num_transitions < 1:
            raise RecipeError(f"{self.dataset_id}: num_transitions must be >= 1, got {self.num_transitions}")
        if self.reference_episodes < 1:
            raise RecipeError(f"{self.dataset_id}: reference_episodes must be >= 1, got {self.reference_episodes}")
        expected_side = "source" if self.quality == "source" else "target"
        if self.collect_in != expected_side:
            raise RecipeError(f"{self.dataset_id}: {self.quality!r} datasets are collected in the {expected_side}, "
                              f"got collect_in={self.collect_in!r}")
        for quality, kind in _QUALITY_KINDS.items():
            if (self.quality == quality) != (self.behaviour.kind == kind):
                raise RecipeError(f"{self.dataset_id}: the {quality!r} quality and only it has the {kind!r} "
                                  f"behaviour, got quality {self.quality!r} with behaviour {self.behaviour.kind!r}")
        if self.behaviour.kind == "medium-expert" and self.oracle_policy is None:
            raise RecipeError(f"{self.dataset_id}: a 'medium-expert' behaviour takes its expert half from the "
                              "recipe's oracle_policy, which is null")
        if self.data_format not in DATA_FORMATS:
            raise RecipeError(f"{self.dataset_id}: data_format {self.data_format!r}; expected one of "
                              f"{DATA_FORMATS} (Minari storages checked to build byte-identically)")

    @property
    def pair(self) -> TaskPair:
        return get_task(self.task)

    def check_task(self) -> TaskPair:
        """The task pair, after checking its dynamics are the ones this recipe was made for."""
        pair = self.pair
        if pair.version != self.task_version:
            raise RecipeError(f"{self.dataset_id}: recipe is for task {self.task} v{self.task_version}, "
                              f"the code defines v{pair.version}; make a new dataset version")
        if task_sha256(pair) != self.task_sha256:
            raise RecipeError(f"{self.dataset_id}: the definition of task {self.task} v{pair.version} changed "
                              "since this recipe was made (released task versions are frozen); "
                              "restore it or bump the task version")
        return pair

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Recipe:
        """A recipe from its JSON form; anything else (a list, a missing or mistyped field) is a
        :class:`RecipeError` that names the field and the type it should have."""
        if not isinstance(data, Mapping):
            raise RecipeError(f"a recipe must be a JSON object, got {json_type(data)}")
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - fields
        if unknown:
            raise RecipeError(f"recipe {data.get('dataset_id')!r}: unknown fields {sorted(unknown)}; "
                              f"expected {sorted(fields)}")
        where = f"recipe {data.get('dataset_id')!r}" if isinstance(data.get("dataset_id"), str) else "recipe"
        _check_fields(where, data, _RECIPE_FIELDS)
        behaviour = data["behaviour"]
        if not isinstance(behaviour, Mapping):
            raise RecipeError(f"{where}: field 'behaviour' must be a JSON object, got {json_type(behaviour)}")
        known = {f.name for f in dataclasses.fields(Behaviour)}
        if set(behaviour) - known:
            raise RecipeError(f"{where}: unknown behaviour fields {sorted(set(behaviour) - known)}; "
                              f"expected {sorted(known)}")
        _check_fields(f"{where}, behaviour", behaviour, _BEHAVIOUR_FIELDS)
        return cls(**{**data, "behaviour": Behaviour(**behaviour)})


# JSON field -> (accepted types, required); bool is refused where an int is meant.
_STR, _INT, _NUM, _OPT_STR = (str,), (int,), (int, float), (str, type(None))
_RECIPE_FIELDS: Mapping[str, tuple[tuple[type, ...], bool]] = {
    "dataset_id": (_STR, True), "task": (_STR, True), "task_version": (_INT, True), "task_sha256": (_STR, True),
    "quality": (_STR, True), "behaviour": ((Mapping,), True), "num_transitions": (_INT, True),
    "seed": (_INT, False), "collect_in": (_STR, False), "reference_episodes": (_INT, False),
    "reference_seed": (_INT, False), "oracle_policy": (_OPT_STR, False), "oracle_policy_sha256": (_OPT_STR, False),
    "data_format": (_STR, False),
}
_BEHAVIOUR_FIELDS: Mapping[str, tuple[tuple[type, ...], bool]] = {
    "kind": (_STR, True), "policy": (_OPT_STR, False), "policy_sha256": (_OPT_STR, False),
    "action_noise_std": (_NUM, False),
}
_TYPE_NAMES = {str: "a string", int: "an integer", float: "a number", type(None): "null", Mapping: "a JSON object"}


def json_type(value: object) -> str:
    """How a JSON value reads in an error message (``a list``, ``null``, ``a string``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    return {dict: "a JSON object", list: "a list", str: "a string", int: "an integer", float: "a number"}.get(
        type(value), type(value).__name__)


def _check_fields(where: str, data: Mapping[str, Any], spec: Mapping[str, tuple[tuple[type, ...], bool]]) -> None:
    for name, (types, required) in spec.items():
        if name not in data:
            if required:
                raise RecipeError(f"{where}: missing field {name!r}")
            continue
        value = data[name]
        if isinstance(value, bool) or not isinstance(value, types):
            expected = " or ".join(dict.fromkeys(_TYPE_NAMES[t] for t in types))
            raise RecipeError(f"{where}: field {name!r} must be {expected}, got {json_type(value)}")


def default_recipe(task: str | TaskPair, quality: str, *, version: int = 0,
                   num_transitions: int | None = None, seed: int = DEFAULT_SEED) -> Recipe:
    """The recipe this suite uses for ``task`` at ``quality`` (any task of the grid)."""
    pair = task if isinstance(task, TaskPair) else get_task(task)
    ident = dataset_id(pair, quality, version)
    _check_quality(pair, quality)
    if quality == "random":
        behaviour = Behaviour(kind="uniform-random")
    elif quality == "human-operator":
        behaviour = Behaviour(kind="human-operator")
    elif quality == "source":
        behaviour = Behaviour(kind="skill-mixture", policy=sac_policy_path(pair, "sac-source"),
                              action_noise_std=SKILL_LEVELS[0][1])  # type: ignore[arg-type]
    elif quality in H2O_QUALITIES:
        kinds = {"medium": "policy", "medium-replay": "training-replay", "medium-expert": "medium-expert"}
        behaviour = Behaviour(kind=kinds[quality], policy=sac_policy_path(pair, "sac-target-medium"),  # type: ignore[arg-type]
                              action_noise_std=0.0 if quality == "medium-replay" else DEFAULT_ACTION_NOISE_STD)
        if quality == "medium-replay" and num_transitions is None:
            num_transitions = replay_transitions(behaviour.policy)  # type: ignore[arg-type]
    else:
        behaviour = Behaviour(kind="policy", policy=sac_policy_path(pair, "sac-source"),
                              action_noise_std=DEFAULT_ACTION_NOISE_STD)
    return Recipe(
        dataset_id=ident, task=pair.name, task_version=pair.version, task_sha256=task_sha256(pair),
        quality=quality,  # type: ignore[arg-type]
        behaviour=behaviour,
        num_transitions=DEFAULT_TRANSITIONS[quality] if num_transitions is None else num_transitions,  # type: ignore[index]
        seed=seed, oracle_policy=sac_policy_path(pair, "sac-target"),
        collect_in="source" if quality == "source" else "target",
    )


def replay_transitions(policy: str) -> int:
    """How many transitions the training run of a checkpoint policy had stored when the checkpoint
    was taken (its sidecar's ``training.checkpoint_step`` for one seed); the default size before
    that policy exists."""
    from offdyn_bench.datasets.policies import sidecar_path

    sidecar = sidecar_path(pathlib.Path(policy) if pathlib.Path(policy).is_absolute() else REPO_ROOT / policy)
    if not sidecar.is_file():
        return DEFAULT_TRANSITIONS["medium-replay"]
    try:
        step = json.loads(sidecar.read_text())["training"]["checkpoint_step"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise RecipeError(f"{sidecar}: no training.checkpoint_step ({error!r}); it is not a checkpoint policy of "
                          "scripts/make_h2o_behaviours.py") from None
    if not is_integer(step) or step < 1:
        raise RecipeError(f"{sidecar}: training.checkpoint_step is {step!r}; expected an integer >= 1")
    return step


def default_tasks() -> list[TaskPair]:
    """The default set: one level of every shift family for each locomotion robot (the middle
    of the grid: x0.5 scales, the first part at ``medium``, action noise 0.5 in both of its
    versions), plus every H2O
    setting, both wheel-legged tasks, the MuJoCo-to-DART pairs and the protocol's core suite.
    Everything else in the grid builds on demand."""
    from offdyn_bench.protocol.definition import CORE_SUITE

    chosen = []
    for pair in TASKS.values():
        if pair.robot in HUMAN_OPERATOR_ROBOTS or pair.target_engine != "mujoco" or pair.name in CORE_SUITE:
            chosen.append(pair)
            continue
        if pair.robot not in ("Ant", "HalfCheetah", "Hopper", "Walker2d"):
            continue
        first_part = next((p.part for p in TASKS.values() if p.robot == pair.robot and p.shift == pair.shift), None)
        if pair.shift in ("gravity", "friction", "joint-noise") and pair.level == "0.5":
            chosen.append(pair)
        elif pair.shift in ("kinematic", "morph") and pair.level == "medium" and pair.part == first_part:
            chosen.append(pair)
        elif pair.source_effects and not pair.target_effects:  # the H2O settings: shifted simulator
            chosen.append(pair)
    return chosen


def default_recipes() -> list[Recipe]:
    """Every quality of every default task; ``source`` data for the protocol's core suite only
    (the offline-source tracks run there); any other task's builds on demand."""
    from offdyn_bench.protocol.definition import CORE_SUITE

    return [default_recipe(pair, quality) for pair in default_tasks() for quality in qualities_of(pair)
            if quality != "source" or pair.name in CORE_SUITE]
