"""``offdyn-bench demo``: the suite end to end on an embedded default, no external service.

1. the task grid; 2. one pair rolled out with the same actions in source and target;
3. its target dataset rebuilt from the recipe and checked byte for byte against the manifest;
4. gap diagnosis of that dataset against plain ``Hopper-v5``, an effect nobody declared to it;
5. short training runs of RL on source, DAP and the sac-target oracle on the learning pair;
6. those runs scored under the protocol (normalized, IQM with a bootstrap interval);
7. the leaderboard page built from the submissions store.
Each step prints the command that does the same thing on its own.
"""

from __future__ import annotations

import dataclasses
import pathlib
import shlex
from typing import Any

import numpy as np
import typer

from offdyn_bench.errors import OffdynError
from offdyn_bench.task_commands import grid_summary
from offdyn_bench.tasks import get_task

DEMO_DATASET_TASK = "hopper-gravity-0.5"
# The learning benchmark's pair (baselines/results/README.md): RL on source fails in its target
# on 4 of 5 seeds, and RL on target learns it at this budget.
DEMO_TRAINING_TASK = "invertedpendulum-rail-offset-hard"
# Small networks and short schedules: the learning test's settings, a CPU minute per method.
DEMO_TRAINING = {"sac.hidden_sizes": "[64, 64]", "sac.batch_size": "128", "sac.actor_lr": "0.001",
                 "sac.critic_lr": "0.001", "sac.temperature_lr": "0.001", "random_steps": "1000"}
DEMO_OFF_DYNAMICS = {"warmup_steps": "3000", "classifier.input_noise_std": "0.1"}
DEMO_EVAL_EPISODES = 5
"""Target episodes per in-training evaluation (the scored evaluation afterwards is the protocol's)."""


def set_flags(overrides: dict[str, str]) -> str:
    """``overrides`` as the ``train`` command's ``--set key=value`` flags, quoted for a POSIX shell."""
    return "".join(f" --set {shlex.quote(f'{key}={value}')}" for key, value in overrides.items())


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


def _train_or_reuse(algo: str, task: str, steps: int, out: pathlib.Path, **kwargs: Any) -> None:
    """Train, or reuse the same finished run from an earlier demo."""
    from baselines.train import RESULT_FILE, train

    if (out / RESULT_FILE).is_file():
        typer.echo(f"   (reusing the finished run in {out})")
        return
    train(algo, task, steps=steps, out=out, eval_episodes=DEMO_EVAL_EPISODES, progress=True, **kwargs)


def demo_training(out: pathlib.Path, steps: int, n_seeds: int) -> list[pathlib.Path]:
    pair = get_task(DEMO_TRAINING_TASK)
    typer.echo(f"\n== 5. Training on {pair.name} ({pair.description}), {n_seeds} seeds each")
    runs = out / "runs" / f"{steps}-steps"
    # The printed commands carry the demo's --set overrides and evaluation count, so each one run
    # alone trains the same run the demo trains.
    common = f"--task {pair.name} --steps {steps} --n-seeds {n_seeds} --eval-episodes {DEMO_EVAL_EPISODES}"
    source_dir = runs / "sac-source"
    typer.echo(f"   RL on source:  offdyn-bench train sac-source {common}{set_flags(DEMO_TRAINING)} "
               f"--out {shlex.quote(str(source_dir))}")
    _train_or_reuse("sac-source", pair.name, steps, source_dir, n_seeds=n_seeds, overrides=DEMO_TRAINING)
    dataset = f"collect:{source_dir}:5000"
    typer.echo(f"   DAP:           offdyn-bench train dap {common}{set_flags(DEMO_TRAINING | DEMO_OFF_DYNAMICS)} "
               f"--dataset {shlex.quote(dataset)} --out {shlex.quote(str(runs / 'dap'))}")
    _train_or_reuse("dap", pair.name, steps, runs / "dap", n_seeds=n_seeds, dataset=dataset,
                    overrides=DEMO_TRAINING | DEMO_OFF_DYNAMICS)
    typer.echo(f"   oracle:        offdyn-bench train sac-target {common}{set_flags(DEMO_TRAINING)} "
               f"--out {shlex.quote(str(runs / 'sac-target'))}")
    _train_or_reuse("sac-target", pair.name, steps, runs / "sac-target", n_seeds=n_seeds, overrides=DEMO_TRAINING)
    return [source_dir, runs / "dap", runs / "sac-target"]


