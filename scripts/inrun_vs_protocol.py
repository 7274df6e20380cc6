"""Why a run's last in-run evaluation and its protocol evaluation disagree.

The trainer's in-run evaluation (`metrics.jsonl`, 10 episodes on its own episode seeds) runs the
torch actor on float32 observations; `offdyn-bench evaluate` (PROTOCOL.md §4, 20 episodes on the
protocol's seeds) runs the same weights in float64. This script scores one finished run's final
policy, through the protocol's own agent loader, three ways:

1. on the trainer's in-run episode seeds, exactly as the protocol evaluates;
2. on the same seeds with each observation rounded to float32 first (what the trainer's actor sees);
3. the run's recorded protocol evaluation (`evaluation.json`), as stored.

Where 1 and 2 differ episode by episode, the robot's episodes are chaotic: a rounding of the
inputs alone moves a return, and the two evaluations can only agree in distribution, not per
episode. Compare the means with their standard errors, never the numbers bit for bit.

    .venv/bin/python scripts/inrun_vs_protocol.py runs/<sweep>/runs/sac-target/<task>/seed-0
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from leaderboard.assemble import read_learning_curve
from offdyn_bench.envs import flat_observations
from offdyn_bench.errors import OffdynError
from offdyn_bench.evaluate import Agent, load_run_agents, read_evaluation, run_episode
from offdyn_bench.tasks import get_task


class Float32Observations:
    """``agent`` fed each observation rounded to float32, as the trainer's torch actor receives it."""

    def __init__(self, agent: Agent) -> None:
        self.agent = agent

    def act(self, observation: np.ndarray) -> np.ndarray:
        return self.agent.act(np.asarray(observation, dtype=np.float32).astype(np.float64))


def _describe(name: str, returns: list[float]) -> str:
    values = np.asarray(returns, dtype=np.float64)
    error = values.std(ddof=1) / np.sqrt(len(values)) if len(values) > 1 else float("nan")
    listed = ", ".join(f"{x:.1f}" for x in values)
    return f"{name}: mean {values.mean():.1f} +- {error:.1f} (standard error, {len(values)} episodes): {listed}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=pathlib.Path, help="a finished `offdyn-bench train` run folder, one training seed")
    args = parser.parse_args()
    try:
        loaded = load_run_agents(args.run)
        evaluation = read_evaluation(args.run / "evaluation.json")
        curve = read_learning_curve(args.run / "metrics.jsonl", len(loaded.agents))
    except OffdynError as error:
        raise SystemExit(f"error: {error}") from None
    if len(loaded.agents) != 1:
        raise SystemExit(f"error: {args.run} holds {len(loaded.agents)} training seeds; pass a run of one seed "
                         "(a sweep's run folder)")
    if not curve:
        raise SystemExit(f"error: {args.run} has no in-run evaluation (metrics.jsonl) to compare with")
    # The episode seeds the trainer recorded for its in-run evaluation (load_run_agents checked the file).
    in_run_seeds = [int(s) for s in json.loads((args.run / "result.json").read_text())["eval_episode_seeds"]]
    seed, agent = loaded.agents[0]
    env = flat_observations(get_task(loaded.task).make("target"))
    try:
        exact = [run_episode(agent, env, s, f"episode seed {s}").episode_return for s in in_run_seeds]
        rounded = [run_episode(Float32Observations(agent), env, s, f"episode seed {s}").episode_return
                   for s in in_run_seeds]
    finally:
        env.close()
    last = curve[-1]
    print(f"{loaded.method} on {loaded.task}, training seed {seed}, final policy ({loaded.steps} steps)")
    print(f"trainer's in-run evaluation at step {last['step']}: {last['target_return'][0]:.1f} "
          f"({len(in_run_seeds)} episodes, torch float32)")
    print(_describe("its episode seeds, protocol loader (float64)", exact))
    print(_describe("its episode seeds, float32 observations", rounded))
    recorded = [x for entry in evaluation["seeds"] for x in entry["returns"]]
    print(_describe("protocol evaluation.json (its own seeds)", recorded))
    moved = float(np.mean(np.abs(np.subtract(exact, rounded))))
    print(f"float32 rounding of the observations alone moves an episode's return by {moved:.1f} on average")


if __name__ == "__main__":
    main()
