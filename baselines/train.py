"""The training loop shared by every method: environments, evaluation, metrics, checkpoints, resume.

``train(algo, task, steps=..., out=...)`` writes into ``out``:

* ``config.json`` -- everything that defines the run (algorithm, task and its version, seeds,
  budget, dataset spec and provenance, the method's full config); written first;
* ``metrics.jsonl`` -- the learning curve: every ``eval_every`` steps, per-seed mean return of the
  deployed (deterministic) policy over ``eval_episodes`` target episodes with fixed seeds;
* ``checkpoints/step_<N>/`` -- safetensors state (networks, optimizers, buffers, random streams);
* ``result.json`` -- the final per-seed, per-episode target returns, versions, task and dataset.

Several seeds train in one process, vectorised: one environment per seed stepped together, one
batched network per role (see :mod:`baselines.networks`).

Resuming: run the same command again. The run continues from the newest checkpoint and ends with
the same result as an uninterrupted run. To make that exact without restoring simulators
mid-episode, every training episode is seeded by (seed, episode index) and a checkpoint ends the
running training episodes (as time-limit truncations, so the critics still bootstrap); an
uninterrupted run does the same at the same steps.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from baselines.algorithms import apply_overrides, config_to_dict, get_algorithm
from baselines.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from baselines.data import load_dataset
from baselines.method import Method, MethodContext
from baselines.networks import mlp
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import TaskPair, get_task
from offdyn_bench.versions import versions

CONFIG_FILE, METRICS_FILE, RESULT_FILE = "config.json", "metrics.jsonl", "result.json"
EVAL_SEED = 1_000_000
"""Evaluation episode e is reset with seed EVAL_SEED + e, for every method and training seed."""
DATASET_SEED = 0
"""Seed of datasets collected on the spot (fixed so every training seed sees the same data)."""


def train(algo: str, task: str, *, steps: int, out: str | Path, seed: int = 0, n_seeds: int = 1,
          dataset: str | None = None, overrides: Mapping[str, str] | None = None,
          eval_every: int | None = None, eval_episodes: int = 10, checkpoint_every: int | None = None,
          threads: int | None = 1, progress: bool = True, stop_after: int | None = None) -> dict[str, Any] | None:
    """Train ``algo`` on ``task`` for ``steps`` steps with seeds ``seed .. seed + n_seeds - 1``.

    ``steps`` counts interaction-environment steps (gradient updates for offline CQL).
    ``eval_every`` defaults to steps/20, ``checkpoint_every`` to steps/10. ``stop_after`` stops the
    run after that many steps without finishing it, as a kill would (for tests). Returns the
    result, or None when stopped early.
    """
    if threads:
        torch.set_num_threads(threads)
    method_spec = get_algorithm(algo)
    pair = get_task(task)
    if steps <= 0 or n_seeds <= 0 or eval_episodes <= 0:
        raise OffdynError(f"steps, n_seeds and eval_episodes must be positive; got {steps}, {n_seeds}, {eval_episodes}")
    config = apply_overrides(method_spec.default_config(), dict(overrides or {}), algo)
    # DARC with target_data=online (the darc-online entry, or --set target_data=online) takes its
    # target transitions from the environment instead of a dataset.
    needs_dataset = method_spec.needs_dataset and getattr(config, "target_data", "offline") != "online"
    if needs_dataset and dataset is None:
        raise OffdynError(f"{algo} needs a target dataset: pass --dataset, e.g. collect:random:5000, "
                          "collect:<sac-source run folder>:5000 or a path to an .npz")
    if not needs_dataset and dataset is not None:
        raise OffdynError(f"{algo} does not use a target dataset; drop --dataset")
    eval_every = eval_every or max(1, steps // 20)
    checkpoint_every = checkpoint_every or max(1, steps // 10)
    seeds = tuple(range(seed, seed + n_seeds))
    settings = {"algo": algo, "task": pair.name, "task_version": pair.version, "steps": steps,
                "seeds": list(seeds), "dataset": dataset, "eval_every": eval_every,
                "eval_episodes": eval_episodes, "checkpoint_every": checkpoint_every,
                "config": config_to_dict(config)}

    out = Path(out)
    resuming = _check_out_dir(out, settings)
    dataset_provenance = None
    target_data = None
    if dataset is not None:
        data, dataset_provenance = load_dataset(dataset, pair, DATASET_SEED)
        if resuming:
            stored = json.loads((out / CONFIG_FILE).read_text())["dataset_provenance"]
            if stored["sha256"] != dataset_provenance["sha256"]:
                raise OffdynError(f"{out} was trained on another dataset (sha256 {stored['sha256'][:12]}..., now "
                                  f"{dataset_provenance['sha256'][:12]}...); use a new --out folder")
        target_data = data.to_batch(pair.make("target").action_space)
    if not resuming:
        out.mkdir(parents=True, exist_ok=True)
        _write_json_atomic(out / CONFIG_FILE, settings | {"task_spec": pair.to_dict(),
                                                          "dataset_provenance": dataset_provenance})

    probe = pair.make("target")
    context = MethodContext(observation_dim=int(np.prod(probe.observation_space.shape)),
                            action_dim=int(np.prod(probe.action_space.shape)), seeds=seeds,
                            target_data=target_data)
    probe.close()
    method = method_spec.build(config, context)
    loop = _Loop(method, pair, seeds, out)
    start = loop.restore() if resuming else 0

    bar = tqdm(total=steps, initial=start, unit="step", disable=not progress, desc=f"{algo} {pair.name}")
    final_returns = None
    for step in range(start, steps):
        metrics = loop.step(step)
        done = step + 1
        bar.update(1)
        if done % eval_every == 0 or done == steps:
            returns = loop.evaluate(eval_episodes)
            loop.log(done, returns, metrics)
            bar.set_postfix(target_return=f"{returns.mean():.1f}")
            final_returns = returns if done == steps else None
        if done % checkpoint_every == 0 or done == steps:
            loop.checkpoint(done)
        if stop_after is not None and done >= stop_after and done < steps:
            bar.close()
            return None
    bar.close()
    if final_returns is None:  # resumed after the last checkpoint but before result.json
        final_returns = loop.evaluate(eval_episodes)
    result = {"algo": algo, "task": pair.to_dict(), "dataset": dataset_provenance, "steps": steps,
              "seeds": list(seeds), "eval_episode_seeds": [EVAL_SEED + e for e in range(eval_episodes)],
              "returns": {str(s): [float(x) for x in final_returns[i]] for i, s in enumerate(seeds)},
              "mean_return": float(final_returns.mean()), "versions": versions(),
              "config": settings["config"]}
    _write_json_atomic(out / RESULT_FILE, result)
    return result


def _check_out_dir(out: Path, settings: dict[str, Any]) -> bool:
    """True when ``out`` holds an unfinished run of the same settings (resume); raises on anything
    that would overwrite other work."""
    if not out.exists():
        return False
    if not out.is_dir():
        raise OffdynError(f"--out {str(out)!r} exists and is not a folder")
    if not (out / CONFIG_FILE).exists():
        if any(out.iterdir()):
            raise OffdynError(f"--out {str(out)!r} is not empty and holds no training run; use a new folder")
        return False
    stored = json.loads((out / CONFIG_FILE).read_text())
    stored_settings = {k: stored.get(k) for k in settings}
    if stored_settings != json.loads(json.dumps(settings)):
        diffs = [k for k in settings if json.dumps(stored_settings[k], sort_keys=True)
                 != json.dumps(settings[k], sort_keys=True)]
        raise OffdynError(f"--out {str(out)!r} holds a run with other settings (differs in: {', '.join(diffs)}); "
                          "nothing was changed. Use a new --out folder, or the same settings to resume.")
    if (out / RESULT_FILE).exists():
        raise OffdynError(f"--out {str(out)!r} holds a finished run (result.json exists); nothing was changed")
    return True


def _write_json_atomic(path: Path, data: Any) -> None:
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(data, indent=1))
    os.replace(partial, path)


def _episode_seed(seed: int, stream: int, episode: int) -> int:
    return int(np.random.SeedSequence([int(seed), stream, int(episode)]).generate_state(1)[0])


class _Envs:
    """One environment per training seed, stepped together, each episode seeded by its index."""

    def __init__(self, pair: TaskPair, side: str, seeds: Sequence[int], stream: int) -> None:
        self.envs = [pair.make(side) for _ in seeds]
        self.seeds, self.stream = seeds, stream
        space = self.envs[0].action_space
        self.low, self.high = space.low.astype(np.float64), space.high.astype(np.float64)
        self.episodes = [0] * len(seeds)
        self.observations = np.zeros((len(seeds), *self.envs[0].observation_space.shape))

    def reset_all(self) -> None:
        for i, env in enumerate(self.envs):
            self.observations[i] = env.reset(seed=_episode_seed(self.seeds[i], self.stream, self.episodes[i]))[0]

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Step with ``[-1, 1]`` actions; returns (obs, rewards, next_obs, terminations) tensors."""
        scaled = self.low + (actions.numpy().astype(np.float64) + 1.0) * 0.5 * (self.high - self.low)
        obs = self.observations.copy()
        next_obs = np.zeros_like(obs)
        rewards, terminations = np.zeros(len(self.envs)), np.zeros(len(self.envs))
        for i, env in enumerate(self.envs):
            next_obs[i], rewards[i], terminated, truncated, _ = env.step(scaled[i])
            terminations[i] = float(terminated)
            if terminated or truncated:
                self.episodes[i] += 1
                self.observations[i] = env.reset(seed=_episode_seed(self.seeds[i], self.stream, self.episodes[i]))[0]
            else:
                self.observations[i] = next_obs[i]
        return tuple(torch.as_tensor(x, dtype=torch.float32) for x in (obs, rewards, next_obs, terminations))

    def end_episodes(self) -> None:
        """Cut every running episode (a checkpoint boundary) and start the next ones."""
        self.episodes = [e + 1 for e in self.episodes]
        self.reset_all()


