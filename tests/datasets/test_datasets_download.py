"""Downloads from a loopback HTTP server or a file:// folder: every failure leaves nothing installed."""

from __future__ import annotations

import dataclasses
import io
import json
import pathlib
import shutil
import tarfile

import minari
import pytest

from offdyn_bench.datasets import DownloadError, download_dataset, verify_installed
from offdyn_bench.datasets.archive import sha256_file
from offdyn_bench.datasets.install import STAGING_DIR, is_installed
from offdyn_bench.datasets.manifest import ArchiveRecord, Entry, Manifest, archive_name, entry_name

EMPTY = Manifest({})  # no shipped hashes: the remote's entry is what is checked against


def serve(published: tuple, folder: pathlib.Path) -> tuple[str, Entry]:
    """Copy the published dataset into ``folder``; returns its id and entry."""
    recipe, result, remote = published
    for name in (archive_name(recipe.dataset_id), entry_name(recipe.dataset_id)):
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(remote / name, folder / name)
    return recipe.dataset_id, result.entry


def assert_nothing_installed(root: pathlib.Path, dataset_id: str) -> None:
    assert not is_installed(dataset_id, root)
    assert not (root / dataset_id).exists()
    assert not (root / STAGING_DIR).exists() or not any((root / STAGING_DIR).iterdir())


def rewrite_entry(folder: pathlib.Path, dataset_id: str, **changes: object) -> None:
    path = folder / entry_name(dataset_id)
    entry = Entry.from_dict(json.loads(path.read_text()))
    path.write_text(json.dumps(dataclasses.replace(entry, **changes).to_dict()))


def test_http_download_installs_a_loadable_verified_dataset(published, loopback_remote, isolated_paths) -> None:
    dataset_id, entry = serve(published, loopback_remote.folder)
    path = download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert path == isolated_paths / dataset_id
    assert verify_installed(entry).ok
    assert minari.load_dataset(dataset_id).total_steps == entry.total_steps
    assert loopback_remote.requests == [entry_name(dataset_id), archive_name(dataset_id)]


def test_remote_from_environment_and_file_scheme(published, monkeypatch, isolated_paths) -> None:
    recipe, _, remote = published
    monkeypatch.setenv("OFFDYN_REMOTE", remote.as_uri())
    download_dataset(recipe.dataset_id, manifest=EMPTY)
    assert is_installed(recipe.dataset_id)


def test_shipped_manifest_is_trusted_over_the_remote(published, loopback_remote, isolated_paths) -> None:
    dataset_id, entry = serve(published, loopback_remote.folder)
    shipped = Manifest.from_entries([dataclasses.replace(entry, archive=dataclasses.replace(entry.archive, sha256="a" * 64))])
    with pytest.raises(DownloadError, match="disagrees with the manifest shipped"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=shipped)
    assert_nothing_installed(isolated_paths, dataset_id)
    download_dataset(dataset_id, remote=loopback_remote.url, manifest=Manifest.from_entries([entry]))
    assert is_installed(dataset_id)


