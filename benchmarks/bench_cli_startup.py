"""Start-up time of the command line against a bare interpreter, side by side in one run.

    .venv/bin/python benchmarks/bench_cli_startup.py [--repeats 15]

Each round runs, in a fresh process each and in this order: ``python -c pass`` (the floor: the
interpreter and site-packages), ``offdyn-bench --help``, ``offdyn-bench tasks list --help`` and
``offdyn-bench --version``. Rounds interleave the commands so a busy machine slows all of them
alike. The figures are median wall times and each command's ratio to the bare interpreter.

``offdyn-bench`` registers the task ids (``import offdyn_bench`` imports Gymnasium and MuJoCo);
sub-commands load on first use, so help imports neither torch, scipy, matplotlib, minari nor
``mujoco.sysid``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path


def commands() -> dict[str, list[str]]:
    script = shutil.which("offdyn-bench", path=str(Path(sys.executable).parent))
    cli = [script] if script else [sys.executable, "-m", "offdyn_bench"]
    return {
        "python -c pass": [sys.executable, "-c", "pass"],
        "offdyn-bench --help": [*cli, "--help"],
        "offdyn-bench tasks list --help": [*cli, "tasks", "list", "--help"],
        "offdyn-bench --version": [*cli, "--version"],
    }


def wall_time(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15, help="rounds (each runs every command once)")
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    args = parser.parse_args()

    runs = commands()
    for command in runs.values():  # warm the file cache once
        wall_time(command)
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(args.repeats):
        for name, command in runs.items():
            times[name].append(wall_time(command))

    floor = statistics.median(times["python -c pass"])
    rows = {name: {"median_s": statistics.median(t), "min_s": min(t), "ratio_to_python": statistics.median(t) / floor}
            for name, t in times.items()}
    width = max(len(name) for name in rows)
    print(f"{'command':<{width}}  median s    min s   x python -c pass   ({args.repeats} rounds)")
    for name, row in rows.items():
        print(f"{name:<{width}}  {row['median_s']:8.3f} {row['min_s']:8.3f}   {row['ratio_to_python']:8.1f}")
    if args.json:
        args.json.write_text(json.dumps({"repeats": args.repeats, "commands": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
