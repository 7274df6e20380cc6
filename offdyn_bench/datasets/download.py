"""Fetch a dataset from a remote, verify it, and install it atomically.

A remote is any URL prefix (``https://...``, ``http://...`` or ``file:///...``), set with
``OFFDYN_REMOTE`` or passed explicitly. It holds, per dataset id, the archive
``<id>.tar.gz`` and its manifest entry ``<id>.json``: the layout that ``offdyn-bench datasets
build --out DIR`` writes, so ``OFFDYN_REMOTE=file:///abs/DIR`` serves a local build.

Trust: when the shipped manifest records hashes for the id, the remote's entry must agree with
them; otherwise the remote's entry is used (and said so). The archive is checked against the
recorded sha256 and size while it streams in, unpacked into a staging directory refusing links
and paths outside it, every file is checked against its sha256, and only then is the dataset
renamed into place. Any failure (HTTP error, short read, checksum, unsafe member) raises a
:class:`DownloadError` and leaves nothing installed; running the command again starts afresh.
"""

from __future__ import annotations

import hashlib
import http.client
import json
import os
import pathlib
import re
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable

from offdyn_bench.datasets.archive import ArchiveError, compare_files, extract_archive
from offdyn_bench.datasets.install import install_tree, is_installed, resolve_root, staging, verify_installed
from offdyn_bench.datasets.manifest import Entry, Manifest, ManifestError, archive_name, entry_name, read_manifest
from offdyn_bench.errors import OffdynError

REMOTE_ENV = "OFFDYN_REMOTE"
_SAFE_ID = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")
_CHUNK = 1 << 16
_MAX_ENTRY_BYTES = 16 << 20
_TIMEOUT_S = 60


class DownloadError(OffdynError):
    """A download that failed; nothing was installed."""


def remote_url(remote: str | None = None) -> str:
    """The configured remote, checked for a supported scheme."""
    remote = remote or os.environ.get(REMOTE_ENV)
    if not remote:
        raise DownloadError(f"no remote configured: set {REMOTE_ENV} (an https://, http:// or file:// URL of a "
                            "folder written by `offdyn-bench datasets build --out`) or pass --remote")
    scheme = urllib.parse.urlsplit(remote).scheme
    if scheme not in ("http", "https", "file"):
        raise DownloadError(f"remote {remote!r} has scheme {scheme!r}; expected http://, https:// or file://")
    return remote.rstrip("/") + "/"


def _check_id(dataset_id: str) -> None:
    if not _SAFE_ID.fullmatch(dataset_id) or any(part in (".", "..") for part in dataset_id.split("/")):
        raise DownloadError(f"malformed dataset id {dataset_id!r}; expected e.g. "
                            "'offdyn/hopper-gravity-0p5/source-policy-v0'")


def _open(url: str):  # noqa: ANN202 - an http.client.HTTPResponse or a file-like for file://
    try:
        return urllib.request.urlopen(url, timeout=_TIMEOUT_S)  # noqa: S310 - scheme checked in remote_url
    except urllib.error.HTTPError as error:
        if error.code == 404:
            raise DownloadError(f"{url} not found on the remote (HTTP 404): is the dataset id right, and has "
                                "the remote been published with this dataset?") from error
        raise DownloadError(f"{url}: HTTP {error.code} {error.reason}") from error
    except (urllib.error.URLError, OSError) as error:
        reason = getattr(error, "reason", error)
        if isinstance(reason, FileNotFoundError):  # file:// remotes
            raise DownloadError(f"{url} not found on the remote: is the dataset id right, and has the remote "
                                "been published with this dataset?") from error
        raise DownloadError(f"cannot reach {url}: {reason}") from error


