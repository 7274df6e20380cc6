"""Builds: byte-identical rebuilds, a Minari round trip, exact replays from the stored states."""

from __future__ import annotations

import dataclasses
import json
import pathlib
from collections.abc import Callable

import gymnasium
import minari
import numpy as np
import pytest

from offdyn_bench import set_full_state
from offdyn_bench.datasets import BuildMismatchError, InstallError, MissingPolicyError, build_dataset, verify_installed
from offdyn_bench.datasets.archive import sha256_file, tree_sha256
from offdyn_bench.datasets.install import STAGING_DIR, is_installed
from offdyn_bench.datasets.manifest import Entry
from offdyn_bench.datasets.recipes import Recipe, RecipeError, task_sha256
from offdyn_bench.tasks import get_task

MakeRecipe = Callable[..., Recipe]


@pytest.mark.parametrize("data_format", ["hdf5", "arrow"])
def test_two_builds_give_identical_bytes(data_format: str, tiny_recipe: MakeRecipe, tmp_path: pathlib.Path) -> None:
    if data_format == "arrow":
        pytest.importorskip("pyarrow", reason="minari[arrow] not installed")
    recipe = tiny_recipe("halfcheetah-joint-noise-0.5", transitions=120, data_format=data_format)
    first = build_dataset(recipe, root=tmp_path / "a", out_dir=tmp_path / "out-a")
    second = build_dataset(recipe, root=tmp_path / "b", out_dir=tmp_path / "out-b")
    files_a = tree_sha256(first.installed_at)
    assert files_a == tree_sha256(second.installed_at) == first.entry.files
    assert "data/metadata.json" in files_a and len(files_a) >= 2
    assert sha256_file(first.archive_path) == sha256_file(second.archive_path) == first.entry.archive.sha256
    assert (tmp_path / "out-a/datasets.json").read_bytes() == (tmp_path / "out-b/datasets.json").read_bytes()


def test_another_seed_gives_other_bytes(tiny_recipe: MakeRecipe, tmp_path: pathlib.Path) -> None:
    # The determinism test above could pass on a build that ignores its inputs; this one could not.
    a = build_dataset(tiny_recipe(transitions=60), root=tmp_path / "a", install=False)
    b = build_dataset(tiny_recipe(transitions=60, seed=1), root=tmp_path / "b", install=False)
    assert a.entry.files != b.entry.files


def test_round_trip_through_minari(tiny_recipe: MakeRecipe, isolated_paths: pathlib.Path) -> None:
    recipe = tiny_recipe("hopper-gravity-0.5", transitions=150)
    result = build_dataset(recipe)
    assert result.installed_at == isolated_paths / recipe.dataset_id
    dataset = minari.load_dataset(recipe.dataset_id)
    pair = get_task("hopper-gravity-0.5")
    assert dataset.total_steps == 150 == result.entry.total_steps
    assert dataset.env_spec.id == pair.env_id("source")
    metadata = dataset.storage.metadata
    assert gymnasium.envs.registration.EnvSpec.from_json(metadata["eval_env_spec"]).id == pair.env_id("target")
    assert dataset.recover_environment(eval_env=True).spec.id == pair.env_id("target")
    assert dataset.recover_environment().spec.id == pair.env_id("source")
    episodes = list(dataset.iterate_episodes())
    assert sum(len(e.rewards) for e in episodes) == 150
    assert episodes[-1].truncations[-1] or episodes[-1].terminations[-1]
    assert [e.id for e in episodes] == list(range(len(episodes)))
    for episode in episodes:
        assert episode.observations.shape == (len(episode.rewards) + 1, 11)
        assert episode.infos["state"].shape[0] == len(episode.rewards) + 1
        assert np.isnan(episode.infos["x_velocity"][0]) and np.isfinite(episode.infos["x_velocity"][1:]).all()


def test_provenance_is_stored(tiny_recipe: MakeRecipe, isolated_paths: pathlib.Path) -> None:
    recipe = tiny_recipe("walker2d-gravity-2.0", transitions=50)
    build_dataset(recipe)
    meta = minari.load_dataset(recipe.dataset_id).storage.metadata
    offdyn = meta["offdyn"]
    pair = get_task("walker2d-gravity-2.0")
    assert offdyn["task"] == pair.to_dict() and offdyn["recipe"]["task_sha256"] == task_sha256(pair)
    assert offdyn["versions"]["mujoco"] == __import__("mujoco").__version__
    assert offdyn["recipe"]["seed"] == recipe.seed and offdyn["seeds"]["episodes"] >= 1
    random_score = offdyn["reference_scores"]["random"]
    assert len(random_score["returns"]) == 2 and random_score["value"] == pytest.approx(np.mean(random_score["returns"]))
    assert random_score["episode_seeds"] == [recipe.reference_seed, recipe.reference_seed + 1]
    assert random_score["command"].startswith("offdyn-bench datasets build")
    oracle = offdyn["reference_scores"]["sac-target"]
    assert oracle["value"] is None and "no sac-target policy" in oracle["note"]
    assert "ref_max_score" not in meta  # Minari's normalization needs the oracle: absent, not invented


def test_stored_states_replay_exactly(tiny_recipe: MakeRecipe, isolated_paths: pathlib.Path) -> None:
    recipe = tiny_recipe("hopper-gravity-0.5", transitions=80)
    build_dataset(recipe)
    dataset = minari.load_dataset(recipe.dataset_id)
    env = dataset.recover_environment(eval_env=True)
    env.reset(seed=0)
    episode = dataset[0]
    for t in range(len(episode.rewards)):
        set_full_state(env, episode.infos["state"][t])
        obs, reward, *_ , info = env.step(episode.actions[t])
        np.testing.assert_array_equal(info["state"], episode.infos["state"][t + 1])
        np.testing.assert_array_equal(obs, episode.observations[t + 1])
        assert reward == episode.rewards[t]


