"""Steps per second of the wheel-legged envs against a bare ``mujoco.mj_step`` loop of the same model.

    .venv/bin/python benchmarks/bench_wheel_legged.py [--steps 2000] [--rounds 30] [--clock wall|cpu]

The bare loop is the least any env of this model can cost: write the command, ``mj_step`` five
physics steps (one 200 Hz control step). The env adds Gymnasium's wrappers (time limit, order
enforcing, passive checker), the observation, reward and termination, the full physics state in
``info``, and on the target the channel effects (dead zone, observation delay and noise).

Both loops replay the same commands from the same state: the actions of a balancing run of the
clean controller recorded once in that env (on the target, the commands after its dead zone go to
the bare loop), so neither falls and neither resets while timed. Rounds alternate between the
loops so drifts in machine load hit both alike; the figure is the median over rounds, reported as
the ratio env / bare measured in this one run.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import gymnasium
import mujoco
import numpy as np

import offdyn_bench  # noqa: F401  (registers the ids)
from offdyn_bench.wheel_legged.operator import BalancingController

CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}
FULL_PHYSICS = mujoco.mjtState.mjSTATE_FULLPHYSICS


def record_balancing_run(env_id: str, steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The env's actions, the commands the physics got, and the physics state at reset."""
    env = gymnasium.make(env_id)
    task = env.unwrapped.task
    controller = BalancingController(task)
    obs, info = env.reset(seed=0)
    physics_size = mujoco.mj_stateSize(env.unwrapped.model, FULL_PHYSICS)
    start = np.array(info["state"][:physics_size])
    actions, applied = [], []
    for _ in range(steps):
        action = controller(obs).astype(np.float32)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            raise RuntimeError(f"the clean controller fell in {env_id}; the benchmark needs a balancing run")
        actions.append(action)
        applied.append(np.asarray(info.get("applied_action", action), dtype=float))
    return np.array(actions), np.array(applied), start


def env_rate(env: gymnasium.Env, actions: np.ndarray, clock: Callable[[], float]) -> float:
    env.reset(seed=0)
    step = env.step
    began = clock()
    for action in actions:
        step(action)
    return len(actions) / (clock() - began)


def bare_rate(model: mujoco.MjModel, data: mujoco.MjData, start: np.ndarray, commands: np.ndarray,
              frame_skip: int, clock: Callable[[], float]) -> float:
    mujoco.mj_setState(model, data, start, FULL_PHYSICS)
    ctrl = data.ctrl
    began = clock()
    for command in commands:
        ctrl[0] = command[0]
        mujoco.mj_step(model, data, frame_skip)
    return len(commands) / (clock() - began)


def measure(env_id: str, steps: int, rounds: int, clock: Callable[[], float]) -> tuple[float, float]:
    actions, applied, start = record_balancing_run(env_id, steps)
    env = gymnasium.make(env_id)
    base = env.unwrapped
    model, data = base.model, mujoco.MjData(base.model)
    env_rate(env, actions[:200], clock)  # warm-up
    bare_rate(model, data, start, applied[:200], base.frame_skip, clock)
    env_rates, bare_rates = [], []
    for _ in range(rounds):
        env_rates.append(env_rate(env, actions, clock))
        bare_rates.append(bare_rate(model, data, start, applied, base.frame_skip, clock))
    return statistics.median(env_rates), statistics.median(bare_rates)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--clock", choices=CLOCKS, default="wall")
    args = parser.parse_args()
    if args.steps < 1 or args.rounds < 1:
        parser.error(f"--steps and --rounds must be positive, got {args.steps} and {args.rounds}")
    if args.steps > 4000:
        parser.error(f"--steps must be at most 4000 (a movestraight episode), got {args.steps}")
    print(f"mujoco {mujoco.__version__}, {args.steps} control steps x {args.rounds} rounds, {args.clock} clock")
    print(f"{'env':45} {'env steps/s':>12} {'bare steps/s':>13} {'ratio':>6}")
    for task in ("standstill", "movestraight"):
        for side in ("source", "target"):
            env_id = f"offdyn/WheelLegged-{task}-{side}-v0"
            env_steps, bare_steps = measure(env_id, args.steps, args.rounds, CLOCKS[args.clock])
            print(f"{env_id:45} {env_steps:12,.0f} {bare_steps:13,.0f} {env_steps / bare_steps:6.2f}")


if __name__ == "__main__":
    main()
