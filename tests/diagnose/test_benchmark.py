"""The 20,000-transition Hopper diagnosis (a benchmark: `make bench`; reports, never asserts speed)."""

from __future__ import annotations

import importlib.util
import json
import pathlib

import pytest

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks" / "bench_diagnose.py"


@pytest.mark.benchmark
def test_full_diagnosis_of_20k_hopper_transitions(capsys: pytest.CaptureFixture[str]) -> None:
    spec = importlib.util.spec_from_file_location("bench_diagnose", BENCH)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    figures = bench.run(20_000)
    with capsys.disabled():
        print("\n" + json.dumps({k: figures[k] for k in ("wall_s", "breakdown_s", "one_pass_s", "wall_in_passes",
                                                          "load_average_1min")}))
    found = {(e["kind"], e["target"]) for e in figures["effects_added"]}
    assert found == {("action_deadzone", "thigh_joint"), ("mass", "torso")}
    assert not figures["unexplained_residual"]
