"""The ``offdyn-bench`` command line: tasks, datasets, train, diagnose and the demo."""

from __future__ import annotations

import typer

from baselines.cli import train_command
from offdyn_bench.datasets.cli import datasets_app
from offdyn_bench.diagnose.command import diagnose_command
from offdyn_bench.task_commands import tasks_app

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="offdyn-bench: off-dynamics RL task pairs, datasets, baselines and gap diagnosis.")

app.add_typer(tasks_app, name="tasks")
app.add_typer(datasets_app, name="datasets")
app.command("train")(train_command)
app.command("diagnose")(diagnose_command)


@app.command("demo")
def demo(task: str = typer.Option("hopper-gravity-0.5", help="the pair to roll out"),
         seed: int = typer.Option(0, help="seed of the rollout")) -> None:
    """Run the suite end to end on an embedded default (no external service)."""
    from offdyn_bench.demo import run_demo

    run_demo(task=task, seed=seed)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
