"""Staging directories that outlive no one, and a replace that a kill cannot half-do.

Builds and downloads assemble a dataset under ``<datasets root>/.offdyn-staging/`` (same file
system as the install, so the final move is one rename). Each staging directory is named after
its owner: ``<host hash>.<pid>.<process start time>.<random>``. A process killed with
``kill -9`` cannot remove its own; the next build, download, verify or list removes every
staging directory whose owner is gone (the pid no longer runs, or runs a process started at
another time), and leaves alone those of live processes and of other hosts sharing the root.
Directories without an owner in their name (older versions' ``tmp*``) go once a day old.

Replacing an installed dataset (``--force``) swaps the two directories with one
``renameat2(RENAME_EXCHANGE)`` on Linux. Where that is unavailable it takes two renames (the
old copy aside, the new one in), after writing a journal in its own staging directory; a kill
between them is undone by that same cleanup, which puts the old copy back.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import hashlib
import json
import os
import pathlib
import re
import shutil
import socket
import sys
import tempfile
import time
from collections.abc import Iterator

STAGING_DIR = ".offdyn-staging"  # hidden: Minari's listing skips names starting with "."
REPLACE_JOURNAL = "replace.json"
_ASIDE = "replaced"
_LEGACY_STALE_S = 24 * 3600
_OWNER = re.compile(r"^(?P<host>[0-9a-f]{8})\.(?P<pid>[0-9]+)\.(?P<start>[0-9]+)\.")


def _host_tag() -> str:
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def _process_start(pid: int) -> str | None:
    """When ``pid`` started (clock ticks since boot, from /proc), "0" where /proc is not
    there, and None when no such process runs (or it is a zombie: it will never clean up)."""
    try:
        stat = pathlib.Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        if pathlib.Path("/proc/self/stat").exists():
            return None
        if os.name == "nt":
            return "0"  # os.kill would terminate it there: assume it runs, never clean it up
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass
        return "0"
    except OSError:
        return "0"
    fields = stat.rsplit(")", 1)[-1].split()  # the command name may hold spaces and parentheses
    return None if fields[0] in ("Z", "X") else fields[19]


def owner_tag() -> str:
    """This process's prefix for staging directory names."""
    return f"{_host_tag()}.{os.getpid()}.{_process_start(os.getpid()) or '0'}."


def _is_stale(path: pathlib.Path, now: float) -> bool:
    match = _OWNER.match(path.name)
    if match is None:
        with contextlib.suppress(OSError):
            return now - path.lstat().st_mtime > _LEGACY_STALE_S
        return False
    if match["host"] != _host_tag():
        return False  # another machine's process, which this one cannot see
    pid = int(match["pid"])
    if pid <= 0:
        return True
    started = _process_start(pid)
    return started is None or (match["start"] != "0" and started != "0" and started != match["start"])


def _recover(work: pathlib.Path) -> None:
    """Undo a replace that stopped between its two renames: put the old copy back."""
    journal = work / REPLACE_JOURNAL
    if not journal.is_file():
        return
    try:
        final = pathlib.Path(json.loads(journal.read_text())["final"])
    except (OSError, ValueError, KeyError, TypeError):
        return  # written before the first rename, so nothing was moved yet
    aside = work / _ASIDE
    if aside.is_dir() and not final.exists():
        os.rename(aside, final)
    journal.unlink(missing_ok=True)


def clean_stale_staging(root: pathlib.Path) -> list[pathlib.Path]:
    """Recover and remove the staging directories of processes that are gone; returns what was
    removed. Creates nothing (a missing staging area is left missing)."""
    base = root / STAGING_DIR
    try:
        children = sorted(base.iterdir())
    except OSError:
        return []
    removed = []
    now = time.time()
    for child in children:
        if not child.is_dir() or child.is_symlink() or not _is_stale(child, now):
            continue
        # Claim it with one rename, so two processes cleaning at once never both recover it.
        claimed = base / f"{owner_tag()}claimed-{child.name[-24:]}"
        try:
            os.rename(child, claimed)
        except OSError:
            continue  # another process claimed it first
        _recover(claimed)
        shutil.rmtree(claimed, ignore_errors=True)
        removed.append(child)
    with contextlib.suppress(OSError):
        base.rmdir()  # only when empty
    return removed


@contextlib.contextmanager
def staging(root: pathlib.Path) -> Iterator[pathlib.Path]:
    """A fresh directory under the datasets root, owned by this process and removed on exit
    whatever happens (stale ones of dead processes are removed on entry)."""
    clean_stale_staging(root)
    base = root / STAGING_DIR
    for attempt in range(100):
        base.mkdir(parents=True, exist_ok=True)
        try:
            path = pathlib.Path(tempfile.mkdtemp(prefix=owner_tag(), dir=base))
            break
        except FileNotFoundError:
            # Another process's cleanup removed the (then empty) staging area between our
            # mkdir and mkdtemp: make it again.
            if attempt == 99:
                raise
    try:
        yield path
    finally:
        _recover(path)
        shutil.rmtree(path, ignore_errors=True)
        with contextlib.suppress(OSError):
            base.rmdir()  # only when empty: another install may be staging beside us


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def exchange(first: pathlib.Path, second: pathlib.Path) -> bool:
    """Swap two paths atomically (Linux ``renameat2(RENAME_EXCHANGE)``); False where the
    platform, libc or file system cannot, so the caller falls back to two renames."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False  # a libc older than glibc 2.28
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    renameat2.restype = ctypes.c_int
    if renameat2(_AT_FDCWD, os.fsencode(first), _AT_FDCWD, os.fsencode(second), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(code, os.strerror(code), str(first), None, str(second))


def _between_renames() -> None:
    """Nothing; a test puts a kill here to check that the next start recovers."""


def replace_directory(new: pathlib.Path, final: pathlib.Path, root: pathlib.Path) -> None:
    """Put ``new`` at ``final`` (which exists) so that an observer, or a process killed at any
    point, finds a complete dataset there: the old one or the new one."""
    with staging(root) as work:
        if exchange(new, final):
            shutil.rmtree(new, ignore_errors=True)  # the old copy, now at the new one's path
            return
        journal = work / REPLACE_JOURNAL
        partial = work / (REPLACE_JOURNAL + ".partial")
        partial.write_text(json.dumps({"final": str(final)}))
        os.replace(partial, journal)
        os.rename(final, work / _ASIDE)
        _between_renames()
        try:
            os.rename(new, final)
        except OSError:
            _recover(work)
            raise
        journal.unlink()
        # staging's exit removes the old copy with the work directory
