"""First contact: `datasets download ID` and ensure_dataset work on a fresh clone with no remote
(rebuild from the recipe, verified against the manifest), say which source they used, and fail
with an actionable message, never Minari's "Use download=True" nor an empty progress bar."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import re
import shlex

import pytest
from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.datasets import (
    DatasetUnavailableError,
    InstallError,
    build_dataset,
    ensure_dataset,
    load_installed,
    verify_installed,
)
from offdyn_bench.datasets.archive import tree_sha256
from offdyn_bench.datasets.manifest import Entry, Manifest, archive_name, entry_name, read_manifest, write_manifest
from offdyn_bench.errors import OffdynError

runner = CliRunner()


@pytest.fixture
def no_remote(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OFFDYN_REMOTE", raising=False)


@pytest.fixture
def recorded(tiny_recipe, tmp_path_factory) -> Entry:  # noqa: ANN001
    """A tiny dataset's manifest entry with its hashes, as `build --update-manifest` records it."""
    recipe = tiny_recipe("hopper-gravity-0.5", transitions=120)
    return build_dataset(recipe, root=tmp_path_factory.mktemp("recording"), install=False).entry


def test_no_remote_rebuilds_and_verifies_and_says_so(recorded: Entry, no_remote, isolated_paths) -> None:
    said: list[str] = []
    path = ensure_dataset(recorded.dataset_id, manifest=Manifest.from_entries([recorded]), echo=said.append,
                          progress=False)
    assert path == isolated_paths / recorded.dataset_id
    assert tree_sha256(path) == recorded.files and verify_installed(recorded).ok
    assert "no remote configured (OFFDYN_REMOTE unset); rebuilding it from its recipe" in said[0]
    assert re.search(r"rebuilt from its recipe in .* s; all 2 files match the manifest's sha256", said[-1])
    said.clear()
    assert ensure_dataset(recorded.dataset_id, manifest=Manifest.from_entries([recorded]), echo=said.append) == path
    assert said == [f"{recorded.dataset_id}: installed at {path}; 2 files match the manifest's sha256"]


def test_with_a_remote_it_downloads_and_says_so(published, loopback_remote, isolated_paths) -> None:
    recipe, result, remote = published
    for name in (archive_name(recipe.dataset_id), entry_name(recipe.dataset_id)):
        (loopback_remote.folder / name).parent.mkdir(parents=True, exist_ok=True)
        (loopback_remote.folder / name).write_bytes((remote / name).read_bytes())
    said: list[str] = []
    path = ensure_dataset(recipe.dataset_id, remote=loopback_remote.url, manifest=Manifest.from_entries([result.entry]),
                          echo=said.append, progress=False)
    assert said[0] == f"{recipe.dataset_id}: downloading from {loopback_remote.url}/"
    assert "downloaded from" in said[-1] and "match the manifest's sha256" in said[-1]
    assert tree_sha256(path) == result.entry.files


def test_a_rebuild_that_differs_from_the_manifest_installs_nothing(recorded: Entry, no_remote, isolated_paths,
                                                                   nothing_installed) -> None:
    wrong = dataclasses.replace(recorded, files={**recorded.files, "data/metadata.json": "0" * 64})
    with pytest.raises(DatasetUnavailableError, match="differs from the manifest.*set OFFDYN_REMOTE"):
        ensure_dataset(recorded.dataset_id, manifest=Manifest.from_entries([wrong]), echo=lambda m: None,
                       progress=False)
    nothing_installed(recorded.dataset_id)


def test_a_damaged_install_is_refused_then_replaced_with_force(recorded: Entry, no_remote, isolated_paths) -> None:
    manifest = Manifest.from_entries([recorded])
    path = ensure_dataset(recorded.dataset_id, manifest=manifest, echo=lambda m: None, progress=False)
    (path / "data" / "metadata.json").write_text("{}")
    with pytest.raises(InstallError, match=f"does not match the manifest .*run: offdyn-bench datasets download "
                                           f"{recorded.dataset_id} --force"):
        ensure_dataset(recorded.dataset_id, manifest=manifest, echo=lambda m: None, progress=False)
    ensure_dataset(recorded.dataset_id, manifest=manifest, force=True, echo=lambda m: None, progress=False)
    assert tree_sha256(path) == recorded.files


