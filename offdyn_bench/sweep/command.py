"""``offdyn-bench sweep SPEC``: run methods x tasks x seeds, locally or on Ray, resumably.

Only typer and the standard library load with this module; the spec, the registry and the
backends load when the command runs.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Annotated

import typer

from offdyn_bench.errors import OffdynError, exit_on_error


def sweep_command(
    spec_path: Annotated[Path, typer.Argument(metavar="SPEC", help="Sweep spec file (YAML, or JSON by its .json "
                                                                   "suffix): methods, tasks, seeds, track, budget, "
                                                                   "out, retries and resources.")],
    backend: Annotated[str, typer.Option(help="local (a pool of runs on this machine) or ray (one Ray task per "
                                              "run; ray_address in the spec, or a local Ray instance).")] = "local",
    workers: Annotated[int | None, typer.Option(help="Runs at once (local; default: CPUs / cpus_per_run), or "
                                                        "the CPUs of a local Ray instance's runs.")] = None,
    out: Annotated[Path | None, typer.Option(help="Output folder (replaces the spec's out).")] = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="List the runs and their commands; run nothing.")] = False,
    status: Annotated[bool, typer.Option("--status", help="Where the sweep in OUT stands (from another shell while "
                                                          "it runs, or after it stopped): each run's status, "
                                                          "steps, tries and compute, and the ETA; runs and "
                                                          "writes nothing.")] = False,
    submit: Annotated[bool, typer.Option("--submit", help="When every run of a method is done and the sweep is a "
                                                          "protocol result (core suite, budget, seeds), write its "
                                                          "leaderboard submission to OUT/submission/METHOD.json.")]
    = False,
    description: Annotated[str, typer.Option(help="Method description for --submit.")] = "",
    quiet: Annotated[bool, typer.Option("--quiet", help="No progress lines; only the summary.")] = False,
    start_before: Annotated[str | None, typer.Option(
        "--start-before", metavar="DURATION",
        help="Start no run or retry after this long (90m, 2h, 1h30m): the runs in flight finish, the rest stay "
             "pending, and the sweep exits with code 3; run it again to continue. For an allocation or a lease "
             "that ends: leave it the longest run's time.")] = None,
    skip_published: Annotated[bool, typer.Option(
        "--skip-published",
        help="Leave out the runs whose records are published already in the reference runs (as "
             "`leaderboard coverage` counts them): fill in a reference grid with only what is missing. Give it "
             "to --status and --dry-run too.")] = False,
    reference_runs: Annotated[Path | None, typer.Option(
        "--reference-runs", help="The published runs --skip-published reads (default: the repository's "
                                 "leaderboard/reference-runs).")] = None,
) -> None:
    """Run a sweep of training runs and their evaluations (resumable: run it again to continue)."""
    import shlex

    from offdyn_bench.sweep.execute import command_line
    from offdyn_bench.sweep.spec import load_spec

    with exit_on_error():
        from offdyn_bench.sweep.driver import parse_duration

        limit = parse_duration(start_before) if start_before is not None else None
        spec = load_spec(spec_path, out=out)
        if reference_runs is not None and not skip_published:
            raise OffdynError("--reference-runs says where --skip-published looks for published runs; give "
                              "--skip-published too, or drop --reference-runs")
        skip: frozenset[str] = frozenset()
        if skip_published:
            from leaderboard.coverage import reference_coverage
            from leaderboard.reference_runs import REFERENCE_RUNS_DIR

            coverage = reference_coverage(spec, reference_runs or REFERENCE_RUNS_DIR)
            skip = coverage.skippable
            if coverage.partly_published and not status:
                raise OffdynError(_partly_published_message(coverage.partly_published))
        again = shlex.quote(str(spec_path)) + (" --skip-published" if skip_published else "")
        if status:
            if dry_run or submit or start_before is not None:
                raise OffdynError("--status only reads where the sweep stands; it takes no --dry-run, --submit "
                                  "or --start-before")
            from offdyn_bench.sweep.status import read_status, status_lines

            for line in status_lines(read_status(spec, skip), spec_path=again):
                typer.echo(line)
            return
        if dry_run:
            from offdyn_bench.sweep.runs import expand, run_finished

            runs = expand(spec)
            for run in runs:
                status = "published: skipped" if run.run_id in skip else "done" if run_finished(run) else "to run"
                shared = f", scores the policy of {run.shared_training}" if run.shared_training is not None else ""
                typer.echo(f"{run.run_id} ({status}{shared})")
                for args in filter(None, (run.train_args, run.evaluate_args, run.source_evaluate_args)):
                    typer.echo("  " + shlex.join(["offdyn-bench", *args]))
            published = f" ({len(skip)} published: skipped)" if skip else ""
            typer.echo(f"{len(runs)} runs{published}; python: {command_line([])[0]}")
            return
        from offdyn_bench.sweep.driver import run_sweep, summary_lines

        report = run_sweep(spec, backend=backend, workers=workers, echo=None if quiet else _progress_echo,
                           submit=submit, description=description, start_before=limit, skip=skip)
    for line in summary_lines(report):
        typer.echo(line)
    if report.failed:
        raise typer.Exit(1)
    if report.not_started:
        raise typer.Exit(3)  # unfinished, but nothing wrong: a loop can tell it from done (0) and failed (1)


def _partly_published_message(partly: Mapping[str, tuple[int, ...]]) -> str:
    """Why a sweep with runs whose seeds are partly published is refused, and what to run instead."""
    named = "; ".join(f"{run_id} (seed(s) {', '.join(map(str, seeds))} published)"
                      for run_id, seeds in sorted(partly.items()))
    return (f"{len(partly)} run(s) of the spec train seeds that are published already in other seed folders: "
            f"{named}. A seed is published once (publish-runs refuses a second), so these runs could not be "
            "published: give the spec only the unpublished seeds in `seeds`, or `seeds_per_run: 1`")


def _progress_echo(line: str) -> None:
    typer.echo(line, err=True)
