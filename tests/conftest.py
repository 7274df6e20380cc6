"""Every test gets its own Minari root and dataset remote: nothing reads or writes ~/.minari and
nothing goes to the internet."""

from __future__ import annotations

import pathlib

import pytest


@pytest.fixture(autouse=True)
def isolated_paths(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> pathlib.Path:
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    # A remote that does not exist: a test that forgets to set its own fails instead of going out.
    monkeypatch.setenv("OFFDYN_REMOTE", (tmp_path / "no-remote-configured").as_uri())
    return root
