"""Reference baselines for off-dynamics RL on one SAC core: SAC (source / target), CQL, DARC, H2O,
DAP and DAP+U. See the "Baselines" section of the top-level README.

Names load on first use, so ``import baselines.cli`` (the CLI attach) does not import torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "ALGORITHMS": "baselines.algorithms", "Algorithm": "baselines.algorithms", "get_algorithm": "baselines.algorithms",
    "train": "baselines.train", "load_trained_policy": "baselines.train",
    "TransitionDataset": "baselines.data", "collect_target_dataset": "baselines.data", "load_dataset": "baselines.data",
    "SACAgent": "baselines.sac", "SACConfig": "baselines.sac", "Batch": "baselines.sac",
    "critic_update": "baselines.sac", "actor_update": "baselines.sac", "update_targets": "baselines.sac",
    "sac_update": "baselines.sac",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'baselines' has no attribute {name!r}")
