"""Where datasets live locally, how one is put there atomically, and how it is checked.

Datasets install where Minari looks for them: ``$MINARI_DATASETS_PATH/<dataset id>`` (default
``~/.minari/datasets``). A build or download first assembles the dataset in a hidden staging
directory under that same root (same file system), then moves it into place with one rename: a
reader sees either no dataset or a complete one, and a failure leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pathlib
import shutil
import tempfile
from collections.abc import Iterator

from offdyn_bench.datasets.archive import compare_files, tree_sha256
from offdyn_bench.datasets.manifest import Entry
from offdyn_bench.errors import OffdynError

STAGING_DIR = ".offdyn-staging"  # hidden: Minari's listing skips names starting with "."


class InstallError(OffdynError):
    """A dataset that cannot be installed, or an installed one that does not verify."""


def datasets_root() -> pathlib.Path:
    """Minari's dataset directory, as Minari itself resolves it (made absolute)."""
    root = os.environ.get("MINARI_DATASETS_PATH")
    path = pathlib.Path(root) if root else pathlib.Path.home() / ".minari" / "datasets"
    path.mkdir(parents=True, exist_ok=True)
    return path.resolve()


def resolve_root(root: pathlib.Path | str | None) -> pathlib.Path:
    """``root`` as an absolute path, or Minari's own root. Absolute because Minari's size
    computation joins a relative folder with its own relative listing and loses the files."""
    return pathlib.Path(root).resolve() if root else datasets_root()


def dataset_dir(dataset_id: str, root: pathlib.Path | None = None) -> pathlib.Path:
    return resolve_root(root) / dataset_id


def is_installed(dataset_id: str, root: pathlib.Path | None = None) -> bool:
    return (dataset_dir(dataset_id, root) / "data" / "metadata.json").is_file()


@contextlib.contextmanager
def staging(root: pathlib.Path | None = None) -> Iterator[pathlib.Path]:
    """A fresh directory under the datasets root, removed on exit whatever happens."""
    base = resolve_root(root) / STAGING_DIR
    base.mkdir(parents=True, exist_ok=True)
    path = pathlib.Path(tempfile.mkdtemp(dir=base))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)
        with contextlib.suppress(OSError):
            base.rmdir()  # only when empty: another install may be staging beside us


def install_tree(staged: pathlib.Path, dataset_id: str, *, root: pathlib.Path | None = None,
                 replace: bool = False) -> pathlib.Path:
    """Move a complete dataset directory into place with a rename.

    An existing dataset is an error unless ``replace``; then it is first renamed aside (inside
    the staging area) and removed only after the new one is in place."""
    root = resolve_root(root)
    final = dataset_dir(dataset_id, root)
    final.parent.mkdir(parents=True, exist_ok=True)
    if final.exists():
        if not replace:
            raise InstallError(f"{dataset_id} is already installed at {final}; pass --force to replace it")
        aside = staged.parent / (staged.name + ".replaced")
        os.rename(final, aside)
        try:
            os.rename(staged, final)
        except OSError:
            os.rename(aside, final)  # put the old one back rather than leave nothing
            raise
        shutil.rmtree(aside, ignore_errors=True)
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
