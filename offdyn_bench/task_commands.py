"""``offdyn-bench tasks list | show``: the task grid and what each pair changes."""

from __future__ import annotations

import collections
import json
import re

import typer

from offdyn_bench.effects.model import ModelEffect
from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.robots import get_robot
from offdyn_bench.tasks import SIDES, TASKS, TaskPair, get_task

tasks_app = typer.Typer(no_args_is_help=True, help="List the task pairs and show what each changes.")


def grid_summary() -> str:
    """A robot x shift-family table of how many pairs the grid has."""
    counts: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for pair in TASKS.values():
        counts[pair.robot][pair.shift] += 1
    families = sorted({pair.shift for pair in TASKS.values()})
    width = max(len(r) for r in counts) + 2
    lines = [" " * width + "  ".join(families)]
    for robot in sorted(counts):
        cells = [str(counts[robot].get(f, "-")).center(len(f)) for f in families]
        lines.append(robot.ljust(width) + "  ".join(cells))
    lines.append(f"{len(TASKS)} pairs, {2 * len(TASKS)} registered Gymnasium ids")
    return "\n".join(lines)


def plain_text(docstring_line: str) -> str:
    """A docstring line as a terminal shows it: without reST markup (````x````, ``:class:`X```)."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", docstring_line)
    return text.replace("``", "")


def describe_pair(pair: TaskPair) -> str:
    """The pair's effects and the compiled differences of each side from the robot's base model."""
    # Here, not at the top: listing tasks (and the CLI's help) needs neither MuJoCo nor the envs.
    from offdyn_bench.envs import ENV_CLASSES
    from offdyn_bench.model_diff import model_differences

    robot = get_robot(pair.robot)
    lines = [f"{pair.name}  (version {pair.version})", f"  {pair.description}" if pair.description else "",
             f"  robot: {robot.name} ({robot.env_class})"]
    base = ENV_CLASSES[pair.robot]().unwrapped.model
    for side in SIDES:
        effects = pair.effects(side)
        lines.append(f"\n{side}: {pair.env_id(side)}")
        if pair.engine(side) != "mujoco":  # the engine is the shift: the same MJCF on another simulator
            lines.append(f"  physics engine: {pair.engine(side)} ({pair.entry_point(side)}), the same MJCF file")
        if not effects and pair.engine(side) != "mujoco":
            lines.append("  effects: none")
            continue
        if not effects:
            lines.append("  effects: none (the nominal model)")
            continue
        lines.append("  effects:")
        lines += [f"    - {effect.describe()}" for effect in effects]
        model_effects = [e for e in effects if isinstance(e, ModelEffect)]
        channel_effects = [e for e in effects if not isinstance(e, ModelEffect)]
        if model_effects:
            compiled = ENV_CLASSES[pair.robot](model_effects=model_effects).unwrapped.model
            lines.append("  compiled model, differences from the base model:")
            lines += ["    " + line for d in model_differences(base, compiled) for line in d.describe().splitlines()]
        if channel_effects:
            lines.append("  channel (between agent and physics; the compiled model is the base model):")
            lines += [f"    - {plain_text((type(e).__doc__ or e.kind).strip().splitlines()[0])}" for e in channel_effects]
    return "\n".join(line for line in lines if line != "")


@tasks_app.command("list")
def list_tasks(
    robot: str = typer.Option(None, help="only this robot, e.g. Hopper"),
    shift: str = typer.Option(None, help="only this shift family, e.g. gravity"),
    as_json: bool = typer.Option(False, "--json", help="print the full definitions as JSON"),
) -> None:
    """List the task pairs (name, source id, target id)."""
    robots = {p.robot.lower(): p.robot for p in TASKS.values()}
    shifts = {p.shift for p in TASKS.values()}
    try:
        if robot is not None and robot.lower() not in robots:
            raise UnknownNameError("robot", robot, robots.values())
        if shift is not None and shift not in shifts:
            raise UnknownNameError("shift family", shift, shifts)
    except OffdynError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(2) from None
    pairs = [p for p in TASKS.values()
             if (robot is None or p.robot.lower() == robot.lower()) and (shift is None or p.shift == shift)]
    if as_json:
        typer.echo(json.dumps([p.to_dict() for p in pairs], indent=2))
        return
    if not pairs:
        families = sorted({p.shift for p in TASKS.values() if p.robot.lower() == str(robot).lower()})
        typer.echo(f"no pair of {robots[str(robot).lower()]} has the shift {shift!r}; its shift families: "
                   + ", ".join(families), err=True)
        return
    if robot is None and shift is None:
        typer.echo(grid_summary() + "\n")
    for pair in pairs:
        typer.echo(f"{pair.name:<36} {pair.env_id('source')}  ->  {pair.env_id('target')}")


@tasks_app.command("show")
def show_task(task: str = typer.Argument(..., help="a task name, e.g. hopper-gravity-0.5")) -> None:
    """Show a pair's effects and how its compiled models differ from the base model."""
    try:
        pair = get_task(task)
    except OffdynError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(2) from None
    typer.echo(describe_pair(pair))
