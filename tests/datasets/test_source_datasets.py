"""The ``source`` quality: D4RL-style skill mixtures collected in a task's source (issue 16)."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

from offdyn_bench.datasets.build import SKILL_LEVEL_INFO, build_dataset, minari_root
from offdyn_bench.datasets.manifest import read_manifest
from offdyn_bench.datasets.recipes import (
    SKILL_LEVELS,
    Behaviour,
    Recipe,
    RecipeError,
    dataset_id,
    default_recipe,
    default_recipes,
    parse_dataset_id,
)
from offdyn_bench.envs import set_full_state
from offdyn_bench.protocol.definition import CORE_SUITE
from offdyn_bench.tasks import get_task


def test_a_source_dataset_is_a_skill_mixture_collected_in_the_source():
    recipe = default_recipe("hopper-gravity-0.5", "source")
    assert recipe.dataset_id == dataset_id("hopper-gravity-0.5", "source") == "offdyn/hopper-gravity-0p5/source-v0"
    assert parse_dataset_id(recipe.dataset_id)[1] == "source"
    assert recipe.collect_in == "source"
    assert recipe.behaviour.kind == "skill-mixture"
    assert recipe.behaviour.policy == "assets/policies/sac-source/hopper-nominal.safetensors"
    assert recipe.num_transitions == 60_000
    assert Recipe.from_dict(json.loads(json.dumps(recipe.to_dict()))) == recipe


@pytest.mark.parametrize("change, message", [
    ({"collect_in": "target"}, "'source' datasets are collected in the source"),
    ({"behaviour": Behaviour(kind="policy", policy="p.safetensors")}, "only it has the 'skill-mixture' behaviour"),
])
def test_a_source_recipe_that_contradicts_itself_is_refused(change, message):
    recipe = default_recipe("hopper-gravity-0.5", "source")
    with pytest.raises(RecipeError, match=message):
        dataclasses.replace(recipe, **change)


def test_target_qualities_stay_in_the_target_and_the_wheel_legged_robot_has_no_source_data():
    recipe = default_recipe("hopper-gravity-0.5", "source-policy")
    with pytest.raises(RecipeError, match="'source-policy' datasets are collected in the target"):
        dataclasses.replace(recipe, collect_in="source")
    with pytest.raises(RecipeError, match="only it has the 'skill-mixture' behaviour"):
        dataclasses.replace(recipe, behaviour=Behaviour(kind="skill-mixture", policy="p.safetensors"))
    with pytest.raises(RecipeError, match="has no 'source' dataset"):
        dataset_id("wheellegged-standstill", "source")


def test_source_data_ships_for_the_core_suite_only():
    shipped = {recipe.task for recipe in default_recipes() if recipe.quality == "source"}
    assert shipped == set(CORE_SUITE)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A small hopper-gravity-0.5 source dataset (the source has full gravity, the target half)."""
    recipe = dataclasses.replace(default_recipe("hopper-gravity-0.5", "source", num_transitions=3000),
                                 reference_episodes=2)
    root = tmp_path_factory.mktemp("minari")
    return recipe, build_dataset(recipe, root=root), root


def test_each_skill_level_fills_its_share_labelled_and_the_levels_are_ordered_by_return(built):
    recipe, _, root = built
    import minari

    with minari_root(root):
        dataset = minari.load_dataset(recipe.dataset_id)
        levels = np.concatenate([np.asarray(episode.infos[SKILL_LEVEL_INFO])[1:]
                                 for episode in dataset.iterate_episodes()])
        metadata = dataset.storage.metadata["offdyn"]["behaviour"]
    np.testing.assert_array_equal(levels, np.repeat(np.arange(len(SKILL_LEVELS)), 1000))
    described = metadata["levels"]
    assert [level["level"] for level in described] == [name for name, _ in SKILL_LEVELS]
    assert [level["transitions"] for level in described] == [1000, 1000, 1000]
    expert, medium, random = (level["mean_return_of_complete_episodes"] for level in described)
    assert expert > medium > random  # noise makes the same policy measurably worse, random worst


def test_the_data_follows_the_source_dynamics_not_the_target(built):
    """Restarted from a stored state, the source env reproduces the next observation exactly; the
    target (half gravity) does not."""
    recipe, _, root = built
    import minari

    pair = get_task(recipe.task)
    with minari_root(root):
        episode = next(iter(minari.load_dataset(recipe.dataset_id).iterate_episodes()))
    errors = {}
    for side in ("source", "target"):
        env = pair.make(side)
        env.reset(seed=0)
        worst = 0.0
        for t in range(min(40, len(episode.actions))):
            set_full_state(env, episode.infos["state"][t])
            obs, *_ = env.step(episode.actions[t])
            worst = max(worst, float(np.max(np.abs(obs - episode.observations[t + 1]))))
        errors[side] = worst
    assert errors["source"] < 1e-6  # the constraint solver's warm start: round-off, not bits
    assert errors["target"] > 1e-3


def test_a_source_dataset_rebuilds_byte_for_byte(built, tmp_path):
    recipe, first, _ = built
    again = build_dataset(recipe, root=tmp_path / "again")
    assert again.entry.files == first.entry.files


def test_the_core_suite_source_datasets_are_in_the_manifest_with_hashes():
    manifest = read_manifest()
    for task in CORE_SUITE:
        entry = manifest.entries.get(dataset_id(task, "source"))
        assert entry is not None and entry.files, f"{task}: no source dataset in the manifest"
        assert entry.recipe == default_recipe(task, "source") or entry.recipe.behaviour.policy_sha256
        assert entry.recipe.collect_in == "source" and entry.total_steps == 60_000
        assert os.path.basename(entry.recipe.behaviour.policy or "").endswith(".safetensors")
