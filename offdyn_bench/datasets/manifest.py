"""The dataset manifest: per dataset id, its recipe and what a build of it produced.

``assets/datasets.json`` ships with the code. An entry's ``recipe`` says how to build the
dataset; ``files`` (sha256 of every file), ``archive`` (name, sha256, size), ``total_steps``,
``total_episodes``, ``reference_scores`` and ``built_with`` (library versions) are filled in by
``offdyn-bench datasets build --update-manifest`` and are null until a build has run (for
instance while a behaviour policy is missing). A remote holds the same entries, one JSON file per
dataset next to its archive (``<id>.json``, ``<id>.tar.gz``), plus a ``datasets.json`` of them all.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import re
from collections.abc import Iterable, Mapping
from typing import Any

from offdyn_bench.datasets.recipes import ASSETS_DIR, Recipe, json_type, default_recipe, parse_dataset_id
from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.json_values import is_integer

MANIFEST_FORMAT = "offdyn-datasets-manifest/1"
MANIFEST_PATH = ASSETS_DIR / "datasets.json"


class ManifestError(OffdynError):
    """A manifest that is missing, malformed, or disagrees with another one."""


@dataclasses.dataclass(frozen=True)
class ArchiveRecord:
    name: str
    sha256: str
    size: int


@dataclasses.dataclass(frozen=True)
class Entry:
    """One dataset: its recipe and, once built, its file hashes, archive and scores."""

    recipe: Recipe
    files: Mapping[str, str] | None = None
    archive: ArchiveRecord | None = None
    total_steps: int | None = None
    total_episodes: int | None = None
    reference_scores: Mapping[str, Any] | None = None
    built_with: Mapping[str, Any] | None = None
    # Bytes of every file: extraction writes no more than this (absent in entries built before).
    file_sizes: Mapping[str, int] | None = None

    @property
    def dataset_id(self) -> str:
        return self.recipe.dataset_id

    @property
    def is_built(self) -> bool:
        return self.files is not None and self.archive is not None

    def to_dict(self) -> dict[str, Any]:
        return {
            "recipe": self.recipe.to_dict(),
            "files": None if self.files is None else dict(sorted(self.files.items())),
            "archive": None if self.archive is None else dataclasses.asdict(self.archive),
            "total_steps": self.total_steps,
            "total_episodes": self.total_episodes,
            "reference_scores": self.reference_scores,
            "built_with": self.built_with,
            # Only when known, so entries recorded before sizes were kept read back unchanged.
            **({} if self.file_sizes is None else {"file_sizes": dict(sorted(self.file_sizes.items()))}),
        }

    @classmethod
    def from_dict(cls, data: Any, where: str = "manifest") -> Entry:
        """An entry from its JSON form. Any other JSON value (a list, a string, a field of the
        wrong type, a path that could leave the dataset folder) is a :class:`ManifestError`
        that says where, what was found and what was expected."""
        if not isinstance(data, Mapping):
            raise ManifestError(f"{where}: a dataset entry must be a JSON object with keys {_ENTRY_KEYS}, "
                                f"got {json_type(data)}")
        unknown = sorted(set(data) - set(_ENTRY_KEYS))
        if unknown:
            raise ManifestError(f"{where}: unknown keys {unknown} in a dataset entry; expected {_ENTRY_KEYS}")
        if "recipe" not in data:
            raise ManifestError(f"{where}: the dataset entry has no 'recipe'; expected keys {_ENTRY_KEYS}")
        try:
            recipe = Recipe.from_dict(data["recipe"])
        except OffdynError as error:
            raise ManifestError(f"{where}: {error}") from error
        files = _files(where, data.get("files"))
        return cls(
            recipe=recipe,
            files=files,
            archive=_archive(where, data.get("archive")),
            total_steps=_count(where, "total_steps", data.get("total_steps")),
            total_episodes=_count(where, "total_episodes", data.get("total_episodes")),
            reference_scores=_object(where, "reference_scores", data.get("reference_scores")),
            built_with=_object(where, "built_with", data.get("built_with")),
            file_sizes=_file_sizes(where, data.get("file_sizes"), files),
        )


_ENTRY_KEYS = ["recipe", "files", "file_sizes", "archive", "total_steps", "total_episodes", "reference_scores",
               "built_with"]
_SHA256 = re.compile(r"[0-9a-f]{64}")


def _object(where: str, key: str, value: Any) -> Mapping[str, Any] | None:
    if value is not None and not isinstance(value, Mapping):
        raise ManifestError(f"{where}: {key!r} must be a JSON object or null, got {json_type(value)}")
    return value


def _count(where: str, key: str, value: Any) -> int | None:
    if value is not None and (not is_integer(value) or value < 0):
        raise ManifestError(f"{where}: {key!r} must be a non-negative integer or null, got {value!r:.60}")
    return value


def _relative_file(where: str, path: Any) -> str:
    """A dataset file's path: relative, posix, and unable to leave the dataset folder."""
    if not isinstance(path, str) or not path or path.startswith("/") or "\\" in path \
            or any(part in ("", ".", "..") for part in path.split("/")) or "\0" in path:
        raise ManifestError(f"{where}: file name {path!r:.80} is not a relative path inside the dataset folder")
    return path


