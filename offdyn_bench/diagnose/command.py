"""``offdyn-bench diagnose``: the gap-diagnosis loop on the command line."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from offdyn_bench.errors import OffdynError


def _fail(message: str) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(2)


def diagnose_command(
    env: str = typer.Option(..., "--env", help="source env id: any Gymnasium MuJoCo id (Hopper-v5, offdyn/..., your own)"),
    data: str = typer.Option(..., "--data", help="measured data: an .npz file or a Minari dataset id or directory"),
    out: Optional[Path] = typer.Option(None, "--out", help="directory for diagnosis.json, report.md and the plot"),
    json_path: Optional[Path] = typer.Option(None, "--json", help="write the JSON result to this file"),
    horizon: int = typer.Option(10, help="H of the H-step open-loop error, in control steps (1 to 1000)"),
    search_horizon: int = typer.Option(1, help="steps ahead the search compares (1 to 1000): more than 1 for "
                                               "high-rate data whose one-step change is below the sensor noise"),
    search_target: str = typer.Option("auto", help="what the search compares predictions with: observations, "
                                                   "states (the stored physics states: the dynamics without the "
                                                   "sensors) or auto (states where the data store them and the "
                                                   "sensors differ from them)"),
    max_effects: int = typer.Option(4, help="add at most this many effects (0 to 20)"),
    seed: int = typer.Option(0, help="seed of the train/held-out split and the subsets"),
) -> None:
    """Find the residual of the source model on measured data, trace it to the missing effect,
    add it, and report the error before and after."""
    # Bad settings or an unwritable output fail at once, before the diagnosis spends minutes.
    from offdyn_bench.diagnose.loop import DiagnosisSettings
    from offdyn_bench.diagnose.report import unwritable_reason

    try:
        settings = DiagnosisSettings(horizon=horizon, search_horizon=search_horizon, max_effects=max_effects, seed=seed,
                                     search_target=search_target)  # type: ignore[arg-type]  # checked there
    except OffdynError as error:
        raise _fail(str(error)) from None
    for path, directory, option in ((out, True, "--out"), (json_path, False, "--json")):
        if path is None:
            continue
        try:
            reason = unwritable_reason(path, directory=directory)
        except (OSError, ValueError) as error:
            reason = f"{path}: {error}"
        if reason is not None:
            raise _fail(f"{option}: {reason}; nothing was run")

    from offdyn_bench.diagnose.loop import diagnose
    from offdyn_bench.diagnose.report import summary_text, write_json, write_report

    try:
        result = diagnose(env, data, settings)
    except OffdynError as error:
        raise _fail(str(error)) from None
    typer.echo(summary_text(result))
    try:
        if out is not None:
            paths = write_report(result, out)
            typer.echo(f"report written to {paths['report']}")
        if json_path is not None:
            write_json(result, json_path)
            typer.echo(f"JSON written to {json_path}")
    except OSError as error:
        typer.echo(f"error: cannot write the results: {error}", err=True)
        raise typer.Exit(1) from None