def fetch_entry(dataset_id: str, remote: str | None = None) -> Entry:
    """The manifest entry the remote publishes for ``dataset_id``."""
    _check_id(dataset_id)
    url = remote_url(remote) + entry_name(dataset_id)
    with _open(url) as response:
        try:
            body = response.read(_MAX_ENTRY_BYTES + 1)
        except (OSError, http.client.HTTPException) as error:
            raise DownloadError(f"download of {url} interrupted: {error}; nothing was installed") from error
    if len(body) > _MAX_ENTRY_BYTES:
        raise DownloadError(f"{url} is larger than {_MAX_ENTRY_BYTES} bytes; not a manifest entry")
    try:
        entry = Entry.from_dict(json.loads(body), where=url)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DownloadError(f"{url} is not a valid manifest entry: {error}") from error
    except ManifestError as error:
        raise DownloadError(str(error)) from error
    if entry.dataset_id != dataset_id:
        raise DownloadError(f"{url} describes {entry.dataset_id!r}, not {dataset_id!r}")
    if not entry.is_built:
        raise DownloadError(f"{url} has no archive or file hashes for {dataset_id}")
    return entry


def _expected_entry(dataset_id: str, remote_entry: Entry, shipped: Manifest,
                    say: Callable[[str], None]) -> Entry:
    if dataset_id in shipped and shipped.get(dataset_id).is_built:
        local = shipped.get(dataset_id)
        assert local.archive is not None and remote_entry.archive is not None
        if local.archive.sha256 != remote_entry.archive.sha256 or local.files != remote_entry.files:
            raise DownloadError(f"the remote's manifest for {dataset_id} disagrees with the manifest shipped with "
                                "offdyn-bench (different archive or file hashes); refusing to install. The remote "
                                "may hold another build; pass a matching --manifest if that is intended")
        return local
    say(f"{dataset_id} has no recorded hashes in the shipped manifest; verifying against the remote's manifest")
    return remote_entry


def _fetch_archive(url: str, target: pathlib.Path, expected_sha256: str, expected_size: int,
                   on_bytes: Callable[[int], None] | None) -> None:
    digest = hashlib.sha256()
    received = 0
    with _open(url) as response, open(target, "wb") as out:
        try:
            while True:
                block = response.read(_CHUNK)
                if not block:
                    break
                received += len(block)
                if received > expected_size:
                    raise DownloadError(f"{url} is larger than the {expected_size} bytes the manifest records; "
                                        "nothing was installed")
                digest.update(block)
                out.write(block)
                if on_bytes is not None:
                    on_bytes(len(block))
        except (OSError, http.client.HTTPException) as error:
            raise DownloadError(f"download of {url} interrupted after {received} of {expected_size} bytes "
                                f"({type(error).__name__}: {error}); nothing was installed, run the command "
                                "again") from error
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
                     say: Callable[[str], None] = lambda message: None) -> pathlib.Path:
    """Download, verify and install ``dataset_id``; returns where it was installed.

    ``manifest`` is the trusted manifest (default: the shipped ``assets/datasets.json``).
    An installed dataset is left alone unless ``force``; its files are verified first.
    """
    _check_id(dataset_id)
    root = resolve_root(root)
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
    entry = _expected_entry(dataset_id, fetch_entry(dataset_id, base), shipped, say)
    assert entry.archive is not None and entry.files is not None
    if on_total is not None:
        on_total(entry.archive.size)
    with staging(root) as work:
        archive_path = work / "archive.tar.gz"
        _fetch_archive(base + archive_name(dataset_id), archive_path, entry.archive.sha256, entry.archive.size,
                       on_bytes)
        unpacked = work / "dataset"
        try:
            files = extract_archive(archive_path, unpacked)
        except ArchiveError as error:
            raise DownloadError(f"{dataset_id}: {error}; nothing was installed") from error
        problems = compare_files(entry.files, files)
        if problems:
            raise DownloadError(f"{dataset_id}: unpacked files do not match the manifest ({'; '.join(problems[:3])}); "
                                "nothing was installed")
        return install_tree(unpacked, dataset_id, root=root, replace=force)
