"""Make a dataset available, whatever the machine has: the one entry point for users and for
the protocol (``offdyn-bench datasets download ID`` and :func:`ensure_dataset`).

- installed already: its files are checked against the manifest's sha256 and it is used;
- a remote is configured (``--remote`` or ``$OFFDYN_REMOTE``): downloaded from it and verified;
- no remote: rebuilt from its recipe (the build is deterministic) and every file compared with
  the sha256 the manifest records, so a fresh clone gets the same bytes a remote would serve.

Each says which of these it did. Loading goes through :func:`load_installed`, whose error for
a missing dataset names the command that installs it (Minari's own says "Use download=True",
which would ask Minari's servers for an id they do not hold).
"""

from __future__ import annotations

import contextlib
import pathlib
import sys
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

from offdyn_bench.datasets.build import (
    BuildMismatchError,
    MissingPolicyError,
    build_dataset,
    check_buildable,
    minari_root,
)
from offdyn_bench.datasets.download import REMOTE_ENV, check_id, configured_remote, download_dataset, remote_url
from offdyn_bench.datasets.install import InstallError, dataset_dir, is_installed, resolve_root, verify_installed
from offdyn_bench.datasets.manifest import Manifest, read_manifest
from offdyn_bench.datasets.recipes import parse_dataset_id
from offdyn_bench.datasets.staging import clean_stale_staging
from offdyn_bench.datasets.transfer import TransferLimits
from offdyn_bench.errors import OffdynError

if TYPE_CHECKING:
    import minari


class DatasetUnavailableError(OffdynError):
    """A dataset that can be neither downloaded nor rebuilt here; the message says what to do."""


def _install_hint(dataset_id: str) -> str:
    return (f"run: offdyn-bench datasets download {dataset_id} (it downloads from ${REMOTE_ENV} when that is "
            "set, and otherwise rebuilds the dataset from its recipe and checks it against the manifest)")


@contextlib.contextmanager
def _progress_bar(enabled: bool, description: str, unit: str, total: int | None = None,
                  **options: Any) -> Iterator[Callable[[int], None]]:
    """A tqdm bar on stderr (or nothing); yields its ``update``."""
    if not enabled:
        yield lambda n: None
        return
    from tqdm import tqdm

    with tqdm(total=total, desc=description, unit=unit, file=sys.stderr, leave=False, **options) as bar:
        yield bar.update


def ensure_dataset(dataset_id: str, *, progress: bool = True, echo: Callable[[str], None] = print,
                   remote: str | None = None, root: pathlib.Path | str | None = None,
                   manifest: Manifest | None = None, force: bool = False,
                   limits: TransferLimits | None = None) -> pathlib.Path:
    """The installed, verified dataset ``dataset_id``: where it is, installing it first if needed.

    Uses an installed copy when its files match the manifest (an installed copy that does not
    match is an error, unless ``force`` replaces it). Otherwise downloads it from ``remote``
    (default ``$OFFDYN_REMOTE``) or, with no remote configured, rebuilds it from its recipe and
    checks every file against the sha256 the manifest records. ``echo`` receives one line per
    thing done (which source, what was verified); ``progress`` shows a bar on stderr.
    ``manifest`` defaults to the shipped ``assets/datasets.json``; ``limits`` to the
    environment's download limits.
    """
    check_id(dataset_id)
    manifest = manifest if manifest is not None else read_manifest()
    if dataset_id not in manifest.entries:
        parse_dataset_id(dataset_id)  # an id of the task grid, or a clear error before any request
    root = resolve_root(root)
    clean_stale_staging(root)
    recorded = manifest.entries.get(dataset_id)
    hashes = recorded is not None and recorded.files is not None
    if is_installed(dataset_id, root) and not force:
        path = dataset_dir(dataset_id, root)
        if not hashes:
            echo(f"{dataset_id}: installed at {path} (not verified: the manifest records no hashes for it)")
            return path
        assert recorded is not None
        report = verify_installed(recorded, root)
        if not report.ok:
            raise InstallError(f"{dataset_id} is installed at {path} but does not match the manifest "
                               f"({report.problems[0]}); run: offdyn-bench datasets download {dataset_id} --force")
        echo(f"{dataset_id}: installed at {path}; {len(recorded.files or {})} files match the manifest's sha256")
        return path
    try:
        if configured_remote(remote):
            return _download(dataset_id, remote_url(remote), root, manifest, force, limits, progress, echo)
        return _rebuild(dataset_id, root, manifest, force, progress, echo)
    except InstallError:
        # Another process installed it while this one worked: use that copy if it verifies.
        if force or not hashes or not is_installed(dataset_id, root):
            raise
        assert recorded is not None
        if not verify_installed(recorded, root).ok:
            raise
        echo(f"{dataset_id}: installed meanwhile by another process at {dataset_dir(dataset_id, root)}; "
             f"{len(recorded.files or {})} files match the manifest's sha256")
        return dataset_dir(dataset_id, root)


