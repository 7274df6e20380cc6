"""File hashes, reproducible archives, and extraction that refuses anything but plain files.

An archive holds one dataset directory: its regular files, sorted by path, with fixed owner,
mode and time, in a gzip stream with no name and time in its header, so the same files always
give the same archive bytes (with the same zlib).
"""

from __future__ import annotations

import gzip
import hashlib
import os
import pathlib
import posixpath
import tarfile
import zlib
from collections.abc import Callable, Mapping

from offdyn_bench.errors import OffdynError

_CHUNK = 1 << 20


class ArchiveError(OffdynError):
    """An archive that is truncated, corrupt, unsafe or not what the manifest says."""


def sha256_file(path: str | os.PathLike[str]) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(_CHUNK), b""):
            digest.update(block)
    return digest.hexdigest()


def tree_files(root: pathlib.Path) -> list[str]:
    """Relative posix paths of every file under ``root``, sorted; anything that is not a plain
    file or directory (a link, a device) is an error, not something to hash around."""
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for name in dirnames + filenames:
            path = pathlib.Path(dirpath, name)
            if path.is_symlink() or not (path.is_file() or path.is_dir()):
                raise ArchiveError(f"{path} is not a regular file or directory; datasets hold plain files only")
        found += [pathlib.Path(dirpath, name).relative_to(root).as_posix() for name in filenames]
    return sorted(found)


def tree_sha256(root: pathlib.Path) -> dict[str, str]:
    """sha256 of every file under ``root``, keyed by relative posix path (sorted)."""
    return {rel: sha256_file(root / rel) for rel in tree_files(root)}


def write_archive(root: pathlib.Path, archive_path: pathlib.Path) -> str:
    """Pack every file under ``root`` into ``archive_path`` (tar.gz); returns its sha256.
    Written to a temporary name first, so a failed write never leaves a complete-looking file."""
    archive_path.parent.mkdir(parents=True, exist_ok=True)
    partial = archive_path.with_name(archive_path.name + ".partial")
    try:
        with open(partial, "wb") as raw, \
                gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=6) as zipped, \
                tarfile.open(fileobj=zipped, mode="w", format=tarfile.GNU_FORMAT) as tar:
            for rel in tree_files(root):
                info = tarfile.TarInfo(rel)
                info.size = (root / rel).stat().st_size
                info.mode = 0o644
                info.mtime = 0
                info.uid = info.gid = 0
                info.uname = info.gname = ""
                with open(root / rel, "rb") as file:
                    tar.addfile(info, file)
        os.replace(partial, archive_path)
    finally:
        partial.unlink(missing_ok=True)
    return sha256_file(archive_path)


def _safe_member_path(name: str) -> str:
    """The member's normalized relative path, or an error if it could land outside the
    destination (absolute, ``..``, drive letters, backslashes)."""
    if not name or name.startswith(("/", "\\")) or "\\" in name or ":" in name.split("/")[0]:
        raise ArchiveError(f"archive member {name!r} has an absolute or non-posix path; refusing to extract")
    normalized = posixpath.normpath(name)
    if normalized == ".." or normalized.startswith("../") or "/../" in f"/{normalized}/":
        raise ArchiveError(f"archive member {name!r} escapes the target directory; refusing to extract")
    return normalized


def _plan_members(tar: tarfile.TarFile, expected: Mapping[str, str] | None,
                  sizes: Mapping[str, int] | None) -> list[tuple[tarfile.TarInfo, str]]:
    """Every member's header checked, before any byte is written: plain files and folders
    only, each file named in ``expected`` (once) and no larger than ``sizes`` declares. Reading
    the headers skips each member's data, which the size checks bound before it is read."""
    planned: list[tuple[tarfile.TarInfo, str]] = []
    seen: set[str] = set()
    wanted_dirs = {posixpath.dirname(rel) for rel in expected or {}}  # and their parents, by prefix below
    for member in tar:
        rel = _safe_member_path(member.name)
        if member.isdir():
            if expected is not None and not any(rel == d or d.startswith(rel + "/") for d in wanted_dirs if d):
                raise ArchiveError(f"archive member {member.name!r} is a folder the manifest does not list; "
                                   "refusing to extract")
            planned.append((member, rel))
            continue
        if not member.isfile() or member.issparse():
            kind = "link" if (member.issym() or member.islnk()) else "special file"
            raise ArchiveError(f"archive member {member.name!r} is a {kind}; datasets hold plain files only")
        if rel in seen:
            raise ArchiveError(f"archive member {member.name!r} appears twice")
        seen.add(rel)
        if expected is not None and rel not in expected:
            raise ArchiveError(f"archive member {member.name!r} is not a file the manifest lists; refusing to "
                               "extract (nothing was written)")
        if sizes is not None and member.size > sizes[rel]:
            raise ArchiveError(f"archive member {member.name!r} holds {member.size} bytes, the manifest declares "
                               f"{sizes[rel]}; refusing to extract (nothing was written)")
        planned.append((member, rel))
    missing = sorted(set(expected or {}) - seen)
    if missing:
        raise ArchiveError(f"archive lacks files the manifest lists: {', '.join(missing[:3])}")
    return planned


