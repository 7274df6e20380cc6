"""Whole ``train`` runs on a GPU against the same seeds trained one after another on one CPU core.

Issue 9's third GPU target: ``--n-seeds N --device cuda`` (networks batched over seeds, the update
replayed from a CUDA graph, the N environments stepped together, in-training evaluation included)
at least 5x the aggregate training steps per second of those seeds trained one after another with
``--device cpu`` and one torch thread. Both sides run :func:`baselines.train.train` with the same
method, task, steps and evaluation settings, in one process, so load hits both alike.

Runs one after another have an aggregate rate equal to one run's rate (every seed costs the same
number of steps), so the CPU side trains ``--cpu-seeds`` of the N seeds and reports their aggregate
rate; the ratio is (N x steps / GPU wall time) / (cpu-seeds x steps / CPU wall time).

    python benchmarks/bench_gpu_train.py [--seeds 20] [--cpu-seeds 2] [--steps 2500] [--json out.json]

Without a CUDA device it says so and measures nothing (exit status 0).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

from baselines.train import train


def _timed_train(out: Path, *, method: str, task: str, steps: int, seed: int, n_seeds: int, device: str,
                 random_steps: int) -> float:
    start = time.perf_counter()
    train(method, task, steps=steps, out=out, seed=seed, n_seeds=n_seeds, device=device, threads=1,
          overrides={"random_steps": str(random_steps)}, eval_every=steps, eval_episodes=2, progress=False)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", default="sac-target")
    parser.add_argument("--task", default="hopper-gravity-0.5")
    parser.add_argument("--seeds", type=int, default=20, help="seeds trained together on the GPU")
    parser.add_argument("--cpu-seeds", type=int, default=2, help="of those, trained one after another on the CPU")
    parser.add_argument("--steps", type=int, default=2500, help="environment steps per seed")
    parser.add_argument("--random-steps", type=int, default=500, help="uniform-random steps before updates start")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not torch.cuda.is_available():
        print(f"no CUDA device visible to torch {torch.__version__}: nothing measured", file=sys.stderr)
        return
    common = {"method": args.method, "task": args.task, "steps": args.steps, "random_steps": args.random_steps}
    with tempfile.TemporaryDirectory() as tmp:
        # Warm-up: CUDA context, cuBLAS handles, the graph capture path, MuJoCo model compilation.
        _timed_train(Path(tmp) / "warm-up", seed=0, n_seeds=args.seeds, device="cuda",
                     **common | {"steps": args.random_steps + 50})
        gpu_s = _timed_train(Path(tmp) / "cuda", seed=0, n_seeds=args.seeds, device="cuda", **common)
        cpu_s = sum(_timed_train(Path(tmp) / f"cpu-{seed}", seed=seed, n_seeds=1, device="cpu", **common)
                    for seed in range(args.cpu_seeds))
    gpu_rate, cpu_rate = args.seeds * args.steps / gpu_s, args.cpu_seeds * args.steps / cpu_s
    report = {"device": torch.cuda.get_device_name(), "torch": torch.__version__, **vars(args) | {"json": None},
              "gpu_seconds": gpu_s, "cpu_seconds": cpu_s, "gpu_seed_steps_per_s": gpu_rate,
              "cpu_seed_steps_per_s": cpu_rate, "ratio": gpu_rate / cpu_rate}
    print(f"{args.method} on {args.task}, {args.steps} steps per seed ({args.random_steps} random): "
          f"{args.seeds} seeds together on {report['device']}: {gpu_rate:.0f} seed-steps/s; "
          f"one after another on one CPU core: {cpu_rate:.0f} seed-steps/s; ratio {report['ratio']:.1f}x", flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
