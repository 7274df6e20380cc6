"""Several training runs sharing one GPU, as a lease's reference sweep runs them: their evaluations
acting from a CPU copy of the policy (the default) against acting on the GPU (``--eval-on-device``),
side by side; and, as a third way, the same seeds all in one process.

Each round starts ``--runs`` processes at once (``offdyn-bench train``, ``--seeds`` seeds each, one
torch thread, the CUDA-graph update where the method has one) and times them until the last one
ends; rounds alternate between the ways. ``host``: evaluations from a CPU copy of the policy;
``device``: ``--eval-on-device``; ``batched``: one process training all ``runs x seeds`` seeds in
one batch (one graph), host evaluations. ``batched`` stands in for training several tasks of one
robot in one process (the same update work; only the data each seed samples would differ), which
the suite does not do: it measures whether that would pay before it is built. Per way: seed-steps
per second of the whole round (``runs x seeds x steps / wall``), and the share of the runs' time
their evaluations took (``evaluation_wall_time_s`` over ``wall_time_s`` of ``metrics.jsonl``).
Ratios (host over device, batched over host) are per round, median over rounds. ``same_updates``
says whether each host run's losses equal its device partner's at every evaluation (they must:
where the policy acts in an evaluation changes no update).

HalfCheetah by default: its episodes never end early, so an evaluation's length does not depend on
how well the policy has learnt. Without a CUDA device it says so and measures nothing (exit status
0), unless ``--device cpu --ways host batched`` asks for a check of the script itself.

    python benchmarks/bench_shared_gpu.py --runs 4 --steps 2000 --rounds 1 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from baselines.algorithms import get_algorithm
from baselines.run_folder import training_progress
from offdyn_bench.datasets.ensure import ensure_dataset
from offdyn_bench.protocol import official_dataset


def _round(args: argparse.Namespace, way: str, folder: Path) -> dict:
    commands = []
    # batched: one process with every seed; otherwise one process per run
    processes_seeds = [args.runs * args.seeds] if way == "batched" else [args.seeds] * args.runs
    for index, n_seeds in enumerate(processes_seeds):
        command = [sys.executable, "-m", "offdyn_bench", "train", args.method, "--task", args.task,
                   "--steps", str(args.steps), "--eval-every", str(args.eval_every),
                   "--eval-episodes", str(args.eval_episodes), "--n-seeds", str(n_seeds),
                   "--seed", str(index * args.seeds), "--threads", "1", "--device", args.device,
                   "--no-progress", "--out", str(folder / f"run-{index}")]
        # the CUDA-graph update where the method has one, as the lease's sweep runs it
        if args.device != "cpu" and hasattr(get_algorithm(args.method).default_config(), "cuda_graph"):
            command += ["--set", "cuda_graph=true"]
        if way == "device":
            command.append("--eval-on-device")
        commands.append(command)
    start = time.perf_counter()
    processes = [subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                 for command in commands]
    failures = [(p.args, p.communicate()[1]) for p in processes if p.wait() != 0]
    wall_s = time.perf_counter() - start
    if failures:
        command, stderr = failures[0]
        sys.exit(f"error: a {way} run failed: {' '.join(command)}\n{stderr[-2000:]}")
    runs = [folder / f"run-{i}" for i in range(len(processes_seeds))]
    lines = [[json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()] for run in runs]
    evaluation_share = statistics.mean(training_progress(run).evaluation_share for run in runs)
    return {"way": way, "wall_s": round(wall_s, 2),
            "seed_steps_per_s": round(args.runs * args.seeds * args.steps / wall_s, 1),
            "evaluation_share": round(evaluation_share, 3),
            "losses": [[line["train"] for line in run] for run in lines]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", default="cql")
    parser.add_argument("--task", default="halfcheetah-friction-5.0")
    parser.add_argument("--runs", type=int, default=4, help="processes sharing the GPU in each round")
    parser.add_argument("--seeds", type=int, default=5, help="seeds trained together in each process")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--eval-every", type=int, default=1000)
    parser.add_argument("--eval-episodes", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=1, help="rounds of each way (the ways alternate)")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--ways", nargs="+", choices=["host", "device", "batched"], default=["host", "device", "batched"])
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    if args.device != "cpu" and not torch.cuda.is_available():
        print(f"no CUDA device visible to torch {torch.__version__}: nothing measured")
        return 0
    if len(set(args.ways)) != len(args.ways):
        parser.error(f"--ways {' '.join(args.ways)}: each way once (the ways alternate within a round)")
    if args.device == "cpu" and "device" in args.ways:
        parser.error("--device cpu: a CPU run evaluates on the CPU already; use --ways host batched to check the script")
    dataset = official_dataset(args.task, "offline-target") if get_algorithm(args.method).needs_dataset else None
    if dataset is not None:  # installed (or verified) once, not by every process at once
        ensure_dataset(dataset, progress=False, echo=lambda line: print(line, file=sys.stderr))
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    rounds: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for way in args.ways:
                result = _round(args, way, Path(tmp) / f"{way}-{r}")
                rounds.append(result)
                print(f"round {r} {way}: {result['wall_s']} s, {result['seed_steps_per_s']} seed-steps/s, "
                      f"evaluations {100 * result['evaluation_share']:.0f}% of the runs' time", flush=True)
    summary: dict = {"method": args.method, "task": args.task, "runs": args.runs, "seeds": args.seeds,
                     "steps": args.steps, "eval_every": args.eval_every, "eval_episodes": args.eval_episodes,
                     "device": torch.cuda.get_device_name(0) if args.device != "cpu" else "cpu",
                     "torch": torch.__version__, "rounds": [{k: v for k, v in r.items() if k != "losses"}
                                                            for r in rounds]}
    by_way = {way: [r for r in rounds if r["way"] == way] for way in args.ways}
    for name, (top, bottom) in {"host_over_device": ("host", "device"), "batched_over_host": ("batched", "host")}.items():
        if top in by_way and bottom in by_way:
            summary[name] = statistics.median(a["seed_steps_per_s"] / b["seed_steps_per_s"]
                                              for a, b in zip(by_way[top], by_way[bottom]))
            print(f"{top} over {bottom}: {summary[name]:.2f}x seed-steps/s (median of {len(by_way[top])})")
    if "host" in by_way and "device" in by_way:
        summary["same_updates"] = all(a["losses"] == b["losses"] for a, b in zip(by_way["host"], by_way["device"]))
        print(f"host and device evaluation made the same updates: {summary['same_updates']}")
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
