from __future__ import annotations

import pytest

from baselines.data import collect_target_dataset
from offdyn_bench.tasks import get_task


@pytest.fixture(scope="session")
def pendulum_dataset(tmp_path_factory):
    """A small random-policy dataset in the short-rail pendulum's target, as an .npz."""
    path = tmp_path_factory.mktemp("data") / "pendulum-random.npz"
    collect_target_dataset(get_task("invertedpendulum-kinematic-slider-hard"), "random", 300, seed=0).save_npz(path)
    return path


@pytest.fixture(scope="session")
def hopper_dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "hopper-random.npz"
    collect_target_dataset(get_task("hopper-gravity-0.5"), "random", 300, seed=0).save_npz(path)
    return path
