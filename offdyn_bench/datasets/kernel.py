"""The matrix kernel dataset builds run on, so that a rebuild gives the manifest's bytes on any x86-64 CPU.

A behaviour policy's actions are numpy matrix-vector products (:class:`~offdyn_bench.datasets.policies.MLPPolicy`),
which numpy hands to OpenBLAS. OpenBLAS picks a kernel for the CPU it finds: ``SkylakeX`` on an
AVX-512 Intel Xeon, ``Haswell`` on AVX2 processors. The kernels sum in different
orders, so the same weights give actions that differ in the last bits, and a contact-rich robot
turns that into another trajectory within a few hundred steps: Ant's source-policy datasets rebuilt
on an AVX-512 Xeon differ from the manifest, while Hopper's, with fewer contacts, still match.

Every manifest dataset was built on OpenBLAS's ``Haswell`` kernel (:data:`DATASET_BLAS_KERNEL`),
which any x86-64 CPU with AVX2 and FMA runs. OpenBLAS fixes its kernel when numpy loads it, from
``OPENBLAS_CORETYPE``, so a build that finds another kernel loaded runs in a child Python process
started with that variable set (:func:`call_on_kernel`). ``OFFDYN_BLAS_KERNEL`` names another kernel
to build on, or ``native`` for whatever numpy loaded; neither reproduces the manifest.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import pathlib
import pickle
import platform
import struct
import subprocess
import sys
import time
import traceback
from collections.abc import Callable, Mapping
from typing import IO, Any

from offdyn_bench.errors import OffdynError
from offdyn_bench.versions import cpu_flags

DATASET_BLAS_KERNEL = "Haswell"
KERNEL_ENV = "OFFDYN_BLAS_KERNEL"
NATIVE = "native"
OPENBLAS_ENV = "OPENBLAS_CORETYPE"

# The instruction sets each x86-64 OpenBLAS kernel executes: a CPU without them cannot be pinned to it.
KERNEL_NEEDS: Mapping[str, tuple[str, ...]] = {
    "Nehalem": ("sse4_2",),
    "Sandybridge": ("avx",),
    "Haswell": ("avx2", "fma"),
    "SkylakeX": ("avx512f", "avx512bw", "avx512vl", "avx512dq"),
    "Cooperlake": ("avx512f", "avx512bw", "avx512vl", "avx512dq", "avx512_bf16"),
}
_PROGRESS_INTERVAL_S = 0.1


class KernelError(OffdynError):
    """A build that cannot run on the kernel it asks for, or whose child process failed."""


@dataclasses.dataclass(frozen=True)
class BlasInfo:
    """The BLAS numpy uses in this process: its library (``openblas``, ``mkl``, ...) and, for
    OpenBLAS, the kernel it loaded."""

    library: str | None
    kernel: str | None

    def describe(self) -> str:
        if self.library is None:
            return "no BLAS that threadpoolctl recognises"
        return f"{self.library} with its {self.kernel} kernel" if self.kernel else self.library


@dataclasses.dataclass(frozen=True)
class KernelPlan:
    """Where a build runs: ``here``, or in a ``child`` process pinned to ``kernel``; ``reason`` says why."""

    where: str
    kernel: str | None
    reason: str


def numpy_blas() -> BlasInfo:
    """The BLAS behind numpy's matrix products in this process (threadpoolctl's report)."""
    import numpy  # noqa: F401  (threadpoolctl lists only libraries already loaded)
    from threadpoolctl import threadpool_info

    for library in threadpool_info():
        if library.get("user_api") == "blas":
            return BlasInfo(library.get("internal_api"), library.get("architecture"))
    return BlasInfo(None, None)


def requested_kernel(environ: Mapping[str, str] | None = None) -> str:
    """The kernel builds run on: ``OFFDYN_BLAS_KERNEL`` if set, else :data:`DATASET_BLAS_KERNEL`."""
    value = (os.environ if environ is None else environ).get(KERNEL_ENV, "").strip()
    if not value:
        return DATASET_BLAS_KERNEL
    if value != NATIVE and value not in KERNEL_NEEDS:
        raise KernelError(f"{KERNEL_ENV}={value!r} is not a kernel builds can run on; expected one of "
                          + ", ".join(repr(k) for k in (*KERNEL_NEEDS, NATIVE)) + f" (default {DATASET_BLAS_KERNEL!r})")
    return value


def plan_kernel(blas: BlasInfo, wanted: str, *, machine: str, flags: frozenset[str]) -> KernelPlan:
    """Decide where a build runs, given numpy's BLAS, the kernel wanted, the architecture and CPU flags."""
    if wanted == NATIVE:
        return KernelPlan("here", blas.kernel, f"{KERNEL_ENV}={NATIVE}: on {blas.describe()}")
    if blas.library == "openblas" and blas.kernel == wanted:
        return KernelPlan("here", wanted, f"numpy's OpenBLAS runs the {wanted} kernel already")
    if blas.library != "openblas":
        return KernelPlan("here", blas.kernel, f"numpy uses {blas.describe()}, not OpenBLAS, so its kernel "
                                               f"cannot be pinned to {wanted}")
    if machine.lower() not in ("x86_64", "amd64"):
        return KernelPlan("here", blas.kernel, f"the {wanted} kernel is x86-64 code and this machine is {machine}")
    missing = [flag for flag in KERNEL_NEEDS.get(wanted, ()) if flag not in flags]
    if missing:
        return KernelPlan("here", blas.kernel, f"this CPU lacks {', '.join(missing)}, which the {wanted} kernel needs")
    return KernelPlan("child", wanted, f"numpy's OpenBLAS loaded its {blas.kernel} kernel; the build runs in a "
                                       f"child process on {wanted}")


