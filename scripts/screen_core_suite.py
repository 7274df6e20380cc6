"""Screen the grid for the protocol's core suite: how much of its source return the shipped
RL-on-source behaviour policy keeps in each nominal-source pair's target.

    .venv/bin/python scripts/screen_core_suite.py [--episodes 5] [--json screen.json]

Each pair: the robot's `assets/policies/sac-source/<robot>-nominal` policy, deterministic, for
`--episodes` fixed-seed episodes (seeds 3,000,000...) in the source and in the target. PROTOCOL.md
section 7 quotes this table.
"""

from __future__ import annotations

import argparse
import json

import offdyn_bench  # noqa: F401  (registers the pairs)
from offdyn_bench.datasets.policies import evaluate_policy
from offdyn_bench.tasks import TASKS

FIRST_SEED = 3_000_000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--json", default=None, help="also write the table here")
    args = parser.parse_args()
    table = {}
    print(f"{'pair':40s} {'source':>8s} {'target':>8s} {'kept':>6s}")
    for name, pair in TASKS.items():
        if pair.robot == "InvertedPendulum" or pair.source_effects:
            continue  # only nominal sources have a shipped behaviour policy
        policy = f"assets/policies/sac-source/{pair.robot.lower()}-nominal.safetensors"
        row = {side: evaluate_policy(policy, pair.env_id(side), args.episodes, first_seed=FIRST_SEED)["mean_return"]
               for side in ("source", "target")}
        table[name] = row
        print(f"{name:40s} {row['source']:8.1f} {row['target']:8.1f} {row['target'] / row['source']:6.2f}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(table, f, indent=1)


if __name__ == "__main__":
    main()
