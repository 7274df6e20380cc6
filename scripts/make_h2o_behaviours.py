"""Train the oracle of the H2O settings' target and export the behaviours of their D4RL-style data.

The H2O pairs (``*-h2o-*``) shift the simulator and keep the nominal robot as the target, so one
``sac-target`` run per robot serves all three of its settings. This script trains it (resumable,
every checkpoint's actor kept), then writes

* ``assets/policies/sac-target/<robot>-nominal.safetensors``: the final policy, the oracle that
  scores these tasks' datasets and the ``medium-expert`` data's expert half;
* ``assets/policies/sac-target-medium/<robot>-nominal.safetensors``: the checkpoint whose return
  is closest to a third of the way from random to the oracle, the ``medium`` behaviour, whose
  sidecar also says how to re-run the training up to it for ``medium-replay``.

Then build and record the datasets: ``offdyn-bench datasets build offdyn/<task>/<quality>-v0
--update-manifest`` for each H2O task and quality (``medium``, ``medium-replay``, ``medium-expert``).

    python scripts/make_h2o_behaviours.py --robot halfcheetah --steps 1000000 --runs runs/h2o-behaviours
"""

from __future__ import annotations

import argparse
import json
import pathlib

from offdyn_bench.datasets.recipes import MEDIUM_FRACTION, REFERENCE_EPISODES, REFERENCE_SEED, REPO_ROOT, is_h2o_setting
from offdyn_bench.datasets.training_data import export_h2o_behaviours, size_replay_recipes, train_keeping_checkpoints
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import TASKS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    robots = sorted({pair.robot.lower() for pair in TASKS.values() if is_h2o_setting(pair)})
    parser.add_argument("--robot", required=True, choices=robots)
    parser.add_argument("--steps", type=int, default=1_000_000, help="SAC steps in the target (the oracle's budget)")
    parser.add_argument("--checkpoint-every", type=int, default=None,
                        help="Steps between the checkpoints the medium level is chosen from (default: steps / 40)")
    parser.add_argument("--runs", type=pathlib.Path, default=pathlib.Path("runs/h2o-behaviours"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-root", type=pathlib.Path, default=REPO_ROOT,
                        help="Where assets/policies/... is written (default: this checkout)")
    args = parser.parse_args()
    if args.steps < 2:
        parser.error(f"--steps {args.steps}: expected at least 2 (a medium checkpoint before the final one)")
    every = args.checkpoint_every or max(1, args.steps // 40)
    if every < 1 or args.steps % every:
        parser.error(f"--checkpoint-every {every} must divide --steps {args.steps}")
    pair = next(p for p in TASKS.values() if is_h2o_setting(p) and p.robot.lower() == args.robot)
    out = args.runs / args.robot
    try:
        kept = train_keeping_checkpoints(pair.name, steps=args.steps, checkpoint_every=every, out=out, seed=args.seed)
        summary = export_h2o_behaviours(out / "run", kept, pair, out_root=args.out_root, episodes=REFERENCE_EPISODES,
                                        first_seed=REFERENCE_SEED, fraction=MEDIUM_FRACTION)
        # medium-replay is what the run stored up to the medium step: this checkout's recipes take
        # that size now (they read the policy where this checkout ships it).
        sized = size_replay_recipes(args.robot) if args.out_root.resolve() == REPO_ROOT else []
    except OffdynError as error:
        raise SystemExit(f"error: {error}") from None
    level = summary["level"]
    print(json.dumps({"oracle": str(summary["expert"]), "medium": str(summary["medium"]),
                      "random_return": level["random_return"], "oracle_return": level["expert_return"],
                      "medium_step": level["chosen_step"],
                      "medium_return": level["checkpoint_returns"][str(level["chosen_step"])],
                      "medium_replay_recipes_sized": sized}, indent=1))


if __name__ == "__main__":
    main()
