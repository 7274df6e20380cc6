"""``offdyn-bench datasets ...`` end to end: build --out is a remote that download installs from."""

from __future__ import annotations

import dataclasses
import json
import pathlib

import minari
from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.datasets.manifest import Entry, Manifest, read_manifest, write_manifest
from offdyn_bench.datasets.recipes import default_recipes

runner = CliRunner()


def invoke(*args: str):  # noqa: ANN201 - click's Result
    return runner.invoke(app, ["datasets", *args])


def tiny_manifest(path: pathlib.Path, tiny_recipe) -> tuple[Manifest, str]:  # noqa: ANN001
    recipe = tiny_recipe("walker2d-friction-0.5", transitions=90)
    manifest = Manifest.from_entries([Entry(recipe=recipe)])
    write_manifest(manifest, path)
    return manifest, recipe.dataset_id


def test_list_shows_the_shipped_manifest() -> None:
    result = invoke("list")
    assert result.exit_code == 0, result.output
    for recipe in default_recipes():
        assert recipe.dataset_id in result.output
    assert f"{len(read_manifest().entries)} datasets" in result.output  # the defaults and any recorded since


def test_shipped_manifest_holds_the_default_recipes() -> None:
    shipped = read_manifest()
    assert {r.dataset_id for r in default_recipes()} <= set(shipped.entries)
    for recipe in default_recipes():
        entry = shipped.get(recipe.dataset_id)
        # Same recipe, except the policy hashes a build pins (the behaviour's, and the oracle's where one ships).
        pinned = dataclasses.replace(entry.recipe, behaviour=dataclasses.replace(entry.recipe.behaviour,
                                                                                 policy_sha256=None),
                                     oracle_policy_sha256=None)
        assert pinned == recipe
        entry.recipe.check_task()  # the task definitions it was made for are unchanged


def test_build_out_then_download_from_file_remote(tmp_path: pathlib.Path, tiny_recipe, monkeypatch) -> None:
    manifest_path = tmp_path / "manifest.json"
    _, ident = tiny_manifest(manifest_path, tiny_recipe)
    remote = tmp_path / "remote"
    built = invoke("build", ident, "--out", str(remote), "--no-install", "--update-manifest",
                   "--manifest", str(manifest_path))
    assert built.exit_code == 0, built.output
    assert read_manifest(manifest_path).get(ident).is_built
    assert json.loads((remote / f"{ident}.json").read_text())["files"] == read_manifest(manifest_path).get(ident).files
    monkeypatch.setenv("OFFDYN_REMOTE", remote.as_uri())
    fetched = invoke("download", ident, "--manifest", str(manifest_path))
    assert fetched.exit_code == 0, fetched.output
    assert f"downloaded from {remote.as_uri()}/; the archive and every file match the manifest's sha256" \
        in fetched.output
    verified = invoke("verify", ident, "--manifest", str(manifest_path))
    assert verified.exit_code == 0 and "OK" in verified.output
    assert minari.load_dataset(ident).total_steps == 90
    # A rebuild reproduces the recorded bytes (and says so).
    rebuilt = invoke("build", ident, "--no-install", "--manifest", str(manifest_path))
    assert rebuilt.exit_code == 0 and "matches the manifest" in rebuilt.output


def test_verify_fails_on_tampered_data(tmp_path: pathlib.Path, tiny_recipe, isolated_paths) -> None:
    manifest_path = tmp_path / "manifest.json"
    _, ident = tiny_manifest(manifest_path, tiny_recipe)
    assert invoke("build", ident, "--update-manifest", "--manifest", str(manifest_path)).exit_code == 0
    victim = isolated_paths / ident / "data" / "main_data.hdf5"
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    result = invoke("verify", ident, "--manifest", str(manifest_path))
    assert result.exit_code == 1
    assert "sha256 mismatch" in result.output and "FAILED" in result.output


