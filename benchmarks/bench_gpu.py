"""Seed-batched SAC updates on a GPU, measured side by side in one process (ratios, not timings).

Issue 9's targets on an H100: one seed at least 10x Stable-Baselines3's SAC updates/s on the same
GPU (SB3 measured 105 updates/s there), and 20 seeds at least 10,000 seed-updates/s. Measured, in
alternating rounds so background load hits every variant alike:

* ``sb3``: Stable-Baselines3 SAC, ``model.train`` on a filled buffer, ``device="cuda"``;
* ``eager``: :func:`baselines.sac.sac_update`, all seeds' networks batched, on the GPU;
* ``graph``: the same update replayed from a CUDA graph (:class:`baselines.sac.GraphedUpdate`);

each with 256x256 networks, batch 256, Hopper's sizes (11/3), random transitions, for 1 seed and
for ``--seeds`` seeds. The eager variants alternate with SB3 in one block; each graphed variant then
alternates with SB3 in a block of its own, since only the newest CUDA graph of a process may replay.

Then the third target: whole ``train`` runs, environments and evaluation included, at least 5x
the aggregate training steps/s of the same seeds trained one after another on the CPU.
``--train-seeds`` seeds run together (``--n-seeds N --device cuda``, the eager update)
against ``--train-cpu-seeds`` of them one after another with ``--device cpu`` and one torch thread,
with the same method, task, steps and evaluation settings. Runs one after another have an aggregate rate equal to one run's
(every seed costs the same steps), so a few CPU seeds measure it; ``--train-seeds 0`` skips this.

Then, with ``--methods``, the reference methods as a sweep runs them on one GPU machine: for each
method, ``--methods-gpu-seeds`` seeds trained together on CUDA and one seed on one CPU core, all of
these runs at once in their own processes (the GPU runs share the GPU), on ``--methods-task``; per
method the ratio of aggregate seed-steps/s (CQL: seed-updates/s).

Without a CUDA device it says so and measures nothing (exit status 0).

    .venv/bin/pip install -e ".[bench]"        # Stable-Baselines3, pinned
    .venv/bin/python benchmarks/bench_gpu.py [--seeds 1 20] [--rounds 5] [--train-seeds 20] [--json out.json]
    .venv/bin/python benchmarks/bench_gpu.py --seeds --skip-sb3 --train-seeds 0 --methods cql dap   # methods only
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from baselines.buffers import ReplayBuffer
from baselines.sac import GraphedUpdate, SACAgent, SACConfig, make_capturable, sac_update
from baselines.train import train
from offdyn_bench.datasets.ensure import ensure_dataset
from offdyn_bench.protocol import official_dataset

OBS_DIM, ACTION_DIM, BATCH, BUFFER = 11, 3, 256, 10_000


class NonFiniteLoss(RuntimeError):
    """A measured update computed a NaN or infinite loss: its speed means nothing."""


def _filled_buffer(n_seeds: int, device: str) -> ReplayBuffer:
    buffer = ReplayBuffer(n_seeds, BUFFER, OBS_DIM, ACTION_DIM, seed=0, device=device)
    g = torch.Generator().manual_seed(0)
    for _ in range(BUFFER):
        buffer.add(torch.randn(n_seeds, OBS_DIM, generator=g), torch.rand(n_seeds, ACTION_DIM, generator=g) * 2 - 1,
                   torch.randn(n_seeds, generator=g), torch.randn(n_seeds, OBS_DIM, generator=g), torch.zeros(n_seeds))
    return buffer


def _ours(n_seeds: int, updates: int, graphed: bool) -> Callable[[], float]:
    config = SACConfig(hidden_sizes=(256, 256), batch_size=BATCH)
    agent = SACAgent(OBS_DIM, ACTION_DIM, seeds=list(range(n_seeds)), config=config, device="cuda")
    buffer = _filled_buffer(n_seeds, "cuda")
    if graphed:
        make_capturable(agent)
        step = GraphedUpdate(lambda batch: sac_update(agent, batch), buffer.sample(BATCH), [agent.generator])
    else:
        def step(batch):
            return sac_update(agent, batch)

    def run() -> float:
        torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(updates):
            metrics = step(buffer.sample(BATCH))
        torch.cuda.synchronize()  # the only host sync: the timing needs the work done
        if not torch.isfinite(metrics["critic/td_loss"]).all():
            raise NonFiniteLoss(f"non-finite TD loss after {updates} more updates")
        return updates / (time.perf_counter() - start)

    return run


def _stable_baselines3(updates: int) -> Callable[[], float]:
    import gymnasium
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import configure

    env = gymnasium.make("Hopper-v5")
    model = SAC("MlpPolicy", env, batch_size=BATCH, learning_starts=BUFFER, buffer_size=BUFFER, seed=0,
                policy_kwargs={"net_arch": [256, 256]}, device="cuda", verbose=0)
    model.set_logger(configure(None, []))
    rng = np.random.default_rng(0)
    for _ in range(BUFFER):
        model.replay_buffer.add(rng.normal(size=(1, OBS_DIM)), rng.normal(size=(1, OBS_DIM)),
                                rng.uniform(-1, 1, size=(1, ACTION_DIM)), rng.normal(size=1), np.zeros(1), [{}])

    def run() -> float:
        torch.cuda.synchronize()
        start = time.perf_counter()
        model.train(gradient_steps=updates, batch_size=BATCH)
        torch.cuda.synchronize()
        return updates / (time.perf_counter() - start)

    return run


# Config keys that shorten the start-up phases, per method: the benchmark measures the updates the
# run spends most of its budget on, not the uniform-random prefill.
_PHASE_KEYS = {"sac-source": ("random_steps",), "sac-target": ("random_steps",), "h2o": ("random_steps",),
               "darc": ("random_steps", "warmup_steps"), "dap": ("random_steps", "warmup_steps"),
               "dap-u": ("random_steps", "warmup_steps"), "cql": ()}


def _overrides(method: str, random_steps: int) -> dict[str, str]:
    keys = _PHASE_KEYS.get(method)
    if keys is None:
        raise SystemExit(f"bench_gpu: no start-up phases known for method {method!r}; known: {sorted(_PHASE_KEYS)}")
    # warmup_steps (DARC's and DAP's classifier start) follows the random prefill, as in the defaults.
    return {key: str(random_steps * (2 if key == "warmup_steps" else 1)) for key in keys}


def _timed_train(out: Path, *, method: str, task: str, steps: int, random_steps: int, seed: int, n_seeds: int,
                 device: str) -> float:
    overrides = _overrides(method, random_steps)
    start = time.perf_counter()
    train(method, task, steps=steps, out=out, seed=seed, n_seeds=n_seeds, device=device, threads=1,
          overrides=overrides, eval_every=steps, eval_episodes=2, progress=False)
    return time.perf_counter() - start


def bench_train(method: str, task: str, steps: int, random_steps: int, gpu_seeds: int, cpu_seeds: int) -> dict:
    """Aggregate seed-steps/s of ``gpu_seeds`` trained together on CUDA and of ``cpu_seeds`` of
    them trained one after another on one CPU core."""
    common = {"method": method, "task": task, "steps": steps, "random_steps": random_steps}
    with tempfile.TemporaryDirectory() as tmp:
        # Warm-up: CUDA context, cuBLAS handles, MuJoCo model compilation.
        _timed_train(Path(tmp) / "warm-up", seed=0, n_seeds=gpu_seeds, device="cuda",
                     **common | {"steps": random_steps + 50})
        gpu_s = _timed_train(Path(tmp) / "cuda", seed=0, n_seeds=gpu_seeds, device="cuda", **common)
        cpu_s = sum(_timed_train(Path(tmp) / f"cpu-{seed}", seed=seed, n_seeds=1, device="cpu", **common)
                    for seed in range(cpu_seeds))
    gpu_rate, cpu_rate = gpu_seeds * steps / gpu_s, cpu_seeds * steps / cpu_s
    return {"method": method, "task": task, "steps_per_seed": steps, "random_steps": random_steps,
            "gpu_seeds": gpu_seeds, "cpu_seeds": cpu_seeds, "gpu_seconds": gpu_s, "cpu_seconds": cpu_s,
            "gpu_seed_steps_per_s": gpu_rate, "cpu_seed_steps_per_s": cpu_rate, "ratio": gpu_rate / cpu_rate}


def _timed_job(job: dict) -> dict:
    """One process of :func:`bench_methods` (module level so that a spawned worker can import it)."""
    seconds = _timed_train(Path(job.pop("out")), **job)
    return job | {"seconds": seconds}


def bench_methods(methods: list[str], task: str, steps: int, random_steps: int, gpu_seeds: int,
                  accelerator: str = "cuda") -> list[dict]:
    """Per method, ``gpu_seeds`` seeds trained together on CUDA against one seed trained on one CPU
    core, every run at once in its own process: a sweep's layout on one GPU machine (the GPU runs
    share the GPU, each CPU run has a core). Same method, task, steps and evaluation on both sides."""
    import concurrent.futures
    import multiprocessing

    common = {"task": task, "steps": steps, "random_steps": random_steps, "seed": 0}
    with tempfile.TemporaryDirectory() as tmp:
        # The task's official target dataset, installed and verified once before anything is timed.
        ensure_dataset(official_dataset(task, "offline-target"), progress=False, echo=print)
        jobs = [common | {"method": m, "n_seeds": n, "device": d, "out": str(Path(tmp) / f"{m}-{d}-{n}")}
                for m in methods for d, n in ((accelerator, gpu_seeds), ("cpu", 1))]
        # spawn: CUDA cannot be used in a forked child.
        done = []
        with concurrent.futures.ProcessPoolExecutor(len(jobs), mp_context=multiprocessing.get_context("spawn")) as pool:
            for future in concurrent.futures.as_completed([pool.submit(_timed_job, dict(job)) for job in jobs]):
                done.append(future.result())
                # Printed as each run ends, so a call cut short still reports the runs that finished.
                print(f"  {done[-1]['method']} on {done[-1]['device']}, {done[-1]['n_seeds']} seeds: "
                      f"{done[-1]['seconds']:.1f} s", flush=True)
    rows = []
    for method in methods:
        gpu, cpu = (next(j for j in done if j["method"] == method and j["device"] == d and j["n_seeds"] == n)
                    for d, n in ((accelerator, gpu_seeds), ("cpu", 1)))
        gpu_rate, cpu_rate = gpu["n_seeds"] * steps / gpu["seconds"], steps / cpu["seconds"]
        rows.append({"method": method, "task": task, "steps_per_seed": steps, "gpu_seeds": gpu["n_seeds"],
                     "gpu_seconds": gpu["seconds"], "cpu_seconds": cpu["seconds"],
                     "gpu_seed_steps_per_s": gpu_rate, "cpu_seed_steps_per_s": cpu_rate, "ratio": gpu_rate / cpu_rate,
                     "concurrent_processes": len(jobs)})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 20], help="none: skip the update benchmark")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--updates-per-round", type=int, default=500)
    parser.add_argument("--skip-sb3", action="store_true")
    parser.add_argument("--train-seeds", type=int, default=20, help="seeds of the whole-train run on the GPU (0: skip)")
    parser.add_argument("--train-cpu-seeds", type=int, default=2, help="of those, trained one after another on the CPU")
    parser.add_argument("--train-steps", type=int, default=2500, help="environment steps per seed")
    parser.add_argument("--train-random-steps", type=int, default=500, help="random steps before updates start")
    parser.add_argument("--train-task", default="hopper-gravity-0.5")
    parser.add_argument("--methods", nargs="*", default=[],
                        help="also train these methods at once, each seed-batched on CUDA and one seed on a CPU core")
    parser.add_argument("--methods-task", default="halfcheetah-friction-5.0")
    parser.add_argument("--methods-steps", type=int, default=3000, help="steps (CQL: updates) per seed")
    parser.add_argument("--methods-random-steps", type=int, default=500)
    parser.add_argument("--methods-gpu-seeds", type=int, default=5)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not torch.cuda.is_available():
        print(f"no CUDA device visible to torch {torch.__version__}: nothing measured", file=sys.stderr)
        return
    report: dict = {"device": torch.cuda.get_device_name(), "torch": torch.__version__, "rows": []}
    sb3 = None if args.skip_sb3 else _stable_baselines3(args.updates_per_round)

    def measure(block: dict[str, Callable[[], float]]) -> None:
        """Time the block's variants and SB3 in alternating rounds; ratios to SB3 come per round."""
        runs = block | ({"sb3": sb3} if sb3 else {})
        for run in runs.values():
            run()  # warm-up (allocator, kernels, cuBLAS handles)
        timed: dict[str, list[float]] = {name: [] for name in runs}
        for _ in range(args.rounds):
            for name, run in runs.items():
                timed[name].append(run())
        for name, rates in timed.items():
            if name == "sb3" and any(row["variant"] == "sb3" for row in report["rows"]):
                continue  # SB3's own row once, from the first block
            n = 1 if name == "sb3" else int(name.rsplit("-", 1)[1])
            row = {"variant": name, "seeds": n, "updates_per_s": statistics.median(rates),
                   "seed_updates_per_s": n * statistics.median(rates)}
            if sb3 and name != "sb3":
                row["seed_updates_vs_sb3"] = n * statistics.median(a / b for a, b in zip(rates, timed["sb3"]))
            report["rows"].append(row)
            print(f"{name:>10}: {row['updates_per_s']:9.1f} updates/s, {row['seed_updates_per_s']:10.1f} "
                  "seed-updates/s" + (f", {row['seed_updates_vs_sb3']:.1f}x SB3" if "seed_updates_vs_sb3" in row
                                      else ""), flush=True)

    measure({f"eager-{n}": _ours(n, args.updates_per_round, graphed=False) for n in args.seeds})
    # One CUDA graph at a time: only the newest GraphedUpdate of a process may replay.
    for n in args.seeds:
        try:
            graph = _ours(n, args.updates_per_round, graphed=True)
        except RuntimeError as error:  # reported, not hidden: the graph path is the one to fix
            print(f"graph capture failed for {n} seeds: {error}", file=sys.stderr)
            continue
        try:
            measure({f"graph-{n}": graph})
        except NonFiniteLoss as error:
            # Seen once on an H200 (torch 2.11), not reproduced since (README, Devices). Reported,
            # not hidden, should it come back.
            report["rows"].append({"variant": f"graph-{n}", "seeds": n, "non_finite": str(error)})
            print(f"   graph-{n}: {error}: do not train with cuda_graph=true on this machine "
                  "(benchmarks/graph_soak.py checks a graph against its eager twin)", flush=True)
    if args.train_seeds:
        t = bench_train("sac-target", args.train_task, args.train_steps, args.train_random_steps, args.train_seeds,
                        args.train_cpu_seeds)
        report["train"] = t
        print(f"whole train runs, sac-target on {t['task']}, {t['steps_per_seed']} steps per seed: {t['gpu_seeds']} "
              f"seeds together on CUDA {t['gpu_seed_steps_per_s']:.0f} seed-steps/s, one after another on one CPU "
              f"core {t['cpu_seed_steps_per_s']:.0f}, ratio {t['ratio']:.1f}x", flush=True)
    if args.methods:
        report["methods"] = bench_methods(args.methods, args.methods_task, args.methods_steps,
                                          args.methods_random_steps, args.methods_gpu_seeds)
        for row in report["methods"]:
            print(f"{row['method']:>10} on {row['task']}, {row['steps_per_seed']} steps per seed, "
                  f"{row['concurrent_processes']} processes at once: {row['gpu_seeds']} seeds on CUDA "
                  f"{row['gpu_seed_steps_per_s']:.0f} seed-steps/s ({row['gpu_seconds']:.0f} s), one seed on a CPU "
                  f"core {row['cpu_seed_steps_per_s']:.0f} ({row['cpu_seconds']:.0f} s), ratio {row['ratio']:.1f}x",
                  flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
