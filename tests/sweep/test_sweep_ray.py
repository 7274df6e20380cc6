"""The Ray backend on a local Ray instance (``ray.init(num_cpus=2)``): the same tiny sweep."""

from __future__ import annotations

import json

import pytest

from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import STATE_FILE, run_sweep

ray = pytest.importorskip("ray", reason="the Ray backend needs ray (pip install 'ray==2.60.0', in the test extra)")


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


def test_the_ray_backend_completes_a_tiny_sweep_and_skips_it_on_re_run(tmp_path, tiny_spec, local_ray):
    spec = parse_spec(tiny_spec(tmp_path / "out"))
    lines = []
    report = run_sweep(spec, backend="ray", echo=lines.append)
    assert not report.failed and report.launched == 2
    state = json.loads((spec.out / STATE_FILE).read_text())
    assert state["backend"] == "ray"
    for run in report.runs:
        entry = state["runs"][run.run_id]
        assert entry["status"] == "done" and entry["attempts"] == 1 and entry["cpu_time_s"] > 0
        evaluation = json.loads((run.folder / "evaluation.json").read_text())
        assert [s["seed"] for s in evaluation["seeds"]] == list(run.seeds)
    assert lines[-1].startswith("sweep: 2/2 done, 0 running, 0 failed, 0 pending")
    # The instance this process started is the one used, and left running.
    assert local_ray.is_initialized() and local_ray.cluster_resources()["CPU"] == 2
    again = run_sweep(spec, backend="ray", echo=None)
    assert again.launched == 0 and not again.failed


def test_a_run_that_cannot_be_placed_is_refused_before_anything_runs(tmp_path, tiny_spec, local_ray):
    from offdyn_bench.errors import OffdynError

    spec = parse_spec(tiny_spec(tmp_path / "out", cpus_per_run=4))
    with pytest.raises(OffdynError, match="cpus_per_run is 4 but the Ray cluster has 2 CPUs"):
        run_sweep(spec, backend="ray", echo=None)
    assert not spec.out.exists()
