"""``offdyn-bench demo``: the suite end to end on an embedded default, no external service.

1. the task grid; 2. one pair rolled out with the same actions in source and target;
3. its target dataset rebuilt from the recipe and checked byte for byte against the manifest;
4. gap diagnosis of that dataset against plain ``Hopper-v5``, an effect nobody declared to it;
5. a short training run of RL on source and DARC on a fast pair, scored in the target.
Each step prints the command that does the same thing on its own.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Any

import numpy as np
import typer

from offdyn_bench.task_commands import grid_summary
from offdyn_bench.tasks import get_task

DEMO_DATASET_TASK = "hopper-gravity-0.5"
DEMO_TRAINING_TASK = "invertedpendulum-kinematic-slider-hard"
# Small networks and short schedules: the learning test's settings, a CPU minute per method.
DEMO_TRAINING = {"sac.hidden_sizes": "[64, 64]", "sac.batch_size": "128", "sac.actor_lr": "0.001",
                 "sac.critic_lr": "0.001", "sac.temperature_lr": "0.001", "random_steps": "1000"}
DEMO_OFF_DYNAMICS = {"warmup_steps": "3000", "classifier.input_noise_std": "0.1"}


@dataclasses.dataclass(frozen=True)
class Divergence:
    """How far two rollouts driven by the same actions drift apart."""

    steps: np.ndarray
    qpos_rmse: np.ndarray
    source_return: float
    target_return: float
    source_length: int
    target_length: int


def same_action_divergence(task: str, seed: int = 0, horizon: int = 200) -> Divergence:
    """Roll the pair's source and target from the same start with the same actions."""
    pair = get_task(task)
    # No early termination: the point is to watch the two systems drift apart for ``horizon`` steps.
    kwargs = {"terminate_when_unhealthy": False} if pair.robot in ("Hopper", "Walker2d", "Ant") else {}
    source, target = pair.make("source", **kwargs), pair.make("target", **kwargs)
    source.reset(seed=seed)
    target.reset(seed=seed)
    # Same initial physics state in both (reset noise is drawn from the same seed, but make sure).
    start = source.unwrapped.data
    target.unwrapped.set_state(start.qpos.copy(), start.qvel.copy())
    # A periodic gait-like command: random actions make both robots fall at once.
    phases = np.random.default_rng(seed).uniform(0, 2 * np.pi, size=source.action_space.shape)
    returns = {"source": 0.0, "target": 0.0}
    lengths = {"source": horizon, "target": horizon}
    done = {"source": False, "target": False}
    rmse = []
    for t in range(horizon):
        action = 0.5 * np.sin(2 * np.pi * t / 25 + phases)
        for side, env in (("source", source), ("target", target)):
            if done[side]:
                continue
            _, reward, terminated, truncated, _ = env.step(action.astype(np.float32))
            returns[side] += float(reward)
            if terminated or truncated:
                done[side] = True
                lengths[side] = t + 1
        diff = source.unwrapped.data.qpos - target.unwrapped.data.qpos
        rmse.append(float(np.sqrt(np.mean(diff**2))))
    return Divergence(np.arange(1, horizon + 1), np.array(rmse), returns["source"], returns["target"],
                      lengths["source"], lengths["target"])


def _random_return(task: str, episodes: int, first_seed: int) -> float:
    from offdyn_bench.datasets.collect import episode_returns
    from offdyn_bench.datasets.policies import UniformRandomPolicy

    env = get_task(task).make("target")
    policy = UniformRandomPolicy(env.action_space.low, env.action_space.high, seed=0)  # type: ignore[attr-defined]
    return float(np.mean(episode_returns(env, policy, episodes=episodes, seed=first_seed)))


def demo_dataset(out: pathlib.Path) -> pathlib.Path:
    from offdyn_bench.datasets import build_dataset, default_recipe, read_manifest

    recipe = default_recipe(DEMO_DATASET_TASK, "source-policy")
    typer.echo(f"\n== 3. A target dataset, rebuilt from its recipe: {recipe.dataset_id}")
    typer.echo(f"   (offdyn-bench datasets build {recipe.dataset_id})")
    recorded = read_manifest().entries.get(recipe.dataset_id)
    result = build_dataset(recipe, root=out / "datasets", recorded=recorded, replace=True)
    entry = result.entry
    match = "identical to the manifest's sha256, file by file" if recorded and recorded.files else "no hashes recorded"
    typer.echo(f"   {entry.total_steps} transitions in {entry.total_episodes} episodes collected in the target by "
               f"the RL-on-source policy, {result.seconds:.1f} s; bytes {match}")
    scores = entry.reference_scores
    typer.echo(f"   reference scores recorded with it: {_describe_scores(scores)}")
    typer.echo(f"   installed at {result.installed_at}")
    assert result.installed_at is not None
    return result.installed_at


