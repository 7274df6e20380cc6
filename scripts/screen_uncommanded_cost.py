"""Screen task pairs for a reward shift hidden in a dynamics shift: control cost nobody commanded.

Off-dynamics RL assumes one reward function on both sides; only the dynamics differ. A shift that
perturbs the command between the policy and the motors (joint noise, a bias) changes what the
robot's own reward charges as control cost, because Gymnasium's MuJoCo robots charge the action
they are stepped with. This script steps every selected pair with the zero command (the centre of
the action box, which commands no effort) on both sides, for the protocol's first `--episodes`
episode seeds, and reports per step the mean of each `reward_*` term the robot reports, the
return and the episode length. A control term that is zero in the source and not in the target is
cost the agent never commanded; where the robot also ends episodes on a fall, it can outweigh the
survival reward and make ending an episode early the best a policy can do.

    .venv/bin/python scripts/screen_uncommanded_cost.py --match joint-noise --episodes 5
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from offdyn_bench.envs import flat_observations
from offdyn_bench.protocol import EPISODE_SEEDS
from offdyn_bench.protocol.references import zero_command
from offdyn_bench.tasks import TASKS, get_task


def zero_command_episodes(task: str, side: str, episodes: int) -> dict[str, float]:
    """Mean return, length and per-step ``reward_*`` terms of the zero command on ``side``."""
    env = flat_observations(get_task(task).make(side))
    space = env.action_space
    command = zero_command(space).astype(space.dtype)
    returns, lengths, terms = [], [], {}
    try:
        for e in range(episodes):
            env.reset(seed=int(EPISODE_SEEDS[0]) + e)
            total, steps, done = 0.0, 0, False
            while not done:
                _, reward, terminated, truncated, info = env.step(command)
                total, steps, done = total + float(reward), steps + 1, terminated or truncated
                for key, value in info.items():
                    if key.startswith("reward_") and np.isscalar(value):
                        terms.setdefault(key, []).append(float(value))
            returns.append(total)
            lengths.append(steps)
    finally:
        env.close()
    return {"return": float(np.mean(returns)), "length": float(np.mean(lengths))} | {
        key: float(np.mean(values)) for key, values in sorted(terms.items())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--match", default="noise", help="pairs whose name contains this (default: noise)")
    parser.add_argument("--skip", nargs="*", default=["dart"],
                        help="skip pairs whose name contains one of these (default: dart, an optional engine)")
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--json", type=pathlib.Path, default=None, help="also write the rows here")
    args = parser.parse_args()
    if not 1 <= args.episodes <= len(EPISODE_SEEDS):
        raise SystemExit(f"error: --episodes {args.episodes}; expected 1 to {len(EPISODE_SEEDS)}")
    tasks = [name for name in TASKS if args.match in name and not any(word in name for word in args.skip)]
    if not tasks:
        raise SystemExit(f"error: no registered pair's name contains {args.match!r}")
    print("| pair | zero command: source return (length) | target return (length) | "
          "control term per step, source / target |")
    print("|---|---:|---:|---:|")
    rows = []
    for task in tasks:
        source = zero_command_episodes(task, "source", args.episodes)
        target = zero_command_episodes(task, "target", args.episodes)
        control = f"{source.get('reward_ctrl', float('nan')):.3f} / {target.get('reward_ctrl', float('nan')):.3f}"
        print(f"| `{task}` | {source['return']:.1f} ({source['length']:.0f}) | {target['return']:.1f} "
              f"({target['length']:.0f}) | {control} |", flush=True)
        rows.append({"task": task, "source": source, "target": target})
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