def extract_archive(archive_path: pathlib.Path, destination: pathlib.Path,
                    expected: Mapping[str, str] | None = None, sizes: Mapping[str, int] | None = None,
                    on_bytes: Callable[[int], None] | None = None) -> dict[str, str]:
    """Extract the plain files of a tar.gz into ``destination`` (which must be empty or new);
    returns the sha256 of every extracted file.

    Links, devices and paths that would escape ``destination`` are refused, and a truncated or
    corrupt archive is an :class:`ArchiveError`. With ``expected`` ({path: sha256}), a member it
    does not name is refused before anything is written, and a file whose bytes do not match
    stops the extraction at that file. With ``sizes`` ({path: bytes}), no member may be larger
    than declared, so the bytes written are at most their sum (a gzip bomb stops at its header).
    """
    if sizes is not None and expected is not None and set(sizes) != set(expected):
        raise ArchiveError("the manifest's file sizes and file hashes name different files")
    hashes: dict[str, str] = {}
    try:
        with tarfile.open(archive_path, mode="r:gz") as tar:
            planned = _plan_members(tar, expected, sizes)
            destination.mkdir(parents=True, exist_ok=True)
            for member, rel in planned:
                if member.isdir():
                    (destination / rel).mkdir(parents=True, exist_ok=True)
                    continue
                hashes[rel] = _extract_member(tar, member, destination / rel, on_bytes)
                if expected is not None and hashes[rel] != expected[rel]:
                    raise ArchiveError(f"unpacked file {rel} does not match the manifest (sha256 {hashes[rel]}, "
                                       f"expected {expected[rel]})")
    except ArchiveError:
        raise
    except (tarfile.TarError, EOFError, zlib.error, gzip.BadGzipFile, OSError) as error:
        raise ArchiveError(f"archive {archive_path.name} is truncated or corrupt: {error}") from error
    return dict(sorted(hashes.items()))


def _extract_member(tar: tarfile.TarFile, member: tarfile.TarInfo, target: pathlib.Path,
                    on_bytes: Callable[[int], None] | None) -> str:
    target.parent.mkdir(parents=True, exist_ok=True)
    source = tar.extractfile(member)
    if source is None:
        raise ArchiveError(f"archive member {member.name!r} has no data")
    digest = hashlib.sha256()
    written = 0
    with source, open(target, "xb") as out:
        for block in iter(lambda: source.read(_CHUNK), b""):
            written += len(block)
            if written > member.size:  # the checked header size is the bound, whatever the stream holds
                raise ArchiveError(f"archive member {member.name!r} holds more than its header's {member.size} bytes")
            digest.update(block)
            out.write(block)
            if on_bytes is not None:
                on_bytes(len(block))
    return digest.hexdigest()


def compare_files(expected: Mapping[str, str], actual: Mapping[str, str]) -> list[str]:
    """Human-readable differences between two {path: sha256} maps (empty when equal)."""
    problems = [f"missing file {rel}" for rel in sorted(set(expected) - set(actual))]
    problems += [f"unexpected file {rel}" for rel in sorted(set(actual) - set(expected))]
    problems += [f"sha256 mismatch for {rel}: expected {expected[rel]}, found {actual[rel]}"
                 for rel in sorted(set(expected) & set(actual)) if expected[rel] != actual[rel]]
    return problems
