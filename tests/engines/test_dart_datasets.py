"""DART target datasets: in the manifest, and rebuilt byte for byte from their recipes."""

from __future__ import annotations

import numpy as np
import pytest

from offdyn_bench.datasets.build import build_dataset
from offdyn_bench.datasets.manifest import read_manifest
from offdyn_bench.datasets.recipes import dataset_id, default_recipe
from offdyn_bench.engines import make_dart_env


def test_both_qualities_of_both_dart_pairs_are_in_the_manifest_with_hashes():
    manifest = read_manifest()
    for task in ("hopper-dart", "walker2d-dart"):
        for quality in ("source-policy", "random"):
            entry = manifest.get(dataset_id(task, quality))
            assert entry.files and entry.archive is not None
            assert entry.recipe.oracle_policy == f"assets/policies/sac-target/{task}-target.safetensors"


@pytest.mark.parametrize("quality", ["source-policy", "random"])
def test_a_dart_dataset_rebuilds_byte_for_byte_and_its_states_replay(tmp_path, quality):
    recipe = default_recipe("hopper-dart", quality, num_transitions=400)
    first = build_dataset(recipe)  # the test's own Minari root (conftest)
    second = build_dataset(recipe, root=tmp_path / "b")
    assert first.entry.files == second.entry.files and first.entry.files

    import minari

    episode = next(iter(minari.load_dataset(recipe.dataset_id).iterate_episodes()))
    env = make_dart_env("Hopper")
    env.reset(seed=0)
    states = np.asarray(episode.infos["state"])
    for t in range(min(len(episode.actions), 20)):  # the stored states replay the stored steps exactly
        env.unwrapped.set_full_state(states[t])
        obs, *_ = env.step(episode.actions[t])
        np.testing.assert_array_equal(obs, episode.observations[t + 1])
        np.testing.assert_array_equal(env.unwrapped.dart.qpos(), states[t + 1][1:7])
