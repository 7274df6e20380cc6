"""The reference workload that times the machine, and the training CPU counted in it."""

from __future__ import annotations

import pytest
import torch

import baselines.train as training
from baselines.run_folder import TrainingCompute
from baselines.train import RECALIBRATE_EVERY_CPU_S, _Clock
from offdyn_bench.machine_speed import reference_update_seconds


def test_the_workload_takes_milliseconds_and_changes_no_random_stream_or_thread_count():
    torch.manual_seed(123)
    state = torch.get_rng_state()
    threads = torch.get_num_threads()
    update_s = reference_update_seconds()
    assert 1e-5 < update_s < 0.1  # about 2.5 ms an update here
    # A training that times it between two steps draws the same random numbers as one that does not.
    assert torch.equal(torch.get_rng_state(), state)
    assert torch.get_num_threads() == threads


def test_more_work_per_update_is_not_what_it_reports_but_time_per_update():
    """Blocks of more updates measure the same per-update time (within the machine's noise), not more."""
    short, long = reference_update_seconds(blocks=5, updates_per_block=4), reference_update_seconds(3, 16)
    assert 0.33 < short / long < 3.0


def test_it_measures_the_same_work_inside_a_callers_no_grad_block():
    with torch.no_grad():
        assert reference_update_seconds(blocks=1, updates_per_block=2) > 0


@pytest.mark.parametrize("blocks, updates", [(0, 8), (5, 0), (-1, 1)])
def test_an_empty_measurement_is_refused(blocks, updates):
    with pytest.raises(ValueError, match="must be at least 1"):
        reference_update_seconds(blocks, updates)


class _FakeCpu:
    """A process CPU clock the test advances by hand, and a machine whose speed it sets."""

    def __init__(self, monkeypatch, update_s: float) -> None:
        self.cpu, self.update_s, self.measurements = 0.0, update_s, 0
        monkeypatch.setattr(training.time, "process_time", lambda: self.cpu)

    def measure(self) -> float:
        self.measurements += 1
        return self.update_s


def test_each_stretch_of_cpu_is_counted_at_the_speed_measured_at_its_start(monkeypatch):
    fake = _FakeCpu(monkeypatch, 0.002)
    clock = _Clock(fake.measure)
    assert fake.measurements == 1
    fake.cpu = 60.0
    clock.recalibrate()  # under RECALIBRATE_EVERY_CPU_S since the last measurement: not measured again
    assert fake.measurements == 1 and clock.now().reference_updates == pytest.approx(30_000)
    fake.cpu = 200.0
    fake.update_s = 0.004  # the machine got twice as slow
    clock.recalibrate()
    assert fake.measurements == 2
    fake.cpu = 400.0
    now = clock.now()
    # 200 s at 2 ms an update, then 200 s at 4 ms.
    assert now.reference_updates == pytest.approx(100_000 + 50_000)
    assert now.reference_update_s == pytest.approx(400.0 / 150_000)
    assert RECALIBRATE_EVERY_CPU_S <= 200.0


def test_a_resumed_training_adds_to_its_checkpoints_count_or_keeps_it_unknown(monkeypatch):
    fake = _FakeCpu(monkeypatch, 0.002)
    clock = _Clock(fake.measure)
    clock.resumed(TrainingCompute(10.0, 100.0, 1, True, 40_000.0))
    fake.cpu = 50.0
    assert clock.now().reference_updates == pytest.approx(40_000 + 25_000)
    # A checkpoint written before trainings timed the machine: the whole is unknown, not a part.
    clock.resumed(TrainingCompute(10.0, 100.0, 1, True))
    assert clock.now().reference_updates is None and clock.now().to_dict().keys() == {
        "wall_time_s", "cpu_time_s", "attempts", "complete"}
    # A timer that read zero makes it unknown rather than infinite.
    fake.update_s = 0.0
    assert _Clock(fake.measure).now().reference_updates is None


@pytest.mark.parametrize("updates", [-1.0, float("nan"), "many"])
def test_a_count_that_is_not_a_count_makes_the_compute_unreadable(updates):
    stored = {"wall_time_s": 2, "cpu_time_s": 3.5, "attempts": 2, "complete": True, "reference_updates": updates}
    assert TrainingCompute.parse(stored) is None
    assert TrainingCompute.parse(stored | {"reference_updates": 1750}) == TrainingCompute(2.0, 3.5, 2, True, 1750.0)

