"""The human-operator datasets: recipe, byte-identical builds, exact replays, and the shipped manifest."""

from __future__ import annotations

import dataclasses
import pathlib

import h5py
import numpy as np
import pytest

from offdyn_bench import set_full_state
from offdyn_bench.datasets import build_dataset
from offdyn_bench.datasets.archive import tree_sha256
from offdyn_bench.datasets.manifest import read_manifest
from offdyn_bench.datasets.recipes import (
    Behaviour,
    RecipeError,
    dataset_id,
    default_recipe,
    parse_dataset_id,
    qualities_of,
    task_sha256,
)
from offdyn_bench.tasks import get_task

STANDSTILL = "offdyn/wheellegged-standstill/human-operator-v0"


def _tiny(task: str = "wheellegged-standstill", transitions: int = 1500, **changes: object):
    recipe = default_recipe(task, "human-operator", num_transitions=transitions)
    return dataclasses.replace(recipe, reference_episodes=1, **changes)  # type: ignore[arg-type]


def test_recipe_is_the_human_operator_at_the_papers_size():
    recipe = default_recipe("wheellegged-standstill", "human-operator")
    assert recipe.dataset_id == STANDSTILL
    assert recipe.behaviour == Behaviour(kind="human-operator")
    assert recipe.num_transitions == 100_000  # as H2O recorded on its real robot
    assert parse_dataset_id(STANDSTILL)[1] == "human-operator"
    assert qualities_of(get_task("wheellegged-movestraight")) == ("random", "human-operator")


def test_human_operator_is_only_the_wheel_legged_robots():
    with pytest.raises(RecipeError, match="task hopper-gravity-0.5 has no 'human-operator' dataset"):
        dataset_id("hopper-gravity-0.5", "human-operator")
    with pytest.raises(RecipeError, match="has no 'source-policy' dataset; its qualities are"):
        parse_dataset_id("offdyn/wheellegged-standstill/source-policy-v0")
    with pytest.raises(RecipeError, match="takes no policy file"):
        Behaviour(kind="human-operator", policy="assets/policies/x.safetensors")


def test_two_builds_give_identical_bytes_and_another_seed_does_not(tmp_path: pathlib.Path):
    first = build_dataset(_tiny(), root=tmp_path / "a")
    second = build_dataset(_tiny(), root=tmp_path / "b")
    assert tree_sha256(first.installed_at) == tree_sha256(second.installed_at) == first.entry.files
    assert first.entry.archive.sha256 == second.entry.archive.sha256
    other = build_dataset(_tiny(seed=1), root=tmp_path / "c", install=False)
    assert other.entry.files != first.entry.files


def test_stored_states_replay_the_target_exactly_and_stay_near_balance(tmp_path: pathlib.Path):
    recipe = _tiny("wheellegged-movestraight", transitions=800)
    result = build_dataset(recipe, root=tmp_path)
    with h5py.File(result.installed_at / "data" / "main_data.hdf5", "r") as f:
        episode = f["episode_0"]
        states = episode["infos/state"][()]
        actions = episode["actions"][()]
        tilts = episode["infos/tilt"][()][1:]
    assert len(actions) == 800
    assert np.mean(np.abs(tilts) < 0.05) > 0.99
    env = get_task("wheellegged-movestraight").make("target")
    env.reset(seed=0)
    for t in (0, 250, 799):
        set_full_state(env, states[t])
        _, _, _, _, info = env.step(actions[t])
        np.testing.assert_allclose(info["state"], states[t + 1], rtol=0, atol=1e-10)


def test_shipped_manifest_records_both_datasets_with_hashes():
    manifest = read_manifest()
    for task in ("wheellegged-standstill", "wheellegged-movestraight"):
        entry = manifest.entries[dataset_id(task, "human-operator")]
        assert entry.is_built and entry.total_steps == 100_000
        assert entry.recipe.behaviour.kind == "human-operator"
        assert entry.recipe.task_sha256 == task_sha256(get_task(task))  # the code still defines that task


def test_offline_track_uses_the_operator_data_as_the_official_dataset():
    from offdyn_bench.protocol.definition import official_dataset

    assert official_dataset("wheellegged-standstill", "offline-target") == STANDSTILL
    assert official_dataset("hopper-gravity-0.5", "offline-target") == "offdyn/hopper-gravity-0p5/source-policy-v0"
    assert official_dataset("wheellegged-movestraight", "online-target") is None
