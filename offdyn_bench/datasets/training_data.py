"""Target data from one SAC training run: the H2O settings' ``medium-expert`` and ``medium-replay``.

``medium-replay`` is what D4RL calls it: every transition the run stored in its replay buffer until
its policy reached the medium level. The run is re-run to the medium checkpoint from the settings
its checkpoint policy's sidecar records (training is deterministic on one device), its actor is
checked against the pinned policy, and then every episode in the buffer is simulated again from
the training's own reset seed with the stored actions, so the dataset carries the full physics
state like every other one. Each replayed observation, reward and termination must equal the
buffer's (which holds them in float32); a mismatch stops the build.
"""

from __future__ import annotations

import dataclasses
import pathlib
import tempfile
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium
import numpy as np

from offdyn_bench.datasets.archive import sha256_file
from offdyn_bench.datasets.collect import Level, run_episode
from offdyn_bench.datasets.policies import Policy, read_sidecar, sidecar_path
from offdyn_bench.datasets.recipes import Recipe, RecipeError, dynamics_label
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import TaskPair, get_task

TRAINING_ENV_STREAM = 1
"""The trainer's random stream of its training environments' episode seeds (``baselines.train``)."""
MAX_SKIPPED_EPISODES = 2
"""Episode indices the trainer may skip between two stored episodes: a checkpoint ends the running
episode, and one that ended on the very step before it leaves an index with no transition."""


class ReplayMismatchError(OffdynError):
    """A re-run or re-simulation of a training run that does not reproduce what the run stored."""


def medium_expert_levels(recipe: Recipe, medium: Policy, expert: Policy) -> list[Level]:
    """D4RL's ``medium-expert``: the medium policy's half first, then the oracle's, both with the
    recipe's Gaussian action noise, each level on its own noise stream."""
    std = recipe.behaviour.action_noise_std
    levels = []
    for index, (name, actor, path) in enumerate((("medium", medium, recipe.behaviour.policy),
                                                 ("expert", expert, recipe.oracle_policy))):
        noise_seed = [recipe.seed, 2, index]
        levels.append(Level(name, actor, {"actions": f"{path} (deterministic mean)", "action_noise_std": std,
                                          "action_noise_seed": noise_seed}, std, noise_seed))
    return levels


@dataclasses.dataclass
class _StoredActions:
    """A "policy" that plays back one stored episode's actions, mapped as the trainer maps them."""

    actions: np.ndarray
    low: np.ndarray
    high: np.ndarray
    step: int = 0
    scaled: np.ndarray = dataclasses.field(init=False)

    def __post_init__(self) -> None:
        # Every action as the env received it: the trainer's own scaling of a [-1, 1] action to
        # the box, in float64 (baselines.train._Envs.step).
        self.scaled = self.low + (self.actions.astype(np.float64) + 1.0) * 0.5 * (self.high - self.low)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        self.step += 1
        return self.scaled[self.step - 1]


def _training_settings(sidecar: Mapping[str, Any], where: str) -> tuple[dict[str, Any], int, int]:
    """(the run's config.json, the checkpoint step, the seed's member) from a checkpoint policy's sidecar."""
    training = sidecar.get("training")
    config = training.get("config") if isinstance(training, Mapping) else None
    step = training.get("checkpoint_step") if isinstance(training, Mapping) else None
    member = training.get("checkpoint_member", 0) if isinstance(training, Mapping) else None
    if not isinstance(config, Mapping) or not isinstance(step, int) or not isinstance(member, int):
        raise RecipeError(f"{where}: the policy's sidecar has no training.config, training.checkpoint_step and "
                          "training.checkpoint_member; only a checkpoint exported by scripts/make_h2o_behaviours.py "
                          "says how to re-run the training that stored the replay")
    for key in ("algo", "task", "steps", "seeds", "eval_every", "eval_episodes", "checkpoint_every", "config"):
        if key not in config:
            raise RecipeError(f"{where}: the policy's training.config lacks {key!r} (a train config.json has it)")
    if config["algo"] not in ("sac-target", "sac-source"):
        raise RecipeError(f"{where}: the replay of a {config['algo']!r} run; expected a plain SAC run "
                          "(sac-target or sac-source), whose buffer holds every transition it stepped")
    if step % int(config["checkpoint_every"]):
        raise RecipeError(f"{where}: checkpoint_step {step} is not a multiple of the run's checkpoint_every "
                          f"{config['checkpoint_every']}; no checkpoint was taken there")
    return dict(config), step, member


