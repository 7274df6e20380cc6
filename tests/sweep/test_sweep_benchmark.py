"""The sweep's own overhead: a tiny sweep (2 runs, 2 workers) against the very same train and
evaluate commands run directly, 2 at a time, side by side in one run (``pytest -m benchmark
tests/sweep/test_sweep_benchmark.py -s``). The difference is what the sweep adds: expansion,
the state file, skipping checks, merging the evaluations."""

from __future__ import annotations

import concurrent.futures
import os
import statistics
import subprocess
import time

import pytest

from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import run_sweep
from offdyn_bench.sweep.execute import command_line
from offdyn_bench.sweep.runs import expand

ROUNDS = 3


def _direct(runs) -> None:
    def chain(run) -> None:
        for args in filter(None, (run.train_args, run.evaluate_args, run.source_evaluate_args)):
            subprocess.run(command_line(args), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        list(pool.map(chain, runs))


@pytest.mark.benchmark
def test_sweep_wall_time_against_the_same_commands_run_directly(tmp_path, tiny_spec, capsys):
    direct, swept = [], []
    for round_ in range(ROUNDS):
        runs = expand(parse_spec(tiny_spec(tmp_path / f"direct-{round_}")))
        started = time.perf_counter()
        _direct(runs)
        direct.append(time.perf_counter() - started)
        started = time.perf_counter()
        report = run_sweep(parse_spec(tiny_spec(tmp_path / f"sweep-{round_}")), workers=2, echo=None)
        swept.append(time.perf_counter() - started)
        assert not report.failed and report.launched == 2
    ratio = statistics.median(swept) / statistics.median(direct)
    with capsys.disabled():
        print(f"\ntiny sweep (2 runs x 300 steps, 2 workers), {ROUNDS} rounds interleaved, load average "
              f"{os.getloadavg()[0]:.1f}: direct commands median {statistics.median(direct):.2f} s "
              f"{[round(x, 2) for x in direct]}, sweep median {statistics.median(swept):.2f} s "
              f"{[round(x, 2) for x in swept]}, ratio sweep/direct {ratio:.3f}")
    assert ratio > 0