def test_404_is_a_clear_error(loopback_remote, isolated_paths) -> None:
    dataset_id = "offdyn/hopper-gravity-0p5/random-v0"
    with pytest.raises(DownloadError, match="not found on the remote \\(HTTP 404\\)"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert_nothing_installed(isolated_paths, dataset_id)


def test_missing_dataset_on_a_file_remote(tmp_path, isolated_paths) -> None:
    (tmp_path / "empty-remote").mkdir()
    with pytest.raises(DownloadError, match="not found on the remote"):
        download_dataset("offdyn/hopper-gravity-0p5/random-v0", remote=(tmp_path / "empty-remote").as_uri(),
                         manifest=EMPTY)
    assert_nothing_installed(isolated_paths, "offdyn/hopper-gravity-0p5/random-v0")


def test_checksum_mismatch_installs_nothing(published, loopback_remote, isolated_paths) -> None:
    dataset_id, entry = serve(published, loopback_remote.folder)
    archive = loopback_remote.folder / archive_name(dataset_id)
    data = bytearray(archive.read_bytes())
    data[len(data) // 2] ^= 0xFF  # same size, other bytes
    archive.write_bytes(bytes(data))
    with pytest.raises(DownloadError, match="checksum mismatch"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert_nothing_installed(isolated_paths, dataset_id)


def test_truncated_archive_installs_nothing(published, loopback_remote, isolated_paths) -> None:
    dataset_id, entry = serve(published, loopback_remote.folder)
    archive = loopback_remote.folder / archive_name(dataset_id)
    archive.write_bytes(archive.read_bytes()[: entry.archive.size // 2])
    with pytest.raises(DownloadError, match="got .* of .* bytes"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert_nothing_installed(isolated_paths, dataset_id)


def test_truncated_archive_that_matches_its_manifest_is_still_refused(published, loopback_remote,
                                                                      isolated_paths) -> None:
    # A remote whose manifest describes the truncated bytes: the hash passes, unpacking must not.
    dataset_id, entry = serve(published, loopback_remote.folder)
    archive = loopback_remote.folder / archive_name(dataset_id)
    archive.write_bytes(archive.read_bytes()[: entry.archive.size // 2])
    rewrite_entry(loopback_remote.folder, dataset_id,
                  archive=ArchiveRecord(entry.archive.name, sha256_file(archive), archive.stat().st_size))
    with pytest.raises(DownloadError, match="truncated or corrupt"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert_nothing_installed(isolated_paths, dataset_id)


@pytest.mark.parametrize("member", ["../escaped.txt", "/tmp/offdyn-escaped.txt", "data/../../escaped.txt", "link"])
def test_members_escaping_the_target_are_refused(member, published, loopback_remote, isolated_paths,
                                                 tmp_path) -> None:
    dataset_id, entry = serve(published, loopback_remote.folder)
    archive = loopback_remote.folder / archive_name(dataset_id)
    with tarfile.open(archive, "w:gz") as tar:
        info = tarfile.TarInfo("data/metadata.json")
        info.size = 2
        tar.addfile(info, io.BytesIO(b"{}"))
        evil = tarfile.TarInfo(member)
        if member == "link":
            evil.type, evil.linkname = tarfile.SYMTYPE, "../../../../outside"
            tar.addfile(evil)
        else:
            evil.size = 4
            tar.addfile(evil, io.BytesIO(b"evil"))
    rewrite_entry(loopback_remote.folder, dataset_id,
                  archive=ArchiveRecord(entry.archive.name, sha256_file(archive), archive.stat().st_size))
    with pytest.raises(DownloadError, match="escapes the target|absolute|is a link"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert_nothing_installed(isolated_paths, dataset_id)
    assert not list(tmp_path.rglob("escaped.txt")) and not pathlib.Path("/tmp/offdyn-escaped.txt").exists()


def test_interrupted_download_then_retry_succeeds(published, loopback_remote, isolated_paths) -> None:
    dataset_id, entry = serve(published, loopback_remote.folder)
    loopback_remote.cut_after[archive_name(dataset_id)] = entry.archive.size // 3
    with pytest.raises(DownloadError, match="interrupted"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert_nothing_installed(isolated_paths, dataset_id)
    download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert verify_installed(entry).ok


def test_files_not_matching_the_entry_are_refused(published, loopback_remote, isolated_paths) -> None:
    dataset_id, entry = serve(published, loopback_remote.folder)
    files = dict(entry.files)
    files["data/metadata.json"] = "0" * 64
    rewrite_entry(loopback_remote.folder, dataset_id, files=files)
    with pytest.raises(DownloadError, match="does not match the manifest"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert_nothing_installed(isolated_paths, dataset_id)


def test_installed_dataset_is_kept_unless_forced(published, loopback_remote, isolated_paths) -> None:
    dataset_id, entry = serve(published, loopback_remote.folder)
    download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    loopback_remote.requests.clear()
    download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert loopback_remote.requests == []
    download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY, force=True)
    assert verify_installed(entry).ok and loopback_remote.requests


@pytest.mark.parametrize("remote, message", [(None, "no remote configured"), ("ftp://host/x", "scheme 'ftp'")])
def test_bad_remote_configuration(remote, message, monkeypatch) -> None:
    monkeypatch.delenv("OFFDYN_REMOTE")
    with pytest.raises(DownloadError, match=message):
        download_dataset("offdyn/hopper-gravity-0p5/random-v0", remote=remote, manifest=EMPTY)


@pytest.mark.parametrize("bad_id", ["offdyn/../../etc/passwd-v0", "/abs/x-v0", "offdyn/a b/random-v0"])
def test_malformed_ids_are_refused(bad_id, loopback_remote) -> None:
    with pytest.raises(DownloadError, match="malformed dataset id"):
        download_dataset(bad_id, remote=loopback_remote.url, manifest=EMPTY)
    assert loopback_remote.requests == []