def _download(dataset_id: str, base: str, root: pathlib.Path, manifest: Manifest, force: bool,
              limits: TransferLimits | None, progress: bool, echo: Callable[[str], None]) -> pathlib.Path:
    echo(f"{dataset_id}: downloading from {base}")
    with contextlib.ExitStack() as stack:
        update: list[Callable[[int], None]] = [lambda n: None]

        def start_bar(total: int) -> None:  # only once the entry is checked: no empty bar before an error
            update[0] = stack.enter_context(_progress_bar(progress, dataset_id, "B", total, unit_scale=True))

        path = download_dataset(dataset_id, remote=base, root=root, manifest=manifest, force=force,
                                on_bytes=lambda n: update[0](n), on_total=start_bar, say=echo, limits=limits)
    entry = manifest.entries.get(dataset_id)
    against = ("the manifest's sha256" if entry is not None and entry.is_built
               else "the sha256 of the remote's entry (the manifest records none for this dataset)")
    echo(f"{dataset_id}: downloaded from {base}; the archive and every file match {against}; installed at {path}")
    return path


def _rebuild(dataset_id: str, root: pathlib.Path, manifest: Manifest, force: bool, progress: bool,
             echo: Callable[[str], None]) -> pathlib.Path:
    entry = manifest.entry_or_default(dataset_id)
    recipe = entry.recipe
    no_remote = (f"No remote is configured either: set {REMOTE_ENV} (or pass --remote) to a remote that "
                 f"publishes {dataset_id} to download it instead")
    try:
        check_buildable(recipe)
    except MissingPolicyError as error:
        reason = str(error).removeprefix(f"{dataset_id}: ")
        raise DatasetUnavailableError(f"cannot rebuild {dataset_id}: {reason}. {no_remote}") from error
    verified = entry.files is not None
    echo(f"{dataset_id}: no remote configured ({REMOTE_ENV} unset); rebuilding it from its recipe "
         f"({recipe.num_transitions} transitions in the {recipe.collect_in} of {recipe.task})"
         + (", then checking every file against the manifest's sha256" if verified else
            "; the manifest records no hashes for it, so the result cannot be verified"))
    try:
        with _progress_bar(progress, dataset_id, "step", recipe.num_transitions) as update:
            result = build_dataset(recipe, root=root, recorded=entry if verified else None, replace=force,
                                   on_progress=update)
    except BuildMismatchError as error:
        raise DatasetUnavailableError(f"{error}. To get the published bytes, set {REMOTE_ENV} (or pass --remote) "
                                      "to a remote that publishes this dataset, or install the library versions "
                                      "the manifest records") from error
    assert result.installed_at is not None
    checked = (f"all {len(result.entry.files or {})} files match the manifest's sha256" if verified
               else "not verified (no recorded hashes)")
    echo(f"{dataset_id}: rebuilt from its recipe in {result.seconds:.1f} s; {checked}; installed at "
         f"{result.installed_at}")
    return result.installed_at


def load_installed(dataset_id: str, root: pathlib.Path | str | None = None) -> minari.MinariDataset:
    """The installed dataset as a ``minari.MinariDataset``. A missing or unreadable one is an
    :class:`InstallError` naming the command that installs it (never Minari's "Use
    download=True", which asks Minari's own servers)."""
    import minari

    check_id(dataset_id)
    root = resolve_root(root)
    clean_stale_staging(root)
    path = dataset_dir(dataset_id, root)
    if not is_installed(dataset_id, root):
        raise InstallError(f"dataset {dataset_id} is not installed (looked in {path}); {_install_hint(dataset_id)}")
    try:
        with minari_root(root):
            return minari.load_dataset(dataset_id)
    except Exception as error:  # Minari raises several kinds for a damaged dataset
        raise InstallError(f"dataset {dataset_id} at {path} cannot be read by Minari ({type(error).__name__}: "
                           f"{str(error)[:200]}); run: offdyn-bench datasets download {dataset_id} --force") from error


__all__ = ["ensure_dataset", "load_installed", "DatasetUnavailableError"]
