"""Where datasets live locally, how one is put there atomically, and how it is checked.

Datasets install where Minari looks for them: ``$MINARI_DATASETS_PATH/<dataset id>`` (default
``~/.minari/datasets``). A build or download first assembles the dataset in a hidden staging
directory under that same root (same file system), then moves it into place with one rename: a
reader sees either no dataset or a complete one, and a failure leaves nothing behind (a killed
process's staging is removed by the next run: ``staging.py``).
"""

from __future__ import annotations

import dataclasses
import os
import pathlib

from offdyn_bench.datasets.archive import compare_files, tree_sha256
from offdyn_bench.datasets.manifest import Entry
from offdyn_bench.datasets.staging import STAGING_DIR, clean_stale_staging, replace_directory, staging
from offdyn_bench.errors import OffdynError

__all__ = ["STAGING_DIR", "InstallError", "VerifyReport", "datasets_root", "resolve_root", "dataset_dir",
           "is_installed", "install_tree", "verify_installed", "staging", "clean_stale_staging"]


class InstallError(OffdynError):
    """A dataset that cannot be installed, or an installed one that does not verify."""


def datasets_root() -> pathlib.Path:
    """Minari's dataset directory, as Minari itself resolves it (made absolute)."""
    root = os.environ.get("MINARI_DATASETS_PATH")
    path = pathlib.Path(root) if root else pathlib.Path.home() / ".minari" / "datasets"
    return path.resolve()  # not created here: only a build or download writes anything


def resolve_root(root: pathlib.Path | str | None) -> pathlib.Path:
    """``root`` as an absolute path, or Minari's own root. Absolute because Minari's size
    computation joins a relative folder with its own relative listing and loses the files."""
    return pathlib.Path(root).resolve() if root else datasets_root()


def dataset_dir(dataset_id: str, root: pathlib.Path | None = None) -> pathlib.Path:
    return resolve_root(root) / dataset_id


def is_installed(dataset_id: str, root: pathlib.Path | None = None) -> bool:
    return (dataset_dir(dataset_id, root) / "data" / "metadata.json").is_file()


def install_tree(staged: pathlib.Path, dataset_id: str, *, root: pathlib.Path | None = None,
                 replace: bool = False) -> pathlib.Path:
    """Move a complete dataset directory (staged on the same file system) into place.

    An existing dataset is an error unless ``replace``; then the two are exchanged so that the
    id always names a complete dataset, even if the process is killed (see ``staging.py``)."""
    root = resolve_root(root)
    final = dataset_dir(dataset_id, root)
    final.parent.mkdir(parents=True, exist_ok=True)
    if final.exists():
        if not replace:
            raise InstallError(f"{dataset_id} is already installed at {final}; pass --force to replace it")
        replace_directory(staged, final, root)
    else:
        os.rename(staged, final)
    return final


@dataclasses.dataclass(frozen=True)
class VerifyReport:
    dataset_id: str
    path: pathlib.Path
    problems: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.problems


def verify_installed(entry: Entry, root: pathlib.Path | None = None) -> VerifyReport:
    """Compare an installed dataset with the sha256 of every file its manifest entry records,
    then load it with Minari and compare its step count."""
    path = dataset_dir(entry.dataset_id, root)
    clean_stale_staging(resolve_root(root))  # may put back a copy a killed --force had moved aside
    if not is_installed(entry.dataset_id, root):
        raise InstallError(f"{entry.dataset_id} is not installed (looked in {path}); "
                           f"run: offdyn-bench datasets download {entry.dataset_id}")
    if entry.files is None:
        raise InstallError(f"the manifest has no file hashes for {entry.dataset_id} (it was never built with "
                           "--update-manifest); pass --manifest with the manifest of the build or remote it came from")
    problems = compare_files(entry.files, tree_sha256(path))
    if not problems:
        import minari

        from offdyn_bench.datasets.build import minari_root

        with minari_root(resolve_root(root)):
            dataset = minari.load_dataset(entry.dataset_id)
        if entry.total_steps is not None and dataset.total_steps != entry.total_steps:
            problems.append(f"Minari reads {dataset.total_steps} steps, the manifest says {entry.total_steps}")
    return VerifyReport(entry.dataset_id, path, tuple(problems))
