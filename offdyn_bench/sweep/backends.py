"""Where attempts run: ``local`` (a pool of worker threads on this machine, each driving one run's
subprocesses at a time) or ``ray`` (one Ray task per attempt, with its CPUs and GPUs declared).

Both hand back an :class:`~offdyn_bench.sweep.execute.AttemptOutcome` per attempt. Retries are the
driver's (:mod:`offdyn_bench.sweep.driver`), not Ray's (``max_retries=0`` on every task): the state
file counts every attempt, and a run lost with its worker, node or process comes back as a
failed attempt like any other.
"""

from __future__ import annotations

import concurrent.futures
import os
import socket
from collections.abc import Sequence
from typing import Any, Protocol

from offdyn_bench.errors import OffdynError
from offdyn_bench.sweep.execute import AttemptOutcome, execute_run
from offdyn_bench.sweep.runs import Run

BACKENDS = ("local", "ray")


class Backend(Protocol):
    """Runs attempts somewhere and reports each one's outcome."""

    name: str
    capacity: int
    """Attempts that can run at once (the driver keeps at most this many in flight)."""

    def submit(self, run: Run, attempt: int) -> Any: ...

    def wait(self, handles: Sequence[Any], timeout: float) -> list[Any]:
        """The handles among ``handles`` that have finished (possibly none after ``timeout`` s)."""
        ...

    def outcome(self, handle: Any, run: Run) -> AttemptOutcome: ...

    def close(self) -> None: ...


def _lost(run: Run, error: BaseException, where: str) -> AttemptOutcome:
    """An attempt whose worker failed before it could report: a failed attempt, never a crash."""
    return AttemptOutcome(ok=False, stage="worker", exit_code=None,
                          error=f"{where}: {type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
                                f"; see {run.log}",
                          wall_time_s=0.0, cpu_time_s=0.0, host=socket.gethostname())