def _describe_scores(scores: dict) -> str:
    parts = []
    for name in ("random", "sac-target"):
        value = (scores.get(name) or {}).get("value")
        parts.append(f"{name} {value:.1f}" if isinstance(value, (int, float)) else f"{name} not recorded (no policy yet)")
    return ", ".join(parts)


def demo_diagnosis(dataset: pathlib.Path, out: pathlib.Path) -> None:
    from offdyn_bench.diagnose import diagnose
    from offdyn_bench.diagnose.report import summary_text, write_report

    typer.echo("\n== 4. Gap diagnosis: the plain Hopper-v5 simulator against that target data")
    typer.echo(f"   (offdyn-bench diagnose --env Hopper-v5 --data {dataset} --out {out / 'diagnosis'})")
    result = diagnose("Hopper-v5", str(dataset))
    write_report(result, out / "diagnosis")
    typer.echo("   " + summary_text(result).replace("\n", "\n   "))


def _train_or_reuse(algo: str, task: str, steps: int, out: pathlib.Path, **kwargs: Any) -> dict[str, Any]:
    """Train, or read the result of the same finished run from an earlier demo."""
    from baselines.train import RESULT_FILE, train

    finished = out / RESULT_FILE
    if finished.is_file():
        typer.echo(f"   (reusing the finished run in {out})")
        return json.loads(finished.read_text())
    result = train(algo, task, steps=steps, out=out, eval_episodes=5, progress=False, **kwargs)
    assert result is not None
    return result


def demo_training(out: pathlib.Path, steps: int) -> None:
    from baselines.train import EVAL_SEED

    pair = get_task(DEMO_TRAINING_TASK)
    typer.echo(f"\n== 5. Training on {pair.name}: {pair.description}")
    runs = out / "runs" / f"{steps}-steps"
    source_dir = runs / "sac-source"
    typer.echo(f"   (offdyn-bench train sac-source --task {pair.name} --steps {steps} --out {source_dir})")
    source = _train_or_reuse("sac-source", pair.name, steps, source_dir, overrides=DEMO_TRAINING)
    dataset = f"collect:{source_dir}:5000"
    typer.echo(f"   (offdyn-bench train darc --task {pair.name} --dataset {dataset} --steps {steps} "
               f"--out {runs / 'darc'})")
    darc = _train_or_reuse("darc", pair.name, steps, runs / "darc", dataset=dataset,
                           overrides=DEMO_TRAINING | DEMO_OFF_DYNAMICS)
    random_return = _random_return(pair.name, 5, EVAL_SEED)
    # InvertedPendulum pays 1 per step for at most 1000 steps: the best possible return is 1000.
    best = 1000.0
    typer.echo("   score in the target (5 episodes with fixed seeds; normalized = 100 (J - J_random) / "
               "(J_max - J_random), J_max = 1000, the task's maximum return)")
    typer.echo(f"   {'policy':<12} {'return':>8} {'normalized':>11}")
    for name, value in (("random", random_return), ("sac-source", source["mean_return"]),
                        ("darc", darc["mean_return"])):
        typer.echo(f"   {name:<12} {value:>8.1f} {100 * (value - random_return) / (best - random_return):>11.1f}")


def run_demo(task: str = "hopper-gravity-0.5", seed: int = 0, out: pathlib.Path = pathlib.Path("demo-out"),
             training_steps: int = 12_000) -> None:
    typer.echo("== 1. The task grid (robot x shift family: number of pairs)")
    typer.echo(grid_summary())

    pair = get_task(task)
    typer.echo(f"\n== 2. One pair, same actions in source and target: {pair.name}")
    typer.echo(f"   source {pair.env_id('source')}: " + (", ".join(e.describe() for e in pair.source_effects) or "nominal"))
    typer.echo(f"   target {pair.env_id('target')}: " + (", ".join(e.describe() for e in pair.target_effects) or "nominal"))
    result = same_action_divergence(task, seed=seed)
    typer.echo("   step   qpos RMSE (source vs target)")
    for t in (1, 10, 25, 50, 100, 200):
        if t <= len(result.steps):
            typer.echo(f"   {t:>4}   {result.qpos_rmse[t - 1]:.4f}")
    typer.echo(f"   return over {len(result.steps)} steps: source {result.source_return:.1f} "
               f"(episode length {result.source_length}), target {result.target_return:.1f} "
               f"(episode length {result.target_length})")

    out.mkdir(parents=True, exist_ok=True)
    dataset = demo_dataset(out)
    demo_diagnosis(dataset, out)
    if training_steps > 0:
        demo_training(out, training_steps)
    typer.echo(f"\nEverything the demo wrote is under {out}/")