def rerun_to_checkpoint(sidecar: Mapping[str, Any], out: pathlib.Path, where: str,
                        progress: bool = False) -> pathlib.Path:
    """Re-run the training a checkpoint policy came from up to its checkpoint (with the trainer's
    progress bar when ``progress``: at full scale it takes hours); the checkpoint's state file."""
    from baselines.algorithms import config_overrides
    from baselines.checkpoint import checkpoints
    from baselines.train import train

    config, step, _ = _training_settings(sidecar, where)
    train(config["algo"], config["task"], steps=int(config["steps"]), out=out, seed=int(config["seeds"][0]),
          n_seeds=len(config["seeds"]), overrides=config_overrides(config["config"]),
          eval_every=int(config["eval_every"]), eval_episodes=int(config["eval_episodes"]),
          checkpoint_every=int(config["checkpoint_every"]), progress=progress, stop_after=step,
          device=str(config.get("device", "cpu")))
    found = [path for path in checkpoints(out) if path.name == f"step_{step:09d}"]
    if not found:
        raise ReplayMismatchError(f"{where}: the re-run wrote no checkpoint at step {step}")
    return found[0] / "state.safetensors"


def _episodes_of(buffer: Mapping[str, np.ndarray]) -> list[slice]:
    """Row ranges of the stored episodes: one ends where a transition terminated or where the next
    row does not start from its next observation (a time limit, a checkpoint's cut)."""
    observations, next_observations = buffer["observations"], buffer["next_observations"]
    ends = [i for i in range(len(observations) - 1)
            if buffer["terminations"][i] or not np.array_equal(next_observations[i], observations[i + 1])]
    starts = [0] + [i + 1 for i in ends]
    return [slice(a, b) for a, b in zip(starts, [i + 1 for i in ends] + [len(observations)])]


_REPLAYED_BUFFERS: dict[tuple[str, str, int], dict[str, np.ndarray]] = {}
"""Replay buffers re-run and checked in this process, by (policy sha256, sidecar sha256, member). A
build pinned to the manifest's BLAS kernel in a child process (datasets/kernel.py) starts without them."""