def _files(where: str, value: Any) -> dict[str, str] | None:
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise ManifestError(f"{where}: 'files' must map file names to sha256 hex digests, got {json_type(value)}")
    files = {}
    for path, digest in value.items():
        if not isinstance(digest, str) or not _SHA256.fullmatch(digest):
            raise ManifestError(f"{where}: sha256 of {path!r:.80} must be 64 lowercase hex digits, got {digest!r:.80}")
        files[_relative_file(where, path)] = digest
    return files


def _file_sizes(where: str, value: Any, files: Mapping[str, str] | None) -> dict[str, int] | None:
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise ManifestError(f"{where}: 'file_sizes' must map file names to byte counts, got {json_type(value)}")
    sizes = {_relative_file(where, path): _count(where, f"file_sizes[{path!r:.80}]", size)
             for path, size in value.items()}
    if files is None or set(sizes) != set(files):
        raise ManifestError(f"{where}: 'file_sizes' must name exactly the files of 'files'")
    return sizes  # type: ignore[return-value]


def _archive(where: str, value: Any) -> ArchiveRecord | None:
    if value is None:
        return None
    if not isinstance(value, Mapping) or set(value) != {"name", "sha256", "size"}:
        raise ManifestError(f"{where}: 'archive' must be a JSON object with keys name, sha256, size; "
                            f"got {json_type(value) if not isinstance(value, Mapping) else sorted(value)}")
    name, digest, size = value["name"], value["sha256"], value["size"]
    if not isinstance(name, str) or not isinstance(digest, str) or not _SHA256.fullmatch(digest):
        raise ManifestError(f"{where}: archive name must be a string and sha256 64 lowercase hex digits, "
                            f"got {name!r:.80}, {digest!r:.80}")
    size = _count(where, "archive size", size)
    if size is None:
        raise ManifestError(f"{where}: 'archive size' must be a non-negative integer, got null")
    return ArchiveRecord(name, digest, size)


def archive_name(dataset_id: str) -> str:
    """Where a dataset's archive sits on a remote, relative to its root."""
    return f"{dataset_id}.tar.gz"


def entry_name(dataset_id: str) -> str:
    """Where a dataset's manifest entry sits on a remote, relative to its root."""
    return f"{dataset_id}.json"


@dataclasses.dataclass
class Manifest:
    entries: dict[str, Entry]

    def __contains__(self, dataset_id: object) -> bool:
        return dataset_id in self.entries

    def get(self, dataset_id: str) -> Entry:
        if dataset_id not in self.entries:
            raise UnknownNameError("dataset", dataset_id, self.entries)
        return self.entries[dataset_id]

    def entry_or_default(self, dataset_id: str) -> Entry:
        """The manifest's entry, or an unbuilt entry with the default recipe for any other id
        of the task grid (built on demand)."""
        if dataset_id in self.entries:
            return self.entries[dataset_id]
        pair, quality, version = parse_dataset_id(dataset_id)
        return Entry(recipe=default_recipe(pair, quality, version=version))

    def with_entry(self, entry: Entry) -> Manifest:
        return Manifest({**self.entries, entry.dataset_id: entry})

    def to_dict(self) -> dict[str, Any]:
        return {"format": MANIFEST_FORMAT,
                "datasets": {ident: self.entries[ident].to_dict() for ident in sorted(self.entries)}}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "manifest") -> Manifest:
        if not isinstance(data, Mapping) or data.get("format") != MANIFEST_FORMAT:
            found = data.get("format") if isinstance(data, Mapping) else type(data).__name__
            raise ManifestError(f"{where}: format {found!r}, expected {MANIFEST_FORMAT!r}")
        datasets = data.get("datasets", {})
        if not isinstance(datasets, Mapping):
            raise ManifestError(f"{where}: 'datasets' must map dataset ids to entries, got {json_type(datasets)}")
        entries = {}
        for ident, raw in datasets.items():
            entry = Entry.from_dict(raw, where=f"{where}, dataset {ident!r}")
            if entry.dataset_id != ident:
                raise ManifestError(f"{where}: entry {ident!r} holds the recipe of {entry.dataset_id!r}")
            entries[ident] = entry
        return cls(entries)

    @classmethod
    def from_entries(cls, entries: Iterable[Entry]) -> Manifest:
        return cls({entry.dataset_id: entry for entry in entries})


def dumps(data: Mapping[str, Any]) -> str:
    """The one JSON layout of manifests and entries (stable: sorted keys, fixed indent)."""
    return json.dumps(data, indent=1, sort_keys=True) + "\n"


def write_json_atomically(path: pathlib.Path, data: Mapping[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    partial.write_text(dumps(data))
    os.replace(partial, path)


def read_manifest(path: str | os.PathLike[str] | None = None) -> Manifest:
    """The shipped manifest (``assets/datasets.json``), or the one at ``path``."""
    path = pathlib.Path(path) if path is not None else MANIFEST_PATH
    if not path.is_file():
        if path == MANIFEST_PATH:
            return Manifest({})
        raise ManifestError(f"manifest {path} not found")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ManifestError(f"manifest {path} is not valid JSON: {error}") from error
    return Manifest.from_dict(data, where=str(path))


def write_manifest(manifest: Manifest, path: str | os.PathLike[str] | None = None) -> pathlib.Path:
    path = pathlib.Path(path) if path is not None else MANIFEST_PATH
    write_json_atomically(path, manifest.to_dict())
    return path


__all__ = ["Manifest", "Entry", "ArchiveRecord", "ManifestError", "MANIFEST_PATH",
           "read_manifest", "write_manifest", "archive_name", "entry_name", "dumps", "write_json_atomically"]
