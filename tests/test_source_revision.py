"""Which code computed a number: the suite's git commit where it runs from a checkout, and
"unknown" (None) everywhere else, never another repository's commit."""

from __future__ import annotations

import datetime
import importlib.util
import shutil
import subprocess
from pathlib import Path

import pytest

import offdyn_bench
from offdyn_bench.versions import source_revision, utc_now

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")

PACKAGE = Path(offdyn_bench.__file__).resolve().parent


def _git(where: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(where), *args], check=True, capture_output=True, text=True).stdout.strip()


def _versions_module_at(package_dir: Path):
    """``offdyn_bench/versions.py`` loaded from a copy under ``package_dir`` (its own ``__file__``)."""
    package_dir.mkdir(parents=True, exist_ok=True)
    shutil.copy(PACKAGE / "versions.py", package_dir / "versions.py")
    name = f"versions_copy_{abs(hash(package_dir))}"
    spec = importlib.util.spec_from_file_location(name, package_dir / "versions.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _repository(root: Path) -> Path:
    root.mkdir()
    _git(root, "init", "-q")
    _git(root, "config", "user.email", "ci@example.invalid")
    _git(root, "config", "user.name", "ci")
    return root


def test_the_checkout_in_use_reports_its_head_commit():
    try:
        head = _git(PACKAGE.parent, "rev-parse", "HEAD")
    except subprocess.CalledProcessError:
        pytest.skip("the suite under test is not a git checkout (installed from a package)")
    revision = source_revision()
    assert revision is not None and revision["commit"] == head
    assert revision["modified"] == bool(_git(PACKAGE.parent, "status", "--porcelain", "--untracked-files=no"))


def test_a_commit_and_whether_tracked_files_changed_since(tmp_path):
    root = _repository(tmp_path / "clone")
    versions = _versions_module_at(root / "offdyn_bench")
    _git(root, "add", "-A")
    _git(root, "commit", "-q", "-m", "first")
    assert versions.source_revision() == {"commit": _git(root, "rev-parse", "HEAD"), "modified": False}
    (root / "notes.txt").write_text("untracked files are not the code")
    assert versions.source_revision()["modified"] is False
    with open(root / "offdyn_bench" / "versions.py", "a") as edited:
        edited.write("\n# an edit\n")
    assert versions.source_revision()["modified"] is True


def test_a_copy_installed_inside_another_repository_is_not_that_repositorys_code(tmp_path):
    """pip install into a .venv inside some project: git finds the project, whose commit says
    nothing about the installed copy."""
    root = _repository(tmp_path / "project")
    (root / "README").write_text("x")
    _git(root, "add", "-A")
    _git(root, "commit", "-q", "-m", "first")
    installed = _versions_module_at(root / ".venv" / "lib" / "python3.11" / "site-packages" / "offdyn_bench")
    assert installed.source_revision() is None


def test_outside_any_repository_or_without_git_it_is_unknown(tmp_path, monkeypatch):
    assert _versions_module_at(tmp_path / "site-packages" / "offdyn_bench").source_revision() is None
    monkeypatch.setenv("PATH", str(tmp_path / "no-tools-here"))
    assert source_revision() is None


def test_times_are_utc_to_the_second():
    stamp = datetime.datetime.fromisoformat(utc_now())
    assert stamp.utcoffset() == datetime.timedelta(0) and stamp.microsecond == 0
    assert abs((datetime.datetime.now(datetime.UTC) - stamp).total_seconds()) < 5
