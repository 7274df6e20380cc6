"""Speed of the baselines' SAC core, measured side by side in one process (ratios, not timings).

1. Gradient updates per second of this SAC against Stable-Baselines3's SAC with the same networks
   (256x256 actor and twin critics), batch 256 and observation/action sizes (Hopper's 11/3), both on
   replay buffers of random transitions. Rounds alternate between the two so background load hits
   both alike; the reported ratio is the median of the per-round ratios.
2. Several seeds trained in one process (``--n-seeds 5``: batched networks, environments stepped
   together) against the same seeds trained one after another, as aggregate training steps
   (environment step + gradient update) per second on a Hopper pair.

    .venv/bin/pip install -e ".[bench]"        # Stable-Baselines3, pinned
    .venv/bin/python benchmarks/bench_sac.py [--threads 1] [--rounds 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from baselines.buffers import ReplayBuffer
from baselines.sac import SACAgent, SACConfig, sac_update
from baselines.train import train

OBS_DIM, ACTION_DIM, BATCH = 11, 3, 256


def _ours(updates_per_round: int, hidden: int):
    agent = SACAgent(OBS_DIM, ACTION_DIM, seeds=[0], config=SACConfig(hidden_sizes=(hidden, hidden), batch_size=BATCH))
    buffer = ReplayBuffer(1, 10_000, OBS_DIM, ACTION_DIM, seed=0)
    g = torch.Generator().manual_seed(0)
    for _ in range(10_000):
        buffer.add(torch.randn(1, OBS_DIM, generator=g), torch.rand(1, ACTION_DIM, generator=g) * 2 - 1,
                   torch.randn(1, generator=g), torch.randn(1, OBS_DIM, generator=g), torch.zeros(1))

    def run() -> float:
        start = time.perf_counter()
        for _ in range(updates_per_round):
            sac_update(agent, buffer.sample(BATCH))
        return updates_per_round / (time.perf_counter() - start)

    return run


def _stable_baselines3(updates_per_round: int, hidden: int):
    import gymnasium
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import configure

    env = gymnasium.make("Hopper-v5")
    model = SAC("MlpPolicy", env, batch_size=BATCH, learning_starts=10_000, buffer_size=10_000, seed=0,
                policy_kwargs={"net_arch": [hidden, hidden]}, device="cpu", verbose=0)
    model.set_logger(configure(None, []))
    rng = np.random.default_rng(0)
    for _ in range(10_000):
        model.replay_buffer.add(rng.normal(size=(1, OBS_DIM)), rng.normal(size=(1, OBS_DIM)),
                                rng.uniform(-1, 1, size=(1, ACTION_DIM)), rng.normal(size=1), np.zeros(1),
                                [{}])

    def run() -> float:
        start = time.perf_counter()
        model.train(gradient_steps=updates_per_round, batch_size=BATCH)
        return updates_per_round / (time.perf_counter() - start)

    return run


def bench_updates(rounds: int, updates_per_round: int, hidden: int) -> dict:
    ours, theirs = _ours(updates_per_round, hidden), _stable_baselines3(updates_per_round, hidden)
    ours(), theirs()  # warm up
    pairs = [(ours(), theirs()) for _ in range(rounds)]
    ratios = [a / b for a, b in pairs]
    return {"hidden": hidden, "ours_updates_per_s": statistics.median(a for a, _ in pairs),
            "sb3_updates_per_s": statistics.median(b for _, b in pairs),
            "ratio_median": statistics.median(ratios), "ratios": ratios}


def bench_seeds(n_seeds: int, steps: int, task: str, hidden: int, rounds: int) -> dict:
    overrides = {"random_steps": "20", "sac.hidden_sizes": f"[{hidden}, {hidden}]"}
    common = dict(task=task, steps=steps, eval_every=steps, eval_episodes=1, checkpoint_every=steps,
                  progress=False, threads=None, overrides=overrides)
    together, one_by_one = [], []
    with tempfile.TemporaryDirectory() as tmp:
        # Warm-up: one-time costs (imports, model compilation, allocator) stay out of the timings.
        train("sac-source", out=Path(tmp) / "warm-up", seed=0, n_seeds=n_seeds, **common)
        for r in range(rounds):  # alternate, so background load hits both alike
            start = time.perf_counter()
            train("sac-source", out=Path(tmp) / f"together{r}", seed=0, n_seeds=n_seeds, **common)
            together.append(time.perf_counter() - start)
            start = time.perf_counter()
            for seed in range(n_seeds):
                train("sac-source", out=Path(tmp) / f"alone{r}-{seed}", seed=seed, n_seeds=1, **common)
            one_by_one.append(time.perf_counter() - start)
    total = n_seeds * steps
    return {"hidden": hidden, "n_seeds": n_seeds, "steps_per_seed": steps,
            "together_steps_per_s": total / statistics.median(together),
            "one_by_one_steps_per_s": total / statistics.median(one_by_one),
            "ratio": statistics.median(b / a for a, b in zip(together, one_by_one)),
            "ratios": [b / a for a, b in zip(together, one_by_one)]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--updates-per-round", type=int, default=100)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--seed-steps", type=int, default=300)
    parser.add_argument("--seed-rounds", type=int, default=3)
    parser.add_argument("--task", default="hopper-gravity-0.5")
    parser.add_argument("--hidden", type=int, nargs="+", default=[256],
                        help="hidden widths to measure (the issue's comparison is 256)")
    parser.add_argument("--skip-sb3", action="store_true")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    report: dict = {"threads": args.threads, "updates": [], "seeds": []}
    for hidden in args.hidden:
        if not args.skip_sb3:
            u = bench_updates(args.rounds, args.updates_per_round, hidden)
            report["updates"].append(u)
            print(f"SAC gradient updates/s ({hidden}x{hidden}, batch 256): ours {u['ours_updates_per_s']:.1f}, "
                  f"SB3 {u['sb3_updates_per_s']:.1f}, ratio {u['ratio_median']:.2f}x "
                  f"(per round: {', '.join(f'{r:.2f}' for r in u['ratios'])})", flush=True)
        s = bench_seeds(args.seeds, args.seed_steps, args.task, hidden, args.seed_rounds)
        report["seeds"].append(s)
        print(f"{s['n_seeds']} seeds x {s['steps_per_seed']} steps ({hidden}x{hidden}): together "
              f"{s['together_steps_per_s']:.1f} steps/s, one after another {s['one_by_one_steps_per_s']:.1f} steps/s, "
              f"ratio {s['ratio']:.2f}x (per round: {', '.join(f'{r:.2f}' for r in s['ratios'])})", flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
