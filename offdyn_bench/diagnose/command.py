"""``offdyn-bench diagnose``: the gap-diagnosis loop on the command line."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from offdyn_bench.errors import OffdynError


def diagnose_command(
    env: str = typer.Option(..., "--env", help="source env id: any Gymnasium MuJoCo id (Hopper-v5, offdyn/..., your own)"),
    data: str = typer.Option(..., "--data", help="measured data: an .npz file or a Minari dataset id or directory"),
    out: Optional[Path] = typer.Option(None, "--out", help="directory for diagnosis.json, report.md and the plot"),
    json_path: Optional[Path] = typer.Option(None, "--json", help="write the JSON result to this file"),
    horizon: int = typer.Option(10, help="H of the H-step open-loop error"),
    max_effects: int = typer.Option(4, help="add at most this many effects"),
    seed: int = typer.Option(0, help="seed of the train/held-out split and the subsets"),
) -> None:
    """Find the residual of the source model on measured data, trace it to the missing effect,
    add it, and report the error before and after."""
    from offdyn_bench.diagnose.loop import DiagnosisSettings, diagnose
    from offdyn_bench.diagnose.report import summary_text, write_json, write_report

    if horizon < 1 or max_effects < 0:
        typer.echo("error: --horizon must be >= 1 and --max-effects >= 0", err=True)
        raise typer.Exit(2)
    try:
        result = diagnose(env, data, DiagnosisSettings(horizon=horizon, max_effects=max_effects, seed=seed))
    except OffdynError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(2) from None
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
