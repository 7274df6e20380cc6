"""Extraction is bounded by the manifest: a member it does not list, or one larger than it
declares (a gzip bomb), is refused from the headers, before a single byte is written."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import pathlib
import tarfile

import pytest

from offdyn_bench.datasets import DownloadError, download_dataset, verify_installed
from offdyn_bench.datasets.archive import ArchiveError, extract_archive, sha256_file
from offdyn_bench.datasets.manifest import ArchiveRecord, Entry, Manifest, archive_name, entry_name

EMPTY = Manifest({})
METADATA = b'{"total_steps": 3}'
DATA = b"\x01\x02\x03" * 100
EXPECTED = {"data/metadata.json": hashlib.sha256(METADATA).hexdigest(),
            "data/main_data.hdf5": hashlib.sha256(DATA).hexdigest()}
SIZES = {"data/metadata.json": len(METADATA), "data/main_data.hdf5": len(DATA)}
BOMB_BYTES = 64 << 20  # 64 MiB of zeros: about 64 KiB compressed


class Zeros(io.RawIOBase):
    """``size`` zero bytes, never held in memory at once."""

    def __init__(self, size: int) -> None:
        self.left = size

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:  # noqa: ANN001
        n = min(len(buffer), self.left)
        buffer[:n] = bytes(n)
        self.left -= n
        return n


def write_tar(path: pathlib.Path, members: list[tuple[str, int, io.RawIOBase | bytes]]) -> pathlib.Path:
    with tarfile.open(path, "w:gz") as tar:
        for name, size, content in members:
            info = tarfile.TarInfo(name)
            info.size = size
            tar.addfile(info, io.BytesIO(content) if isinstance(content, bytes) else io.BufferedReader(content))
    return path


def good_members() -> list[tuple[str, int, io.RawIOBase | bytes]]:
    return [("data/metadata.json", len(METADATA), METADATA), ("data/main_data.hdf5", len(DATA), DATA)]


def test_a_matching_archive_extracts(tmp_path: pathlib.Path) -> None:
    archive = write_tar(tmp_path / "a.tar.gz", good_members())
    assert extract_archive(archive, tmp_path / "out", expected=EXPECTED, sizes=SIZES) == dict(sorted(EXPECTED.items()))
    assert (tmp_path / "out" / "data" / "main_data.hdf5").read_bytes() == DATA


def test_a_gzip_bomb_member_is_refused_before_writing(tmp_path: pathlib.Path) -> None:
    archive = write_tar(tmp_path / "bomb.tar.gz", [good_members()[0],
                                                   ("data/main_data.hdf5", BOMB_BYTES, Zeros(BOMB_BYTES))])
    assert archive.stat().st_size < BOMB_BYTES // 100
    with pytest.raises(ArchiveError, match=f"'data/main_data.hdf5' holds {BOMB_BYTES} bytes, the manifest declares "
                                           f"{len(DATA)}; refusing to extract \\(nothing was written\\)"):
        extract_archive(archive, tmp_path / "out", expected=EXPECTED, sizes=SIZES)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("position", [0, 2])
def test_a_member_the_manifest_does_not_list_is_refused_before_writing(position: int, tmp_path: pathlib.Path) -> None:
    members = good_members()
    members.insert(position, ("data/extra.bin", 4, b"evil"))
    archive = write_tar(tmp_path / "extra.tar.gz", members)
    with pytest.raises(ArchiveError, match="'data/extra.bin' is not a file the manifest lists"):
        extract_archive(archive, tmp_path / "out", expected=EXPECTED, sizes=SIZES)
    assert not (tmp_path / "out").exists()


def test_a_missing_member_and_an_unlisted_folder_are_refused(tmp_path: pathlib.Path) -> None:
    archive = write_tar(tmp_path / "short.tar.gz", good_members()[:1])
    with pytest.raises(ArchiveError, match="lacks files the manifest lists: data/main_data.hdf5"):
        extract_archive(archive, tmp_path / "out", expected=EXPECTED, sizes=SIZES)
    with tarfile.open(tmp_path / "dir.tar.gz", "w:gz") as tar:
        info = tarfile.TarInfo("elsewhere")
        info.type = tarfile.DIRTYPE
        tar.addfile(info)
    with pytest.raises(ArchiveError, match="'elsewhere' is a folder the manifest does not list"):
        extract_archive(tmp_path / "dir.tar.gz", tmp_path / "out", expected=EXPECTED, sizes=SIZES)
    assert not (tmp_path / "out").exists()


def test_bytes_that_do_not_match_stop_at_that_file(tmp_path: pathlib.Path) -> None:
    archive = write_tar(tmp_path / "a.tar.gz", good_members())
    wrong = {**EXPECTED, "data/metadata.json": "0" * 64}
    with pytest.raises(ArchiveError, match="unpacked file data/metadata.json does not match the manifest"):
        extract_archive(archive, tmp_path / "out", expected=wrong, sizes=SIZES)
    assert not (tmp_path / "out" / "data" / "main_data.hdf5").exists()  # the next member was never written


def publish_bomb(published: tuple, folder: pathlib.Path, entry_changes: dict) -> tuple[str, Entry]:
    """Serve ``published``'s entry beside an archive whose hdf5 member is a 64 MiB run of zeros,
    the entry's archive hash updated to match (an unpinned remote can claim anything)."""
    recipe, result, remote = published
    dataset_id = recipe.dataset_id
    archive = folder / archive_name(dataset_id)
    archive.parent.mkdir(parents=True, exist_ok=True)
    metadata = remote_metadata(remote, dataset_id)
    write_tar(archive, [("data/metadata.json", len(metadata), metadata),
                        ("data/main_data.hdf5", BOMB_BYTES, Zeros(BOMB_BYTES))])
    entry = dataclasses.replace(result.entry, archive=ArchiveRecord(result.entry.archive.name, sha256_file(archive),
                                                                    archive.stat().st_size), **entry_changes)
    (folder / entry_name(dataset_id)).write_text(json.dumps(entry.to_dict()))
    return dataset_id, entry


