"""Screen candidate pairs for a next core suite with the lite RL-on-source runs themselves.

PROTOCOL.md §7 screened the grid with one shipped 220,000-step policy; §9 found that at the lite
budget the chosen Hopper pairs no longer show RL on source clearly failing. This script measures,
for every pair whose source is the runs' source, what the lite `sac-source` runs (one folder per
training seed, as a sweep writes them) keep in its target: each run's final policy, deterministic,
on the protocol's first `--episodes` episode seeds, through `offdyn-bench evaluate` (so the numbers
are the protocol's, on fewer episodes). The source side is measured once per run (every pair here
has the same source).

    .venv/bin/python scripts/screen_lite_gap.py runs/reference-lite/runs/sac-source/hopper-gravity-0.5/seed-* \\
        --episodes 5 --json screen-lite-hopper.json

It ranks candidates; it decides nothing: a pair joins a protocol's core suite only when the oracle
runs at that budget beat RL on source there (`offdyn-bench protocol gap`).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import tempfile

import numpy as np

from offdyn_bench.errors import OffdynError
from offdyn_bench.evaluate import evaluate
from offdyn_bench.protocol.scoring import seed_means
from offdyn_bench.tasks import TASKS, get_task


def _mean(record: dict) -> float:
    """The record's mean return over its training seeds (each seed's the mean of its episodes)."""
    return float(np.mean(list(seed_means(record).values())))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=pathlib.Path, help="sac-source run folders, one training seed each")
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--skip", nargs="*", default=["dart"],
                        help="skip pairs whose name contains one of these (default: dart, an optional engine)")
    parser.add_argument("--json", type=pathlib.Path, default=None, help="also write the table here")
    args = parser.parse_args()
    configs = [json.loads((run / "config.json").read_text()) for run in args.runs]
    if any(config.get("algo") != "sac-source" for config in configs):
        raise SystemExit("error: every run must be a sac-source run (its config.json algo)")
    trained = {config["task"] for config in configs}
    source_key = {get_task(task).source_key for task in trained}
    if len(source_key) != 1:
        raise SystemExit(f"error: the runs train in different sources ({sorted(trained)})")
    key = source_key.pop()
    pairs = [name for name, pair in TASKS.items()
             if pair.source_key == key and not any(word in name for word in args.skip)]
    with tempfile.TemporaryDirectory() as scratch:
        out = pathlib.Path(scratch)

        def score(run: pathlib.Path, task: str, side: str) -> float:
            path = out / f"{run.name}-{task}-{side}.json"
            return _mean(evaluate(run, task, episodes=args.episodes, out=path, progress=False, side=side))

        source = [score(run, configs[i]["task"], "source") for i, run in enumerate(args.runs)]
        print(f"source return per run: {', '.join(f'{x:.1f}' for x in source)} (mean {np.mean(source):.1f})")
        print(f"{'pair':34s} {'target per run':>44s} {'mean':>8s} {'kept':>6s}")
        table = {"source": source, "episodes": args.episodes, "runs": [str(run) for run in args.runs], "pairs": {}}
        for task in pairs:
            try:
                target = [score(run, task, "target") for run in args.runs]
            except OffdynError as error:
                print(f"{task:34s} skipped: {error}", flush=True)
                continue
            kept = float(np.mean(target) / np.mean(source))
            table["pairs"][task] = {"target": target, "mean": float(np.mean(target)), "kept": kept}
            print(f"{task:34s} {' '.join(f'{x:8.1f}' for x in target):>44s} {np.mean(target):8.1f} {kept:6.2f}",
                  flush=True)
    if args.json:
        args.json.write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
