"""The H2O settings' D4RL-style target data (medium, medium-replay, medium-expert), end to end at a
tiny scale: a SAC run in the nominal Walker2d (the H2O pairs' target) with every checkpoint kept,
its oracle and medium policies exported, and each quality built from them."""

from __future__ import annotations

import dataclasses
import json

import minari
import numpy as np
import pytest
from safetensors.numpy import load_file

from offdyn_bench.datasets.build import SKILL_LEVEL_INFO, build_dataset, minari_root
from offdyn_bench.datasets.recipes import (
    H2O_QUALITIES,
    MEDIUM_FRACTION,
    REPO_ROOT,
    Behaviour,
    Recipe,
    RecipeError,
    dataset_id,
    default_recipe,
    qualities_of,
    replay_transitions,
    sac_policy_path,
)
from offdyn_bench.datasets.training_data import (
    ReplayMismatchError,
    choose_medium,
    export_h2o_behaviours,
    train_keeping_checkpoints,
)
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import get_task

TASK = "walker2d-h2o-gravity-2.0"
TINY = {"sac.hidden_sizes": "[16, 16]", "sac.batch_size": "16", "random_steps": "50"}
STEPS, EVERY = 300, 100


def test_only_the_h2o_settings_have_the_d4rl_qualities():
    for name in ("walker2d-h2o-gravity-2.0", "halfcheetah-h2o-friction-0.3", "halfcheetah-h2o-joint-noise-1.0"):
        assert set(H2O_QUALITIES) <= set(qualities_of(get_task(name)))
    for name in ("hopper-gravity-0.5", "walker2d-gravity-2.0", "hopper-dart"):
        assert not set(H2O_QUALITIES) & set(qualities_of(get_task(name)))
    assert dataset_id(TASK, "medium-replay") == "offdyn/walker2d-h2o-gravity-2p0/medium-replay-v0"
    with pytest.raises(RecipeError, match="hopper-gravity-0.5 has no 'medium' dataset"):
        dataset_id("hopper-gravity-0.5", "medium")
    # Every H2O setting of a robot collects in the same nominal target: one oracle, one medium policy.
    assert {sac_policy_path(get_task(name), "sac-target-medium") for name in
            ("walker2d-h2o-gravity-2.0", "walker2d-h2o-friction-0.3")} == \
        {"assets/policies/sac-target-medium/walker2d-nominal.safetensors"}


def test_each_quality_has_its_own_behaviour_kind():
    recipe = default_recipe(TASK, "medium-replay")
    assert recipe.behaviour.kind == "training-replay" and recipe.behaviour.action_noise_std == 0
    assert default_recipe(TASK, "medium-expert").behaviour.kind == "medium-expert"
    assert default_recipe(TASK, "medium").behaviour.kind == "policy"
    with pytest.raises(RecipeError, match="the 'medium-replay' quality and only it has the 'training-replay'"):
        dataclasses.replace(recipe, behaviour=Behaviour(kind="policy", policy=recipe.behaviour.policy))
    with pytest.raises(RecipeError, match="expert half from the recipe's oracle_policy, which is null"):
        dataclasses.replace(default_recipe(TASK, "medium-expert"), oracle_policy=None)
    data = recipe.to_dict()
    assert Recipe.from_dict(data) == recipe


def test_the_medium_level_is_the_checkpoint_closest_to_a_third_from_random():
    # random 10, expert 310: a third of the way is 110.
    returns = {100: 40.0, 200: 100.0, 300: 120.0, 400: 310.0}
    assert choose_medium(returns, 10.0, 310.0, MEDIUM_FRACTION) == 200  # 10 away, against 300's 10: earlier wins
    assert choose_medium({100: 40.0, 200: 150.0, 300: 310.0}, 10.0, 310.0, MEDIUM_FRACTION) == 200
    # The final checkpoint is the expert itself, never the medium level.
    assert choose_medium({100: 300.0, 200: 110.0}, 10.0, 110.0, 1.0) == 100
    with pytest.raises(OffdynError, match="does not exceed a random policy's"):
        choose_medium(returns, 400.0, 310.0, MEDIUM_FRACTION)
    with pytest.raises(OffdynError, match="has one checkpoint"):
        choose_medium({300: 310.0}, 10.0, 310.0, MEDIUM_FRACTION)