def missing_policy_manifest(tiny_recipe, path: pathlib.Path) -> str:  # noqa: ANN001
    recipe = tiny_recipe(quality="source-policy")
    recipe = dataclasses.replace(recipe, behaviour=dataclasses.replace(
        recipe.behaviour, policy="assets/policies/sac-source/not-trained-yet.safetensors"))
    write_manifest(Manifest.from_entries([Entry(recipe=recipe)]), path)
    return recipe.dataset_id


def test_cli_download_without_remote_rebuilds(recorded: Entry, no_remote, tmp_path, isolated_paths) -> None:
    write_manifest(Manifest.from_entries([recorded]), tmp_path / "manifest.json")
    result = runner.invoke(app, ["datasets", "download", recorded.dataset_id, "--manifest", str(tmp_path / "manifest.json")])
    assert result.exit_code == 0, result.output
    assert "no remote configured" in result.output and "rebuilt from its recipe" in result.output
    assert tree_sha256(isolated_paths / recorded.dataset_id) == recorded.files


def test_an_impossible_rebuild_says_why_and_shows_no_progress_bar(tiny_recipe, no_remote, tmp_path,
                                                                  nothing_installed) -> None:
    ident = missing_policy_manifest(tiny_recipe, tmp_path / "manifest.json")
    result = runner.invoke(app, ["datasets", "download", ident, "--manifest", str(tmp_path / "manifest.json")])
    assert result.exit_code == 2
    assert result.output.startswith(f"error: cannot rebuild {ident}: ")
    assert "not-trained-yet.safetensors is missing" in result.output
    assert "No remote is configured either: set OFFDYN_REMOTE" in result.output
    assert "%|" not in result.output and "step/s" not in result.output  # no bar drawn before the error
    nothing_installed(ident)


def test_download_errors_before_any_byte_show_no_progress_bar(loopback_remote, tmp_path) -> None:
    result = runner.invoke(app, ["datasets", "download", "offdyn/hopper-gravity-0p5/random-v0",
                                 "--remote", loopback_remote.url])
    assert result.exit_code == 2 and "not found on the remote (HTTP 404)" in result.output
    assert "%|" not in result.output and "B/s" not in result.output


def test_the_verify_hint_names_a_command_that_works(recorded: Entry, no_remote, tmp_path, isolated_paths) -> None:
    manifest = tmp_path / "manifest.json"
    write_manifest(Manifest.from_entries([recorded]), manifest)
    result = runner.invoke(app, ["datasets", "verify", recorded.dataset_id, "--manifest", str(manifest)])
    assert result.exit_code == 2
    hint = re.search(r"run: (offdyn-bench datasets download \S+)", result.output)
    assert hint is not None, result.output
    words = shlex.split(hint.group(1))[1:]  # the hinted command, run as is
    assert runner.invoke(app, [*words, "--manifest", str(manifest)]).exit_code == 0
    verified = runner.invoke(app, ["datasets", "verify", recorded.dataset_id, "--manifest", str(manifest)])
    assert verified.exit_code == 0 and "OK" in verified.output
    # A damaged copy: verify fails and names the command that replaces it, which works too.
    (isolated_paths / recorded.dataset_id / "data" / "metadata.json").write_text("{}")
    failed = runner.invoke(app, ["datasets", "verify", recorded.dataset_id, "--manifest", str(manifest)])
    assert failed.exit_code == 1
    words = shlex.split(re.search(r"run: (offdyn-bench datasets download \S+ --force)", failed.output).group(1))[1:]
    assert runner.invoke(app, [*words, "--manifest", str(manifest)]).exit_code == 0
    assert verify_installed(recorded).ok


def test_load_installed_names_the_suite_command_not_minari_download(recorded: Entry, no_remote,
                                                                   isolated_paths) -> None:
    with pytest.raises(InstallError) as missing:
        load_installed(recorded.dataset_id)
    assert f"run: offdyn-bench datasets download {recorded.dataset_id}" in str(missing.value)
    assert "download=True" not in str(missing.value)
    ensure_dataset(recorded.dataset_id, manifest=Manifest.from_entries([recorded]), echo=lambda m: None,
                   progress=False)
    assert load_installed(recorded.dataset_id).total_steps == recorded.total_steps == 120
    metadata = isolated_paths / recorded.dataset_id / "data" / "metadata.json"
    metadata.write_text(json.dumps({"broken": True}))
    with pytest.raises(InstallError, match=f"cannot be read by Minari .*download {recorded.dataset_id} --force"):
        load_installed(recorded.dataset_id)


