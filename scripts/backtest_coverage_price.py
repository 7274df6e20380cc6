"""Backtest `leaderboard coverage`'s price of a missing training against the trainings published since.

`leaderboard coverage` prices each missing training at the median CPU of its method's published
trainings on the same robot, or on every robot where the method has none on that one. This script
checks that rule on what it would have predicted: for every (method, task) with published one-seed
CPU trainings, it prices them from the method's other tasks only (leave one task out), once at the
method's median over every robot and once per robot as coverage does, and reports the relative
error of each against what the task's trainings took.

    PYTHONPATH=. .venv/bin/python scripts/backtest_coverage_price.py [--budget lite] [--method dap]
"""

from __future__ import annotations

import argparse
import statistics
from collections import defaultdict

from leaderboard.coverage import published_training_cpu
from leaderboard.reference_runs import REFERENCE_RUNS_DIR
from offdyn_bench.tasks import TASKS


def task_trainings(budget: str) -> dict[tuple[str, str], list[float]]:
    """(method, task) -> the CPU seconds of its published one-seed CPU trainings that coverage
    prices from (counted whole, no GPU among the training machines)."""
    cells: dict[tuple[str, str], list[float]] = defaultdict(list)
    for run_id, cpu in sorted(published_training_cpu(REFERENCE_RUNS_DIR / budget, seeds_per_run=1).items()):
        method, task, _ = run_id.split("/")
        cells[(method, task)].append(cpu)
    return cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--budget", default="lite")
    parser.add_argument("--method", action="append", help="only these methods (default: every one)")
    args = parser.parse_args()
    cells = task_trainings(args.budget)
    errors: dict[str, list[float]] = {"every robot": [], "its robot": []}
    print("| method | task | trainings | took (median) | every robot | its robot |")
    print("|---|---|---:|---:|---:|---:|")
    for (method, task), times in sorted(cells.items()):
        if args.method and method not in args.method:
            continue
        robot = TASKS[task].robot
        others = [cpu for (m, t), ts in cells.items() if m == method and t != task for cpu in ts]
        same_robot = [cpu for (m, t), ts in cells.items()
                      if m == method and t != task and TASKS[t].robot == robot for cpu in ts]
        if not others:
            continue
        took = sum(times)
        every = len(times) * statistics.median(others)
        own = len(times) * statistics.median(same_robot) if same_robot else every
        errors["every robot"].append((every - took) / took)
        errors["its robot"].append((own - took) / took)
        print(f"| {method} | {task} | {len(times)} | {statistics.median(times) / 60:.1f} min | "
              f"{every / len(times) / 60:.1f} min ({(every - took) / took:+.0%}) | "
              f"{own / len(times) / 60:.1f} min ({(own - took) / took:+.0%}){'' if same_robot else ' (none on it)'} |")
    for rule, errs in errors.items():
        absolute = [abs(e) for e in errs]
        print(f"priced on {rule}: {len(errs)} cells, relative error median {statistics.median(absolute):.1%}, "
              f"mean {statistics.mean(absolute):.1%}, worst {max(errs, key=abs):+.1%}")


if __name__ == "__main__":
    main()
