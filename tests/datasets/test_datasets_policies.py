"""Behaviour policies: safetensors + JSON sidecar, no pickle; pinned by hash in recipes."""

from __future__ import annotations

import dataclasses
import json
import pathlib
from collections.abc import Callable

import minari
import numpy as np
import pytest

from offdyn_bench.datasets import MissingPolicyError, PolicyError, RecipeError, build_dataset, load_policy, save_policy
from offdyn_bench.datasets.policies import import_sac_actor, policy_sha256, sidecar_path
from offdyn_bench.datasets.recipes import Recipe

MakeRecipe = Callable[..., Recipe]


def random_layers(obs_dim: int, action_dim: int, seed: int = 0, hidden: int = 16) -> dict:
    rng = np.random.default_rng(seed)
    return {"fc1": (rng.normal(size=(hidden, obs_dim)), rng.normal(size=hidden)),
            "fc2": (rng.normal(size=(hidden, hidden)) / 4, rng.normal(size=hidden)),
            "fc_mean": (rng.normal(size=(action_dim, hidden)) / 4, rng.normal(size=action_dim))}


def write_policy(path: pathlib.Path, obs_dim: int = 11, action_dim: int = 3, low: float = -1.0,
                 high: float = 1.0, seed: int = 0) -> pathlib.Path:
    return save_policy(path, random_layers(obs_dim, action_dim, seed), action_low=[low] * action_dim,
                       action_high=[high] * action_dim, trained_on="offdyn/Hopper-gravity-0.5-source-v0",
                       training={"algorithm": "none (random weights, test fixture)"}, score=None)


def test_round_trip_matches_a_reference_forward_pass(tmp_path: pathlib.Path) -> None:
    layers = random_layers(11, 3)
    path = write_policy(tmp_path / "p.safetensors", low=-2.0, high=4.0)
    policy = load_policy(path)
    obs = np.linspace(-1, 1, 11)
    x = obs
    for name in ("fc1", "fc2"):
        w, b = (a.astype(np.float32).astype(np.float64) for a in layers[name])
        x = np.maximum(w @ x + b, 0)
    w, b = (a.astype(np.float32).astype(np.float64) for a in layers["fc_mean"])
    expected = -2.0 + (np.tanh(w @ x + b) + 1) * 3.0
    np.testing.assert_allclose(policy(obs), expected, rtol=1e-12)
    assert path.read_bytes()[:8] != b"\x80\x04\x95"  # not a pickle
    assert json.loads(sidecar_path(path).read_text())["architecture"]["mean_layer"] == "fc_mean"


@pytest.mark.parametrize("damage, message", [
    (lambda p: sidecar_path(p).unlink(), "sidecar not found"),
    (lambda p: sidecar_path(p).write_text("{"), "not valid JSON"),
    (lambda p: p.write_bytes(b"\x80\x04\x95 pickled"), "cannot read policy weights"),
    (lambda p: sidecar_path(p).write_text(json.dumps({**json.loads(sidecar_path(p).read_text()),
                                                      "observation_dim": 12})), "sidecar says 12"),
])
def test_broken_policy_files_give_clear_errors(damage, message, tmp_path: pathlib.Path) -> None:
    path = write_policy(tmp_path / "p.safetensors")
    damage(path)
    with pytest.raises(PolicyError, match=message):
        load_policy(path)


def test_source_policy_build_pins_the_policy_hash(tiny_recipe: MakeRecipe, tmp_path: pathlib.Path) -> None:
    path = write_policy(tmp_path / "hopper.safetensors")
    recipe = tiny_recipe(quality="source-policy", transitions=60)
    recipe = dataclasses.replace(recipe, behaviour=dataclasses.replace(recipe.behaviour, policy=str(path)))
    result = build_dataset(recipe)
    assert result.entry.recipe.behaviour.policy_sha256 == policy_sha256(path)
    stored = minari.load_dataset(recipe.dataset_id).storage.metadata["offdyn"]["behaviour"]
    assert stored["policy_sha256"] == policy_sha256(path) and stored["action_noise_std"] == 0.1
    # Another policy under the pinned recipe is refused: it would be another dataset.
    write_policy(path, seed=1)
    with pytest.raises(RecipeError, match="a new policy is a new dataset version"):
        build_dataset(result.entry.recipe, install=False)