def test_unknown_ids_are_refused_before_any_request(loopback_remote) -> None:
    with pytest.raises(OffdynError, match="unknown dataset task 'hopper-gravity-9p9'"):
        ensure_dataset("offdyn/hopper-gravity-9p9/random-v0", remote=loopback_remote.url, progress=False)
    assert loopback_remote.requests == []


def test_list_creates_no_folder(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv("MINARI_DATASETS_PATH")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    (tmp_path / "home").mkdir()
    result = runner.invoke(app, ["datasets", "list"])
    assert result.exit_code == 0, result.output
    assert list((tmp_path / "home").iterdir()) == []  # no ~/.minari
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "elsewhere" / "datasets"))
    assert runner.invoke(app, ["datasets", "list"]).exit_code == 0
    assert not (tmp_path / "elsewhere").exists()


def test_list_columns_are_what_they_say(recorded: Entry, tmp_path) -> None:
    unbuilt = Entry(recipe=dataclasses.replace(recorded.recipe, dataset_id="offdyn/hopper-gravity-0p5/random-v1"))
    write_manifest(Manifest.from_entries([recorded, unbuilt]), tmp_path / "manifest.json")
    result = runner.invoke(app, ["datasets", "list", "--manifest", str(tmp_path / "manifest.json")])
    lines = result.output.splitlines()
    assert lines[0].split() == ["dataset", "id", "transitions", "archive", "MB", "hashes", "installed", "behaviour"]
    built_row = next(line for line in lines if line.startswith(recorded.dataset_id + " "))
    assert built_row.split()[1:4] == [str(recorded.total_steps), f"{recorded.archive.size / 1e6:.1f}", "yes"]
    unbuilt_row = next(line for line in lines if line.startswith(unbuilt.dataset_id))
    assert unbuilt_row.split()[1:4] == [str(recorded.recipe.num_transitions), "-", "no"]


def test_a_copy_installed_meanwhile_by_another_process_is_used(recorded: Entry, no_remote, monkeypatch,
                                                               isolated_paths) -> None:
    from offdyn_bench.datasets import ensure as ensure_module

    def other_process_wins(recipe, **kwargs):  # noqa: ANN001, ANN202 - build_dataset's signature
        build_dataset(recipe, root=kwargs["root"])  # the other process's install
        raise InstallError(f"{recipe.dataset_id} is already installed; pass --force to replace it")

    monkeypatch.setattr(ensure_module, "build_dataset", other_process_wins)
    said: list[str] = []
    path = ensure_dataset(recorded.dataset_id, manifest=Manifest.from_entries([recorded]), echo=said.append,
                          progress=False)
    assert "installed meanwhile by another process" in said[-1] and tree_sha256(path) == recorded.files
def test_a_missing_minari_dataset_names_the_suites_command():
    from baselines.data import load_dataset
    from offdyn_bench.diagnose.data import load_minari
    from offdyn_bench.tasks import get_task
    from offdyn_bench.errors import OffdynError
    ident = "offdyn/hopper-gravity-0p5/random-v0"
    for load in (lambda: load_dataset(ident, get_task("hopper-gravity-0.5")), lambda: load_minari(ident)):
        with pytest.raises(OffdynError) as caught:
            load()
        assert f"offdyn-bench datasets download {ident}" in str(caught.value)
        assert "download=True" not in str(caught.value)


