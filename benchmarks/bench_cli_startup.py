"""Start-up time of the command line against a bare interpreter, side by side in one run.

    .venv/bin/python benchmarks/bench_cli_startup.py [--repeats 15]

Each round runs, in a fresh process each and in this order: ``python -c pass`` (the floor: the
interpreter and site-packages), ``offdyn-bench --help``, ``offdyn-bench tasks list --help`` and
``offdyn-bench --version``. Rounds interleave the commands so a busy machine slows all of them
alike. The figures are median wall times, each command's ratio to the bare interpreter, and the
median CPU time (user + system) of the process: on a machine shared with other work the wall time
grows with the load, the CPU time much less.

``offdyn-bench`` registers the task ids (``import offdyn_bench`` imports Gymnasium and MuJoCo);
sub-commands load on first use, so help imports neither torch, scipy, matplotlib, minari nor
``mujoco.sysid``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
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


def run_once(command: list[str]) -> tuple[float, float]:
    """Wall time and CPU time (user + system) of one run in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15, help="rounds (each runs every command once)")
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    args = parser.parse_args()

    runs = commands()
    for command in runs.values():  # warm the file cache once
        run_once(command)
    walls: dict[str, list[float]] = {name: [] for name in runs}
    cpus: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(args.repeats):
        for name, command in runs.items():
            wall, cpu = run_once(command)
            walls[name].append(wall)
            cpus[name].append(cpu)

    floor = statistics.median(walls["python -c pass"])
    rows = {name: {"median_s": statistics.median(walls[name]), "min_s": min(walls[name]),
                   "ratio_to_python": statistics.median(walls[name]) / floor,
                   "median_cpu_s": statistics.median(cpus[name])} for name in runs}
    load = os.getloadavg()[0]
    width = max(len(name) for name in rows)
    print(f"{'command':<{width}}  median s    min s   x python -c pass   median CPU s   "
          f"({args.repeats} rounds, load average {load:.1f} at the end)")
    for name, row in rows.items():
        print(f"{name:<{width}}  {row['median_s']:8.3f} {row['min_s']:8.3f}   {row['ratio_to_python']:8.1f}"
              f"           {row['median_cpu_s']:8.3f}")
    if args.json:
        args.json.write_text(json.dumps({"repeats": args.repeats, "load_average": load, "commands": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
