"""Where the suite env's per-step overhead goes: the state capture, measured side by side.

    .venv/bin/python benchmarks/bench_state_capture.py [--robot HalfCheetah] [--rounds 15]

The suite env (`offdyn/<Robot>-gravity-0.5-source-v0`, no effects) against the vanilla Gymnasium
v5 env, and copies of the suite env whose ``step`` is replaced by variants of the state capture,
all interleaved in one run (the method of ``env_step_rate.py``). Printed as steps/s and the ratio
to vanilla. The variants:

- ``plain step``: Gymnasium's step, no capture (what subclassing alone costs);
- ``capture into one buffer``: ``mj_getState`` into one reused array, put in ``info`` (the
  cheapest possible capture, but every info would alias the same array);
- ``capture into a new array``: a fresh ``np.empty`` per step;
- ``block rows, no info``: the suite's row blocks and ``mj_getState``, nothing written to info.
"""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Callable

import gymnasium
import numpy as np

import offdyn_bench  # noqa: F401  (registers the ids)
import offdyn_bench.envs as suite_envs
from env_step_rate import steps_per_second


def _variants(base_step: Callable) -> dict[str, Callable]:
    bits = suite_envs._FULL_PHYSICS_BITS  # the suite's own constants, so the variants match its step
    get_state = suite_envs._get_state

    def plain(env):
        return lambda action: base_step(env, action)

    def one_buffer(env):
        buffer, model, data = np.empty(env.state_size), env.model, env.data

        def step(action):
            result = base_step(env, action)
            get_state(model, data, buffer, bits)
            result[4]["state"] = buffer
            return result
        return step

    def new_array(env):
        size, model, data = env.state_size, env.model, env.data

        def step(action):
            result = base_step(env, action)
            state = np.empty(size)
            get_state(model, data, state, bits)
            result[4]["state"] = state
            return result
        return step

    def block_rows(env):
        def step(action):
            result = base_step(env, action)
            rows = env._suite.rows.free or env._suite.rows.refill()
            destination, _ = rows.pop()
            get_state(env.model, env.data, destination, bits)
            return result
        return step

    return {"plain step": plain, "capture into one buffer": one_buffer, "capture into a new array": new_array,
            "block rows, no info": block_rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robot", default="HalfCheetah", choices=("Hopper", "Walker2d", "HalfCheetah", "Ant"))
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--steps", type=int, default=2000)
    args = parser.parse_args()
    kwargs = {} if args.robot == "HalfCheetah" else {"terminate_when_unhealthy": False}
    vanilla = gymnasium.make(f"{args.robot}-v5", max_episode_steps=1000, **kwargs)
    suite_id = f"offdyn/{args.robot}-gravity-0.5-source-v0"
    base_step = type(vanilla.unwrapped).step
    labelled = [("vanilla v5", vanilla), ("suite env (as shipped)", gymnasium.make(suite_id, max_episode_steps=1000,
                                                                                   **kwargs))]
    for label, make_step in _variants(base_step).items():
        env = gymnasium.make(suite_id, max_episode_steps=1000, **kwargs)
        env.unwrapped.step = make_step(env.unwrapped)
        labelled.append((label, env))
    actions = np.random.default_rng(0).uniform(-1, 1, size=(args.steps, *vanilla.action_space.shape))
    for _, env in labelled:
        steps_per_second(env, actions[:500])
    rates: list[list[float]] = [[] for _ in labelled]
    for _ in range(args.rounds):
        for i, (_, env) in enumerate(labelled):
            rates[i].append(steps_per_second(env, actions))
    medians = [statistics.median(r) for r in rates]
    print(f"| {args.robot} | steps/s | ratio to vanilla |\n|---|---:|---:|")
    for (label, _), rate in zip(labelled, medians, strict=True):
        print(f"| {label} | {rate:,.0f} | {rate / medians[0]:.3f} |")


if __name__ == "__main__":
    main()
