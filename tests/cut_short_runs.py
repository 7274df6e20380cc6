"""Runs cut short, as a lease leaves them: a tiny RL-on-source training stopped at a checkpoint, and
``scripts/pack_unfinished_runs.py`` that carries such runs off a machine. Shared by the tests of
the packer and of ``scripts/gpu_reference_sweep.sh``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
PACKER = REPO / "scripts" / "pack_unfinished_runs.py"
TASK = "invertedpendulum-gravity-3.0"
TINY = {"sac.hidden_sizes": "[32, 32]", "sac.batch_size": "32", "random_steps": "40"}


def train_tiny_source(out: Path, stop_after: int | None = None) -> dict[str, Any] | None:
    """300 steps of RL on source on ``TASK``, a checkpoint every 100; ``stop_after`` cuts it short
    there (None back, as from a run that did not finish)."""
    from baselines.train import train

    return train("sac-source", TASK, steps=300, out=out, checkpoint_every=100, eval_every=100, eval_episodes=1,
                 progress=False, overrides=TINY, stop_after=stop_after)


def pack_unfinished(sweep_out: Path, destination: Path, *options: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(PACKER), str(sweep_out), str(destination), *options], cwd=REPO,
                          capture_output=True, text=True, check=True, timeout=300)
