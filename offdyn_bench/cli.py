"""The ``offdyn-bench`` command line."""

from __future__ import annotations

import typer

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="offdyn-bench: off-dynamics RL task pairs, datasets, baselines and gap diagnosis.")

# --- sub-commands are attached below (one line each) ---
from offdyn_bench.task_commands import tasks_app  # noqa: E402

app.add_typer(tasks_app, name="tasks")
from offdyn_bench.datasets.cli import datasets_app  # noqa: E402

app.add_typer(datasets_app, name="datasets")
from baselines.cli import train_command  # noqa: E402

app.command("train")(train_command)
from offdyn_bench.diagnose.command import diagnose_command  # noqa: E402

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