def collect_training_replay(recipe: Recipe, pair: TaskPair, env: gymnasium.Env,
                            on_progress: Callable[[int], None] | None) -> tuple[list, dict[str, Any]]:
    """The stored episodes of the recipe's training run up to its checkpoint, simulated again in
    ``env`` with full infos; and what was replayed."""
    from safetensors.numpy import load_file

    from baselines.train import _episode_seed
    from offdyn_bench.datasets.build import repo_path
    from offdyn_bench.datasets.policies import import_sac_actor

    where = recipe.dataset_id
    policy_path = repo_path(str(recipe.behaviour.policy))
    sidecar = read_sidecar(policy_path)
    config, step, member = _training_settings(sidecar, where)
    trained_in = dynamics_label(get_task(config["task"]), "target" if config["algo"] == "sac-target" else "source")
    if trained_in != dynamics_label(pair, "target"):
        raise RecipeError(f"{where}: {recipe.behaviour.policy} was trained in {trained_in}; this data is collected "
                          f"in {dynamics_label(pair, 'target')}, so its replay is not this target's")
    if step != recipe.num_transitions:  # plain SAC stores one transition per step: refuse before re-running
        raise RecipeError(f"{where}: the run stored {step} transitions up to step {step}; the recipe asks for "
                          f"{recipe.num_transitions} (medium-replay is all of them)")
    # One robot's H2O settings share a target, so their medium-replay data replay one run: re-run it
    # once per process (keyed by the exact policy it must reproduce).
    key = (sha256_file(policy_path), sha256_file(sidecar_path(policy_path)), member)
    buffer = _REPLAYED_BUFFERS.get(key)
    if buffer is None:
        with tempfile.TemporaryDirectory(prefix="offdyn-replay-") as scratch:
            scratch_dir = pathlib.Path(scratch)
            state_file = rerun_to_checkpoint(sidecar, scratch_dir / "run", where, progress=on_progress is not None)
            # The re-run must have trained the very policy the recipe pins, or its buffer is another run's.
            again = import_sac_actor(state_file, scratch_dir / "actor.safetensors", member=member,
                                     trained_on=str(sidecar.get("trained_on")), training={}, score=None)
            if sha256_file(again) != key[0]:
                raise ReplayMismatchError(f"{where}: re-running the training of {recipe.behaviour.policy} to step "
                                          f"{step} gave other actor weights than the pinned policy's (another "
                                          "platform, library version or code); the replay it stored cannot be "
                                          "reproduced here")
            state = load_file(str(state_file))
        buffer = {name: state[f"buffer.{name}"][member] for name in
                  ("observations", "actions", "rewards", "next_observations", "terminations")}
        _REPLAYED_BUFFERS[key] = buffer
    rows = len(buffer["rewards"])
    if rows != recipe.num_transitions:
        raise RecipeError(f"{where}: the run stored {rows} transitions up to step {step}; the recipe asks for "
                          f"{recipe.num_transitions} (medium-replay is all of them)")
    space = env.action_space
    assert isinstance(space, gymnasium.spaces.Box)
    low, high = space.low.astype(np.float64), space.high.astype(np.float64)
    seed = int(config["seeds"][member])
    episodes, index = [], 0
    for number, rows_of in enumerate(_episodes_of(buffer)):
        observations = buffer["observations"][rows_of]
        # The trainer's episode index, skipping indices a checkpoint cut left without a transition.
        for candidate in range(index, index + MAX_SKIPPED_EPISODES + 1):
            reset = np.asarray(env.reset(seed=_episode_seed(seed, TRAINING_ENV_STREAM, candidate))[0], np.float32)
            if np.array_equal(reset, observations[0]):
                index = candidate
                break
        else:
            tried = f"{index}-{index + MAX_SKIPPED_EPISODES}"
            raise ReplayMismatchError(f"{where}: stored episode {number} (rows {rows_of.start}-{rows_of.stop - 1}) "
                                      f"starts from no reset of training episodes {tried}")
        player = _StoredActions(buffer["actions"][rows_of], low, high)
        scaled = player.scaled
        if not np.array_equal(scaled.astype(space.dtype).astype(np.float64), scaled):
            raise ReplayMismatchError(f"{where}: the trainer's actions are not exact in the action space's dtype "
                                      f"{space.dtype}; a dataset could not store what the training applied")
        # Stepped in float64 as the trainer did (a reward's control cost depends on the dtype).
        episode = run_episode(env, player, seed=_episode_seed(seed, TRAINING_ENV_STREAM, index),
                              max_steps=len(observations), episode_id=number, step_in_space_dtype=False)
        stored_next = buffer["next_observations"][rows_of]
        checks = {"observations": (np.asarray(episode.observations[1:], np.float32), stored_next),
                  "rewards": (np.asarray(episode.rewards, np.float32), buffer["rewards"][rows_of]),
                  "terminations": (np.asarray(episode.terminations, np.float32), buffer["terminations"][rows_of])}
        for name, (replayed, stored) in checks.items():
            if replayed.shape != stored.shape or not np.array_equal(replayed, stored):
                raise ReplayMismatchError(f"{where}: replaying stored episode {number} gives other {name} than the "
                                          "run stored; the target is not the training's environment")
        episodes.append(episode)
        index += 1
        if on_progress is not None:
            on_progress(len(observations))
    described = {"training": {key: config[key] for key in ("algo", "task", "steps", "seeds", "checkpoint_every")},
                 "checkpoint_step": step, "transitions": rows, "episodes": len(episodes),
                 "episode_seeds": "the training run's own: SeedSequence([seed, 1, episode index]), in baselines.train",
                 "checked": "every replayed observation, reward and termination equals the run's float32 buffer"}
    return episodes, described