def test_recorded_hashes_that_differ_stop_the_build(tiny_recipe: MakeRecipe, isolated_paths: pathlib.Path) -> None:
    recipe = tiny_recipe(transitions=40)
    wrong = Entry(recipe=recipe, files={"data/metadata.json": "0" * 64})
    with pytest.raises(BuildMismatchError, match="differs from the manifest"):
        build_dataset(recipe, recorded=wrong)
    assert not is_installed(recipe.dataset_id)
    assert not (isolated_paths / STAGING_DIR).exists()


def test_verify_detects_a_changed_file(tiny_recipe: MakeRecipe, isolated_paths: pathlib.Path) -> None:
    recipe = tiny_recipe(transitions=40)
    result = build_dataset(recipe)
    assert verify_installed(result.entry).ok
    metadata = result.installed_at / "data" / "metadata.json"
    data = json.loads(metadata.read_text())
    data["total_steps"] += 1
    metadata.write_text(json.dumps(data))
    report = verify_installed(result.entry)
    assert not report.ok and "data/metadata.json" in report.problems[0]


def test_changed_task_definition_is_refused(tiny_recipe: MakeRecipe) -> None:
    recipe = dataclasses.replace(tiny_recipe(), task_sha256="f" * 64)
    with pytest.raises(RecipeError, match="changed since this recipe was made"):
        build_dataset(recipe)


def test_missing_behaviour_policy_is_reported(tiny_recipe: MakeRecipe, isolated_paths: pathlib.Path) -> None:
    recipe = tiny_recipe(quality="source-policy")
    recipe = dataclasses.replace(recipe, behaviour=dataclasses.replace(
        recipe.behaviour, policy="assets/policies/sac-source/does-not-exist.safetensors"))
    with pytest.raises(MissingPolicyError, match="does-not-exist.safetensors is missing.*RL on source"):
        build_dataset(recipe)
    assert not is_installed(recipe.dataset_id)


def test_rebuild_keeps_an_identical_install_and_replaces_another_only_when_forced(
        tiny_recipe: MakeRecipe, isolated_paths: pathlib.Path) -> None:
    recipe = tiny_recipe(transitions=40)
    first = build_dataset(recipe)
    again = build_dataset(recipe)
    assert again.already_installed and again.installed_at == first.installed_at
    other = dataclasses.replace(recipe, seed=3)
    with pytest.raises(InstallError, match="with other bytes; pass --force"):
        build_dataset(other)
    assert tree_sha256(first.installed_at) == first.entry.files  # untouched
    replaced = build_dataset(other, replace=True)
    assert tree_sha256(replaced.installed_at) == replaced.entry.files != first.entry.files
    assert not (isolated_paths / STAGING_DIR).exists()


def test_a_shipped_dataset_rebuilds_byte_for_byte() -> None:
    """The manifest's hashes are reproducible from code: the same bytes on the same platform and
    library versions (skipped where the versions differ from the ones the manifest records)."""
    from offdyn_bench.datasets.manifest import read_manifest
    from offdyn_bench.versions import versions

    entry = read_manifest().get("offdyn/halfcheetah-gravity-0p5/random-v0")
    assert entry.is_built, "the shipped manifest should record this dataset's hashes"
    if dict(entry.built_with) != versions():
        pytest.skip(f"manifest built with {entry.built_with}, this environment has {versions()}")
    result = build_dataset(entry.recipe, recorded=entry, install=False)  # raises on any difference
    assert result.entry.files == entry.files
    assert result.entry.archive == entry.archive


def test_the_libraries_the_manifest_records_are_the_ones_a_fresh_install_gets() -> None:
    """Each library the manifest's entries record in `built_with` that pyproject.toml depends on is
    pinned there to exactly that version, so a fresh clone rebuilds the recorded bytes; a looser
    requirement would let a new release (numpy's bundled OpenBLAS, its SIMD math) change them, and
    the rebuild test above would only skip."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.version import Version

    from offdyn_bench.datasets.manifest import read_manifest

    project = tomllib.loads((pathlib.Path(__file__).parents[2] / "pyproject.toml").read_text())["project"]
    requirements = {requirement.name: requirement for requirement in map(Requirement, project["dependencies"])}
    recorded: dict[str, set[str]] = {}
    for entry in read_manifest().entries.values():
        for library, version in (entry.built_with or {}).items():
            if library in requirements and version is not None:
                recorded.setdefault(library, set()).add(version)
    assert {"numpy", "mujoco", "minari", "gymnasium", "torch"} <= set(recorded)
    for library, versions_seen in recorded.items():
        specifiers = list(requirements[library].specifier)
        assert [spec.operator for spec in specifiers] == ["=="], f"{library}: pinned as {specifiers}, expected =="
        # torch records its local build tag (2.13.0+cpu); the pin names the release.
        assert {Version(version).public for version in versions_seen} == {specifiers[0].version}, library


def test_a_relative_datasets_root_builds_and_installs(tiny_recipe: MakeRecipe, tmp_path: pathlib.Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """`offdyn-bench demo --out demo-out` passes a relative root; Minari's size computation would
    join it with its own relative listing and lose every file."""
    monkeypatch.chdir(tmp_path)
    result = build_dataset(tiny_recipe(), root=pathlib.Path("relative-root"))
    assert result.installed_at == tmp_path / "relative-root" / result.entry.dataset_id
    assert is_installed(result.entry.dataset_id, tmp_path / "relative-root")
