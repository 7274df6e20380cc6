"""Cost of a CQL update relative to a SAC update on the same batch, measured side by side in one
process (ratios, not timings).

Three updates on one fixed batch (Hopper's sizes: observation 11, action 3; batch 256; networks
256x256; one seed): plain SAC (:func:`baselines.sac.sac_update`), CQL as it is
(:meth:`baselines.cql.CQL.conservative_penalty`: one critic pass over every sampled action, the
policy run once per state, the data term taken from the TD loss) and CQL as first written
(:meth:`~baselines.cql.CQL.conservative_penalty_unbatched`: three critic passes plus one on the
data actions, the policy run on every repeated state). Rounds alternate between the three so
background load hits all alike; reported: the median over rounds of CQL-update-time /
SAC-update-time for both CQL versions, and of unbatched-time / batched-time.

    .venv/bin/python benchmarks/bench_cql.py [--threads 1] [--rounds 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from baselines import cql
from baselines.method import MethodContext
from baselines.sac import Batch, SACAgent, SACConfig, sac_update

OBS_DIM, ACTION_DIM, BATCH, DATASET = 11, 3, 256, 10_000


def _dataset() -> Batch:
    g = torch.Generator().manual_seed(0)
    return Batch(torch.randn(DATASET, OBS_DIM, generator=g), torch.rand(DATASET, ACTION_DIM, generator=g) * 2 - 1,
                 torch.randn(DATASET, generator=g), torch.randn(DATASET, OBS_DIM, generator=g),
                 (torch.rand(DATASET, generator=g) < 0.01).float())


def _updaters(hidden: int) -> dict[str, Callable[[], None]]:
    sac_config = SACConfig(hidden_sizes=(hidden, hidden), batch_size=BATCH)
    context = MethodContext(OBS_DIM, ACTION_DIM, seeds=(0,), target_data=_dataset())
    batch = cql.CQL(cql.Config(sac=sac_config), context).data.sample(BATCH)  # one batch for all three
    sac_agent = SACAgent(OBS_DIM, ACTION_DIM, (0,), sac_config)
    batched = cql.CQL(cql.Config(sac=sac_config), context)
    unbatched = cql.CQL(cql.Config(sac=sac_config), context)
    return {
        "sac": lambda: sac_update(sac_agent, batch),
        "cql": lambda: sac_update(batched.agent, batch, extra_loss=batched.conservative_penalty(batch)),
        "cql_unbatched": lambda: sac_update(unbatched.agent, batch,
                                            extra_loss=unbatched.conservative_penalty_unbatched(batch)),
    }


def _seconds_per_update(update: Callable[[], None], updates: int) -> float:
    start = time.perf_counter()
    for _ in range(updates):
        update()
    return (time.perf_counter() - start) / updates


def bench(rounds: int, sac_updates: int, cql_updates: int, hidden: int) -> dict:
    updaters = _updaters(hidden)
    counts = {"sac": sac_updates, "cql": cql_updates, "cql_unbatched": cql_updates}
    for name, update in updaters.items():  # warm up (allocator, first-call costs)
        _seconds_per_update(update, 2)
    times: dict[str, list[float]] = {name: [] for name in updaters}
    for _ in range(rounds):
        for name, update in updaters.items():
            times[name].append(_seconds_per_update(update, counts[name]))
    per_round = {
        "cql_over_sac": [c / s for c, s in zip(times["cql"], times["sac"])],
        "cql_unbatched_over_sac": [c / s for c, s in zip(times["cql_unbatched"], times["sac"])],
        "unbatched_over_batched": [u / c for u, c in zip(times["cql_unbatched"], times["cql"])],
    }
    return {"hidden": hidden, "batch": BATCH, "n_action_samples": cql.Config().n_action_samples,
            "updates_per_s": {name: 1.0 / statistics.median(t) for name, t in times.items()},
            "ratios_median": {name: statistics.median(r) for name, r in per_round.items()},
            "ratios_per_round": per_round}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--sac-updates", type=int, default=40, help="SAC updates per round")
    parser.add_argument("--cql-updates", type=int, default=4, help="updates per round of each CQL version")
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    report = bench(args.rounds, args.sac_updates, args.cql_updates, args.hidden) | {"threads": args.threads}
    rate, ratio = report["updates_per_s"], report["ratios_median"]
    print(f"updates/s ({args.hidden}x{args.hidden}, batch {BATCH}, {report['n_action_samples']} samples per kind): "
          f"SAC {rate['sac']:.1f}, CQL {rate['cql']:.2f}, CQL unbatched {rate['cql_unbatched']:.2f}")
    print(f"CQL-update / SAC-update time: {ratio['cql_over_sac']:.2f}x (unbatched: "
          f"{ratio['cql_unbatched_over_sac']:.2f}x); unbatched / batched: {ratio['unbatched_over_batched']:.2f}x")
    print("per round, CQL/SAC: " + ", ".join(f"{r:.2f}" for r in report["ratios_per_round"]["cql_over_sac"])
          + "; unbatched/batched: "
          + ", ".join(f"{r:.2f}" for r in report["ratios_per_round"]["unbatched_over_batched"]))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
