"""The ``offdyn-bench`` command line: tasks, datasets, train, evaluate, protocol, leaderboard,
diagnose and the demo.

Sub-commands load on first use: ``offdyn-bench --help`` lists them from :data:`SUB_COMMANDS`
without importing their modules (the datasets, diagnosis and training code pull in torch, scipy,
minari and ``mujoco.sysid``, seconds before anything prints), and running one imports only its
own module. A new sub-command is one line in that table.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
from pathlib import Path
from typing import Any

import typer
from typer.core import TyperCommand, TyperGroup


@dataclasses.dataclass(frozen=True)
class SubCommand:
    """Where a sub-command lives (a ``typer.Typer`` app or a command function) and the one-line
    help ``--help`` shows without importing it (a test checks it matches the command's own)."""

    module: str
    attribute: str
    help: str


SUB_COMMANDS: dict[str, SubCommand] = {
    "tasks": SubCommand("offdyn_bench.task_commands", "tasks_app", "List the task pairs and show what each changes."),
    "datasets": SubCommand("offdyn_bench.datasets.cli", "datasets_app",
                           "Target datasets (Minari format): list, build from recipes, verify, download."),
    "train": SubCommand("baselines.cli", "train_command",
                        "Train a reference baseline and write config.json, metrics.jsonl, result.json and checkpoints."),
    "evaluate": SubCommand("offdyn_bench.protocol.command", "evaluate_command",
                           "Evaluate the final policy of every training seed on the task's target under the protocol: "
                           "deterministic actions, fixed episode seeds; writes raw per-episode returns with versions."),
    "protocol": SubCommand("offdyn_bench.protocol.command", "protocol_app",
                           "The fixed evaluation protocol: show it, record reference scores, score results."),
    "sweep": SubCommand("offdyn_bench.sweep.command", "sweep_command",
                        "Run a sweep of training runs and their evaluations (resumable: run it again to continue)."),
    "leaderboard": SubCommand("leaderboard.cli", "leaderboard_app",
                              "Leaderboard: assemble and validate submissions, render the board, serve it."),
    "diagnose": SubCommand("offdyn_bench.diagnose.command", "diagnose_command",
                           "Find the residual of the source model on measured data, trace it to the missing effect, "
                           "add it, and report the error before and after."),
}


def load_sub_command(name: str) -> TyperCommand | TyperGroup:
    """Import sub-command ``name`` and build its command."""
    entry = SUB_COMMANDS[name]
    target = getattr(importlib.import_module(entry.module), entry.attribute)
    if isinstance(target, typer.Typer):
        command: TyperCommand | TyperGroup = typer.main.get_group(target)
    else:
        single = typer.Typer(add_completion=False)
        single.command(name)(target)
        command = typer.main.get_command(single)
    command.name = name
    return command


class LazyCommands(TyperGroup):
    """A group whose sub-commands in :data:`SUB_COMMANDS` are imported when one is run (or its
    own help is asked for); listing them shows the table's help lines."""

    def list_commands(self, ctx: typer.Context) -> list[str]:
        return [*SUB_COMMANDS, *(name for name in self.commands if name not in SUB_COMMANDS)]

    def get_command(self, ctx: typer.Context, cmd_name: str) -> Any:
        if cmd_name in self.commands or cmd_name not in SUB_COMMANDS:
            return self.commands.get(cmd_name)
        # A stand-in that only describes the command: enough for the top-level help.
        entry = SUB_COMMANDS[cmd_name]
        return TyperCommand(cmd_name, help=entry.help, short_help=entry.help)

    def resolve_command(self, ctx: typer.Context, args: list[str]) -> Any:
        name = args[0] if args else None
        if name in SUB_COMMANDS and name not in self.commands:
            self.commands[name] = load_sub_command(name)
        elif name is not None and not name.startswith("-") and name not in self.list_commands(ctx):
            # Typer would suggest only among the commands loaded so far.
            close = difflib.get_close_matches(name, self.list_commands(ctx))
            ctx.fail(f"No such command {name!r}." + (f" Did you mean {', '.join(map(repr, close))}?" if close else ""))
        return super().resolve_command(ctx, args)


app = typer.Typer(cls=LazyCommands, no_args_is_help=True, add_completion=False,
                  help="offdyn-bench: off-dynamics RL task pairs, datasets, baselines and gap diagnosis.")


def version_lines() -> list[str]:
    """The suite's version, then the libraries its numbers depend on, read from the installed
    package metadata (nothing is imported)."""
    from importlib import metadata

    from offdyn_bench.versions import __version__

    lines = [f"offdyn-bench {__version__}"]
    for package in ("mujoco", "gymnasium", "minari", "torch"):
        try:
            lines.append(f"{package} {metadata.version(package)}")
        except metadata.PackageNotFoundError:
            lines.append(f"{package} not installed")
    return lines


def _print_version(value: bool) -> None:
    if value:
        typer.echo("\n".join(version_lines()))
        raise typer.Exit()


@app.callback()
def _top_level(version: bool = typer.Option(
        False, "--version", is_eager=True, callback=_print_version,
        help="Print the suite's version and those of MuJoCo, Gymnasium, Minari and torch, then exit.")) -> None:
    """offdyn-bench: off-dynamics RL task pairs, datasets, baselines and gap diagnosis."""


@app.command("demo")
def demo(task: str = typer.Option("hopper-gravity-0.5", help="the pair to roll out in step 2"),
         seed: int = typer.Option(0, help="seed of the rollout"),
         out: Path = typer.Option(Path("demo-out"), help="folder for the dataset, diagnosis and runs"),
         training_steps: int = typer.Option(12_000, help="steps of each training run (0 skips training)"),
         n_seeds: int = typer.Option(3, "--n-seeds", help="training seeds of each method, trained together")) -> None:
    """Run the suite end to end on an embedded default (no external service): task grid, a pair's
    divergence, a target dataset, a gap diagnosis, a short training run and its score."""
    from offdyn_bench.demo import run_demo
    from offdyn_bench.errors import exit_on_error

    with exit_on_error():
        run_demo(task=task, seed=seed, out=out, training_steps=training_steps, n_seeds=n_seeds)


def main(args: Any = None) -> None:
    app(args)


if __name__ == "__main__":
    main()
