"""Steps per second of the DART targets against the MuJoCo source, side by side in one run.

    .venv/bin/python benchmarks/bench_dart.py [--steps 2000] [--rounds 20] [--clock wall|cpu]

For Hopper and Walker2d: the MuJoCo source (``offdyn/<Robot>-dart-source-v0``), the DART target
with ODE's collision detector (the registered ``offdyn/<Robot>-dart-target-v0``) and with Bullet's.
Every env runs the same pre-drawn actions with ``terminate_when_unhealthy=False`` (reset frequency
does not depend on the dynamics), in short interleaved rounds so drifts in machine load hit all
envs alike. The figure is the median over rounds of env steps/s, reported as a ratio to the MuJoCo
source measured in the same run. ``--clock cpu`` times the process's CPU time (for a shared machine).
"""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Callable

import gymnasium
import numpy as np

import offdyn_bench  # noqa: F401  (registers the ids)
# The same timing loop and clocks as the env step-rate benchmark (run as a script, this folder is
# on sys.path).
from env_step_rate import CLOCKS, steps_per_second

ROBOTS = ("Hopper", "Walker2d")


def cases(robot: str) -> list[tuple[str, str, dict]]:
    """(label, env id, make kwargs); the MuJoCo source, the reference, first."""
    return [
        ("MuJoCo source", f"offdyn/{robot}-dart-source-v0", {}),
        ("DART target (ODE detector)", f"offdyn/{robot}-dart-target-v0", {}),
        ("DART target (Bullet detector)", f"offdyn/{robot}-dart-target-v0", {"collision_detector": "bullet"}),
    ]


def measure(robot: str, steps: int, rounds: int, clock: Callable[[], float]) -> list[tuple[str, float, float]]:
    labelled = cases(robot)
    envs = [gymnasium.make(env_id, max_episode_steps=1000, terminate_when_unhealthy=False, **kwargs)
            for _, env_id, kwargs in labelled]
    actions = np.random.default_rng(0).uniform(-1, 1, size=(steps, *envs[0].action_space.shape))
    for env in envs:  # warm-up
        steps_per_second(env, actions[:200], clock)
    rates: list[list[float]] = [[] for _ in envs]
    for _ in range(rounds):
        for i, env in enumerate(envs):
            rates[i].append(steps_per_second(env, actions, clock))
    medians = [statistics.median(r) for r in rates]
    return [(label, rate, rate / medians[0]) for (label, _, _), rate in zip(labelled, medians, strict=True)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--robots", nargs="*", default=list(ROBOTS), choices=ROBOTS)
    parser.add_argument("--clock", choices=CLOCKS, default="wall")
    args = parser.parse_args()
    if args.steps < 1 or args.rounds < 1:
        parser.error(f"--steps and --rounds must be positive, got {args.steps} and {args.rounds}")
    print(f"| robot | env | steps/s | ratio to MuJoCo |  ({args.steps} steps x {args.rounds} rounds, "
          f"{args.clock} clock, median)")
    print("|---|---|---|---|")
    for robot in args.robots:
        for label, rate, ratio in measure(robot, args.steps, args.rounds, CLOCKS[args.clock]):
            print(f"| {robot} | {label} | {rate:,.0f} | {ratio:.3f} |")


if __name__ == "__main__":
    main()