class LocalBackend:
    """``workers`` runs at a time on this machine. Each worker is a thread that waits on its
    run's subprocess: the work is in the subprocesses, so a run that crashes or is killed takes
    down only itself."""

    name = "local"

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise OffdynError(f"--workers {workers}: expected an integer >= 1")
        self.capacity = workers
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="sweep-run")

    def submit(self, run: Run, attempt: int) -> concurrent.futures.Future[AttemptOutcome]:
        return self._pool.submit(execute_run, run, attempt)

    def wait(self, handles: Sequence[Any], timeout: float) -> list[Any]:
        done, _ = concurrent.futures.wait(handles, timeout=timeout, return_when=concurrent.futures.FIRST_COMPLETED)
        return list(done)

    def outcome(self, handle: Any, run: Run) -> AttemptOutcome:
        try:
            return handle.result()
        except Exception as error:  # noqa: BLE001 - any worker failure is a failed attempt
            return _lost(run, error, "local worker")

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def default_workers(cpus_per_run: float) -> int:
    return max(1, int((os.cpu_count() or 1) // max(cpus_per_run, 1.0)))


# Ray accounts resources in whole units of 1/10,000 (a GPU asked for as 0.2 is 2,000 units), so
# five runs of 0.2 fit one GPU; floats would say four (1.0 // 0.2 == 4.0).
_RAY_RESOURCE_UNITS = 10_000


def runs_that_fit(available: float, per_run: float) -> int:
    """How many runs asking for ``per_run`` of a resource fit in ``available`` of it, as Ray counts
    (a huge number when runs ask for none)."""
    if per_run <= 0:
        return 10**6
    return int(round(available * _RAY_RESOURCE_UNITS) // round(per_run * _RAY_RESOURCE_UNITS))


def cpus_for(workers: int, cpus_per_run: float) -> int:
    """The whole CPUs a local Ray instance needs to hold ``workers`` runs of ``cpus_per_run`` at
    once, counted as Ray counts: 10 runs of 0.3 need 3 (``ceil(10 * 0.3)`` says 4, which would let
    13 run)."""
    units = workers * round(cpus_per_run * _RAY_RESOURCE_UNITS)
    return max(1, -(-units // _RAY_RESOURCE_UNITS))


def unreserved_gpu_error(device: str, cluster_gpus: float | None = None) -> OffdynError:
    """A CUDA run that asks Ray for no GPU: Ray neither counts it on a GPU nor sets its
    CUDA_VISIBLE_DEVICES (Ray 2.60), so every such run would train on every GPU of its node, unseen
    by the scheduler that is placing the GPU runs beside it."""
    where = "" if cluster_gpus is None else f" and the Ray cluster has {cluster_gpus:g} GPUs"
    return OffdynError(f"device is {device!r} with gpus_per_run 0{where}: Ray would reserve no GPU for the runs "
                       "and leave CUDA_VISIBLE_DEVICES unset, so they would share every GPU of a node unscheduled; "
                       "expected gpus_per_run above 0 (0.33 puts three runs on a GPU) or device: cpu")


class RayBackend:
    """One Ray task per attempt, declaring ``num_cpus``/``num_gpus``; Ray places it on a node with
    those resources free. ``address`` joins a cluster (``auto``, ``ray://head:10001``); None starts
    a local Ray instance with ``local_cpus`` CPUs (default: all of them), unless this process is
    already connected to one (then that one is used, and left running)."""

    name = "ray"

    def __init__(self, *, address: str | None, cpus_per_run: float, gpus_per_run: float,
                 local_cpus: int | None = None, device: str = "cpu") -> None:
        if device.startswith("cuda") and gpus_per_run == 0:
            raise unreserved_gpu_error(device)
        try:
            import ray
        except ImportError:
            raise OffdynError("the ray backend needs Ray: pip install 'ray==2.60.0' (or pip install "
                              "'offdyn-bench[ray]')") from None
        self._ray = ray
        self._owns_ray = not ray.is_initialized()
        if self._owns_ray:
            options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
            if address is None and local_cpus is not None:
                options["num_cpus"] = local_cpus
            try:
                ray.init(address=address, **options)
            except (ConnectionError, ValueError, RuntimeError) as error:
                raise OffdynError(f"cannot start or join Ray (ray_address {address!r}): "
                                  f"{str(error).splitlines()[0]}") from None
        cluster = ray.cluster_resources()
        if gpus_per_run > cluster.get("GPU", 0.0):
            self.close()
            raise OffdynError(f"gpus_per_run is {gpus_per_run:g} but the Ray cluster has {cluster.get('GPU', 0.0):g} "
                              "GPUs; no run could ever be placed")
        if device == "auto" and gpus_per_run == 0 and cluster.get("GPU", 0.0) > 0:
            self.close()
            raise unreserved_gpu_error(device, cluster.get("GPU", 0.0))
        if cpus_per_run > cluster.get("CPU", 0.0):
            self.close()
            raise OffdynError(f"cpus_per_run is {cpus_per_run:g} but the Ray cluster has {cluster.get('CPU', 0.0):g} "
                              "CPUs; no run could ever be placed")
        self._task = ray.remote(execute_run).options(num_cpus=cpus_per_run, num_gpus=gpus_per_run, max_retries=0)
        self._cpus_per_run, self._gpus_per_run = cpus_per_run, gpus_per_run

    @property
    def capacity(self) -> int:
        """Runs the cluster can hold at once now (read again each time: a cluster may grow).
        Submitting more would only queue them inside Ray, and the driver's count of running runs
        stays true when it does not."""
        cluster = self._ray.cluster_resources()
        by_cpu = runs_that_fit(cluster.get("CPU", 0.0), self._cpus_per_run)
        by_gpu = runs_that_fit(cluster.get("GPU", 0.0), self._gpus_per_run)
        return max(1, min(by_cpu, by_gpu))

    def submit(self, run: Run, attempt: int) -> Any:
        return self._task.remote(run, attempt)

    def wait(self, handles: Sequence[Any], timeout: float) -> list[Any]:
        done, _ = self._ray.wait(list(handles), num_returns=1, timeout=timeout)
        return list(done)

    def outcome(self, handle: Any, run: Run) -> AttemptOutcome:
        try:
            return self._ray.get(handle)
        except Exception as error:  # noqa: BLE001 - a lost worker or node is a failed attempt
            return _lost(run, error, "Ray task")

    def close(self) -> None:
        if self._owns_ray and self._ray.is_initialized():
            self._ray.shutdown()