def test_policy_of_the_wrong_shape_is_refused(tiny_recipe: MakeRecipe, tmp_path: pathlib.Path) -> None:
    path = write_policy(tmp_path / "ant-shaped.safetensors", obs_dim=105, action_dim=8)
    recipe = tiny_recipe(quality="source-policy")
    recipe = dataclasses.replace(recipe, behaviour=dataclasses.replace(recipe.behaviour, policy=str(path)))
    with pytest.raises(PolicyError, match="maps 105 -> 8, the task's target env has 11 -> 3"):
        build_dataset(recipe)


def test_policy_without_sidecar_is_reported_missing(tiny_recipe: MakeRecipe, tmp_path: pathlib.Path) -> None:
    path = write_policy(tmp_path / "p.safetensors")
    sidecar_path(path).unlink()
    recipe = tiny_recipe(quality="source-policy")
    recipe = dataclasses.replace(recipe, behaviour=dataclasses.replace(recipe.behaviour, policy=str(path)))
    with pytest.raises(MissingPolicyError, match="sidecar not found"):
        build_dataset(recipe)


def test_import_of_a_baselines_sac_checkpoint_acts_like_its_mean_action(tmp_path: pathlib.Path) -> None:
    torch = pytest.importorskip("torch")
    sac = pytest.importorskip("baselines.sac")
    from safetensors.torch import save_file

    agent = sac.SACAgent(observation_dim=11, action_dim=3, seeds=[3, 4])
    state = {k: v.contiguous() for k, v in agent.state_dict().items() if k.startswith("actor.")}
    save_file(state, str(tmp_path / "state.safetensors"))
    path = import_sac_actor(tmp_path / "state.safetensors", tmp_path / "p.safetensors", member=1,
                            trained_on="offdyn/Hopper-gravity-0.5-source-v0", training={"steps": 0}, score=None)
    policy = load_policy(path)
    obs = np.random.default_rng(0).normal(size=(5, 11))
    expected = agent.mean_actions(torch.as_tensor(obs, dtype=torch.float32)[None].expand(2, -1, -1))[1].numpy()
    np.testing.assert_allclose(np.stack([policy(o) for o in obs]), expected, atol=1e-5)
    with pytest.raises(PolicyError, match="member 2 is out of range"):
        import_sac_actor(tmp_path / "state.safetensors", tmp_path / "q.safetensors", member=2,
                         trained_on="offdyn/Hopper-gravity-0.5-source-v0", training={}, score=None)


def test_oracle_is_scored_and_pinned_on_a_fresh_build(tiny_recipe: MakeRecipe, tmp_path: pathlib.Path) -> None:
    oracle = write_policy(tmp_path / "oracle.safetensors", seed=5)
    recipe = tiny_recipe(transitions=40, oracle_policy=str(oracle))
    result = build_dataset(recipe)
    assert result.entry.recipe.oracle_policy_sha256 == policy_sha256(oracle)
    scores = result.entry.reference_scores
    assert scores["sac-target"]["value"] == pytest.approx(np.mean(scores["sac-target"]["returns"]))
    metadata = minari.load_dataset(recipe.dataset_id).storage.metadata
    assert metadata["ref_max_score"] == scores["sac-target"]["value"]
    assert metadata["ref_min_score"] == scores["random"]["value"]
    write_policy(oracle, seed=6)
    with pytest.raises(RecipeError, match="a new oracle is a new dataset version"):
        build_dataset(result.entry.recipe, install=False)


def test_an_oracle_that_arrives_later_does_not_change_a_recorded_dataset(tiny_recipe: MakeRecipe,
                                                                        tmp_path: pathlib.Path) -> None:
    recipe = tiny_recipe(transitions=40, oracle_policy=str(tmp_path / "later.safetensors"))
    recorded = build_dataset(recipe, install=False).entry
    assert recorded.reference_scores["sac-target"]["value"] is None
    write_policy(tmp_path / "later.safetensors")
    again = build_dataset(recorded.recipe, recorded=recorded, install=False).entry
    assert again.files == recorded.files
    fresh = build_dataset(recorded.recipe, install=False).entry  # a new recording scores it
    assert fresh.reference_scores["sac-target"]["value"] is not None and fresh.files != recorded.files
