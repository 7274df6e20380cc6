"""Does a training's count in reference updates stay put when the machine gets slower?

A training's ``compute.reference_updates`` (:mod:`offdyn_bench.machine_speed`) is meant to be a
unit that does not drift with the machine's speed, where CPU seconds do (PROTOCOL §8). This script
slows the machine down in a controlled way, by making torch and MKL use older vector instructions
(``ATEN_CPU_CAPABILITY``, ``MKL_ENABLE_INSTRUCTIONS``), and trains the same short run under each
setting, one after another in rounds. Per setting it reports the median CPU seconds and reference
updates, each as a ratio to the unslowed machine's: where the count works, the CPU ratio moves and
the updates ratio stays near 1.

    PYTHONPATH=. .venv/bin/python benchmarks/machine_speed_check.py [--method sac-source]
        [--task hopper-gravity-0.5] [--steps 3000] [--rounds 2]

What it does not cover: a machine slowed by its neighbours (shared caches, memory bandwidth, a
busy sibling hyperthread), which is what the drift of PROTOCOL §8 most likely was.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

SETTINGS = {
    "as installed": {},
    "ATen without vector kernels": {"ATEN_CPU_CAPABILITY": "default"},
    "MKL at SSE4.2": {"MKL_ENABLE_INSTRUCTIONS": "SSE4_2"},
    "both": {"ATEN_CPU_CAPABILITY": "default", "MKL_ENABLE_INSTRUCTIONS": "SSE4_2"},
}


def train_once(method: str, task: str, steps: int, extra: list[str], environment: dict[str, str]) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "run"
        command = [sys.executable, "-m", "offdyn_bench", "train", method, "--task", task, "--steps", str(steps),
                   "--seed", "0", "--n-seeds", "1", "--threads", "1", "--eval-episodes", "1",
                   "--eval-every", str(steps), "--out", str(out), *extra]
        subprocess.run(command, check=True, capture_output=True, env=os.environ | environment)
        compute = json.loads((out / "result.json").read_text())["compute"]
    return {"cpu_time_s": compute["cpu_time_s"], "reference_updates": compute["reference_updates"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", default="sac-source")
    parser.add_argument("--task", default="hopper-gravity-0.5")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--random-steps", type=int, default=1000,
                        help="the method's random_steps (its updates start after them)")
    parser.add_argument("--track", default=None, help="the training track, for methods that need one")
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    extra = ["--set", f"random_steps={args.random_steps}"] + (["--track", args.track] if args.track else [])
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in SETTINGS}
    for round_ in range(args.rounds):
        for name, environment in SETTINGS.items():  # interleaved, so a drifting machine hits every setting
            runs[name].append(train_once(args.method, args.task, args.steps, extra, environment))
            print(f"round {round_ + 1} {name}: {runs[name][-1]}", file=sys.stderr)

    def median(name: str, key: str) -> float:
        return statistics.median(run[key] for run in runs[name])

    base_cpu, base_updates = median("as installed", "cpu_time_s"), median("as installed", "reference_updates")
    print(f"{args.method} on {args.task}, {args.steps} steps (random_steps={args.random_steps}), median of "
          f"{args.rounds} round(s):")
    print(f"{'setting':30s} {'CPU s':>8s} {'CPU ratio':>10s} {'ref. updates':>13s} {'updates ratio':>14s}")
    for name in SETTINGS:
        cpu, updates = median(name, "cpu_time_s"), median(name, "reference_updates")
        print(f"{name:30s} {cpu:8.1f} {cpu / base_cpu:10.2f} {updates:13.0f} {updates / base_updates:14.2f}")


if __name__ == "__main__":
    main()