class _Loop:
    def __init__(self, method: Method, pair: TaskPair, seeds: Sequence[int], out: Path) -> None:
        self.method, self.out, self.seeds = method, out, seeds
        self.train_envs = _Envs(pair, method.interaction, seeds, 1) if method.interaction != "none" else None
        self.target_envs = _Envs(pair, "target", seeds, 2) if method.target_step_every else None
        self.eval_envs = [pair.make("target") for _ in seeds]
        for envs in (self.train_envs, self.target_envs):
            if envs is not None:
                envs.reset_all()
        self.started = time.perf_counter()

    def step(self, step: int) -> dict[str, torch.Tensor]:
        method = self.method
        if self.train_envs is not None:
            env_actions, stored = method.explore(torch.as_tensor(self.train_envs.observations, dtype=torch.float32),
                                                 step)
            obs, rewards, next_obs, terminations = self.train_envs.step(env_actions)
            method.record(obs, stored, rewards, next_obs, terminations)
        if self.target_envs is not None and (step + 1) % method.target_step_every == 0:
            env_actions, stored = method.explore(torch.as_tensor(self.target_envs.observations, dtype=torch.float32),
                                                 step)
            obs, rewards, next_obs, terminations = self.target_envs.step(env_actions)
            method.record_target(obs, stored, rewards, next_obs, terminations)
        return method.train_step(step)

    def evaluate(self, episodes: int) -> np.ndarray:
        """Per-seed, per-episode target returns of the deployed policy, ``[seeds, episodes]``."""
        returns = np.zeros((len(self.seeds), episodes))
        space = self.eval_envs[0].action_space
        low, high = space.low.astype(np.float64), space.high.astype(np.float64)
        for e in range(episodes):
            obs = np.stack([env.reset(seed=EVAL_SEED + e)[0] for env in self.eval_envs])
            running = np.ones(len(self.seeds), dtype=bool)
            while running.any():
                actions = self.method.deploy(torch.as_tensor(obs, dtype=torch.float32)).numpy().astype(np.float64)
                scaled = low + (actions + 1.0) * 0.5 * (high - low)
                for i in np.flatnonzero(running):
                    obs[i], reward, terminated, truncated, _ = self.eval_envs[i].step(scaled[i])
                    returns[i, e] += reward
                    running[i] = not (terminated or truncated)
        return returns

    def log(self, step: int, returns: np.ndarray, metrics: Mapping[str, torch.Tensor]) -> None:
        line = {"step": step, "target_return": [float(x) for x in returns.mean(axis=1)],
                "target_return_mean": float(returns.mean()),
                "train": {k: float(torch.as_tensor(v).float().mean()) for k, v in metrics.items()},
                "wall_time_s": round(time.perf_counter() - self.started, 3)}
        with open(self.out / METRICS_FILE, "a") as f:
            f.write(json.dumps(line) + "\n")

    def checkpoint(self, step: int) -> None:
        # End the training episodes first, so the saved state is a clean episode start.
        for envs in (self.train_envs, self.target_envs):
            if envs is not None:
                envs.end_episodes()
        trainer = {"step": step,
                   "train_episodes": self.train_envs.episodes if self.train_envs else None,
                   "target_episodes": self.target_envs.episodes if self.target_envs else None}
        save_checkpoint(self.out, step, self.method.state_dict(), trainer)

    def restore(self) -> int:
        path = latest_checkpoint(self.out)
        if path is None:
            _truncate_metrics(self.out, 0)
            return 0
        tensors, trainer = load_checkpoint(path)
        self.method.load_state_dict(tensors)
        for envs, key in ((self.train_envs, "train_episodes"), (self.target_envs, "target_episodes")):
            if envs is not None:
                envs.episodes = list(trainer[key])
                envs.reset_all()
        _truncate_metrics(self.out, trainer["step"])
        return int(trainer["step"])