def current_plan() -> KernelPlan:
    """:func:`plan_kernel` for this process and machine."""
    return plan_kernel(numpy_blas(), requested_kernel(), machine=platform.machine(), flags=cpu_flags())


def _send(stream: IO[bytes], message: tuple[Any, ...]) -> None:
    payload = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(struct.pack("<Q", len(payload)) + payload)
    stream.flush()


def _receive(stream: IO[bytes]) -> tuple[Any, ...] | None:
    header = stream.read(8)
    if len(header) < 8:
        return None
    (size,) = struct.unpack("<Q", header)
    payload = stream.read(size)
    if len(payload) < size:
        return None
    message = pickle.loads(payload)  # noqa: S301 (our own child process, over a private pipe)
    return message if isinstance(message, tuple) else None


def call_on_kernel(function: Callable[..., Any], kwargs: Mapping[str, Any], kernel: str,
                   on_progress: Callable[[int], None] | None = None) -> Any:
    """``function(**kwargs, on_progress=...)`` in a child Python process whose OpenBLAS runs ``kernel``.

    ``function`` must be a module-level function and ``kwargs`` picklable. Progress the child
    reports reaches ``on_progress`` here (batched every 0.1 s); its exception is raised here (an
    :class:`OffdynError` as itself, anything else as a :class:`KernelError` with the child's traceback).
    """
    import offdyn_bench

    package_parent = pathlib.Path(offdyn_bench.__file__).resolve().parent.parent
    env = dict(os.environ)
    env[OPENBLAS_ENV] = kernel
    env["PYTHONPATH"] = os.pathsep.join([str(package_parent), *filter(None, [env.get("PYTHONPATH")])])
    request = pickle.dumps((function.__module__, function.__qualname__, dict(kwargs), kernel))
    # Not `-m`: run as __main__ the module's classes would be other classes than the parent's. The
    # messages get the real stdout before any import can print; whatever is printed goes to stderr.
    code = ("import os; channel = os.dup(1); os.dup2(2, 1); "
            f"from {__name__} import child_main; raise SystemExit(child_main(channel))")
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
    assert child.stdin is not None and child.stdout is not None
    try:
        try:
            child.stdin.write(request)
            child.stdin.close()
        except BrokenPipeError:
            pass  # it died before reading: said below, with its exit code
        while (message := _receive(child.stdout)) is not None:
            kind = message[0]
            if kind == "progress" and on_progress is not None:
                on_progress(message[1])
            elif kind == "result":
                return message[1]
            elif kind == "error":
                error, text = message[1], message[2]
                if isinstance(error, OffdynError):
                    raise error
                raise KernelError(f"the build failed in its child process on the {kernel} kernel: {text}")
        code = child.wait()
        raise KernelError(f"the build's child process on the {kernel} kernel ended (exit code {code}) without a "
                          "result; its error output is above")
    finally:
        if child.poll() is None:
            child.kill()
        child.wait()
        child.stdout.close()


def child_main(channel_fd: int) -> int:
    """Run one request from stdin, sending messages to ``channel_fd`` (the parent's pipe)."""
    channel = os.fdopen(channel_fd, "wb")
    module, qualname, kwargs, kernel = pickle.loads(sys.stdin.buffer.read())  # noqa: S301 (from our parent)
    try:
        loaded = numpy_blas()
        if loaded.library == "openblas" and loaded.kernel != kernel:
            raise KernelError(f"OpenBLAS did not take {OPENBLAS_ENV}={kernel}: it runs {loaded.describe()}; a "
                              "build here cannot reproduce the manifest's bytes")
        function: Any = importlib.import_module(module)
        for part in qualname.split("."):
            function = getattr(function, part)
        pending, last = 0, time.monotonic()

        def progress(steps: int) -> None:
            nonlocal pending, last
            pending += steps
            if time.monotonic() - last >= _PROGRESS_INTERVAL_S:
                _send(channel, ("progress", pending))
                pending, last = 0, time.monotonic()

        result = function(**kwargs, on_progress=progress)
        if pending:
            _send(channel, ("progress", pending))
        _send(channel, ("result", result))
    except BaseException as error:  # noqa: BLE001 (everything goes back to the parent)
        # A bad-input error comes back as its message; anything else with the child's traceback.
        text = str(error) if isinstance(error, OffdynError) else traceback.format_exc()
        try:  # an exception whose constructor takes other arguments than its message does not come back
            pickle.loads(pickle.dumps(error))  # noqa: S301
            _send(channel, ("error", error, text))
        except Exception:  # noqa: BLE001
            _send(channel, ("error", None, text))
    return 0
