"""Versions recorded with every dataset and result: numbers depend on them."""

from __future__ import annotations

import platform
from importlib import metadata

__version__ = "0.1.0"

# The MuJoCo version the suite is pinned to (pyproject.toml); results from another one are
# not comparable, so it is written next to every stored number.
PINNED_MUJOCO = "3.17.0"


def _installed(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def versions() -> dict[str, str | None]:
    """The versions of the suite and the libraries its numbers depend on."""
    import mujoco

    return {
        "offdyn_bench": __version__,
        "mujoco": mujoco.__version__,
        "gymnasium": _installed("gymnasium"),
        "minari": _installed("minari"),
        "torch": _installed("torch"),
        "numpy": _installed("numpy"),
        "python": platform.python_version(),
    }
