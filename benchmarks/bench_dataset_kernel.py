"""What pinning a dataset build to the manifest's OpenBLAS kernel costs, side by side in one run.

    .venv/bin/python benchmarks/bench_dataset_kernel.py [--task ant-friction-5.0] [--transitions 2000 20000]

For each size, ``build_dataset`` of the task's ``source-policy`` recipe (the shipped behaviour
policy, reference episodes included, not installed), alternately:

* ``in process``: on the kernel numpy loaded (``OFFDYN_BLAS_KERNEL=native``);
* ``child``: in a child process pinned to another kernel (Haswell, or Sandybridge where numpy
  already runs Haswell): what a build costs on a machine whose CPU makes OpenBLAS pick another
  kernel than the manifest's. It includes the child's start (Python, numpy, MuJoCo, Gymnasium
  imports) and the kernels' own speed difference.

Medians of ``--repeats`` builds each; the ratio is child over in process.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import statistics
import tempfile
import time

import offdyn_bench  # noqa: F401  (registers the ids)
from offdyn_bench.datasets.build import build_dataset
from offdyn_bench.datasets.kernel import KERNEL_ENV, NATIVE, numpy_blas
from offdyn_bench.datasets.recipes import default_recipe


def timed_build(task: str, transitions: int, kernel: str) -> float:
    os.environ[KERNEL_ENV] = kernel
    recipe = dataclasses.replace(default_recipe(task, "source-policy", num_transitions=transitions),
                                 reference_episodes=2)
    with tempfile.TemporaryDirectory() as root:
        started = time.perf_counter()
        build_dataset(recipe, root=pathlib.Path(root), install=False)
        return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="ant-friction-5.0")
    parser.add_argument("--transitions", type=int, nargs="+", default=[2000, 20000])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    loaded = numpy_blas()
    other = "Haswell" if loaded.kernel != "Haswell" else "Sandybridge"
    print(f"numpy: {loaded.describe()}; child kernel: {other}")
    rows = []
    for transitions in args.transitions:
        here, child = [], []
        for _ in range(args.repeats):  # alternated, so load changes hit both alike
            here.append(timed_build(args.task, transitions, NATIVE))
            child.append(timed_build(args.task, transitions, other))
        row = {"task": args.task, "transitions": transitions, "in_process_s": statistics.median(here),
               "child_s": statistics.median(child)}
        row["ratio"] = row["child_s"] / row["in_process_s"]
        rows.append(row)
        print(f"{transitions:>7} transitions: in process {row['in_process_s']:.2f} s, child on {other} "
              f"{row['child_s']:.2f} s, ratio {row['ratio']:.2f}")
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
