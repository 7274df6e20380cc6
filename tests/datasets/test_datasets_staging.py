"""Staging left by killed processes is cleaned by the next run (and never a live process's),
and a replace killed between its two renames is recovered to a complete install."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import textwrap
import time

import pytest

from offdyn_bench.datasets import staging as staging_module
from offdyn_bench.datasets.install import install_tree, is_installed
from offdyn_bench.datasets.staging import STAGING_DIR, clean_stale_staging, exchange, owner_tag, staging

DATASET_ID = "offdyn/hopper-gravity-0p5/random-v0"
REPO = pathlib.Path(__file__).resolve().parents[2]


def fake_dataset(path: pathlib.Path, content: str) -> pathlib.Path:
    (path / "data").mkdir(parents=True)
    (path / "data" / "metadata.json").write_text(content)
    (path / "data" / "main_data.hdf5").write_text(content * 100)
    return path


def installed_content(root: pathlib.Path) -> str:
    return (root / DATASET_ID / "data" / "metadata.json").read_text()


def staging_entries(root: pathlib.Path) -> list[str]:
    base = root / STAGING_DIR
    return sorted(p.name for p in base.iterdir()) if base.exists() else []


def start_python(code: str, root: pathlib.Path) -> subprocess.Popen:
    """A child interpreter running ``code`` with ``root`` as ``sys.argv[1]``; it prints a line
    once it has staged something."""
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code), str(root)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


HOLD_STAGING = """
    import pathlib, sys, time
    from offdyn_bench.datasets.staging import staging
    with staging(pathlib.Path(sys.argv[1])) as work:
        (work / "partial.hdf5").write_bytes(b"x" * 4096)
        print(work.name, flush=True)
        time.sleep(120)
"""


@pytest.mark.timeout(120)
def test_staging_of_a_killed_process_is_removed_and_a_live_ones_kept(tmp_path: pathlib.Path) -> None:
    root = tmp_path / "root"
    killed, alive = start_python(HOLD_STAGING, root), start_python(HOLD_STAGING, root)
    try:
        killed_dir, alive_dir = killed.stdout.readline().strip(), alive.stdout.readline().strip()
        if not (killed_dir and alive_dir):  # a child failed: stop both before reading why
            for child in (killed, alive):
                child.kill()
            pytest.fail("a child did not stage: " + killed.communicate()[1] + alive.communicate()[1])
        killed.kill()  # SIGKILL: no finally block runs
        killed.wait()
        assert sorted([killed_dir, alive_dir]) == staging_entries(root)  # what the bug left forever
        removed = clean_stale_staging(root)
        assert [p.name for p in removed] == [killed_dir]
        assert staging_entries(root) == [alive_dir]
        with staging(root) as mine:  # entering staging cleans too, and keeps the live one
            assert sorted(staging_entries(root)) == sorted([alive_dir, mine.name])
    finally:
        alive.kill()
        alive.wait()
    clean_stale_staging(root)
    assert not (root / STAGING_DIR).exists()


def test_owner_checks_pid_start_time_host_and_age(tmp_path: pathlib.Path) -> None:
    base = tmp_path / STAGING_DIR
    host, pid, start = owner_tag().split(".")[:3]
    names = {
        "mine": f"{owner_tag()}live",
        "reused-pid": f"{host}.{pid}.{int(start) + 1}.other",  # same pid, another process's start time
        "other-host": f"{'0' * 8 if host != '0' * 8 else '1' * 8}.1.1.remote",
        "legacy-old": "tmpold",
        "legacy-new": "tmpnew",
    }
    for name in names.values():
        (base / name).mkdir(parents=True)
    day_ago = time.time() - 2 * 24 * 3600
    os.utime(base / names["legacy-old"], (day_ago, day_ago))
    removed = {p.name for p in clean_stale_staging(tmp_path)}
    assert removed == {names["reused-pid"], names["legacy-old"]}
    assert set(staging_entries(tmp_path)) == {names["mine"], names["other-host"], names["legacy-new"]}


def test_cleaning_creates_nothing(tmp_path: pathlib.Path) -> None:
    assert clean_stale_staging(tmp_path / "absent") == []
    assert not (tmp_path / "absent").exists()


def test_exchange_swaps_two_directories(tmp_path: pathlib.Path) -> None:
    first, second = fake_dataset(tmp_path / "a", "A"), fake_dataset(tmp_path / "b", "B")
    if not exchange(first, second):
        pytest.skip("renameat2(RENAME_EXCHANGE) is not available here; the journaled replace is tested below")
    assert (first / "data" / "metadata.json").read_text() == "B"
    assert (second / "data" / "metadata.json").read_text() == "A"


def test_force_replace_uses_the_exchange(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> None:
    probe_a, probe_b = fake_dataset(tmp_path / "pa", "A"), fake_dataset(tmp_path / "pb", "B")
    if not exchange(probe_a, probe_b):
        pytest.skip("renameat2(RENAME_EXCHANGE) is not available here")
    monkeypatch.setattr(staging_module, "_between_renames", lambda: pytest.fail("took the two-rename path"))
    root = tmp_path / "root"
    fake_dataset(root / DATASET_ID, "old")
    with staging(root) as work:
        install_tree(fake_dataset(work / "dataset", "new"), DATASET_ID, root=root, replace=True)
    assert installed_content(root) == "new"
    assert staging_entries(root) == []


class Interrupted(BaseException):
    """Stands for a Ctrl-C between the two renames."""


def test_an_interrupt_between_the_renames_puts_the_old_copy_back(tmp_path: pathlib.Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(staging_module, "exchange", lambda first, second: False)

    def interrupt() -> None:
        assert not (root / DATASET_ID).exists()  # the moment the bug stranded the old copy
        raise Interrupted

    monkeypatch.setattr(staging_module, "_between_renames", interrupt)
    root = tmp_path / "root"
    fake_dataset(root / DATASET_ID, "old")
    with pytest.raises(Interrupted), staging(root) as work:
        install_tree(fake_dataset(work / "dataset", "new"), DATASET_ID, root=root, replace=True)
    assert installed_content(root) == "old" and is_installed(DATASET_ID, root)
    assert staging_entries(root) == []


KILLED_BETWEEN_RENAMES = """
    import os, pathlib, sys
    from offdyn_bench.datasets import staging as staging_module
    from offdyn_bench.datasets.install import install_tree
    staging_module.exchange = lambda first, second: False  # the two-rename path
    staging_module._between_renames = lambda: os._exit(9)  # killed: no cleanup runs
    root = pathlib.Path(sys.argv[1])
    with staging_module.staging(root) as work:
        new = work / "dataset" / "data"
        new.mkdir(parents=True)
        (new / "metadata.json").write_text("new")
        install_tree(work / "dataset", "offdyn/hopper-gravity-0p5/random-v0", root=root, replace=True)
"""


@pytest.mark.timeout(120)
def test_a_kill_between_the_renames_is_recovered_on_the_next_start(tmp_path: pathlib.Path) -> None:
    root = tmp_path / "root"
    fake_dataset(root / DATASET_ID, "old")
    child = start_python(KILLED_BETWEEN_RENAMES, root)
    _, stderr = child.communicate()
    assert child.returncode == 9, stderr
    assert not (root / DATASET_ID).exists()  # the stranded state the bug left forever
    clean_stale_staging(root)  # what the next build, download, verify, list or load runs first
    assert installed_content(root) == "old" and is_installed(DATASET_ID, root)
    assert (root / DATASET_ID / "data" / "main_data.hdf5").read_text() == "old" * 100
    assert not (root / STAGING_DIR).exists()
