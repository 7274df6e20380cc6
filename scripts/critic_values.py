"""Print what runs' critics believe next to what their target data earned (baselines/critic_values.py).

    PYTHONPATH=. .venv/bin/python scripts/critic_values.py RUN_DIR... [--every-checkpoint] [--jsonl FILE]

One row per run, checkpoint and training seed: the data's discounted return-to-go ("G"), the twin
critics' minimum on the data's transitions, at the policy's action and at random actions on the
data's states, and, where the checkpoint holds a simulated buffer, its return-to-go, the critics
on its transitions and at the policy's action on its states. ``--every-checkpoint``
reads each checkpoint the run keeps (the newest two), not only the newest; ``--jsonl`` appends
each row as a JSON line (a run followed during training is read again and again: rows of a
checkpoint already in the file are not written twice).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from baselines.checkpoint import checkpoints
from baselines.critic_values import CriticValues, read_critic_values
from offdyn_bench.errors import OffdynError

COLUMNS = ("run", "step", "seed", "data G", "Q data", "Q pi(s)", "Q rand", "buffer G", "Q buffer", "Q pi(buf)")


def _row(run: Path, values: CriticValues) -> tuple[str, ...]:
    def cell(value: float | None) -> str:
        return "-" if value is None else f"{value:,.1f}"

    return (str(run), str(values.step), str(values.seed), cell(values.data_return_to_go), cell(values.q_data),
            cell(values.q_policy_at_data_states), cell(values.q_random_at_data_states),
            cell(values.buffer_return_to_go), cell(values.q_buffer),
            cell(values.q_policy_at_buffer_states))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--every-checkpoint", action="store_true")
    parser.add_argument("--jsonl", type=Path)
    args = parser.parse_args(argv)
    seen = set()
    if args.jsonl and args.jsonl.exists():
        for line in args.jsonl.read_text().splitlines():
            entry = json.loads(line)
            seen.add((entry["run"], entry["step"], entry["seed"]))
    rows = []
    try:
        for run in args.runs:
            targets = checkpoints(run) if args.every_checkpoint else [None]
            for checkpoint in targets:
                for values in read_critic_values(run, checkpoint):
                    rows.append(_row(run, values))
                    key = (str(run), values.step, values.seed)
                    if args.jsonl and key not in seen:
                        seen.add(key)
                        with args.jsonl.open("a") as out:
                            out.write(json.dumps({"run": str(run), **dataclasses.asdict(values)}) + "\n")
    except OffdynError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(COLUMNS)]
    for row in (COLUMNS, *rows):  # the run's path left-aligned, the numbers right-aligned
        print("  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(row, widths))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
