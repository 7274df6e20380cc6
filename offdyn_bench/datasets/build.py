"""Build a dataset from its recipe: collect in the target (in the source for ``source`` data),
write with Minari, hash, archive, install.

The bytes are a function of the recipe, the code and the platform's libraries only: fixed seeds,
a deterministic behaviour, no time, host or absolute path in the metadata, and archives with
fixed member order, owner and time. Minari's storages add nothing that varies (h5py writes no
object timestamps by default, Arrow IPC files carry none); ``tests/datasets/test_datasets_build.py``
builds each format twice and compares the sha256 of every file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pathlib
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import gymnasium
import numpy as np

from offdyn_bench.datasets.archive import compare_files, tree_sha256, write_archive
from offdyn_bench.datasets.collect import (
    LEVEL_INFO,
    Level,
    collect_levels,
    collect_transitions,
    episode_returns,
    gaussian_action_noise,
    random_reference_returns,
)
from offdyn_bench.datasets.kernel import DATASET_BLAS_KERNEL, KernelPlan, call_on_kernel, current_plan
from offdyn_bench.datasets.install import InstallError, dataset_dir, install_tree, is_installed, resolve_root, staging
from offdyn_bench.datasets.manifest import (
    ArchiveRecord,
    Entry,
    Manifest,
    archive_name,
    entry_name,
    read_manifest,
    write_json_atomically,
    write_manifest,
)
from offdyn_bench.datasets.policies import (
    Policy,
    PolicyError,
    UniformRandomPolicy,
    derived_seed,
    load_policy,
    policy_sha256,
    read_sidecar,
)
from offdyn_bench.datasets.recipes import (
    H2O_QUALITIES,
    POLICY_KINDS,
    REPO_ROOT,
    SKILL_LEVELS,
    Recipe,
    RecipeError,
    dynamics_label,
)
from offdyn_bench.datasets.training_data import collect_training_replay, medium_expert_levels
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import TaskPair
from offdyn_bench.versions import versions

AUTHOR = "offdyn-bench"
AUTHOR_EMAIL = "offdyn-bench@users.noreply.github.com"
INFOS_LAYOUT = ("infos row 0 comes from reset, row t+1 from step t; infos/state[t] is the full physics state "
                "(mjSTATE_FULLPHYSICS, then channel delay buffers) of observation t, so step t goes from "
                "state[t] to state[t+1] under actions[t]; infos/applied_action is the command the physics "
                "received on targets with action-channel effects; keys a reset does not report are NaN in row 0")


class MissingPolicyError(OffdynError):
    """A recipe's behaviour policy (or a required file of it) is not where the recipe says."""


class BuildMismatchError(OffdynError):
    """A rebuild whose bytes differ from the hashes the manifest records."""


