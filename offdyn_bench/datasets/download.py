"""Fetch a dataset from a remote, verify it, and install it atomically.

A remote is any URL prefix (``https://...``, ``http://...`` or ``file:///...``), set with
``OFFDYN_REMOTE`` or passed explicitly. It holds, per dataset id, the archive
``<id>.tar.gz`` and its manifest entry ``<id>.json``: the layout that ``offdyn-bench datasets
build --out DIR`` writes, so ``OFFDYN_REMOTE=file:///abs/DIR`` serves a local build.

Trust: when the shipped manifest records hashes for the id, the remote's entry must agree with
them; otherwise the remote's entry is used (and said so). The archive is checked against the
recorded sha256 and size while it streams in, unpacked into a staging directory refusing links
and paths outside it, every file is checked against its sha256, and only then is the dataset
renamed into place. A remote that is not pinned by the shipped manifest must declare every
file's size (``file_sizes``, written by ``build``): extraction refuses a member the entry does
not list, or one larger than declared, before writing anything. Every read has an overall
deadline and a minimum rate (``transfer.py``). Any failure (HTTP error, garbage reply, short or
slow read, checksum, unsafe member) raises a :class:`DownloadError` and leaves nothing
installed; running the command again starts afresh.
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
import re
import urllib.parse
from collections.abc import Callable

from offdyn_bench.datasets.archive import ArchiveError, compare_files, extract_archive
from offdyn_bench.datasets.install import install_tree, is_installed, resolve_root, verify_installed
from offdyn_bench.datasets.manifest import Entry, Manifest, ManifestError, archive_name, entry_name, read_manifest
from offdyn_bench.datasets.staging import clean_stale_staging, staging
from offdyn_bench.datasets.transfer import TransferError, TransferLimits, open_remote
from offdyn_bench.errors import OffdynError

REMOTE_ENV = "OFFDYN_REMOTE"
_SAFE_ID = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")
_MAX_ENTRY_BYTES = 16 << 20


class DownloadError(OffdynError):
    """A download that failed; nothing was installed."""


def configured_remote(remote: str | None = None) -> str | None:
    """``remote``, else ``$OFFDYN_REMOTE``, else None (no remote: datasets are rebuilt)."""
    return remote or os.environ.get(REMOTE_ENV) or None


def remote_url(remote: str | None = None) -> str:
    """The configured remote, checked for a supported scheme."""
    remote = configured_remote(remote)
    if not remote:
        raise DownloadError(f"no remote configured: set {REMOTE_ENV} (an https://, http:// or file:// URL of a "
                            "folder written by `offdyn-bench datasets build --out`) or pass --remote")
    scheme = urllib.parse.urlsplit(remote).scheme
    if scheme not in ("http", "https", "file"):
        raise DownloadError(f"remote {remote!r} has scheme {scheme!r}; expected http://, https:// or file://")
    return remote.rstrip("/") + "/"


def check_id(dataset_id: str) -> None:
    """Refuse an id that could name a path outside the datasets root or the remote."""
    if not isinstance(dataset_id, str) or not _SAFE_ID.fullmatch(dataset_id) \
            or any(part in (".", "..") for part in dataset_id.split("/")):
        raise DownloadError(f"malformed dataset id {dataset_id!r}; expected e.g. "
                            "'offdyn/hopper-gravity-0p5/source-policy-v0'")


def parse_entry(body: bytes, dataset_id: str, where: str) -> Entry:
    """The manifest entry in ``body`` (a remote's ``<id>.json``), checked to describe
    ``dataset_id`` and a built dataset; any other bytes are a :class:`DownloadError`."""
    try:
        data = json.loads(body)
    except (ValueError, RecursionError) as error:  # bad JSON, bad UTF-8, huge integers, deep nesting
        raise DownloadError(f"{where} is not a valid manifest entry for {dataset_id} ({type(error).__name__}: "
                            f"{str(error)[:200]}); expected the JSON object `datasets build --out` writes") from None
    try:
        entry = Entry.from_dict(data, where=f"{where} (entry for {dataset_id})")
    except ManifestError as error:
        raise DownloadError(str(error)) from error
    if entry.dataset_id != dataset_id:
        raise DownloadError(f"{where} describes {entry.dataset_id!r}, not {dataset_id!r}")
    if not entry.is_built:
        raise DownloadError(f"{where} has no archive or file hashes for {dataset_id}")
    return entry


def fetch_entry(dataset_id: str, remote: str | None = None, limits: TransferLimits | None = None) -> Entry:
    """The manifest entry the remote publishes for ``dataset_id``."""
    check_id(dataset_id)
    url = remote_url(remote) + entry_name(dataset_id)
    body = bytearray()
    try:
        with open_remote(url, limits) as remote_file:
            for block in remote_file.chunks():
                body += block
                if len(body) > _MAX_ENTRY_BYTES:
                    raise DownloadError(f"{url} is larger than {_MAX_ENTRY_BYTES} bytes; not a manifest entry")
    except TransferError as error:
        raise DownloadError(str(error)) from error
    return parse_entry(bytes(body), dataset_id, url)


def _expected_entry(dataset_id: str, remote_entry: Entry, shipped: Manifest,
                    say: Callable[[str], None]) -> tuple[Entry, bool]:
    """The entry to check the download against, and whether the shipped manifest pins it."""
    if dataset_id in shipped and shipped.get(dataset_id).is_built:
        local = shipped.get(dataset_id)
        assert local.archive is not None and remote_entry.archive is not None
        if local.archive.sha256 != remote_entry.archive.sha256 or local.files != remote_entry.files:
            raise DownloadError(f"the remote's manifest for {dataset_id} disagrees with the manifest shipped with "
                                "offdyn-bench (different archive or file hashes); refusing to install. The remote "
                                "may hold another build; pass a matching --manifest if that is intended")
        return local, True
    if remote_entry.file_sizes is None:
        raise DownloadError(f"the remote's entry for {dataset_id} declares no file sizes, and the shipped manifest "
                            "does not pin this dataset: its archive could unpack to any size, so it is refused. "
                            "Republish the remote with this version (`offdyn-bench datasets build --out DIR`), or "
                            "pass --manifest with a manifest that records this dataset's hashes")
    say(f"{dataset_id} has no recorded hashes in the shipped manifest; verifying against the remote's manifest")
    return remote_entry, False


def _fetch_archive(url: str, target: pathlib.Path, expected_sha256: str, expected_size: int,
                   on_bytes: Callable[[int], None] | None, limits: TransferLimits | None) -> None:
    digest = hashlib.sha256()
    received = 0
    try:
        with open_remote(url, limits) as remote_file, open(target, "wb") as out:
            for block in remote_file.chunks():
                received += len(block)
                if received > expected_size:
                    raise DownloadError(f"{url} is larger than the {expected_size} bytes the manifest records; "
                                        "nothing was installed")
                digest.update(block)
                out.write(block)
                if on_bytes is not None:
                    on_bytes(len(block))
    except TransferError as error:
        raise DownloadError(f"{error} (after {received} of {expected_size} bytes)") from error
    if received != expected_size:
        raise DownloadError(f"download of {url} interrupted: got {received} of {expected_size} bytes; nothing was "
                            "installed, run the command again")
    if digest.hexdigest() != expected_sha256:
        raise DownloadError(f"checksum mismatch for {url}: sha256 {digest.hexdigest()}, the manifest records "
                            f"{expected_sha256}; nothing was installed")


def download_dataset(dataset_id: str, *, remote: str | None = None, root: pathlib.Path | None = None,
                     manifest: Manifest | None = None, force: bool = False,
                     on_bytes: Callable[[int], None] | None = None,
                     on_total: Callable[[int], None] | None = None,
                     say: Callable[[str], None] = lambda message: None,
                     limits: TransferLimits | None = None) -> pathlib.Path:
    """Download, verify and install ``dataset_id``; returns where it was installed.

    ``manifest`` is the trusted manifest (default: the shipped ``assets/datasets.json``).
    An installed dataset is left alone unless ``force``; its files are verified first.
    ``limits`` bound each remote file's time and rate (default: from the environment).
    ``on_total`` is called once the archive's size is known, before its first byte.
    """
    check_id(dataset_id)
    root = resolve_root(root)
    clean_stale_staging(root)
    shipped = manifest if manifest is not None else read_manifest()
    if is_installed(dataset_id, root) and not force:
        if dataset_id in shipped and shipped.get(dataset_id).is_built:
            report = verify_installed(shipped.get(dataset_id), root)
            if not report.ok:
                raise DownloadError(f"{dataset_id} is installed but does not verify ({report.problems[0]}); "
                                    "pass --force to replace it")
        say(f"{dataset_id} is already installed at {root / dataset_id}")
        return root / dataset_id
    base = remote_url(remote)
    limits = limits if limits is not None else TransferLimits.from_environment()
    entry, pinned = _expected_entry(dataset_id, fetch_entry(dataset_id, base, limits), shipped, say)
    assert entry.archive is not None and entry.files is not None
    if on_total is not None:
        on_total(entry.archive.size)
    with staging(root) as work:
        archive_path = work / "archive.tar.gz"
        _fetch_archive(base + archive_name(dataset_id), archive_path, entry.archive.sha256, entry.archive.size,
                       on_bytes, limits)
        unpacked = work / "dataset"
        try:
            # A pinned archive's bytes are the ones the shipped manifest records, so its own
            # headers bound it; an unpinned one is held to the sizes its entry declares.
            files = extract_archive(archive_path, unpacked, expected=entry.files,
                                    sizes=entry.file_sizes if not pinned or entry.file_sizes else None)
        except ArchiveError as error:
            raise DownloadError(f"{dataset_id}: {error}; nothing was installed") from error
        problems = compare_files(entry.files, files)
        if problems:
            raise DownloadError(f"{dataset_id}: unpacked files do not match the manifest ({'; '.join(problems[:3])}); "
                                "nothing was installed")
        return install_tree(unpacked, dataset_id, root=root, replace=force)
