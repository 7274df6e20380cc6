"""Datasets of envs with ``Dict`` observations (AntMaze's goal-conditioned ones), as Minari stores them."""

from __future__ import annotations

import dataclasses

import numpy as np

from offdyn_bench.datasets.build import build_dataset, minari_root
from offdyn_bench.datasets.recipes import default_recipe


def test_an_antmaze_dataset_stores_dict_observations_and_rebuilds_byte_for_byte(tmp_path):
    import minari

    recipe = dataclasses.replace(default_recipe("antmazesmall-layout-blocked", "random", num_transitions=120),
                                 reference_episodes=1)
    first = build_dataset(recipe, root=tmp_path / "a")
    assert build_dataset(recipe, root=tmp_path / "b").entry.files == first.entry.files
    with minari_root(tmp_path / "a"):
        dataset = minari.load_dataset(recipe.dataset_id)
        episode = next(iter(dataset.iterate_episodes()))
    assert set(episode.observations) == {"achieved_goal", "desired_goal", "observation"}
    steps = len(episode.actions)
    assert episode.observations["observation"].shape[0] == steps + 1
    # The ant's x, y are what the goal is measured against: achieved_goal follows them.
    assert np.all(np.isfinite(episode.observations["achieved_goal"]))
    assert episode.infos["state"].shape[0] == steps + 1
