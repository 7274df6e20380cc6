"""Dataset build throughput against the bare env step rate, side by side in one run.

    .venv/bin/python benchmarks/bench_datasets.py [--transitions 20000] [--tasks hopper-gravity-0.5 ...]

For each task, three figures in transitions per second, measured in the same process:

* ``bare env``: ``gymnasium.make`` of the task's target id stepped with pre-drawn uniform actions,
  resetting when an episode ends (the same episode lengths a random-policy build sees);
* ``build random``: ``build_dataset`` of the task's ``random`` recipe (collection with the state
  capture, reference scores, Minari Arrow writing, hashing, archive, atomic install);
* ``build policy``: the same with a ``source-policy`` recipe whose behaviour is a 256x256 MLP
  with random weights (the size of a SAC actor; inference cost is what matters here, not skill).

The ratio is build throughput over the bare env rate. Build time includes everything above, so
the ratio is below 1 by the cost of writing and of the reference episodes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import tempfile
import time

import numpy as np

import offdyn_bench  # noqa: F401  (registers the ids)
from offdyn_bench.datasets.build import build_dataset
from offdyn_bench.datasets.policies import save_policy
from offdyn_bench.datasets.recipes import default_recipe
from offdyn_bench.tasks import get_task

DEFAULT_TASKS = ("hopper-gravity-0.5", "halfcheetah-gravity-0.5")


def bare_env_rate(task: str, steps: int) -> float:
    env = get_task(task).make("target")
    actions = np.random.default_rng(0).uniform(-1, 1, size=(steps, *env.action_space.shape)).astype(np.float32)
    env.reset(seed=0)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def benchmark_policy(path: pathlib.Path, task: str) -> pathlib.Path:
    """A SAC-sized actor with random weights, written in the shipped policy format."""
    env = get_task(task).make("target")
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    rng = np.random.default_rng(0)
    sizes = [obs_dim, 256, 256, action_dim]
    layers = {name: (rng.normal(0, 1 / np.sqrt(n_in), (n_out, n_in)), np.zeros(n_out))
              for name, n_in, n_out in zip(("fc1", "fc2", "fc_mean"), sizes[:-1], sizes[1:])}
    return save_policy(path, layers, action_low=env.action_space.low, action_high=env.action_space.high,
                       trained_on=get_task(task).env_id("source"),
                       training={"algorithm": "none: random weights for the build benchmark"}, score=None)


def run(tasks: list[str], transitions: int) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        root = pathlib.Path(scratch)
        for task in tasks:
            bare = bare_env_rate(task, transitions)
            random_recipe = default_recipe(task, "random", num_transitions=transitions)
            built_random = build_dataset(random_recipe, root=root / "random")
            policy_recipe = default_recipe(task, "source-policy", num_transitions=transitions)
            policy_path = benchmark_policy(root / f"{task}.safetensors", task)
            policy_recipe = dataclasses.replace(policy_recipe, behaviour=dataclasses.replace(
                policy_recipe.behaviour, policy=str(policy_path)))
            built_policy = build_dataset(policy_recipe, root=root / "policy")
            for label, result in (("random", built_random), ("policy", built_policy)):
                rows.append({"task": task, "build": label, "transitions": transitions,
                             "episodes": result.entry.total_episodes, "bare_env_per_s": bare,
                             "build_per_s": result.transitions_per_second,
                             "ratio": result.transitions_per_second / bare})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--transitions", type=int, default=20_000)
    parser.add_argument("--tasks", nargs="+", default=list(DEFAULT_TASKS))
    parser.add_argument("--json", type=pathlib.Path, help="also write the rows here")
    args = parser.parse_args()
    rows = run(args.tasks, args.transitions)
    print(f"{'task':28} {'build':7} {'episodes':>8} {'bare env/s':>11} {'build/s':>9} {'ratio':>6}")
    for row in rows:
        print(f"{row['task']:28} {row['build']:7} {row['episodes']:>8} {row['bare_env_per_s']:>11.0f} "
              f"{row['build_per_s']:>9.0f} {row['ratio']:>6.2f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