def choose_medium(returns: Mapping[int, float], random_return: float, expert_return: float,
                  fraction: float) -> int:
    """The checkpoint step whose return is closest to ``fraction`` of the way from random to the
    expert (the earliest on a tie); the expert's own final step is never a candidate."""
    if not expert_return > random_return:
        raise OffdynError(f"the expert's return {expert_return:.1f} does not exceed a random policy's "
                          f"{random_return:.1f}: train longer before choosing a medium level")
    final = max(returns)
    candidates = sorted(step for step in returns if step != final)
    if not candidates:
        raise OffdynError("the run has one checkpoint; a medium level needs earlier ones (lower checkpoint_every)")
    goal = random_return + fraction * (expert_return - random_return)
    return min(candidates, key=lambda step: (abs(returns[step] - goal), step))


KEPT_DIR = "kept-checkpoints"
"""Where :func:`train_keeping_checkpoints` keeps the actor of every checkpoint of a run (``train``
keeps two checkpoints, each with the whole replay buffer)."""
KEPT_ACTOR = "actor.safetensors"


def train_keeping_checkpoints(task: str, *, steps: int, checkpoint_every: int, out: pathlib.Path, seed: int = 0,
                              overrides: Mapping[str, str] | None = None) -> pathlib.Path:
    """``sac-target`` on ``task`` for ``steps``, one stretch of ``checkpoint_every`` steps at a time
    (``train`` resumes exactly), keeping each new checkpoint's actor in
    ``out/kept-checkpoints/step_<N>/`` (its sidecar names the run's config and the checkpoint with
    its sha256), so that every level of the run can be chosen from afterwards. Only the actors are
    kept: a checkpoint also holds the replay buffer, gigabytes over a 1M-step run, and
    ``medium-replay`` re-runs the training for it anyway. Resumable; returns the kept folder."""
    import json

    from baselines.checkpoint import checkpoints
    from baselines.train import train
    from offdyn_bench.datasets.policies import import_sac_actor

    trained_on = get_task(task).env_id("target")
    kept = out / KEPT_DIR
    kept.mkdir(parents=True, exist_ok=True)
    for stop in range(checkpoint_every, steps + 1, checkpoint_every):
        actor = kept / f"step_{stop:09d}" / KEPT_ACTOR
        if actor.is_file():
            continue
        train("sac-target", task, steps=steps, out=out / "run", seed=seed, overrides=overrides,
              eval_every=checkpoint_every, checkpoint_every=checkpoint_every, progress=False, stop_after=stop)
        latest = checkpoints(out / "run")[-1]
        if latest.name != actor.parent.name:
            raise OffdynError(f"{out / 'run'}: the newest checkpoint is {latest.name}, expected {actor.parent.name}")
        state = latest / "state.safetensors"
        training = {"config": json.loads((out / "run" / "config.json").read_text()),
                    "checkpoint": f"checkpoints/{latest.name}/state.safetensors", "checkpoint_step": stop,
                    "checkpoint_sha256": sha256_file(state)}
        import_sac_actor(state, actor, member=0, trained_on=trained_on, training=training, score=None)
    return kept