def _truncate_metrics(out: Path, step: int) -> None:
    """Drop learning-curve lines written after the checkpoint a run resumes from."""
    path = out / METRICS_FILE
    if path.exists():
        lines = [line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step]
        _write_json_lines_atomic(path, lines)


def _write_json_lines_atomic(path: Path, lines: list[str]) -> None:
    partial = path.with_name(path.name + ".partial")
    partial.write_text("".join(line + "\n" for line in lines))
    os.replace(partial, path)


def load_trained_policy(run_dir: str | Path) -> Callable[[np.ndarray], np.ndarray]:
    """The deployed action of a training run's latest checkpoint (seed index 0), as a function of
    one observation in environment units. Used as a behaviour policy for datasets."""
    run_dir = Path(run_dir)
    if not (run_dir / CONFIG_FILE).exists():
        raise OffdynError(f"{str(run_dir)!r} is not a training run folder (no {CONFIG_FILE})")
    path = latest_checkpoint(run_dir)
    if path is None:
        raise OffdynError(f"{str(run_dir)!r} has no checkpoint yet")
    settings = json.loads((run_dir / CONFIG_FILE).read_text())
    pair = get_task(settings["task"])
    tensors, _ = load_checkpoint(path)
    actor = [tensors[f"actor.{i}"][:1] for i in range(sum(1 for k in tensors if k.startswith("actor.")))]
    space = pair.make("target").action_space
    action_dim = int(np.prod(space.shape))
    low, high = space.low.astype(np.float64), space.high.astype(np.float64)

    def act(observation: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            out = mlp(actor, torch.as_tensor(observation, dtype=torch.float32).view(1, 1, -1))
        # Mean of the tanh-Gaussian; the deployed action is the last action_dim entries
        # (all of them for SAC, a_t for DAP).
        mean = out[0, 0, : out.shape[-1] // 2]
        scaled = torch.tanh(mean[-action_dim:]).numpy().astype(np.float64)
        return low + (scaled + 1.0) * 0.5 * (high - low)

    return act
