"""The offline-source methods against their own learners with the correction switched off.

    .venv/bin/python -m baselines.results.offline_source [--seed-groups 0 3]

On the fast ``invertedpendulum-gravity-3.0`` pair with the slow learning test's data and settings
(``tests/baselines/test_offline_source_tracks.py``: a weak controller's 3,000 noisy and 1,000
random source transitions, 600 target ones; 2,000 updates, 64x64 networks, 5 evaluation
episodes), for each group of three training seeds: ``dara``, ``dara`` with ``reward_penalty_weight
= 0`` (CQL on the union of both datasets), ``h2o-offline-source``, and ``h2o-offline-source``
without weights and penalty (SAC on the source data and the target buffer). Prints the per-seed
mean target returns and their IQM. One thread; about 3 minutes per seed group on one core.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

RUNS = (
    ("dara", "dara", {"classifier_steps": "300"}),
    ("dara, eta = 0 (CQL on the union)", "dara", {"classifier_steps": "300", "reward_penalty_weight": "0"}),
    ("h2o-offline-source", "h2o-offline-source", {"random_steps": "300"}),
    ("h2o-offline-source, no weights or penalty (SAC)", "h2o-offline-source",
     {"random_steps": "300", "min_q_weight": "0", "dynamics_ratio_clip": "[1, 1]"}),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed-groups", type=int, nargs="+", default=[0, 3],
                        help="first training seed of each group of three")
    args = parser.parse_args()
    torch.set_num_threads(1)
    # The learning test's own data and settings, so the figures and the test measure one thing.
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "baselines"))
    from test_offline_source_tracks import FAST, LEARNING_STEPS, TASK, write_datasets

    from baselines.train import train
    from offdyn_bench.protocol.statistics import iqm

    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        source, target = write_datasets(root)
        for first in args.seed_groups:
            for index, (label, algo, extra) in enumerate(RUNS):
                data = {"source_dataset": str(source)} | ({"dataset": str(target)} if algo == "dara" else {})
                began = time.perf_counter()
                result = train(algo, TASK, steps=LEARNING_STEPS, out=root / f"{index}-{first}", seed=first, n_seeds=3,
                               overrides=FAST | extra, eval_episodes=5, eval_every=LEARNING_STEPS, progress=False,
                               **data)
                means = [float(np.mean(returns)) for returns in result["returns"].values()]
                print(f"{label:48s} seeds {first}-{first + 2}: {' / '.join(f'{m:.1f}' for m in means)}, "
                      f"IQM {iqm(np.array([[m] for m in means])):.1f} ({time.perf_counter() - began:.0f} s)",
                      flush=True)


if __name__ == "__main__":
    main()