def test_download_by_task_installs_the_dataset_train_uses_and_prints_only_its_id(no_remote, isolated_paths) -> None:
    from offdyn_bench.protocol import official_dataset

    expected = official_dataset("hopper-gravity-0.5", "offline-target")
    result = runner.invoke(app, ["datasets", "download", "--task", "hopper-gravity-0.5", "--print-id"])
    assert result.exit_code == 0, result.output
    assert result.stdout == f"{expected}\n"  # a script's $(...) gets the id and nothing else
    assert "rebuilt from its recipe" in result.stderr and "%|" not in result.stderr
    assert verify_installed(read_manifest().entries[expected]).ok
    again = runner.invoke(app, ["datasets", "download", "--task", "hopper-gravity-0.5", "--print-id"])
    assert again.exit_code == 0 and again.stdout == f"{expected}\n"
    assert f"{expected}: installed at {isolated_paths / expected}; 2 files match" in again.stderr


def test_returns_says_what_an_installed_datasets_behaviour_earns(no_remote, isolated_paths) -> None:
    import re

    from offdyn_bench.datasets.ensure import load_installed

    ident = "offdyn/hopper-gravity-0p5/random-v0"
    missing = runner.invoke(app, ["datasets", "returns", ident])
    assert missing.exit_code == 2 and f"offdyn-bench datasets download {ident}" in missing.stderr
    assert runner.invoke(app, ["datasets", "download", ident]).exit_code == 0
    result = runner.invoke(app, ["datasets", "returns", ident])
    assert result.exit_code == 0, result.output
    found = re.fullmatch(rf"{ident}: (\d+) episodes; return mean (\S+), min (\S+), max (\S+)\n", result.stdout)
    assert found, result.stdout
    episodes, mean, low, high = int(found[1]), *map(float, found.groups()[1:])
    dataset = load_installed(ident)
    assert episodes == dataset.total_episodes
    # Every transition's reward is in one episode's return: the returns add up to the data's rewards.
    total = sum(float(episode.rewards.sum()) for episode in dataset.iterate_episodes())
    assert mean * episodes == pytest.approx(total, abs=0.05 * episodes)
    # A random Hopper falls within a few dozen steps, each worth about 1 (alive) plus forward speed.
    assert 0 < low <= mean <= high < 200


def test_download_by_task_and_quality_installs_that_dataset(no_remote, isolated_paths) -> None:
    from offdyn_bench.protocol import official_dataset

    result = runner.invoke(app, ["datasets", "download", "--task", "hopper-gravity-0.5", "--quality", "random",
                                 "--print-id"])
    assert result.exit_code == 0, result.output
    assert result.stdout == "offdyn/hopper-gravity-0p5/random-v0\n"
    assert result.stdout.strip() != official_dataset("hopper-gravity-0.5", "offline-target")
    assert verify_installed(read_manifest().entries["offdyn/hopper-gravity-0p5/random-v0"]).ok


@pytest.mark.parametrize(("args", "message"), [
    ([], "error: give a dataset ID or --task TASK, one of the two"),
    (["offdyn/hopper-gravity-0p5/source-policy-v0", "--task", "hopper-gravity-0.5"],
     "error: give a dataset ID or --task TASK, one of the two"),
    (["--task", "hopper-gravity-9"], "error: unknown task 'hopper-gravity-9'; closest valid names: "),
    (["--task", "hopper-gravity-0.5", "--track", "online"], "error: unknown track 'online'"),
    (["--task", "hopper-gravity-0.5", "--track", "online-target"],
     "error: track 'online-target' trains on no target dataset; --task needs a track that does"),
    (["--task", "halfcheetah-h2o-gravity-2.0", "--quality", "medum"],
     "error: unknown dataset quality 'medum'; closest valid names: 'medium', 'medium-replay', 'medium-expert'"),
    (["--task", "hopper-gravity-0.5", "--quality", "medium"],
     "error: task hopper-gravity-0.5 has no 'medium' dataset; its qualities are ['random', 'source-policy', 'source']"),
    (["offdyn/hopper-gravity-0p5/random-v0", "--quality", "random"],
     ("error: --quality random picks one of --task's datasets; with a dataset ID "
      "(offdyn/hopper-gravity-0p5/random-v0) leave it out")),
])
def test_download_by_task_refuses_what_names_no_dataset(args, message, no_remote, isolated_paths) -> None:
    result = runner.invoke(app, ["datasets", "download", *args, "--print-id"])
    assert result.exit_code == 2 and result.stdout == "" and result.stderr.startswith(message), result.output
    assert not isolated_paths.exists()  # nothing installed, no datasets root made
