"""Benchmark: a full gap diagnosis of 20,000 Hopper transitions with the whole candidate library.

    .venv/bin/python benchmarks/bench_diagnose.py [--transitions 20000] [--json out.json]

The data come from a Hopper target with two effects nothing declares (a dead zone on the thigh
motor and a heavier torso); the source is plain ``Hopper-v5``. Prints the wall time of the
diagnosis and its breakdown (setup, screen, fits, validation), the effects found, the errors,
and the wall time in units of one batched replay of all transitions measured in the same run
(load on a shared machine scales both). Generating the data is not counted.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "diagnose"))

from diagnose_target_data import record  # noqa: E402

from offdyn_bench.diagnose import Transitions, diagnose  # noqa: E402
from offdyn_bench.diagnose.source import SourceSimulator  # noqa: E402

HIDDEN = [{"kind": "action_deadzone", "target": "thigh_joint", "threshold": 0.2},
          {"kind": "mass", "target": "torso", "scale": 1.25}]


def one_pass_seconds(data: Transitions) -> float:
    """Seconds for one batched one-step replay of every transition with the source model: the
    unit the diagnosis's cost is measured in, side by side, so load on the machine cancels."""
    source = SourceSimulator("Hopper-v5")
    states = source.full_states(data.qpos, data.qvel)  # type: ignore[arg-type]
    started = time.perf_counter()
    source.predict(source.base_model, states, data.actions[:, None])
    return time.perf_counter() - started


def run(transitions: int = 20_000) -> dict:
    """Diagnose ``transitions`` Hopper transitions with two hidden effects; return the figures."""
    data = Transitions(**record(HIDDEN, transitions, seed=0))
    one_pass = one_pass_seconds(data)
    started = time.perf_counter()
    result = diagnose("Hopper-v5", data)
    wall = time.perf_counter() - started
    return {
        "transitions": data.size,
        "candidates": result.candidates_searched,  # observation effects only where the data show them
        "cpu_cores": os.cpu_count(),
        "wall_s": round(wall, 2),
        "breakdown_s": result.timings,
        "one_pass_s": round(one_pass, 3),
        "wall_in_passes": round(wall / one_pass, 1),
        "effects_added": [{k: e[k] for k in ("kind", "target", "value")} for e in result.effects_added],
        "hidden": HIDDEN,
        "error_before": result.error_before.to_json(),
        "error_after": result.error_after.to_json(),
        "unexplained_residual": result.unexplained_residual,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transitions", type=int, default=20_000)
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args()
    figures = run(args.transitions)
    print(json.dumps(figures, indent=2))
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
