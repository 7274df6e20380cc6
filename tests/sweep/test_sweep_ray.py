"""The Ray backend on a local Ray instance (``ray.init(num_cpus=2)``): the same tiny sweep, and a
Ray worker killed under a run."""

from __future__ import annotations

import json
import os
import signal
import threading
from pathlib import Path

import pytest

from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import STATE_FILE, run_sweep
from offdyn_bench.sweep.runs import Run, expand

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


def _parent_of(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("PPid:"):
            return int(line.split()[1])
    raise AssertionError(f"no parent of {pid}")


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds the Ray worker through /proc")
def test_a_ray_worker_killed_mid_run_loses_no_finished_result_and_the_sweep_completes(
        tmp_path, tiny_spec, local_ray, train_process_of, wait_for, attempt_headers):
    # Three runs on 2 CPUs: the first to finish is kept while a worker is killed under another.
    spec = parse_spec(tiny_spec(tmp_path / "out", steps=1000, seeds=3,
                                training={"eval_episodes": 1, "checkpoint_every": 100, "eval_every": 250}))
    runs = expand(spec)
    outcome = {}
    sweep = threading.Thread(target=lambda: outcome.setdefault("report", run_sweep(spec, backend="ray", echo=None)))
    sweep.start()

    def a_victim() -> Run | None:
        finished = [run for run in runs if (run.folder / "evaluation.json").exists()]
        training = [run for run in runs if not (run.folder / "result.json").exists()
                    and any((run.folder / "checkpoints").glob("step_*")) and train_process_of(run.folder)]
        return training[0] if finished and training else None

    wait_for(lambda: a_victim() is not None)
    victim = a_victim()
    kept = {run.run_id: (run.folder / "evaluation.json").read_bytes()
            for run in runs if (run.folder / "evaluation.json").exists()}
    worker = _parent_of(train_process_of(victim.folder))  # the Ray worker executing the victim's task
    assert worker != os.getpid()
    os.kill(worker, signal.SIGKILL)
    sweep.join(timeout=300)
    report = outcome["report"]
    assert not report.failed and all(record.status == "done" for record in report.records.values())
    record = report.records[victim.run_id]
    assert record.attempts == 2 and "Ray task" in record.history[0]["error"]
    assert attempt_headers(victim.log) == 2
    # The retry resumed from the checkpoints, or waited for the train the dead worker left running.
    log = victim.log.read_text()
    assert "=== resuming: " in log or "=== waiting: another process is training in" in log
    for run_id, record_bytes in kept.items():
        finished = next(run for run in runs if run.run_id == run_id)
        assert (finished.folder / "evaluation.json").read_bytes() == record_bytes
        assert report.records[run_id].attempts == 1
