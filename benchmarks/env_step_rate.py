"""Steps per second of registered envs against the vanilla Gymnasium v5 env, side by side.

    .venv/bin/python benchmarks/env_step_rate.py [--steps 2000] [--rounds 40] [--clock wall|cpu]

Every env runs the same pre-drawn actions with ``terminate_when_unhealthy=False`` (so reset
frequency does not depend on the dynamics), in many short interleaved rounds so drifts in machine
load hit all envs alike. The figure is the median over rounds of steps/s, reported as a ratio to
the vanilla env measured in the same run. ``--clock cpu`` times the process's CPU time instead of
wall time: on a machine shared with other work it leaves out the time spent waiting for a core
(on an idle machine the two agree: stepping is single-threaded).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

import gymnasium
import numpy as np

import offdyn_bench  # noqa: F401  (registers the ids)

ROBOTS = ("Hopper", "Walker2d", "HalfCheetah", "Ant")
# Gymnasium-Robotics families (issue 16), measured on request (--robots AntMazeMedium AdroitDoor):
# the vanilla env is the Gymnasium-Robotics one (AntMaze on the suite's map, so start and goal match).
ROBOTICS_ROBOTS = ("AntMazeSmall", "AntMazeMedium", "AntMazeLarge", "AdroitPen", "AdroitDoor", "AdroitRelocate",
                   "AdroitHammer")


def robotics_cases(robot: str) -> list[tuple[str, str, dict]]:
    """(label, env id, make kwargs) of a Gymnasium-Robotics robot: vanilla reference first."""
    import contextlib
    import io

    with contextlib.redirect_stderr(io.StringIO()):  # Gymnasium-Robotics' release notice
        import gymnasium_robotics
    gymnasium.register_envs(gymnasium_robotics)
    from offdyn_bench.robotics.adroit import ADROIT_TASKS
    from offdyn_bench.robotics.mazes import get_maze

    if robot.startswith("AntMaze"):
        maze = get_maze(robot.removeprefix("AntMaze").lower())
        vanilla_map = [[int(c) if c in "01" else c for c in row] for row in maze.source_map]
        return [
            ("vanilla (Gymnasium-Robotics)", maze.vanilla_env_id, {"maze_map": vanilla_map}),
            ("no effects (source)", f"offdyn/{robot}-layout-blocked-source-v0", {}),
            ("model effects (layout blocked)", f"offdyn/{robot}-layout-blocked-target-v0", {}),
        ]
    task = ADROIT_TASKS[robot]
    return [
        ("vanilla (Gymnasium-Robotics)", task.vanilla_env_id, {}),
        ("no effects (source)", f"offdyn/{robot}-broken-joint-{task.broken_joint[0]}-hard-source-v0", {}),
        ("model effects (broken joint hard)", f"offdyn/{robot}-broken-joint-{task.broken_joint[0]}-hard-target-v0", {}),
        ("model effects (shrink finger hard)", f"offdyn/{robot}-shrink-finger-{task.shrunk_finger}-hard-target-v0", {}),
    ]


def cases(robot: str) -> list[tuple[str, str]]:
    """(label, env id) pairs: vanilla reference first."""
    return [
        ("vanilla v5", f"{robot}-v5"),
        ("no effects (source)", f"offdyn/{robot}-gravity-0.5-source-v0"),
        ("model effects (gravity 0.5)", f"offdyn/{robot}-gravity-0.5-target-v0"),
        ("model effects (morph)", next(f"offdyn/{robot}-morph-{p}-easy-target-v0"
                                       for p in offdyn_bench.robots.ROBOTS[robot].morph_parts)),
        ("channel effects (joint noise 0.1)", f"offdyn/{robot}-joint-noise-0.1-target-v0"),
        # Version 1: the same noise, the control cost charged on the commanded action (one wrapper more).
        ("joint noise 0.1, cost on command (v1)", f"offdyn/{robot}-joint-noise-0.1-target-v1"),
    ]


CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def steps_per_second(env: gymnasium.Env, actions: np.ndarray,
                     clock: Callable[[], float] = time.perf_counter) -> float:
    env.reset(seed=0)
    start = clock()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    return len(actions) / (clock() - start)


def measure(robot: str, steps: int, rounds: int,
            clock: Callable[[], float] = time.perf_counter) -> list[tuple[str, float, float]]:
    if robot in ROBOTICS_ROBOTS:
        # AntMaze never ends early (a continuing task); Adroit envs do not terminate.
        labelled_kwargs = robotics_cases(robot)
        labelled = [(label, env_id) for label, env_id, _ in labelled_kwargs]
        envs = [gymnasium.make(env_id, max_episode_steps=1000, **kwargs) for _, env_id, kwargs in labelled_kwargs]
    else:
        labelled = cases(robot)
        kwargs = {} if robot == "HalfCheetah" else {"terminate_when_unhealthy": False}
        envs = [gymnasium.make(env_id, max_episode_steps=1000, **kwargs) for _, env_id in labelled]
    actions = np.random.default_rng(0).uniform(-1, 1, size=(steps, *envs[0].action_space.shape))
    for env in envs:  # warm-up
        steps_per_second(env, actions[:500])
    rates: list[list[float]] = [[] for _ in envs]
    for _ in range(rounds):
        for i, env in enumerate(envs):
            rates[i].append(steps_per_second(env, actions, clock))
    medians = [statistics.median(r) for r in rates]
    return [(label, rate, rate / medians[0]) for (label, _), rate in zip(labelled, medians, strict=True)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--rounds", type=int, default=40)
    parser.add_argument("--robots", nargs="*", default=list(ROBOTS), choices=ROBOTS + ROBOTICS_ROBOTS)
    parser.add_argument("--clock", choices=CLOCKS, default="wall",
                        help="wall time (default) or this process's CPU time (for a shared machine)")
    args = parser.parse_args()
    if args.steps < 1 or args.rounds < 1:
        parser.error(f"--steps and --rounds must be positive, got {args.steps} and {args.rounds}")
    load_before = os.getloadavg()[0]
    print("| robot | env | steps/s | ratio to vanilla |")
    print("|---|---|---:|---:|")
    for robot in args.robots:
        for label, rate, ratio in measure(robot, args.steps, args.rounds, CLOCKS[args.clock]):
            print(f"| {robot} | {label} | {rate:,.0f} | {ratio:.3f} |", flush=True)
    # Ratios hold up under load better than steps/s, but not fully: say what the machine was doing.
    print(f"\n{args.clock} clock; {os.cpu_count()} cores; 1-minute load average {load_before:.2f} at the start, "
          f"{os.getloadavg()[0]:.2f} at the end (this run counts as 1)")


if __name__ == "__main__":
    main()
