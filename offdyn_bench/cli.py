"""The ``offdyn-bench`` command line: tasks, datasets, train, diagnose and the demo."""

from __future__ import annotations

from pathlib import Path

import typer

from baselines.cli import train_command
from leaderboard.cli import leaderboard_app
from offdyn_bench.datasets.cli import datasets_app
from offdyn_bench.diagnose.command import diagnose_command
from offdyn_bench.task_commands import tasks_app

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="offdyn-bench: off-dynamics RL task pairs, datasets, baselines and gap diagnosis.")

app.add_typer(tasks_app, name="tasks")
app.add_typer(datasets_app, name="datasets")
app.command("train")(train_command)
app.command("diagnose")(diagnose_command)
app.add_typer(leaderboard_app, name="leaderboard")


@app.command("demo")
def demo(task: str = typer.Option("hopper-gravity-0.5", help="the pair to roll out in step 2"),
         seed: int = typer.Option(0, help="seed of the rollout"),
         out: Path = typer.Option(Path("demo-out"), help="folder for the dataset, diagnosis and runs"),
         training_steps: int = typer.Option(12_000, help="steps of each training run (0 skips training)")) -> None:
    """Run the suite end to end on an embedded default (no external service): task grid, a pair's
    divergence, a target dataset, a gap diagnosis, a short training run and its score."""
    from offdyn_bench.demo import run_demo

    run_demo(task=task, seed=seed, out=out, training_steps=training_steps)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
