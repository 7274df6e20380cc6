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
from collections.abc import Iterable, Mapping
from typing import Any

from offdyn_bench.datasets.recipes import ASSETS_DIR, Recipe, default_recipe, parse_dataset_id
from offdyn_bench.errors import OffdynError, UnknownNameError

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
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "manifest") -> Entry:
        try:
            archive = data.get("archive")
            return cls(
                recipe=Recipe.from_dict(data["recipe"]),
                files=data.get("files"),
                archive=None if archive is None else ArchiveRecord(str(archive["name"]), str(archive["sha256"]),
                                                                   int(archive["size"])),
                total_steps=data.get("total_steps"),
                total_episodes=data.get("total_episodes"),
                reference_scores=data.get("reference_scores"),
                built_with=data.get("built_with"),
            )
        except (KeyError, TypeError, ValueError) as error:
            if isinstance(error, OffdynError):
                raise
            raise ManifestError(f"{where}: malformed dataset entry ({type(error).__name__}: {error}); expected "
                                "keys recipe, files, archive, total_steps, total_episodes, reference_scores, "
                                "built_with") from error


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
        entries = {}
        for ident, raw in data.get("datasets", {}).items():
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