@contextlib.contextmanager
def minari_root(path: pathlib.Path) -> Iterator[None]:
    """Point Minari at ``path`` for the duration (Minari places datasets by this variable only)."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    try:
        yield
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def repo_path(path: str) -> pathlib.Path:
    """Recipe paths are relative to the repository root (``assets/policies/...``)."""
    candidate = pathlib.Path(path)
    return candidate if candidate.is_absolute() else REPO_ROOT / candidate


@dataclasses.dataclass(frozen=True)
class BuildResult:
    entry: Entry
    installed_at: pathlib.Path | None
    archive_path: pathlib.Path | None
    seconds: float
    already_installed: bool = False

    @property
    def transitions_per_second(self) -> float:
        return (self.entry.total_steps or 0) / self.seconds if self.seconds > 0 else float("nan")


def _behaviour(recipe: Recipe, pair: TaskPair, env: gymnasium.Env) -> tuple[Policy, Recipe, dict[str, Any]]:
    """The behaviour policy, the recipe with its policy hash pinned, and its provenance."""
    space = env.action_space
    assert isinstance(space, gymnasium.spaces.Box)
    behaviour = recipe.behaviour
    if behaviour.kind == "uniform-random":
        seed = [recipe.seed, 1]
        return (UniformRandomPolicy(space.low, space.high, seed=derived_seed(seed)),
                recipe, {"kind": "uniform-random", "rng_seed": seed})
    if behaviour.kind == "human-operator":
        from offdyn_bench.wheel_legged.operator import HumanOperator  # only this robot's builds need scipy

        seed = [recipe.seed, 3]
        operator = HumanOperator(str(pair.task), seed=derived_seed(seed))
        return operator, recipe, {**operator.describe(), "rng_seed": seed,
                                  "episode_rng": "numpy default_rng([operator seed, episode reset seed])"}
    path = repo_path(str(behaviour.policy))
    if not path.is_file():
        raise _missing_behaviour(recipe, pair)
    try:
        sidecar = read_sidecar(path)
        policy = load_policy(path)
        digest = policy_sha256(path)
    except PolicyError as error:
        raise MissingPolicyError(f"{recipe.dataset_id}: {error}") from error
    if behaviour.policy_sha256 is not None and behaviour.policy_sha256 != digest:
        raise RecipeError(f"{recipe.dataset_id}: behaviour policy {behaviour.policy} has sha256 {digest}, the "
                          f"recipe pins {behaviour.policy_sha256}; a new policy is a new dataset version")
    obs_dim = int(np.prod(env.observation_space.shape))  # type: ignore[arg-type]
    if policy.observation_dim != obs_dim or policy.action_dim != space.shape[0]:
        raise PolicyError(f"{recipe.dataset_id}: policy {behaviour.policy} maps {policy.observation_dim} -> "
                          f"{policy.action_dim}, the task's target env has {obs_dim} -> {space.shape[0]}")
    pinned = dataclasses.replace(recipe, behaviour=dataclasses.replace(behaviour, policy_sha256=digest))
    provenance = {"kind": behaviour.kind, "policy": behaviour.policy, "policy_sha256": digest,
                  "trained_on": sidecar.get("trained_on"), "training": sidecar.get("training"),
                  "score": sidecar.get("score"), "action_noise_std": behaviour.action_noise_std,
                  "action_noise_seed": [recipe.seed, 2]}
    return policy, pinned, provenance


def _missing_behaviour(recipe: Recipe, pair: TaskPair) -> MissingPolicyError:
    if recipe.quality in H2O_QUALITIES:
        return MissingPolicyError(
            f"{recipe.dataset_id}: behaviour policy {recipe.behaviour.policy} is missing. It is the medium checkpoint "
            f"of the SAC oracle run in the target ({dynamics_label(pair, 'target')}). Make it and the oracle with: "
            f"python scripts/make_h2o_behaviours.py --robot {pair.robot.lower()}, then run: "
            f"offdyn-bench datasets build {recipe.dataset_id} --update-manifest")
    return MissingPolicyError(
        f"{recipe.dataset_id}: behaviour policy {recipe.behaviour.policy} is missing. It is the SAC policy trained "
        f"in the source dynamics ({dynamics_label(pair, 'source')}), DAP's 'RL on source'. Train it with "
        f"the SAC baseline, put its .safetensors and .json sidecar at {recipe.behaviour.policy}, then run: "
        f"offdyn-bench datasets build {recipe.dataset_id} --update-manifest")


def check_buildable(recipe: Recipe) -> None:
    """Everything a build of ``recipe`` needs from disk is there: the task's dynamics are the
    recipe's, and the policy files it names exist with the hashes it pins. Cheap (no env, no
    step), so a caller can fail before it shows any progress."""
    pair = recipe.check_task()
    behaviour = recipe.behaviour
    if behaviour.kind in POLICY_KINDS:
        path = repo_path(str(behaviour.policy))
        if not path.is_file():
            raise _missing_behaviour(recipe, pair)
        try:
            digest = policy_sha256(path)
        except (OSError, PolicyError) as error:
            raise MissingPolicyError(f"{recipe.dataset_id}: behaviour policy {behaviour.policy}: {error}") from error
        if behaviour.policy_sha256 is not None and behaviour.policy_sha256 != digest:
            raise RecipeError(f"{recipe.dataset_id}: behaviour policy {behaviour.policy} has sha256 {digest}, the "
                              f"recipe pins {behaviour.policy_sha256}; a new policy is a new dataset version")
    if recipe.oracle_policy is not None and recipe.oracle_policy_sha256 is not None \
            and not repo_path(recipe.oracle_policy).is_file():
        raise MissingPolicyError(f"{recipe.dataset_id}: the recipe pins oracle {recipe.oracle_policy} "
                                 f"(sha256 {recipe.oracle_policy_sha256}) but the file is missing")


def _oracle(recipe: Recipe, fresh: bool) -> tuple[pathlib.Path | None, Recipe]:
    """The oracle file to score with, and the recipe with its hash pinned.

    A recipe that pins an oracle must find that very file. One that pins none uses an oracle
    that ships only when the build records a new dataset (``fresh``): reproducing a recorded
    dataset must not pick up an oracle that arrived later (its score would change the bytes;
    it belongs in the next dataset version)."""
    if recipe.oracle_policy is None:
        return None, recipe
    path = repo_path(recipe.oracle_policy)
    if recipe.oracle_policy_sha256 is not None:
        if not path.is_file():
            raise MissingPolicyError(f"{recipe.dataset_id}: the recipe pins oracle {recipe.oracle_policy} "
                                     f"(sha256 {recipe.oracle_policy_sha256}) but the file is missing")
        digest = policy_sha256(path)
        if digest != recipe.oracle_policy_sha256:
            raise RecipeError(f"{recipe.dataset_id}: oracle {recipe.oracle_policy} has sha256 {digest}, the recipe "
                              f"pins {recipe.oracle_policy_sha256}; a new oracle is a new dataset version")
        return path, recipe
    if fresh and path.is_file():
        return path, dataclasses.replace(recipe, oracle_policy_sha256=policy_sha256(path))
    return None, recipe


SKILL_LEVEL_INFO = LEVEL_INFO
"""The infos column of a ``skill-mixture`` dataset that says which of SKILL_LEVELS acted (its index)."""


def _skill_levels(recipe: Recipe, env: gymnasium.Env, policy: Policy) -> list[Level]:
    """:data:`SKILL_LEVELS`: the behaviour policy at each noise level, then uniform-random actions."""
    space = env.action_space
    assert isinstance(space, gymnasium.spaces.Box)
    levels = []
    for index, (name, noise_std) in enumerate(SKILL_LEVELS):
        if noise_std is None:
            rng_seed = [recipe.seed, 1]
            levels.append(Level(name, UniformRandomPolicy(space.low, space.high, seed=derived_seed(rng_seed)),
                                {"actions": "uniform random", "rng_seed": rng_seed}))
        else:
            noise_seed = [recipe.seed, 2, index]
            levels.append(Level(name, policy, {"actions": "behaviour policy", "action_noise_std": noise_std,
                                               "action_noise_seed": noise_seed}, noise_std, noise_seed))
    return levels


def reference_scores(recipe: Recipe, pair: TaskPair, oracle_path: pathlib.Path | None) -> dict[str, Any]:
    """Returns in the target of a uniform-random policy and, when ``oracle_path`` is given, of
    the ``sac-target`` oracle; both on the same fixed episode seeds, with their provenance."""
    env = pair.make("target")
    seeds = list(range(recipe.reference_seed, recipe.reference_seed + recipe.reference_episodes))
    random_returns, rng_seed = random_reference_returns(env, episodes=recipe.reference_episodes,
                                                        first_seed=recipe.reference_seed)
    common = {"env_id": pair.env_id("target"), "episode_seeds": seeds, "versions": versions(),
              "command": f"offdyn-bench datasets build {recipe.dataset_id}"}
    scores: dict[str, Any] = {
        "random": {"value": float(np.mean(random_returns)), "std": float(np.std(random_returns)),
                   "returns": random_returns, "policy": "uniform random actions", "rng_seed": rng_seed, **common},
    }
    if oracle_path is not None:
        oracle = load_policy(oracle_path)
        oracle_returns = episode_returns(env, oracle, episodes=recipe.reference_episodes, seed=seeds[0])
        sidecar = read_sidecar(oracle_path)
        scores["sac-target"] = {"value": float(np.mean(oracle_returns)), "std": float(np.std(oracle_returns)),
                                "returns": oracle_returns, "policy": recipe.oracle_policy,
                                "policy_sha256": recipe.oracle_policy_sha256, "training": sidecar.get("training"),
                                **common}
    else:
        scores["sac-target"] = {"value": None, "policy": recipe.oracle_policy,
                                "note": "no sac-target policy (SAC trained in the target, DAP's 'RL on target') "
                                        "was available when this dataset version was built; the score is left "
                                        "empty rather than guessed"}
    env.close()
    return scores


def _write_with_minari(recipe: Recipe, pair: TaskPair, episodes: list, scores: dict[str, Any],
                       provenance: dict[str, Any], root: pathlib.Path) -> pathlib.Path:
    import minari

    oracle = scores["sac-target"]["value"]
    refs = {} if oracle is None else {"ref_min_score": scores["random"]["value"], "ref_max_score": oracle}
    with minari_root(root), _size_computed_once():
        dataset = minari.create_dataset_from_buffers(
            dataset_id=recipe.dataset_id,
            buffer=episodes,
            env=pair.env_id("source"),
            eval_env=pair.env_id("target"),
            algorithm_name=f"offdyn-bench {recipe.quality}",
            author=AUTHOR,
            author_email=AUTHOR_EMAIL,
            code_permalink="offdyn_bench/datasets/build.py",
            description=(f"{recipe.quality} data collected in the {recipe.collect_in} of task {pair.name} "
                         f"v{pair.version} ({pair.description}); env_spec is the source, eval_env_spec the target."),
            data_format=recipe.data_format,
            requirements=[f"mujoco=={versions()['mujoco']}", f"gymnasium=={versions()['gymnasium']}"],
            **refs,
        )
    storage = dataset.storage
    storage.update_metadata({"dataset_size": storage.get_size(), "offdyn": provenance})
    return root / recipe.dataset_id


@contextlib.contextmanager
def _size_computed_once() -> Iterator[None]:
    """Minari re-measures the whole dataset directory after every episode it writes (quadratic
    in the number of episodes: most of a random-policy build's time). Defer it: the caller
    measures once at the end, which gives the same field."""
    from minari.dataset.minari_storage import MinariStorage

    measure = MinariStorage.get_size
    MinariStorage.get_size = lambda self: 0.0  # type: ignore[method-assign]
    try:
        yield
    finally:
        MinariStorage.get_size = measure  # type: ignore[method-assign]


def build_dataset(recipe: Recipe, *, root: pathlib.Path | None = None, out_dir: pathlib.Path | None = None,
                  recorded: Entry | None = None, install: bool = True, replace: bool = False,
                  on_progress: Callable[[int], None] | None = None) -> BuildResult:
    """Build ``recipe`` and (by default) install it under the Minari datasets root.

    ``out_dir`` receives the archive and manifest entry in the remote layout. ``recorded`` is
    the manifest entry to reproduce: when it has file hashes, a build whose bytes differ is an
    error and nothing is installed or written.

    The build runs on OpenBLAS's Haswell kernel, the one the manifest was built on: in a child
    process when numpy loaded another (:mod:`offdyn_bench.datasets.kernel`).
    """
    plan = current_plan()
    arguments = {"recipe": recipe, "root": resolve_root(root), "out_dir": out_dir, "recorded": recorded,
                 "install": install, "replace": replace, "plan": plan}
    if plan.where == "child":
        started = time.perf_counter()
        result: BuildResult = call_on_kernel(_build_here, arguments, plan.kernel or DATASET_BLAS_KERNEL, on_progress)
        # The child's clock leaves out its start-up: the figure a caller reports is the whole build.
        return dataclasses.replace(result, seconds=time.perf_counter() - started)
    return _build_here(**arguments, on_progress=on_progress)


def _build_here(recipe: Recipe, *, root: pathlib.Path, out_dir: pathlib.Path | None, recorded: Entry | None,
                install: bool, replace: bool, plan: KernelPlan,
                on_progress: Callable[[int], None] | None = None) -> BuildResult:
    started = time.perf_counter()
    pair = recipe.check_task()
    env = pair.make(recipe.collect_in)
    policy, recipe, behaviour = _behaviour(recipe, pair, env)
    fresh = recorded is None or recorded.files is None
    if recipe.behaviour.kind == "medium-expert":
        # The oracle acts in this data, so it must be there before anything is collected.
        oracle_path, recipe = _oracle(recipe, fresh=True)
        if oracle_path is None:
            raise MissingPolicyError(f"{recipe.dataset_id}: the expert half is the oracle {recipe.oracle_policy}, "
                                     "which is missing; make it with scripts/make_h2o_behaviours.py")
    if recipe.behaviour.kind in ("skill-mixture", "medium-expert"):
        for per_level in ("action_noise_std", "action_noise_seed"):  # each level has its own: see "levels"
            behaviour.pop(per_level)
        levels = (_skill_levels(recipe, env, policy) if recipe.behaviour.kind == "skill-mixture"
                  else medium_expert_levels(recipe, policy, load_policy(oracle_path)))
        episodes, behaviour["levels"] = collect_levels(env, levels, num_transitions=recipe.num_transitions,
                                                       seed=recipe.seed, on_step=on_progress)
    elif recipe.behaviour.kind == "training-replay":
        episodes, behaviour["replay"] = collect_training_replay(recipe, pair, env, on_progress)
    else:
        noise = gaussian_action_noise(recipe.behaviour.action_noise_std, derived_seed([recipe.seed, 2]))
        episodes = list(collect_transitions(env, policy, num_transitions=recipe.num_transitions, seed=recipe.seed,
                                            action_noise=noise, on_step=on_progress))
    env.close()
    oracle_path, recipe = _oracle(recipe, fresh=fresh)
    scores = reference_scores(recipe, pair, oracle_path)
    built_with = versions() | ({"blas_kernel": plan.kernel} if plan.kernel else {})
    provenance = {
        "recipe": recipe.to_dict(),
        "task": pair.to_dict(),
        "behaviour": behaviour,
        "seeds": {"episode_seeds": (f"{recipe.seed} + episode index" if recipe.behaviour.kind != "training-replay"
                                    else "the training run's own (see behaviour.replay)"), "episodes": len(episodes)},
        "reference_scores": scores,
        "versions": versions(),
        "infos": INFOS_LAYOUT,
        "command": f"offdyn-bench datasets build {recipe.dataset_id}",
    }
    with staging(root) as work:
        built = _write_with_minari(recipe, pair, episodes, scores, provenance, work / "minari")
        files = tree_sha256(built)
        if recorded is not None and recorded.files is not None:
            problems = compare_files(recorded.files, files)
            if problems:
                raise BuildMismatchError(
                    f"rebuilt {recipe.dataset_id} differs from the manifest ({len(problems)} problems: "
                    + "; ".join(problems[:3]) + "). The manifest was built with "
                    f"{_with_kernel(recorded.built_with)}, this build uses {built_with} ({plan.reason}); "
                    "nothing was installed")
        # An identical installed copy is kept; a different one only goes with --force.
        already = install and not replace and is_installed(recipe.dataset_id, root)
        if already and tree_sha256(dataset_dir(recipe.dataset_id, root)) != files:
            raise InstallError(f"{recipe.dataset_id} is installed at {dataset_dir(recipe.dataset_id, root)} with "
                               "other bytes; pass --force to replace it")
        archive_path = (out_dir if out_dir is not None else work / "archive") / archive_name(recipe.dataset_id)
        archive_sha = write_archive(built, archive_path)
        entry = Entry(recipe=recipe, files=files,
                      file_sizes={rel: (built / rel).stat().st_size for rel in files},
                      archive=ArchiveRecord(archive_name(recipe.dataset_id), archive_sha, archive_path.stat().st_size),
                      total_steps=sum(len(e.rewards) for e in episodes), total_episodes=len(episodes),
                      reference_scores=scores, built_with=built_with)
        if out_dir is not None:
            publish_entry(entry, out_dir)
        installed_at = None
        if already:
            installed_at = dataset_dir(recipe.dataset_id, root)
        elif install:
            installed_at = install_tree(built, recipe.dataset_id, root=root, replace=replace)
    return BuildResult(entry=entry, installed_at=installed_at,
                       archive_path=archive_path if out_dir is not None else None,
                       seconds=time.perf_counter() - started, already_installed=already)


def _with_kernel(built_with: Mapping[str, Any] | None) -> dict[str, Any]:
    """``built_with`` naming the BLAS kernel: entries recorded before it was written down were all built
    on :data:`DATASET_BLAS_KERNEL`."""
    return {"blas_kernel": DATASET_BLAS_KERNEL} | dict(built_with or {})


def publish_entry(entry: Entry, out_dir: pathlib.Path) -> None:
    """Write an entry in the remote layout: ``<id>.json`` beside the archive, and the folder's
    ``datasets.json`` updated to include it."""
    write_json_atomically(out_dir / entry_name(entry.dataset_id), entry.to_dict())
    index = out_dir / "datasets.json"
    manifest = read_manifest(index) if index.is_file() else Manifest({})
    write_manifest(manifest.with_entry(entry), index)


def record_in_manifest(entry: Entry, path: pathlib.Path | None = None) -> pathlib.Path:
    """Write ``entry`` into the shipped manifest (or the one at ``path``)."""
    manifest = read_manifest(path)
    return write_manifest(manifest.with_entry(entry), path)
