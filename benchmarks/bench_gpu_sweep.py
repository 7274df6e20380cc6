"""A sweep on one GPU machine through the Ray backend: does Ray place the runs on the GPU, and how
should a sweep share one GPU among its runs?

1. Placement: a sweep of CQL, H2O and DARC (2 seeds each, ``--placement-steps`` steps) on a local
   Ray instance that sees the machine's GPU, ``device: cuda``, ``gpus_per_run: 0.25`` (4 runs at
   once). Every attempt must record the ``CUDA_VISIBLE_DEVICES`` Ray gave it, every run's
   ``result.json`` must say it trained on CUDA and name the card, and the sweep must finish.
2. Sharing: the same seed-steps of CQL (the method the GPU speeds up most) run as a sweep in several
   layouts: seeds batched in one run (``seeds_per_run``) against single-seed runs sharing the GPU
   (fractional ``gpus_per_run``). Per layout: the sweep's wall time (process start-up, training and
   the 2-episode evaluations, as a user waits for them) and the aggregate seed-steps/s; ratios are
   against the first layout, all measured in one process on one machine.

Without a CUDA device, ``--fake-gpus 1`` runs the same on the CPU with Ray told of a GPU that is
not there (a check of this script, not a measurement of anything).

    python benchmarks/bench_gpu_sweep.py --out /tmp/gpu-sweep --json gpu-sweep.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import ray
import torch

from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import STATE_FILE, run_sweep

TASK = "halfcheetah-friction-5.0"  # its official dataset is small enough to carry to a GPU machine
# (label, seeds, seeds_per_run, gpus_per_run): 5 seeds as one batched run against 5 runs sharing
# the GPU; then 15 seeds as 3 batched runs against 15 single-seed runs (16 CPU cores: one each).
LAYOUTS = [("1 run x 5 seeds", 5, 5, 1.0), ("5 runs x 1 seed", 5, 1, 0.2),
           ("3 runs x 5 seeds", 15, 5, 0.33), ("15 runs x 1 seed", 15, 1, 0.0625)]


def _spec(out: Path, device: str, gpus_per_run: float, **keys: Any) -> Any:
    data = {"tasks": [TASK], "track": "offline-target", "out": str(out), "device": device,
            "evaluation_episodes": 2, "training": {"eval_episodes": 1}, "max_retries": 0,
            "gpus_per_run": gpus_per_run if device != "cpu" else 0} | keys
    spec = parse_spec(data, source="bench_gpu_sweep")
    # --fake-gpus: the spec refuses GPUs for CPU training, so the placement is asked for past it.
    return dataclasses.replace(spec, gpus_per_run=gpus_per_run)


def placement(root: Path, device: str, steps: int) -> dict[str, Any]:
    spec = _spec(root / "placement", device, 0.25, methods=["cql", "h2o", "darc"], seeds=2, steps=steps,
                 overrides={"h2o": {"random_steps": steps // 4}, "darc": {"random_steps": steps // 4,
                                                                         "warmup_steps": steps // 2}})
    started = time.monotonic()
    report = run_sweep(spec, backend="ray", echo=None)
    wall = time.monotonic() - started
    state = json.loads((spec.out / STATE_FILE).read_text())
    runs = []
    for run in report.runs:
        entry = state["runs"][run.run_id]
        result_path = run.folder / "result.json"
        result = json.loads(result_path.read_text()) if result_path.exists() else {}
        machines = result.get("machines") or [{}]
        runs.append({"run": run.run_id, "status": entry["status"],
                     "cuda_visible_devices": [a.get("cuda_visible_devices") for a in entry["history"]],
                     "device": result.get("device"), "card": (machines[-1] or {}).get("cuda"),
                     "error": entry["history"][-1].get("error") if entry["history"] else None})
    ok = (not report.failed and all(r["status"] == "done" and r["device"] == device
                                    and all(v not in (None, "") for v in r["cuda_visible_devices"])
                                    and (device == "cpu" or (r["card"] or {}).get("name")) for r in runs))
    return {"ok": bool(ok), "wall_s": round(wall, 1), "runs": runs}


def sharing(root: Path, device: str, steps: int, backend: str) -> list[dict[str, Any]]:
    rows = []
    for label, seeds, per_run, gpus in LAYOUTS:
        folder = root / ("sharing-" + label.replace(" ", "-"))
        spec = _spec(folder, device, gpus, methods=["cql"], seeds=seeds, seeds_per_run=per_run, steps=steps)
        started = time.monotonic()
        # Without Ray, the local backend runs as many at once as Ray would place.
        workers = None if backend == "ray" else -(-seeds // per_run)
        report = run_sweep(spec, backend=backend, workers=workers, echo=None)
        wall = time.monotonic() - started
        # The training loops' own rate, start-up and evaluation left out (what a 100,000-step run
        # sees): the runs ran at once, so their rates add up.
        training = [json.loads((run.folder / "result.json").read_text())["compute"]["wall_time_s"]
                    for run in report.runs if (run.folder / "result.json").exists()]
        rows.append({"layout": label, "seeds": seeds, "seeds_per_run": per_run, "gpus_per_run": gpus,
                     "runs": len(report.runs), "failed": len(report.failed), "wall_s": round(wall, 1),
                     "seed_steps_per_s": round(seeds * steps / wall, 1),
                     "training_seed_steps_per_s": round(sum(per_run * steps / t for t in training), 1)})
        print(f"  {label:18s} {rows[-1]['wall_s']:7.1f} s  {rows[-1]['seed_steps_per_s']:8.1f} seed-steps/s"
              f" (training loops {rows[-1]['training_seed_steps_per_s']:8.1f})  failed {rows[-1]['failed']}",
              flush=True)
    base, base_training = rows[0]["seed_steps_per_s"], rows[0]["training_seed_steps_per_s"]
    for row in rows:
        row["ratio_to_first"] = round(row["seed_steps_per_s"] / base, 2) if base else None
        row["training_ratio_to_first"] = (round(row["training_seed_steps_per_s"] / base_training, 2)
                                          if base_training else None)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="sweep folders (a fresh one per call)")
    parser.add_argument("--json", type=Path, help="write the measurements here")
    parser.add_argument("--placement-steps", type=int, default=600)
    parser.add_argument("--sharing-steps", type=int, default=1500)
    parser.add_argument("--skip-sharing", action="store_true")
    parser.add_argument("--fake-gpus", type=int, default=0, help="without CUDA: tell Ray of this many GPUs")
    args = parser.parse_args(argv)
    if args.out.exists() and any(args.out.iterdir()):
        parser.error(f"--out {args.out} is not empty: results of another call would be reused")
    if torch.cuda.is_available():
        device, gpus = "cuda", None
    elif args.fake_gpus:
        device, gpus = "cpu", args.fake_gpus
    else:
        print("no CUDA device and no --fake-gpus: nothing measured")
        return 0
    record: dict[str, Any] = {"device": device, "cpus": os.cpu_count(), "ray": ray.__version__,
                              "torch": torch.__version__, "task": TASK,
                              "card": torch.cuda.get_device_name(0) if device == "cuda" else None}
    try:
        ray.init(num_cpus=os.cpu_count(), num_gpus=gpus, include_dashboard=False, log_to_driver=False)
        backend = "ray"
    except Exception as error:  # noqa: BLE001 - say why, and still measure the sharing without Ray
        record["placement"] = {"ok": False, "error": f"ray.init: {type(error).__name__}: {error}", "runs": []}
        print(f"placement: FAILED, {record['placement']['error']}; sharing measured on the local backend")
        backend = "local"
    try:
        if backend == "ray":
            try:
                record["placement"] = placement(args.out, device, args.placement_steps)
            except Exception as error:  # noqa: BLE001 - recorded; the sharing is still worth measuring
                record["placement"] = {"ok": False, "error": f"{type(error).__name__}: {error}", "runs": []}
            print(f"placement: {'ok' if record['placement']['ok'] else 'FAILED'} in "
                  f"{record['placement'].get('wall_s')} s {record['placement'].get('error') or ''}", flush=True)
            for run in record["placement"]["runs"]:
                print(f"  {run['run']}: {run['status']}, CUDA_VISIBLE_DEVICES {run['cuda_visible_devices']}, "
                      f"device {run['device']}, card {(run['card'] or {}).get('name')}"
                      + (f", error {run['error']}" if run["error"] else ""), flush=True)
        if not args.skip_sharing:
            print(f"sharing one GPU, CQL, {args.sharing_steps} steps per seed:", flush=True)
            record["sharing"] = sharing(args.out, device, args.sharing_steps, backend)
            record["sharing_backend"] = backend
    finally:
        if ray.is_initialized():
            ray.shutdown()
        if args.json:
            args.json.write_text(json.dumps(record, indent=2) + "\n")
    return 0 if record["placement"]["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