@pytest.fixture(scope="module")
def behaviours(tmp_path_factory):
    """A tiny oracle run (300 steps, a checkpoint every 100) and its exported policies."""
    out = tmp_path_factory.mktemp("h2o-run")
    kept = train_keeping_checkpoints(TASK, steps=STEPS, checkpoint_every=EVERY, out=out, overrides=TINY)
    root = tmp_path_factory.mktemp("assets")
    summary = export_h2o_behaviours(out / "run", kept, get_task(TASK), out_root=root, episodes=2,
                                    first_seed=1_000_000, fraction=MEDIUM_FRACTION)
    return out, kept, summary


def _recipe(quality: str, behaviours, transitions: int | None = None) -> Recipe:
    _, _, summary = behaviours
    recipe = default_recipe(TASK, quality)
    behaviour = dataclasses.replace(recipe.behaviour, policy=str(summary["medium"]))
    count = replay_transitions(str(summary["medium"])) if quality == "medium-replay" else transitions
    return dataclasses.replace(recipe, behaviour=behaviour, oracle_policy=str(summary["expert"]), num_transitions=count,
                               reference_episodes=2)


def test_every_checkpoint_is_kept_and_the_policies_say_where_they_come_from(behaviours):
    out, kept, summary = behaviours
    assert sorted(p.name for p in kept.iterdir()) == [f"step_{s:09d}" for s in (100, 200, 300)]
    assert (out / "run" / "result.json").is_file()
    level = summary["level"]
    assert level["chosen_step"] in (100, 200) and set(level["checkpoint_returns"]) == {"100", "200", "300"}
    medium = json.loads(summary["medium"].with_suffix(".json").read_text())
    assert medium["training"]["checkpoint_step"] == level["chosen_step"]
    assert medium["training"]["config"]["algo"] == "sac-target" and medium["training"]["level"] == level
    assert medium["trained_on"] == get_task(TASK).env_id("target")
    assert replay_transitions(str(summary["medium"])) == level["chosen_step"]  # one seed: one row per step
    oracle = json.loads(summary["expert"].with_suffix(".json").read_text())
    assert oracle["training"]["checkpoint_step"] == STEPS
    assert str(summary["expert"]).endswith("assets/policies/sac-target/walker2d-nominal.safetensors")


