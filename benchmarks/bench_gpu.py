"""Seed-batched SAC updates on a GPU, measured side by side in one process (ratios, not timings).

Issue 9's targets on an H100: one seed at least 10x Stable-Baselines3's SAC updates/s on the same
GPU (SB3 measured 105 updates/s there), and 20 seeds at least 10,000 seed-updates/s. Measured, in
alternating rounds so background load hits every variant alike:

* ``sb3``: Stable-Baselines3 SAC, ``model.train`` on a filled buffer, ``device="cuda"``;
* ``eager``: :func:`baselines.sac.sac_update`, all seeds' networks batched, on the GPU;
* ``graph``: the same update replayed from a CUDA graph (:class:`baselines.sac.GraphedUpdate`);

each with 256x256 networks, batch 256, Hopper's sizes (11/3), random transitions, for 1 seed and
for ``--seeds`` seeds. Without a CUDA device it says so and measures nothing (exit status 0).

    .venv/bin/pip install -e ".[bench]"        # Stable-Baselines3, pinned
    .venv/bin/python benchmarks/bench_gpu.py [--seeds 1 20] [--rounds 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from baselines.buffers import ReplayBuffer
from baselines.sac import GraphedUpdate, SACAgent, SACConfig, make_capturable, sac_update

OBS_DIM, ACTION_DIM, BATCH, BUFFER = 11, 3, 256, 10_000


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
        assert torch.isfinite(metrics["critic/td_loss"]).all()
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 20])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--updates-per-round", type=int, default=500)
    parser.add_argument("--skip-sb3", action="store_true")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not torch.cuda.is_available():
        print(f"no CUDA device visible to torch {torch.__version__}: nothing measured", file=sys.stderr)
        return
    report: dict = {"device": torch.cuda.get_device_name(), "torch": torch.__version__, "rows": []}
    sb3 = None if args.skip_sb3 else _stable_baselines3(args.updates_per_round)
    variants: dict[str, Callable[[], float]] = {}
    for n in args.seeds:
        variants[f"eager-{n}"] = _ours(n, args.updates_per_round, graphed=False)
        try:
            variants[f"graph-{n}"] = _ours(n, args.updates_per_round, graphed=True)
        except RuntimeError as error:  # reported, not hidden: the graph path is the one to fix
            print(f"graph capture failed for {n} seeds: {error}", file=sys.stderr)
    timed = {name: [] for name in variants} | ({"sb3": []} if sb3 else {})
    for run in list(variants.values()) + ([sb3] if sb3 else []):
        run()  # warm-up (allocator, kernels, cuBLAS handles)
    for _ in range(args.rounds):
        for name, run in variants.items():
            timed[name].append(run())
        if sb3:
            timed["sb3"].append(sb3())
    for name, rates in timed.items():
        n = 1 if name == "sb3" else int(name.rsplit("-", 1)[1])
        row = {"variant": name, "seeds": n, "updates_per_s": statistics.median(rates),
               "seed_updates_per_s": n * statistics.median(rates)}
        if sb3 and name != "sb3":
            ratios = [a / b for a, b in zip(rates, timed["sb3"])]
            row["seed_updates_vs_sb3"] = n * statistics.median(ratios)
        report["rows"].append(row)
        print(f"{name:>10}: {row['updates_per_s']:9.1f} updates/s, {row['seed_updates_per_s']:10.1f} seed-updates/s"
              + (f", {row['seed_updates_vs_sb3']:.1f}x SB3" if "seed_updates_vs_sb3" in row else ""), flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