def remote_metadata(remote: pathlib.Path, dataset_id: str) -> bytes:
    with tarfile.open(remote / archive_name(dataset_id), "r:gz") as tar:
        member = tar.extractfile("data/metadata.json")
        assert member is not None
        return member.read()


def test_a_bomb_from_an_unpinned_remote_writes_nothing(published, loopback_remote, nothing_installed,
                                                       monkeypatch) -> None:
    written: list[int] = []
    monkeypatch.setattr("offdyn_bench.datasets.archive._extract_member",
                        lambda *args: written.append(1) or pytest.fail("a member was extracted"))
    dataset_id, entry = publish_bomb(published, loopback_remote.folder, {})
    with pytest.raises(DownloadError, match="holds 67108864 bytes, the manifest declares"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert written == []
    nothing_installed(dataset_id)


def test_an_unpinned_entry_without_sizes_is_refused_before_the_archive(published, loopback_remote,
                                                                        nothing_installed) -> None:
    dataset_id, _ = publish_bomb(published, loopback_remote.folder, {"file_sizes": None})
    with pytest.raises(DownloadError, match="declares no file sizes, and the shipped manifest does not pin"):
        download_dataset(dataset_id, remote=loopback_remote.url, manifest=EMPTY)
    assert loopback_remote.requests == [entry_name(dataset_id)]
    nothing_installed(dataset_id)


def test_a_pinned_entry_without_sizes_still_downloads(published, loopback_remote, isolated_paths) -> None:
    # The shipped manifest predates file sizes; its archive hashes pin the bytes.
    recipe, result, remote = published
    for name in (archive_name(recipe.dataset_id), entry_name(recipe.dataset_id)):
        (loopback_remote.folder / name).parent.mkdir(parents=True, exist_ok=True)
        (loopback_remote.folder / name).write_bytes((remote / name).read_bytes())
    shipped = Manifest.from_entries([dataclasses.replace(result.entry, file_sizes=None)])
    download_dataset(recipe.dataset_id, remote=loopback_remote.url, manifest=shipped)
    assert verify_installed(result.entry).ok