def demo_score(out: pathlib.Path, run_dirs: list[pathlib.Path]) -> None:
    from offdyn_bench.evaluate import evaluate
    from offdyn_bench.protocol import EVAL_EPISODES
    from offdyn_bench.protocol.claims import check_claims, claims_markdown
    from offdyn_bench.protocol.references import record_random_reference
    from offdyn_bench.protocol.report import score_report

    typer.echo(f"\n== 6. Scored under the protocol: final policies, deterministic, {EVAL_EPISODES} target episodes "
               "with fixed seeds per training seed")
    records = []
    for run in run_dirs:
        typer.echo(f"   (offdyn-bench evaluate --agent {run})")
        records.append(evaluate(run, progress=True))
    references_file = out / "reference_scores.json"
    typer.echo(f"   (offdyn-bench protocol reference random --task {DEMO_TRAINING_TASK}; here into {references_file})")
    random = record_random_reference(DEMO_TRAINING_TASK, references_file)
    oracle = records[-1]
    j_oracle = float(np.mean([x for s in oracle["seeds"] for x in s["returns"]]))
    typer.echo(f"   references: random {random.mean_return:.1f}; oracle = the demo's own sac-target at the same "
               f"{oracle['steps']}-step budget, {j_oracle:.1f} (the protocol's rule at a demo-sized budget, so not a "
               "leaderboard number)")
    typer.echo(f"   (offdyn-bench protocol score --reference {DEMO_TRAINING_TASK}={random.mean_return:.6g},{j_oracle:.6g} "
               + " ".join(str(r / "evaluation.json") for r in run_dirs[:2]) + ")")
    report = score_report(records[:2], references={DEMO_TRAINING_TASK: (random.mean_return, j_oracle)})
    typer.echo("   " + report.to_text().replace("\n", "\n   "))
    typer.echo("   The DAP paper's claim on this task (Section 5.2), checked on the same records:")
    typer.echo("   (offdyn-bench protocol claims " + " ".join(str(r / "evaluation.json") for r in run_dirs[:2]) + ")")
    typer.echo("   " + claims_markdown(check_claims(records[:2])).rstrip("\n").replace("\n", "\n   "))


def demo_leaderboard(out: pathlib.Path) -> None:
    from leaderboard.reference_runs import REFERENCE_RUNS_DIR
    from leaderboard.render import build_site
    from leaderboard.store import DEFAULT_STORE

    typer.echo("\n== 7. The leaderboard page, from the submissions in leaderboard/submissions/ and the reference "
               "runs published so far in leaderboard/reference-runs/")
    typer.echo(f"   (offdyn-bench leaderboard build --out {out / 'leaderboard'})")
    written = build_site(DEFAULT_STORE, out / "leaderboard", reference_runs=REFERENCE_RUNS_DIR)
    typer.echo(f"   wrote {', '.join(str(p) for p in written)}")


def check_demo_arguments(task: str, out: pathlib.Path, training_steps: int, n_seeds: int) -> None:
    """Everything the demo's later steps would refuse, refused before its first step."""
    get_task(task)
    if training_steps < 0:
        raise OffdynError(f"--training-steps {training_steps}: expected 0 (no training) or more")
    if training_steps > 0 and n_seeds < 1:
        raise OffdynError(f"--n-seeds {n_seeds}: expected 1 or more")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise OffdynError(f"--out {str(out)!r}: cannot create the demo's folder ({error.strerror or error}); "
                          "expected a folder this user can write") from None


def run_demo(task: str = "hopper-gravity-0.5", seed: int = 0, out: pathlib.Path = pathlib.Path("demo-out"),
             training_steps: int = 12_000, n_seeds: int = 3) -> None:
    check_demo_arguments(task, out, training_steps, n_seeds)
    typer.echo("== 1. The task grid (robot x shift family: number of pairs)")
    typer.echo("   (offdyn-bench tasks list)")
    typer.echo(grid_summary())

    pair = get_task(task)
    typer.echo(f"\n== 2. One pair, same actions in source and target: {pair.name}")
    typer.echo(f"   (offdyn-bench tasks show {pair.name})")
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

    dataset = demo_dataset(out)
    demo_diagnosis(dataset, out)
    if training_steps > 0:
        demo_score(out, demo_training(out, training_steps, n_seeds))
    demo_leaderboard(out)
    typer.echo(f"\nEverything the demo wrote is under {out}/")
