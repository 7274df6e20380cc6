"""Reference baselines for off-dynamics RL on one SAC core: SAC (source / target), CQL, DARC, H2O,
DAP and DAP+U. See baselines/README.md."""

from baselines.algorithms import ALGORITHMS, Algorithm, get_algorithm
from baselines.data import TransitionDataset, collect_target_dataset, load_dataset
from baselines.sac import Batch, SACAgent, SACConfig, actor_update, critic_update, sac_update, update_targets
from baselines.train import load_trained_policy, train

__all__ = [
    "ALGORITHMS", "Algorithm", "get_algorithm", "train", "load_trained_policy",
    "TransitionDataset", "collect_target_dataset", "load_dataset",
    "SACAgent", "SACConfig", "Batch", "critic_update", "actor_update", "update_targets", "sac_update",
]
