"""Build throughput against the bare env step rate (a benchmark: `make bench`; reports, never asserts speed)."""

from __future__ import annotations

import importlib.util
import pathlib

import pytest

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks" / "bench_datasets.py"


@pytest.mark.benchmark
def test_build_throughput_ratio(capsys: pytest.CaptureFixture[str]) -> None:
    spec = importlib.util.spec_from_file_location("bench_datasets", BENCH)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    rows = bench.run(["hopper-gravity-0.5"], transitions=5_000)
    with capsys.disabled():
        for row in rows:
            print(f"\n{row['task']} build {row['build']}: {row['build_per_s']:.0f} transitions/s, bare env "
                  f"{row['bare_env_per_s']:.0f} steps/s, ratio {row['ratio']:.2f}")
    assert [row["build"] for row in rows] == ["random", "policy"]
    assert all(row["ratio"] > 0 and row["transitions"] == 5_000 for row in rows)