def test_build_reports_a_missing_behaviour_policy(tmp_path: pathlib.Path, tiny_recipe) -> None:
    recipe = tiny_recipe(quality="source-policy")
    recipe = dataclasses.replace(recipe, behaviour=dataclasses.replace(
        recipe.behaviour, policy="assets/policies/sac-source/not-trained-yet.safetensors"))
    write_manifest(Manifest.from_entries([Entry(recipe=recipe)]), tmp_path / "manifest.json")
    result = invoke("build", "--all", "--no-install", "--manifest", str(tmp_path / "manifest.json"))
    assert result.exit_code == 1
    assert "behaviour policy assets/policies/sac-source/not-trained-yet.safetensors is missing" in result.output
    assert "1 of 1 datasets not built" in result.output


def test_build_all_checks_every_dataset_and_names_those_with_other_bytes(tmp_path: pathlib.Path,
                                                                          tiny_recipe) -> None:
    manifest_path = tmp_path / "manifest.json"
    good, bad = tiny_recipe("walker2d-friction-0.5", transitions=60), tiny_recipe("hopper-gravity-0.5", transitions=60)
    write_manifest(Manifest.from_entries([Entry(recipe=good), Entry(recipe=bad)]), manifest_path)
    assert invoke("build", "--all", "--update-manifest", "--no-install", "--manifest",
                  str(manifest_path)).exit_code == 0
    recorded = read_manifest(manifest_path)
    tampered = dataclasses.replace(recorded.entries[bad.dataset_id],
                                   files={**recorded.entries[bad.dataset_id].files, "data/main_data.hdf5": "0" * 64})
    write_manifest(recorded.with_entry(tampered), manifest_path)
    # The mismatch comes first in sorted order; the check goes on to the next dataset.
    result = invoke("build", "--all", "--no-install", "--manifest", str(manifest_path))
    assert result.exit_code == 1
    assert f"rebuilt {bad.dataset_id} differs from the manifest" in result.output
    assert f"{good.dataset_id}: 60 transitions" in result.output and "(matches the manifest)" in result.output
    assert f"1 of 2 datasets not built (missing policy or other bytes than the manifest's): {bad.dataset_id}" \
        in result.output


def test_bad_ids_are_clear_errors() -> None:
    result = invoke("build", "offdyn/hopper-gravity-0p5/expert-v0")
    assert result.exit_code == 2 and "unknown dataset quality 'expert'" in result.output
    result = invoke("build", "hopper-gravity-0.5")
    assert result.exit_code == 2 and "malformed dataset id" in result.output
    result = invoke("download", "hopper-gravity-0.5")
    assert result.exit_code == 2 and "error: malformed dataset id 'hopper-gravity-0.5'" in result.output


def test_import_policy_from_a_baselines_run_folder(tmp_path: pathlib.Path) -> None:
    import pytest

    pytest.importorskip("torch")
    sac = pytest.importorskip("baselines.sac")
    from safetensors.torch import save_file

    step = tmp_path / "run" / "checkpoints" / "step_000000100"
    step.mkdir(parents=True)
    agent = sac.SACAgent(observation_dim=11, action_dim=3, seeds=[0])
    save_file({k: v.contiguous() for k, v in agent.state_dict().items() if k.startswith("actor.")},
              str(step / "state.safetensors"))
    (tmp_path / "run" / "config.json").write_text(json.dumps({"algo": "sac-source", "steps": 100}))
    out = tmp_path / "policies" / "hopper-nominal.safetensors"
    result = invoke("import-policy", str(tmp_path / "run"), "--trained-on", "offdyn/Hopper-gravity-0.5-source-v0",
                    "--out", str(out), "--eval-episodes", "2", "--note", "test fixture")
    assert result.exit_code == 0, result.output
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["training"]["config"] == {"algo": "sac-source", "steps": 100}
    assert sidecar["training"]["checkpoint"] == "checkpoints/step_000000100/state.safetensors"
    assert sidecar["training"]["note"] == "test fixture"
    evaluation = sidecar["score"]["evaluation"]
    assert evaluation["env_id"] == "offdyn/Hopper-gravity-0.5-source-v0" and len(evaluation["returns"]) == 2
    assert sidecar["score"]["run_result"] is None