def test_medium_replay_is_the_runs_buffer_simulated_again(behaviours, tmp_path, monkeypatch):
    from offdyn_bench.datasets import training_data

    out, _, summary = behaviours
    recipe = _recipe("medium-replay", behaviours)
    # In this process, on numpy's own kernel: the replay cache and the counter below live here.
    monkeypatch.setenv("OFFDYN_BLAS_KERNEL", "native")
    monkeypatch.setattr(training_data, "_REPLAYED_BUFFERS", {})
    result = build_dataset(recipe, root=tmp_path / "minari")
    step = summary["level"]["chosen_step"]
    assert result.entry.total_steps == step
    # The run's final checkpoint holds its whole buffer; its first rows are what it stored by the medium step.
    final = load_file(str(out / "run" / "checkpoints" / f"step_{STEPS:09d}" / "state.safetensors"))
    state = {name: value[:, :step] for name, value in final.items() if name.startswith("buffer.")
             and name not in ("buffer.counters", "buffer.generator")}
    with minari_root(tmp_path / "minari"):
        dataset = minari.load_dataset(recipe.dataset_id)
        episodes = list(dataset.iterate_episodes())
        metadata = dataset.storage.metadata
    # The dataset holds exactly the stored transitions, in order, at full precision.
    actions = np.concatenate([e.actions for e in episodes])
    observations = np.concatenate([e.observations[:-1] for e in episodes])
    rewards = np.concatenate([e.rewards for e in episodes])
    assert np.array_equal(actions, state["buffer.actions"][0])  # Walker2d's box is [-1, 1]
    assert np.array_equal(observations.astype(np.float32), state["buffer.observations"][0])
    assert np.array_equal(rewards.astype(np.float32), state["buffer.rewards"][0])
    assert all("state" in e.infos for e in episodes)
    # The training's episodes end in a fall or at a checkpoint's cut; only the last one here is cut.
    assert all(e.terminations[-1] or e.truncations[-1] for e in episodes)
    replay = json.loads(metadata["offdyn"]) if isinstance(metadata["offdyn"], str) else metadata["offdyn"]
    assert replay["behaviour"]["replay"]["checkpoint_step"] == step
    # Built again in this process (another H2O setting of the robot shares the run), the training is
    # not re-run; re-run afresh, it gives the same bytes.
    reruns = []
    rerun = training_data.rerun_to_checkpoint
    monkeypatch.setattr(training_data, "rerun_to_checkpoint", lambda *a, **k: reruns.append(a) or rerun(*a, **k))
    again = build_dataset(recipe, root=tmp_path / "minari-2")
    assert again.entry.files == result.entry.files and reruns == []
    training_data._REPLAYED_BUFFERS.clear()
    fresh = build_dataset(recipe, root=tmp_path / "minari-3")
    assert fresh.entry.files == result.entry.files and len(reruns) == 1


def test_a_replay_that_does_not_reproduce_the_pinned_policy_is_refused(behaviours, tmp_path):
    _, _, summary = behaviours
    tampered = tmp_path / "medium.safetensors"
    weights = load_file(str(summary["medium"]))
    weights["mean.weight"] = weights["mean.weight"] + np.float32(1e-3)
    from safetensors.numpy import save_file

    save_file(weights, str(tampered))
    tampered.with_suffix(".json").write_bytes(summary["medium"].with_suffix(".json").read_bytes())
    recipe = _recipe("medium-replay", behaviours)
    recipe = dataclasses.replace(recipe, behaviour=dataclasses.replace(recipe.behaviour, policy=str(tampered)))
    with pytest.raises(ReplayMismatchError, match="gave other actor weights than the pinned policy's"):
        build_dataset(recipe, root=tmp_path / "minari")
    assert not (tmp_path / "minari" / recipe.dataset_id).exists()
    wrong_size = dataclasses.replace(_recipe("medium-replay", behaviours), num_transitions=7)
    with pytest.raises(RecipeError, match="the recipe asks for 7 \\(medium-replay is all of them\\)"):
        build_dataset(wrong_size, root=tmp_path / "minari")


def test_medium_expert_is_half_medium_then_half_the_oracle(behaviours, tmp_path):
    recipe = _recipe("medium-expert", behaviours, transitions=61)
    result = build_dataset(recipe, root=tmp_path / "minari")
    with minari_root(tmp_path / "minari"):
        episodes = list(minari.load_dataset(recipe.dataset_id).iterate_episodes())
    levels = np.concatenate([np.asarray(e.infos[SKILL_LEVEL_INFO])[1:] for e in episodes])
    assert len(levels) == 61 and list(levels[:31]) == [0.0] * 31 and list(levels[31:]) == [1.0] * 30
    assert result.entry.recipe.oracle_policy_sha256 is not None  # the expert that acted is pinned
    medium = build_dataset(_recipe("medium", behaviours, transitions=31), root=tmp_path / "minari-medium")
    assert medium.entry.total_steps == 31 and medium.entry.recipe.behaviour.policy_sha256 is not None


SHIPPED_MEDIUM = sorted(path for path in (REPO_ROOT / "assets" / "policies" / "sac-target-medium").glob("*.json"))


