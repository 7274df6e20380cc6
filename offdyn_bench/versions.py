"""Versions recorded with every dataset and result: numbers depend on them."""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

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


def source_revision() -> dict[str, Any] | None:
    """The git commit of the suite's own code, when it runs from a git checkout: ``{"commit": <sha>,
    "modified": <whether tracked files differ from it>}``. None when the code is installed from a
    package (it has no git work tree of its own), or git is missing or fails: "unknown", never a guess.

    The package version stays 0.1.0 between releases, so only the commit says which code trained a
    published number."""
    package = Path(__file__).resolve().parent

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(package), *args], capture_output=True, text=True, timeout=30,
                                  check=False)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    # A copy installed into a virtual environment inside some repository is not that repository's
    # code: the package must sit at the top of the work tree that git finds.
    if top is None or Path(top).resolve() / package.name != package:
        return None
    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no")
    if commit is None or status is None:
        return None
    return {"commit": commit, "modified": bool(status)}


def utc_now() -> str:
    """The current time in UTC, to the second (ISO 8601): when a record's numbers were computed."""
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


# Instruction sets whose presence changes which kernels MKL, OpenBLAS, oneDNN and ATen pick, and
# with them the last bits of a float: the same seed trains another policy on another CPU model
# (PROTOCOL.md §8). Recorded, never used to decide anything.
_ISA_FLAGS = ("sse4_2", "avx", "fma", "avx2", "avx512f", "avx512_vnni", "avx512_bf16", "amx_tile")
# Environment variables that pin or change those kernels.
NUMERICS_ENVIRONMENT = ("MKL_CBWR", "MKL_ENABLE_INSTRUCTIONS", "MKL_DEBUG_CPU_TYPE", "ATEN_CPU_CAPABILITY",
                        "DNNL_MAX_CPU_ISA", "ONEDNN_MAX_CPU_ISA", "OPENBLAS_CORETYPE")


def _read_cpuinfo() -> tuple[str | None, frozenset[str]]:
    """The first CPU's model name and all its flags from ``/proc/cpuinfo`` (None and none where it
    cannot be read)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as cpuinfo:
            text = cpuinfo.read()
    except OSError:
        return None, frozenset()
    model, flags = None, frozenset()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and model is None:
            model = value.strip()
        elif key.strip() == "flags" and not flags:
            flags = frozenset(value.split())
    return model, flags


def cpu_flags() -> frozenset[str]:
    """Every instruction-set flag of the CPU (Linux; empty elsewhere)."""
    return _read_cpuinfo()[1]


def _cpu_info() -> tuple[str | None, list[str]]:
    """The CPU's model name and its instruction sets among ``_ISA_FLAGS`` (Linux; elsewhere what
    ``platform`` says and no flags)."""
    model, flags = _read_cpuinfo()
    return model or platform.processor() or None, [flag for flag in _ISA_FLAGS if flag in flags]


def machine(device: str = "cpu") -> dict[str, Any]:
    """Where a number was computed, as far as it changes floating-point results: the CPU model, its
    vector instruction sets, the kernels torch and numpy dispatch to, torch's thread count, and the
    environment variables that pin them; for a CUDA ``device`` (``cuda``, ``cuda:N``) also the GPU
    (:func:`cuda_device`). Records carry it beside :func:`versions`."""
    import numpy
    import torch

    cpu, isa = _cpu_info()
    try:
        simd = numpy.show_config(mode="dicts")["SIMD Extensions"]["found"]
    except (TypeError, KeyError, AttributeError):
        simd = None
    return {
        "cpu": cpu,
        "architecture": platform.machine(),
        "isa": isa,
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch_threads": torch.get_num_threads(),
        "numpy_simd": list(simd) if simd is not None else None,
        "numerics_environment": {name: os.environ[name] for name in NUMERICS_ENVIRONMENT if name in os.environ},
    } | ({"cuda": cuda_device(device)} if device.startswith("cuda") else {})


def cuda_device(device: str) -> dict[str, Any]:
    """The GPU behind a torch CUDA ``device``: its model and compute capability, the CUDA and cuDNN
    versions torch was built with, and the ``CUDA_VISIBLE_DEVICES`` the process was given (a
    scheduler such as Ray sets it to the GPUs it assigned the task), so a CUDA number says which
    card computed it. CPU records never carry this: asking would initialise CUDA."""
    import torch

    index = torch.device(device).index
    index = torch.cuda.current_device() if index is None else index
    properties = torch.cuda.get_device_properties(index)
    cudnn = torch.backends.cudnn.version() if torch.backends.cudnn.is_available() else None
    return {
        "name": properties.name,
        "capability": f"{properties.major}.{properties.minor}",
        "memory_gib": round(properties.total_memory / 2**30, 1),
        "index": index,
        "visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES"),
        "cuda": torch.version.cuda,
        "cudnn": cudnn,
    }
