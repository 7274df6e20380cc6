"""Is the CUDA-graph SAC update sound? A graphed agent against its eager twin, then a long soak.

On an H200 (torch 2.11) a graphed update once went non-finite where the eager one stayed finite,
and ``cuda_graph=true`` was withdrawn until this script found it exact there (README, Devices). It
checks a machine in one process, after other CUDA work (where the graph failed before):

1. twin: two agents with the same seeds (capturable Adam, as every agent on CUDA); one updates eagerly, the other
   through :class:`baselines.sac.GraphedUpdate`, on the same batches (the eager twin also makes the
   graph's warm-up updates). Every ``--every`` updates: both TD losses finite, the median TD loss
   of each over the window, and the largest parameter difference between the twins;
2. soak: the graphed agent alone for ``--soak`` more updates, every window's losses checked.

Prints a line per window and writes JSON; measures nothing without a CUDA device (exit status 0).

    python benchmarks/graph_soak.py --seeds 1 20 --twin-updates 3000 --soak 30000 --json out.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import torch

from baselines.buffers import ReplayBuffer
from baselines.sac import GraphedUpdate, SACAgent, SACConfig, sac_update

OBS_DIM, ACTION_DIM, BATCH, BUFFER = 11, 3, 256, 10_000


def filled_buffer(n_seeds: int, device: str) -> ReplayBuffer:
    """Random transitions with a learnable structure (reward = -|action|^2), so losses move."""
    buffer = ReplayBuffer(n_seeds, BUFFER, OBS_DIM, ACTION_DIM, seed=0, device=device)
    g = torch.Generator().manual_seed(0)
    for _ in range(BUFFER):
        action = torch.rand(n_seeds, ACTION_DIM, generator=g) * 2 - 1
        buffer.add(torch.randn(n_seeds, OBS_DIM, generator=g), action, -(action**2).sum(-1),
                   torch.randn(n_seeds, OBS_DIM, generator=g), torch.zeros(n_seeds))
    return buffer


def largest_difference(a: list[torch.Tensor], b: list[torch.Tensor]) -> float:
    """The largest absolute difference between two agents' stacked parameter lists."""
    return max((pa - pb).abs().max().item() for pa, pb in zip(a, b, strict=True))


def twins(n_seeds: int, device: str) -> tuple[SACAgent, SACAgent]:
    config = SACConfig(hidden_sizes=(256, 256), batch_size=BATCH)
    pair = tuple(SACAgent(OBS_DIM, ACTION_DIM, seeds=list(range(n_seeds)), config=config, device=device)
                 for _ in range(2))
    if largest_difference(pair[0].actor, pair[1].actor) != 0.0:
        raise SystemExit("graph_soak: two agents built from the same seeds differ; the twin test means nothing")
    return pair


def check(n_seeds: int, twin_updates: int, soak: int, every: int, device: str, use_graph: bool) -> dict:
    eager_agent, graph_agent = twins(n_seeds, device)
    buffer = filled_buffer(n_seeds, device)
    example = buffer.sample(BATCH)
    warmup = 3
    for _ in range(warmup):  # the graph's warm-up updates are real: the eager twin makes them too
        sac_update(eager_agent, example)
    if use_graph:
        graphed = GraphedUpdate(lambda batch: sac_update(graph_agent, batch), example, [graph_agent.generator],
                                warmup_updates=warmup)
    else:  # --eager-twin: the harness checked against itself (must report zero differences)
        for _ in range(warmup):
            sac_update(graph_agent, example)

        def graphed(batch):
            return sac_update(graph_agent, batch)

    windows: list[dict] = []
    eager_losses: list[float] = []
    graph_losses: list[float] = []
    first_non_finite = None
    for update in range(1, twin_updates + soak + 1):
        batch = buffer.sample(BATCH)
        graph_loss = graphed(batch)["critic/td_loss"]
        in_twin = update <= twin_updates
        if in_twin:
            eager_loss = sac_update(eager_agent, batch)["critic/td_loss"]
        if update % every and update != twin_updates + soak:
            continue
        # One host sync per window: the losses of its last update, every seed's.
        graph_values = graph_loss.detach().float().cpu()
        graph_losses.append(graph_values.median().item())
        row = {"update": update, "graph_td_loss_median": graph_losses[-1],
               "graph_finite": bool(torch.isfinite(graph_values).all())}
        if in_twin:
            eager_values = eager_loss.detach().float().cpu()
            eager_losses.append(eager_values.median().item())
            row |= {"eager_td_loss_median": eager_losses[-1], "eager_finite": bool(torch.isfinite(eager_values).all()),
                    "largest_actor_difference": largest_difference(eager_agent.actor, graph_agent.actor),
                    "largest_critic_difference": largest_difference(eager_agent.critic, graph_agent.critic)}
        windows.append(row)
        print(f"  {n_seeds:>2} seeds, update {update:>6}: " + ", ".join(
            f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items() if k != "update"),
            flush=True)
        if not row["graph_finite"] and first_non_finite is None:
            first_non_finite = update
            break
    return {"seeds": n_seeds, "twin_updates": twin_updates, "soak_updates": soak, "graphed": use_graph,
            "first_non_finite_update": first_non_finite, "windows": windows,
            "eager_td_loss_median_of_windows": statistics.median(eager_losses) if eager_losses else None,
            "graph_td_loss_median_of_twin_windows": (statistics.median(graph_losses[:len(eager_losses)])
                                                     if eager_losses else None)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 20])
    parser.add_argument("--twin-updates", type=int, default=3000)
    parser.add_argument("--soak", type=int, default=30_000)
    parser.add_argument("--every", type=int, default=500)
    parser.add_argument("--eager-twin", action="store_true",
                        help="replace the graph with a second eager agent (checks the harness; runs on CPU)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.eager_twin:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    elif not torch.cuda.is_available():
        print(f"no CUDA device visible to torch {torch.__version__}: nothing measured", file=sys.stderr)
        return
    else:
        device = "cuda"
    report = {"device": torch.cuda.get_device_name() if device == "cuda" else "cpu", "torch": torch.__version__,
              "checks": []}
    for n_seeds in args.seeds:
        # One GraphedUpdate at a time per process is allowed to replay: each check builds its own,
        # newest, so earlier checks' graphs are never replayed again.
        report["checks"].append(check(n_seeds, args.twin_updates, args.soak, args.every, device,
                                      use_graph=not args.eager_twin))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
