"""Whole training runs on CUDA with and without ``cuda_graph=true``: the speed-up, side by side in one
process, and whether the two runs computed the same numbers (they must: the graph's warm-up is
rewound, see :class:`baselines.sac.GraphedUpdate`).

Per method, ``--seeds`` seeds trained together on CUDA, eager and graphed runs alternating for
``--rounds`` rounds after a short warm-up run (CUDA context, cuBLAS handles, MuJoCo compilation).
Each run's rate is steps per second of the whole ``train`` call (start-up and one 2-episode
evaluation included); the ratio is graphed over eager, per round, median over rounds. ``equal``
says whether each graphed run's learning curve (returns and losses) equals its eager partner's.

Without a CUDA device it says so and measures nothing (exit status 0).

    python benchmarks/bench_cuda_graph.py --methods cql sac-target --task halfcheetah-friction-5.0 --json out.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from baselines.train import train
from offdyn_bench.datasets.ensure import ensure_dataset
from offdyn_bench.protocol import official_dataset

RANDOM_STEPS = 500
"""Uniform-random steps before the online methods' first update (shortened from 5,000: the
benchmark measures updates)."""


def _curve(out: Path) -> list[dict]:
    return [{k: v for k, v in json.loads(line).items() if not k.endswith("time_s")}
            for line in (out / "metrics.jsonl").read_text().splitlines()]


def _timed(method: str, task: str, steps: int, n_seeds: int, out: Path, graphed: bool) -> float:
    overrides = {} if method == "cql" else {"random_steps": str(RANDOM_STEPS)}
    if graphed:
        overrides["cuda_graph"] = "true"
    torch.cuda.synchronize()
    start = time.perf_counter()
    train(method, task, steps=steps, out=out, n_seeds=n_seeds, device="cuda", overrides=overrides, eval_every=steps,
          eval_episodes=2, progress=False)
    torch.cuda.synchronize()
    return time.perf_counter() - start


def bench(method: str, task: str, steps: int, n_seeds: int, rounds: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        _timed(method, task, min(steps, RANDOM_STEPS + 50), n_seeds, root / "warm-up", graphed=False)
        eager_s, graphed_s, equal = [], [], []
        for r in range(rounds):
            eager_s.append(_timed(method, task, steps, n_seeds, root / f"eager-{r}", graphed=False))
            graphed_s.append(_timed(method, task, steps, n_seeds, root / f"graphed-{r}", graphed=True))
            equal.append(_curve(root / f"eager-{r}") == _curve(root / f"graphed-{r}"))
            print(f"  {method}, round {r}: eager {eager_s[-1]:.1f} s, graphed {graphed_s[-1]:.1f} s, "
                  f"same curve: {equal[-1]}", flush=True)
    ratios = [e / g for e, g in zip(eager_s, graphed_s)]
    return {"method": method, "task": task, "steps": steps, "seeds": n_seeds, "eager_seconds": eager_s,
            "graphed_seconds": graphed_s, "ratio": statistics.median(ratios), "equal": equal,
            "graphed_seed_steps_per_s": n_seeds * steps / statistics.median(graphed_s),
            "eager_seed_steps_per_s": n_seeds * steps / statistics.median(eager_s)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", nargs="+", default=["cql", "sac-target"], choices=["cql", "sac-source",
                                                                                         "sac-target"])
    parser.add_argument("--task", default="halfcheetah-friction-5.0")
    parser.add_argument("--steps", type=int, default=2000, help="steps per run (CQL: updates)")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not torch.cuda.is_available():
        print(f"no CUDA device visible to torch {torch.__version__}: nothing measured", file=sys.stderr)
        return
    if "cql" in args.methods:  # installed and verified before anything is timed
        ensure_dataset(official_dataset(args.task, "offline-target"), progress=False, echo=print)
    report = {"device": torch.cuda.get_device_name(), "torch": torch.__version__, "rows": []}
    for method in args.methods:
        row = bench(method, args.task, args.steps, args.seeds, args.rounds)
        report["rows"].append(row)
        print(f"{method}: graphed {row['graphed_seed_steps_per_s']:.0f} seed-steps/s, eager "
              f"{row['eager_seed_steps_per_s']:.0f}, ratio {row['ratio']:.1f}x, same curves {row['equal']}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
