"""GPU placement on the Ray backend: a local Ray instance that declares one GPU (Ray schedules
declared resources whether or not the card exists), runs that each ask for half of it."""

from __future__ import annotations

import dataclasses
import json

import pytest

from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import STATE_FILE, run_sweep

ray = pytest.importorskip("ray", reason="the Ray backend needs ray (pip install 'ray==2.60.0', in the test extra)")


@pytest.fixture(scope="module")
def ray_with_one_gpu():
    ray.init(num_cpus=2, num_gpus=1, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


def test_each_attempt_records_the_gpu_ray_assigned_it(tmp_path, tiny_spec, ray_with_one_gpu):
    # The spec refuses GPUs for CPU training, so the placement is asked for past it: the runs train
    # on the CPU while Ray hands each the declared GPU, which is all this test is about.
    spec = dataclasses.replace(parse_spec(tiny_spec(tmp_path / "out")), gpus_per_run=0.5)
    report = run_sweep(spec, backend="ray", echo=None)
    assert not report.failed and report.launched == 2
    state = json.loads((spec.out / STATE_FILE).read_text())
    for run in report.runs:
        attempt = state["runs"][run.run_id]["history"][0]
        # Ray sets CUDA_VISIBLE_DEVICES in the worker to the GPU it assigned; train inherits it.
        assert attempt["cuda_visible_devices"] == "0"
        assert ", CUDA_VISIBLE_DEVICES=0\n" in run.log.read_text()


@pytest.mark.parametrize(("available", "per_run", "fit"), [(1, 0.2, 5), (1, 0.1, 10), (3, 0.3, 10), (1, 1 / 3, 3),
                                                           (1, 0.0625, 16), (2, 1, 2), (1, 0.7, 1), (4, 0, 10**6)])
def test_fractional_gpus_fit_as_ray_counts_them(available, per_run, fit):
    from offdyn_bench.sweep.backends import runs_that_fit

    # Floats would say 4 for five runs of 0.2 GPU (1.0 // 0.2 == 4.0) and leave a fifth of the GPU idle.
    assert runs_that_fit(available, per_run) == fit


@pytest.mark.parametrize(("workers", "per_run", "cpus"), [(10, 0.3, 3), (3, 0.1, 1), (7, 0.7, 5), (2, 1, 2), (3, 1.5, 5)])
def test_workers_ask_a_local_ray_for_the_cpus_that_hold_exactly_them(workers, per_run, cpus):
    from offdyn_bench.sweep.backends import cpus_for, runs_that_fit

    # ceil(10 * 0.3) is 4 in floats, which would let 13 runs of 0.3 CPU run where --workers said 10.
    assert cpus_for(workers, per_run) == cpus
    assert runs_that_fit(cpus, per_run) >= workers


def test_the_ray_backend_keeps_as_many_fractional_gpu_runs_in_flight_as_fit(ray_with_one_gpu):
    from offdyn_bench.sweep.backends import RayBackend

    assert RayBackend(address=None, cpus_per_run=0.2, gpus_per_run=0.2).capacity == 5
    assert RayBackend(address=None, cpus_per_run=1, gpus_per_run=0.2).capacity == 2  # 2 CPUs


def test_a_cuda_sweep_that_reserves_no_gpu_is_refused_before_anything_is_written(tmp_path, tiny_spec):
    from offdyn_bench.errors import OffdynError

    # Ray sets no CUDA_VISIBLE_DEVICES for a task of 0 GPUs, so these runs would share every GPU unscheduled.
    spec = dataclasses.replace(parse_spec(tiny_spec(tmp_path / "out")), device="cuda", gpus_per_run=0.0)
    with pytest.raises(OffdynError, match="device is 'cuda' with gpus_per_run 0: Ray would reserve no GPU.*"
                                          "expected gpus_per_run above 0"):
        run_sweep(spec, backend="ray", echo=None)
    assert not (spec.out / STATE_FILE).exists()


def test_auto_device_on_a_cluster_with_gpus_must_reserve_one(tmp_path, tiny_spec, ray_with_one_gpu):
    from offdyn_bench.errors import OffdynError

    spec = dataclasses.replace(parse_spec(tiny_spec(tmp_path / "out")), device="auto", gpus_per_run=0.0)
    with pytest.raises(OffdynError, match="device is 'auto' with gpus_per_run 0 and the Ray cluster has 1 GPUs"):
        run_sweep(spec, backend="ray", echo=None)
    assert not (spec.out / STATE_FILE).exists()
    assert ray_with_one_gpu.is_initialized()  # the caller's Ray instance is left running