@pytest.mark.parametrize("sidecar", SHIPPED_MEDIUM, ids=lambda path: path.stem)
def test_a_shipped_medium_policy_is_its_runs_checkpoint_a_third_of_the_way_and_every_recipe_pins_it(sidecar):
    """The medium level, chosen again from the returns its sidecar records, is the checkpoint it
    ships; the oracle beside it is the same run's final checkpoint; and every H2O recipe of the
    robot that the manifest records pins both files' sha256."""
    from offdyn_bench.datasets.manifest import read_manifest
    from offdyn_bench.datasets.policies import policy_sha256

    medium = json.loads(sidecar.read_text())
    level = medium["training"]["level"]
    returns = {int(step): value for step, value in level["checkpoint_returns"].items()}
    assert choose_medium(returns, level["random_return"], level["expert_return"], level["fraction"]) == \
        medium["training"]["checkpoint_step"] == level["chosen_step"]
    goal = level["random_return"] + MEDIUM_FRACTION * (level["expert_return"] - level["random_return"])
    assert abs(returns[level["chosen_step"]] - goal) < 0.25 * (level["expert_return"] - level["random_return"])
    oracle_path = REPO_ROOT / "assets" / "policies" / "sac-target" / sidecar.name
    oracle = json.loads(oracle_path.read_text())
    assert oracle["training"]["checkpoint_step"] == oracle["training"]["config"]["steps"] == max(returns)
    assert oracle["training"]["config"] == medium["training"]["config"]
    assert oracle["score"]["evaluation"]["mean_return"] == pytest.approx(level["expert_return"])
    manifest = read_manifest()
    robot = sidecar.stem.removesuffix("-nominal")
    pinned = [entry.recipe for ident, entry in manifest.entries.items() if ident.startswith(f"offdyn/{robot}-h2o-")
              and entry.files and entry.recipe.quality in H2O_QUALITIES]
    assert pinned, f"no {robot} H2O dataset is recorded"
    for recipe in pinned:
        assert recipe.behaviour.policy_sha256 == policy_sha256(REPO_ROOT / recipe.behaviour.policy)
        assert recipe.oracle_policy_sha256 == policy_sha256(oracle_path.with_suffix(".safetensors"))


def test_unbuilt_replay_recipes_take_the_size_the_shipped_medium_policy_gives(tmp_path):
    """The manifest's medium-replay recipes were written before any medium policy existed; once one
    ships, they take what its run stored up to the medium step. A built one is never resized."""
    from offdyn_bench.datasets.manifest import Entry, read_manifest, write_manifest
    from offdyn_bench.datasets.training_data import size_replay_recipes

    slugs = ("gravity-2p0", "friction-0p3", "joint-noise-1p0")
    ids = [f"offdyn/halfcheetah-h2o-{slug}/medium-replay-v0" for slug in slugs]
    stored = replay_transitions("assets/policies/sac-target-medium/halfcheetah-nominal.safetensors")
    manifest = read_manifest()
    for ident in ids:
        placeholder = dataclasses.replace(manifest.get(ident).recipe, num_transitions=stored + 1)
        manifest = manifest.with_entry(Entry(recipe=placeholder))
    path = write_manifest(manifest, tmp_path / "datasets.json")
    assert sorted(size_replay_recipes("HalfCheetah", path)) == sorted(ids)
    resized = read_manifest(path)
    assert [resized.get(ident).recipe.num_transitions for ident in ids] == [stored] * 3
    assert size_replay_recipes("halfcheetah", path) == []  # nothing left to size
    built = dataclasses.replace(resized.get(ids[0]).recipe, num_transitions=stored + 1)
    write_manifest(resized.with_entry(Entry(recipe=built, files={"data/main_data.hdf5": "ab" * 32})), path)
    with pytest.raises(OffdynError, match=f"is built with {stored + 1} transitions; the medium policy now gives "
                                          f"{stored}: record it as a new version"):
        size_replay_recipes("halfcheetah", path)
