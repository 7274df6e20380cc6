"""The training loop shared by every method: environments, evaluation, metrics, checkpoints, resume.

``train(algo, task, steps=..., out=...)`` writes into ``out``:

* ``config.json`` -- everything that defines the run (algorithm, task and its version, seeds,
  budget, dataset spec and provenance, the source dataset's on the offline-source tracks, the
  method's full config); written first;
* ``metrics.jsonl`` -- the learning curve: every ``eval_every`` steps, per-seed mean return of the
  deployed (deterministic) policy over ``eval_episodes`` target episodes with fixed seeds;
* ``checkpoints/step_<N>/`` -- safetensors state (networks, optimizers, buffers, random streams)
  with the sha256 of its files; the two newest are kept (:mod:`baselines.checkpoint`);
* ``result.json`` -- the final per-seed, per-episode target returns, versions, task and dataset(s),
  ``warnings`` (e.g. a budget too short for the method to make any update), ``compute``: the
  training's wall and CPU seconds over all its attempts, and that CPU in updates of a reference
  workload timed on the machine as it ran (:class:`baselines.run_folder.TrainingCompute`,
  :mod:`offdyn_bench.machine_speed`),
  and ``machines``: the distinct machines its attempts ran on (:func:`offdyn_bench.versions.machine`;
  a ``null`` entry stands for attempts before checkpoints recorded them), since the same seed trains
  another policy on another CPU model; ``source_revisions``: likewise the suite's code revisions
  (:func:`offdyn_bench.versions.source_revision`, ``null`` where unknown); and ``started_at`` /
  ``finished_at``: the UTC times the first attempt started and the last one finished (CPU seconds
  measured on different days of one machine can differ: PROTOCOL §8);
* ``.lock`` -- locked while a process trains in the folder, so a second one is refused.

Every argument and config value is checked before anything is written, so bad input leaves no
folder behind (:mod:`baselines.run_folder`, :mod:`baselines.limits`).

Several seeds train in one process, vectorised: one environment per seed stepped together, one
batched network per role (see :mod:`baselines.networks`).

Resuming: run the same command again. The run continues from the newest checkpoint and ends with
the same result as an uninterrupted run. To make that exact without restoring simulators
mid-episode, every training episode is seeded by (seed, episode index) and a checkpoint ends the
running training episodes (as time-limit truncations, so the critics still bootstrap); an
uninterrupted run does the same at the same steps. A damaged newest checkpoint (truncated,
missing files, flipped bytes) is reported and the run resumes from the one before it; learning-curve
lines after the resumed step, and a line cut off by the kill, are dropped.

Compute is carried across resumes: each checkpoint stores the wall and CPU time spent so far, so a
resumed run's ``metrics.jsonl`` times and its ``result.json`` compute count every attempt (each up to
the checkpoint it was resumed from: steps a killed attempt took after that are done again, and
counted once).
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from baselines.algorithms import apply_overrides, config_to_dict, get_algorithm
from baselines.checkpoint import (CHECKPOINT_DIR, STATE_FILE, TRAINER_FILE, DamagedCheckpointError, checkpoint_step,
                                  checkpoints, latest_checkpoint, load_checkpoint, save_checkpoint)
from baselines.data import load_dataset
from baselines.method import Method, MethodContext
from baselines.networks import mlp
from baselines.run_folder import (CONFIG_FILE, METRICS_FILE, RESULT_FILE, TrainingCompute, check_writable,
                                  holds_files, read_config, read_metrics, run_folder_lock, write_json_atomic,
                                  write_lines_atomic)
from offdyn_bench.envs import flat_observations
from offdyn_bench.errors import OffdynError
from offdyn_bench.json_values import is_integer
from offdyn_bench.machine_speed import reference_update_seconds
from offdyn_bench.protocol.definition import ProtocolError
from offdyn_bench.protocol.training import resolve_run
from offdyn_bench.tasks import TaskPair, get_task
from offdyn_bench.versions import machine, source_revision, utc_now, versions

EVAL_SEED = 1_000_000
"""Evaluation episode e is reset with seed EVAL_SEED + e, for every method and training seed."""
DATASET_SEED = 0
"""Seed of datasets collected on the spot (fixed so every training seed sees the same data)."""
SOURCE_DATASET_SEED = 1
"""Seed of source datasets collected on the spot (another stream than the target's)."""


def train(algo: str, task: str, *, steps: int | None = None, out: str | Path, seed: int = 0, n_seeds: int = 1,
          dataset: str | None = None, overrides: Mapping[str, str] | None = None,
          eval_every: int | None = None, eval_episodes: int = 10, checkpoint_every: int | None = None,
          threads: int | None = 1, progress: bool = True, stop_after: int | None = None,
          track: str | None = None, budget: str | None = None, device: str = "cpu",
          source_dataset: str | None = None, eval_on_device: bool = False) -> dict[str, Any] | None:
    """Train ``algo`` on ``task`` for ``steps`` steps with seeds ``seed .. seed + n_seeds - 1``.

    ``steps`` counts interaction-environment steps (gradient updates for offline CQL and the
    offline-source methods).
    ``eval_every`` defaults to steps/20, ``checkpoint_every`` to steps/10. ``stop_after`` stops the
    run after that many steps without finishing it, as a kill would (for tests). Returns the
    result, or None when stopped early.

    ``budget`` (``lite``/``full``) sets ``steps`` from the protocol; ``track`` is checked against
    the method (default: the method's own track). A method that needs a target dataset and gets
    none trains on the task's official dataset, installed and verified first.

    ``source_dataset`` (same spec forms as ``dataset``; ``collect:`` steps the *source*) is the
    fixed source data of the offline-source methods (``dara``, ``h2o-offline-source``); their
    default is the task's official source dataset, installed and verified the same way.

    ``device`` (``cpu``, ``cuda``, ``cuda:N`` or ``auto``) holds the networks, buffers and random
    streams; a run is deterministic per device (CPU and CUDA draw different random numbers), and the
    device is recorded in ``config.json`` and ``result.json``. On an accelerator the in-training
    evaluations act from a CPU copy of the policy; ``eval_on_device`` keeps them on the device
    (the way to measure the difference; recorded in ``config.json``).
    """
    device = resolve_device(device)
    if eval_on_device and device == "cpu":
        raise OffdynError("--eval-on-device keeps an accelerator run's evaluations on the accelerator; this run is "
                          "on the CPU, where they are already: drop it, or use --device cuda")
    method_spec = get_algorithm(algo)
    pair = get_task(task)
    if steps is not None:
        _check_arguments(steps=steps, n_seeds=n_seeds, eval_episodes=eval_episodes, eval_every=eval_every,
                         checkpoint_every=checkpoint_every, threads=threads)
    config = apply_overrides(method_spec.default_config(), dict(overrides or {}), algo)
    # DARC with target_data=online (the darc-online entry, or --set target_data=online) takes its
    # target transitions from the environment instead of a dataset.
    needs_dataset = method_spec.needs_dataset and getattr(config, "target_data", "offline") != "online"
    if not needs_dataset and dataset is not None:
        raise OffdynError(f"{algo} does not use a target dataset; drop --dataset")
    if not method_spec.needs_source_dataset and source_dataset is not None:
        raise OffdynError(f"{algo} uses no source dataset; drop --source-dataset (the offline-source methods, "
                          "dara and h2o-offline-source, do)")
    plan = resolve_run(algo, pair.name, steps=steps, track=track, budget=budget, dataset=dataset,
                       needs_dataset=needs_dataset, target_step_every=_target_step_every(method_spec, config),
                       source_dataset=source_dataset, needs_source_dataset=method_spec.needs_source_dataset,
                       progress=progress, echo=lambda line: print(line, file=sys.stderr))
    steps, dataset, source_dataset = plan.steps, plan.dataset, plan.source_dataset
    _check_arguments(steps=steps, n_seeds=n_seeds, eval_episodes=eval_episodes, eval_every=eval_every,
                     checkpoint_every=checkpoint_every, threads=threads)
    eval_every = eval_every or max(1, steps // 20)
    checkpoint_every = checkpoint_every or max(1, steps // 10)
    seeds = tuple(range(seed, seed + n_seeds))
    settings = {"algo": algo, "task": pair.name, "task_version": pair.version, "steps": steps,
                "seeds": list(seeds), "dataset": dataset, "eval_every": eval_every,
                "eval_episodes": eval_episodes, "checkpoint_every": checkpoint_every,
                "config": config_to_dict(config)}
    if source_dataset is not None:
        # Only offline-source runs carry the key, so older run folders still resume.
        settings["source_dataset"] = source_dataset
    if eval_on_device:  # likewise only when set
        settings["eval_on_device"] = True
    warnings = budget_warnings(algo, config, steps)

    # Everything below up to the lock only reads: bad input fails before anything is written.
    out = Path(out)
    check_writable(out)
    resuming = _check_out_dir(out, settings)
    if resuming and read_config(out).get("device", "cpu") != device:
        # Random streams differ between devices: a resumed run would not equal an uninterrupted one.
        raise OffdynError(f"--out {str(out)!r} was trained on {read_config(out).get('device', 'cpu')}, not {device}; "
                          "nothing was changed. Resume it with the same --device, or use a new --out folder")
    dataset_provenance = None
    target_data = None
    if dataset is not None:
        data, dataset_provenance = load_dataset(dataset, pair, DATASET_SEED)
        if resuming:
            _check_same_dataset(out, dataset_provenance)
        target_data = data.to_batch(flat_observations(pair.make("target")).action_space)
    source_provenance = None
    source_data = None
    if source_dataset is not None:
        data, source_provenance = load_dataset(source_dataset, pair, SOURCE_DATASET_SEED, side="source")
        if resuming:
            _check_same_dataset(out, source_provenance, key="source_dataset_provenance")
        source_data = data.to_batch(flat_observations(pair.make("source")).action_space)
    if threads:
        torch.set_num_threads(threads)
    probe = flat_observations(pair.make("target"))
    context = MethodContext(observation_dim=int(np.prod(probe.observation_space.shape)),
                            action_dim=int(np.prod(probe.action_space.shape)), seeds=seeds,
                            target_data=target_data, source_data=source_data, task=pair.name, device=device)
    probe.close()
    method = method_spec.build(config, context)
    if not plan.source_interaction_allowed and method.interaction == "source":
        raise ProtocolError(f"{algo} steps the source simulator; the {plan.track} track allows only the fixed "
                            "source dataset")

    with run_folder_lock(out):
        # Look again under the lock: another process may have started or finished a run here since.
        if _check_out_dir(out, settings) != resuming:
            raise OffdynError(f"--out {str(out)!r} changed while this run was being prepared (another process "
                              "started a run there); nothing was written")
        if not resuming:
            extra = {"source_dataset_provenance": source_provenance} if source_provenance is not None else {}
            write_json_atomic(out / CONFIG_FILE, settings | {"task_spec": pair.to_dict(),
                                                             "dataset_provenance": dataset_provenance,
                                                             "track": plan.track, "budget": plan.budget,
                                                             "device": device} | extra)
        loop = _Loop(method, pair, seeds, out, plan.target_step_limit, device, eval_on_device)
        start, notes = loop.restore() if resuming else (0, [])
        for message in warnings:
            print(f"warning: {message}", file=sys.stderr)
        for message in notes:
            print(f"note: {message}", file=sys.stderr)
        final_returns = _run(loop, algo, pair, start, steps, eval_every, eval_episodes, checkpoint_every,
                             progress, stop_after)
        if final_returns is None:
            return None
        result = {"algo": algo, "task": pair.to_dict(), "dataset": dataset_provenance, "steps": steps,
                  "seeds": list(seeds), "eval_episode_seeds": [EVAL_SEED + e for e in range(eval_episodes)],
                  "returns": {str(s): [float(x) for x in final_returns[i]] for i, s in enumerate(seeds)},
                  "mean_return": float(final_returns.mean()), "versions": versions(),
                  "config": settings["config"], "warnings": warnings, "track": plan.track, "budget": plan.budget,
                  "target_steps_per_seed": loop.target_steps_taken(steps), "device": device,
                  "compute": loop.clock.now().to_dict(), "machines": loop.machines,
                  "source_revisions": loop.source_revisions, "started_at": loop.started_at,
                  "finished_at": utc_now()}
        if source_provenance is not None:
            result["source_dataset"] = source_provenance
        write_json_atomic(out / RESULT_FILE, result)
    return result


def _run(loop: _Loop, algo: str, pair: TaskPair, start: int, steps: int, eval_every: int, eval_episodes: int,
         checkpoint_every: int, progress: bool, stop_after: int | None) -> np.ndarray | None:
    """Steps ``start .. steps - 1`` with evaluations and checkpoints; the final returns, or None
    when stopped by ``stop_after``."""
    final_returns = None
    with tqdm(total=steps, initial=start, unit="step", disable=not progress, desc=f"{algo} {pair.name}") as bar:
        for step in range(start, steps):
            metrics = loop.step(step)
            done = step + 1
            bar.update(1)
            if done % eval_every == 0 or done == steps:
                started = time.perf_counter()
                returns = loop.evaluate(eval_episodes)
                loop.log(done, returns, metrics, time.perf_counter() - started)
                bar.set_postfix(target_return=f"{returns.mean():.1f}")
                final_returns = returns if done == steps else None
            if done % checkpoint_every == 0 or done == steps:
                loop.checkpoint(done)
            if stop_after is not None and done >= stop_after and done < steps:
                return None
    if final_returns is None:  # resumed after the last checkpoint but before result.json
        final_returns = loop.evaluate(eval_episodes)
    return final_returns


def resolve_device(device: str) -> str:
    """``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (CUDA when there is one) as a torch device name;
    an error that says what is available when the device is not."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cpu":
        return device
    if device == "cuda" or (device.startswith("cuda:") and device[5:].isdigit()):
        if not torch.cuda.is_available():
            raise OffdynError(f"--device {device}: this torch ({torch.__version__}) sees no CUDA device; "
                              "use --device cpu or auto")
        index = int(device[5:]) if ":" in device else 0
        if index >= torch.cuda.device_count():
            raise OffdynError(f"--device {device}: expected an index below {torch.cuda.device_count()} "
                              "(the CUDA devices torch sees)")
        return device
    raise OffdynError(f"--device {device!r}: expected cpu, cuda, cuda:N or auto")


def _check_arguments(**arguments: int | None) -> None:
    """Budget arguments: whole numbers >= 1 (None: the default; threads 0: torch's default)."""
    for name, value in arguments.items():
        minimum = 0 if name == "threads" else 1
        if value is None and name not in ("steps", "n_seeds", "eval_episodes"):
            continue
        if not is_integer(value) or value < minimum:
            flag = "--" + name.replace("_", "-")
            raise OffdynError(f"{flag}={value!r}: expected an integer >= {minimum}")


def budget_warnings(algo: str, config: Any, steps: int) -> list[str]:
    """What a budget of ``steps`` is too short for. ``random_steps`` (no update before it) and
    ``warmup_steps`` (no reward correction before it) mean the same in every config that has them.
    A config with a ``budget_warnings(algo, steps)`` method (MATL's on-policy batches) says its own."""
    own_warnings = getattr(config, "budget_warnings", None)
    if own_warnings is not None:
        return own_warnings(algo, steps)
    random_steps = getattr(config, "random_steps", 0)
    warmup_steps = getattr(config, "warmup_steps", None)
    if steps <= random_steps:
        return [f"--steps {steps} is not above random_steps={random_steps}: this {algo} run makes no gradient "
                f"update and deploys its untrained initial policy; the minimum useful budget is more than "
                f"{random_steps} steps (or lower it with --set random_steps=N)"]
    if warmup_steps is not None and steps <= warmup_steps:
        return [f"--steps {steps} is not above warmup_steps={warmup_steps}: this {algo} run never applies its "
                f"reward correction and trains plain SAC; the minimum useful budget is more than {warmup_steps} "
                "steps (or lower it with --set warmup_steps=N)"]
    return []


def _target_step_every(method_spec: Any, config: Any) -> int | None:
    """Target-environment steps of an online-target method: one per this many steps (else None)."""
    if getattr(config, "target_data", None) == "online":
        return int(config.target_step_every)
    return None


def _check_out_dir(out: Path, settings: dict[str, Any]) -> bool:
    """True when ``out`` holds an unfinished run of the same settings (resume); raises on anything
    that would overwrite other work."""
    if not out.exists():
        return False
    if not out.is_dir():
        raise OffdynError(f"--out {str(out)!r} exists and is not a folder")
    if not (out / CONFIG_FILE).exists():
        if holds_files(out):
            raise OffdynError(f"--out {str(out)!r} is not empty and holds no training run; use a new folder")
        return False
    stored = read_config(out)
    stored_settings = {k: stored.get(k) for k in settings}
    if stored_settings != json.loads(json.dumps(settings)):
        diffs = [k for k in settings if json.dumps(stored_settings[k], sort_keys=True)
                 != json.dumps(settings[k], sort_keys=True)]
        raise OffdynError(f"--out {str(out)!r} holds a run with other settings (differs in: {', '.join(diffs)}); "
                          "nothing was changed. Use a new --out folder, or the same settings to resume.")
    if (out / RESULT_FILE).exists():
        raise OffdynError(f"--out {str(out)!r} holds a finished run (result.json exists); nothing was changed")
    return True


def _check_same_dataset(out: Path, provenance: dict[str, Any], key: str = "dataset_provenance") -> None:
    stored = read_config(out).get(key)
    stored_sha = stored.get("sha256") if isinstance(stored, dict) else None
    if not isinstance(stored_sha, str):
        raise OffdynError(f"{str(out / CONFIG_FILE)!r} is damaged (no dataset sha256 in {key}); "
                          "use a new --out folder")
    if stored_sha != provenance["sha256"]:
        kind = "source dataset" if key == "source_dataset_provenance" else "dataset"
        raise OffdynError(f"{out} was trained on another {kind} (sha256 {stored_sha[:12]}..., now "
                          f"{provenance['sha256'][:12]}...); use a new --out folder")


def _episode_seed(seed: int, stream: int, episode: int) -> int:
    return int(np.random.SeedSequence([int(seed), stream, int(episode)]).generate_state(1)[0])


class _Envs:
    """One environment per training seed, stepped together, each episode seeded by its index."""

    def __init__(self, pair: TaskPair, side: str, seeds: Sequence[int], stream: int) -> None:
        self.envs = [flat_observations(pair.make(side)) for _ in seeds]
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
        scaled = self.low + (actions.cpu().numpy().astype(np.float64) + 1.0) * 0.5 * (self.high - self.low)
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


RECALIBRATE_EVERY_CPU_S = 120.0
"""At a checkpoint, the machine's speed is measured again once this much CPU has passed since the
last measurement: a long training follows a machine whose speed changes while it runs, and a
short one (a test's) is timed once."""


class _Clock:
    """This attempt's wall and CPU time on top of what earlier attempts spent, and that CPU in
    updates of the reference workload (:mod:`offdyn_bench.machine_speed`), whose speed it measures
    at the start and again at checkpoints (:meth:`recalibrate`)."""

    def __init__(self, measure_update_s: Callable[[], float]) -> None:
        self.before = TrainingCompute(0.0, 0.0, 0, True, 0.0)
        self.wall_start, self.cpu_start = time.perf_counter(), time.process_time()
        self.measure_update_s = measure_update_s
        self.calibrated_cpu = 0.0
        """This attempt's CPU seconds when the speed was last measured."""
        self.updates_before_calibration: float | None = 0.0
        """This attempt's CPU before then, in reference updates (None: a measurement read zero)."""
        self.update_s = measure_update_s()

    def resumed(self, before: TrainingCompute | None) -> None:
        self.before = before if before is not None else TrainingCompute(0.0, 0.0, 1, False)

    def _attempt_updates(self, cpu: float) -> float | None:
        if self.updates_before_calibration is None or self.update_s <= 0:
            return None
        return self.updates_before_calibration + (cpu - self.calibrated_cpu) / self.update_s

    def recalibrate(self) -> None:
        """Measure the machine's speed again, once :data:`RECALIBRATE_EVERY_CPU_S` have passed."""
        cpu = time.process_time() - self.cpu_start
        if cpu - self.calibrated_cpu < RECALIBRATE_EVERY_CPU_S:
            return
        self.updates_before_calibration = self._attempt_updates(cpu)
        self.calibrated_cpu = cpu
        self.update_s = self.measure_update_s()

    def now(self) -> TrainingCompute:
        cpu = time.process_time() - self.cpu_start
        updates = self._attempt_updates(cpu)
        if self.before.reference_updates is None or updates is None:
            total_updates = None
        else:
            total_updates = self.before.reference_updates + updates
        return TrainingCompute(self.before.wall_time_s + time.perf_counter() - self.wall_start,
                               self.before.cpu_time_s + cpu, self.before.attempts + 1, self.before.complete,
                               total_updates)


class _Loop:
    def __init__(self, method: Method, pair: TaskPair, seeds: Sequence[int], out: Path,
                 target_step_limit: int | None = None, device: str = "cpu", eval_on_device: bool = False) -> None:
        self.method, self.out, self.seeds, self.device = method, out, seeds, torch.device(device)
        self.eval_on_device = eval_on_device
        self.target_step_limit = target_step_limit
        self.train_envs = _Envs(pair, method.interaction, seeds, 1) if method.interaction != "none" else None
        self.target_envs = _Envs(pair, "target", seeds, 2) if method.target_step_every else None
        self.eval_envs = [flat_observations(pair.make("target")) for _ in seeds]
        for envs in (self.train_envs, self.target_envs):
            if envs is not None:
                envs.reset_all()
        self.clock = _Clock(reference_update_seconds)
        self.machines: list[dict[str, Any] | None] = [machine(device)]
        """The distinct machines of this training's attempts, in order (None: attempts before
        checkpoints recorded them)."""
        self.source_revisions: list[dict[str, Any] | None] = [source_revision()]
        """The distinct revisions of the suite's code its attempts ran (None: unknown, or attempts
        before checkpoints recorded them)."""
        self.started_at: str | None = utc_now()
        """When the first attempt started (UTC); None for a run resumed from a checkpoint that does
        not say."""

    def step(self, step: int) -> dict[str, torch.Tensor]:
        method = self.method
        if self.train_envs is not None:
            env_actions, stored = method.explore(torch.as_tensor(self.train_envs.observations, dtype=torch.float32,
                                                                 device=self.device), step)
            obs, rewards, next_obs, terminations = self.train_envs.step(env_actions)
            method.record(obs, stored, rewards, next_obs, terminations)
        if self.target_envs is not None and (step + 1) % method.target_step_every == 0:
            if self.target_step_limit is not None and self.target_steps_taken(step + 1) > self.target_step_limit:
                raise ProtocolError(f"target step {self.target_steps_taken(step + 1)} exceeds the track's budget "
                                    f"of {self.target_step_limit} target steps per seed")
            explore_target = getattr(method, "explore_target", method.explore)
            env_actions, stored = explore_target(torch.as_tensor(self.target_envs.observations, dtype=torch.float32,
                                                                 device=self.device),
                                                 step)
            obs, rewards, next_obs, terminations = self.target_envs.step(env_actions)
            method.record_target(obs, stored, rewards, next_obs, terminations)
        return method.train_step(step)

    def target_steps_taken(self, steps: int) -> int:
        """Target-environment steps per seed after ``steps`` steps (the loop is the only place that
        steps the target during training, once every ``target_step_every`` steps)."""
        every = self.method.target_step_every
        return steps // every if every else 0

    def evaluate(self, episodes: int) -> np.ndarray:
        """Per-seed, per-episode target returns of the deployed policy, ``[seeds, episodes]``.

        On an accelerator the policy acts from a CPU copy of its parameters (the method's
        ``host_deploy``), so an episode step waits on no device: where several runs share one
        GPU, each wait would queue behind the others' updates. ``eval_on_device`` keeps it there."""
        returns = np.zeros((len(self.seeds), episodes))
        space = self.eval_envs[0].action_space
        low, high = space.low.astype(np.float64), space.high.astype(np.float64)
        deploy, device = self.method.deploy, self.device
        if device.type != "cpu" and not self.eval_on_device and hasattr(self.method, "host_deploy"):
            deploy, device = self.method.host_deploy(), torch.device("cpu")
        for e in range(episodes):
            obs = np.stack([env.reset(seed=EVAL_SEED + e)[0] for env in self.eval_envs])
            running = np.ones(len(self.seeds), dtype=bool)
            while running.any():
                actions = deploy(torch.as_tensor(obs, dtype=torch.float32, device=device)
                                 ).cpu().numpy().astype(np.float64)
                scaled = low + (actions + 1.0) * 0.5 * (high - low)
                for i in np.flatnonzero(running):
                    obs[i], reward, terminated, truncated, _ = self.eval_envs[i].step(scaled[i])
                    returns[i, e] += reward
                    running[i] = not (terminated or truncated)
        return returns

    def log(self, step: int, returns: np.ndarray, metrics: Mapping[str, torch.Tensor],
            evaluation_wall_time_s: float) -> None:
        spent = self.clock.now()
        line = {"step": step, "target_return": [float(x) for x in returns.mean(axis=1)],
                "target_return_mean": float(returns.mean()),
                "train": {k: float(torch.as_tensor(v).float().mean()) for k, v in metrics.items()},
                "wall_time_s": round(spent.wall_time_s, 3), "cpu_time_s": round(spent.cpu_time_s, 3),
                # this evaluation's own wall time (wall_time_s is the run's total so far): where the time goes
                "evaluation_wall_time_s": round(evaluation_wall_time_s, 3)}
        with open(self.out / METRICS_FILE, "a") as f:
            f.write(json.dumps(line) + "\n")

    def checkpoint(self, step: int) -> None:
        # End the training episodes first, so the saved state is a clean episode start.
        for envs in (self.train_envs, self.target_envs):
            if envs is not None:
                envs.end_episodes()
        self.clock.recalibrate()
        trainer = {"step": step,
                   "train_episodes": self.train_envs.episodes if self.train_envs else None,
                   "target_episodes": self.target_envs.episodes if self.target_envs else None,
                   "compute": self.clock.now().to_dict(), "machines": self.machines,
                   "source_revisions": self.source_revisions, "started_at": self.started_at}
        save_checkpoint(self.out, step, self.method.state_dict(), trainer)

    def restore(self) -> tuple[int, list[str]]:
        """Load the newest checkpoint that verifies; returns its step and notes on what was skipped
        or dropped. Damaged checkpoints newer than it are removed (the resumed run writes them again)."""
        damaged: list[DamagedCheckpointError] = []
        step = 0
        for path in reversed(checkpoints(self.out)):
            try:
                step = self._load(path)
                break
            except DamagedCheckpointError as error:
                damaged.append(error)
        else:
            if damaged:
                raise OffdynError(f"cannot resume {str(self.out)!r}: every checkpoint is damaged ("
                                  + "; ".join(f"{e.path.name}: {e.reason}" for e in damaged)
                                  + f"); nothing was changed. Remove {str(self.out / CHECKPOINT_DIR)!r} "
                                  "to train again from the start, or use a new --out folder")
        resumed_from = f"step_{step:09d}" if step else "the start"
        notes = [f"{error}; resuming from {resumed_from}" for error in damaged]
        for error in damaged:
            shutil.rmtree(error.path, ignore_errors=True)
        kept, metric_notes = read_metrics(self.out, step)
        if (self.out / METRICS_FILE).exists():
            write_lines_atomic(self.out / METRICS_FILE, kept)
        return step, notes + metric_notes

    def _load(self, path: Path) -> int:
        """Restore the method and episode counters from checkpoint ``path``; raises
        :class:`DamagedCheckpointError` (leaving the method unchanged) when it cannot be used."""
        tensors, trainer = load_checkpoint(path)
        missing = sorted(set(self.method.state_dict()) - set(tensors))
        if missing:
            raise DamagedCheckpointError(path, f"{STATE_FILE} lacks {len(missing)} tensor(s) of this run, "
                                               f"e.g. {missing[0]!r}")
        episodes = {}
        for envs, key in ((self.train_envs, "train_episodes"), (self.target_envs, "target_episodes")):
            value = trainer.get(key)
            if envs is not None and not (isinstance(value, list) and len(value) == len(self.seeds)
                                         and all(isinstance(x, int) for x in value)):
                raise DamagedCheckpointError(path, f"{TRAINER_FILE} has no {key} counter per seed")
            episodes[key] = value
        try:
            self.method.load_state_dict(tensors)
        except (RuntimeError, KeyError, ValueError) as error:
            # A later checkpoint loaded in full overwrites whatever this one had set.
            raise DamagedCheckpointError(path, f"its tensors do not fit this run: {error}") from None
        for envs, key in ((self.train_envs, "train_episodes"), (self.target_envs, "target_episodes")):
            if envs is not None:
                envs.episodes = list(episodes[key])
                envs.reset_all()
        self.clock.resumed(TrainingCompute.parse(trainer.get("compute")))
        self.machines = _listed_with(trainer.get("machines"), machine(str(self.device)))
        self.source_revisions = _listed_with(trainer.get("source_revisions"), source_revision())
        started_at = trainer.get("started_at")
        self.started_at = started_at if isinstance(started_at, str) else None
        return checkpoint_step(path)


def _listed_with(earlier: Any, current: dict[str, Any] | None) -> list[dict[str, Any] | None]:
    """A checkpoint's list of the distinct machines (or code revisions) of earlier attempts, with
    this attempt's added unless it is there already; a checkpoint without the list gives ``[None]``
    (earlier attempts, unknown)."""
    listed = [entry if isinstance(entry, dict) else None for entry in earlier] if isinstance(earlier, list) else [None]
    return listed + ([current] if current not in listed else [])


def load_trained_policy(run_dir: str | Path) -> Callable[[np.ndarray], np.ndarray]:
    """The deployed action of a training run's latest checkpoint (seed index 0), as a function of
    one observation in environment units. Used as a behaviour policy for datasets."""
    run_dir = Path(run_dir)
    if not (run_dir / CONFIG_FILE).exists():
        raise OffdynError(f"{str(run_dir)!r} is not a training run folder (no {CONFIG_FILE})")
    path = latest_checkpoint(run_dir)
    if path is None:
        if checkpoints(run_dir):
            load_checkpoint(checkpoints(run_dir)[-1])  # raises, saying what is damaged
        raise OffdynError(f"{str(run_dir)!r} has no checkpoint yet")
    pair = get_task(str(read_config(run_dir).get("task")))
    tensors, _ = load_checkpoint(path)
    actor = [tensors[f"actor.{i}"][:1] for i in range(sum(1 for k in tensors if k.startswith("actor.")))]
    space = flat_observations(pair.make("target")).action_space
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