def export_h2o_behaviours(run_dir: pathlib.Path, kept: pathlib.Path, pair: TaskPair, *, out_root: pathlib.Path,
                          episodes: int, first_seed: int, fraction: float) -> dict[str, Any]:
    """From a finished ``sac-target`` run in ``pair``'s target and the actor of every checkpoint it
    took (``kept``): its final actor as the oracle and its checkpoint closest to ``fraction`` of
    the oracle (from random) as the medium policy, each written where
    :func:`~offdyn_bench.datasets.recipes.sac_policy_path` says under ``out_root``, with the run's
    config and the checkpoint in the sidecar (which ``medium-replay`` re-runs)."""
    import json
    import shutil

    from baselines.checkpoint import checkpoint_step
    from offdyn_bench.datasets.collect import random_reference_returns
    from offdyn_bench.datasets.policies import evaluate_policy, update_sidecar
    from offdyn_bench.datasets.recipes import sac_policy_path

    config = json.loads((run_dir / "config.json").read_text())
    if config.get("algo") != "sac-target" or not (run_dir / "result.json").is_file():
        raise OffdynError(f"{run_dir}: expected a finished sac-target run (config.json algo sac-target, result.json)")
    trained_on = get_task(config["task"]).env_id("target")
    if dynamics_label(get_task(config["task"]), "target") != dynamics_label(pair, "target"):
        raise OffdynError(f"{run_dir} trained in {dynamics_label(get_task(config['task']), 'target')}, not in "
                          f"{pair.name}'s target ({dynamics_label(pair, 'target')})")
    env = gymnasium.make(trained_on)
    random_returns, rng_seed = random_reference_returns(env, episodes=episodes, first_seed=first_seed)
    env.close()
    random_return = float(np.mean(random_returns))

    actors = {checkpoint_step(path): path / KEPT_ACTOR for path in sorted(kept.glob("step_*"))
              if (path / KEPT_ACTOR).is_file()}
    scores = {step: evaluate_policy(actor, trained_on, episodes, first_seed) for step, actor in actors.items()}
    returns = {step: score["mean_return"] for step, score in scores.items()}
    final = max(returns, default=None)
    if final != int(config["steps"]):
        raise OffdynError(f"{kept}: the last kept checkpoint is at step {final}, not the run's final step "
                          f"{config['steps']}")
    medium = choose_medium(returns, random_return, returns[final], fraction)
    level = {"fraction": fraction, "random_return": random_return, "random_rng_seed": rng_seed,
             "expert_return": returns[final], "chosen_step": medium,
             "checkpoint_returns": {str(step): r for step, r in sorted(returns.items())}}
    written = {}
    for role, step in (("sac-target", final), ("sac-target-medium", medium)):
        out = out_root / sac_policy_path(pair, role)  # type: ignore[arg-type]
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(actors[step], out)
        shutil.copyfile(sidecar_path(actors[step]), sidecar_path(out))
        training = read_sidecar(out)["training"] | ({"level": level} if role == "sac-target-medium" else {})
        update_sidecar(out, training=training, score={"evaluation": scores[step], "run_result": None})
        written[role] = out
    return {"expert": written["sac-target"], "medium": written["sac-target-medium"], "level": level}


def size_replay_recipes(robot: str, manifest_path: pathlib.Path | None = None) -> list[str]:
    """Give every unbuilt ``medium-replay`` recipe of ``robot``'s H2O settings in the manifest the
    size its shipped medium policy now says (what the run had stored at that checkpoint); the
    recipes were written before the policy existed, with a placeholder size. A recipe whose
    dataset is built already keeps its size: other data is a new dataset version. Returns the ids
    changed."""
    from offdyn_bench.datasets.manifest import Entry, read_manifest, write_manifest
    from offdyn_bench.datasets.recipes import default_recipe, is_h2o_setting
    from offdyn_bench.tasks import TASKS

    manifest = read_manifest(manifest_path)
    changed = []
    for pair in TASKS.values():
        if pair.robot.lower() != robot.lower() or not is_h2o_setting(pair):
            continue
        fresh = default_recipe(pair, "medium-replay")
        entry = manifest.entries.get(fresh.dataset_id)
        if entry is None or entry.recipe == fresh:
            continue
        if entry.files is not None:
            raise OffdynError(f"{fresh.dataset_id} is built with {entry.recipe.num_transitions} transitions; the "
                              f"medium policy now gives {fresh.num_transitions}: record it as a new version instead")
        manifest = manifest.with_entry(Entry(recipe=fresh))
        changed.append(fresh.dataset_id)
    if changed:
        write_manifest(manifest, manifest_path)
    return changed
