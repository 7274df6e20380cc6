"""``offdyn-bench leaderboard submit | publish-runs | coverage | validate | build | serve | token``.

Only typer and the standard library are imported here: the CLI imports this module at start, so
numpy, jsonschema, matplotlib, SQLAlchemy, Starlette and uvicorn load inside the commands.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from offdyn_bench.errors import OffdynError, exit_on_error

leaderboard_app = typer.Typer(no_args_is_help=True, add_completion=False,
                              help="Leaderboard: assemble and validate submissions, render the board, serve it.")
token_app = typer.Typer(no_args_is_help=True, add_completion=False,
                        help="Submitter tokens of a served leaderboard (stored as sha256 hashes).")
leaderboard_app.add_typer(token_app, name="token")

_REPO_STORE = Path(__file__).resolve().parent / "submissions"
DEFAULT_DB = "sqlite:///leaderboard.sqlite3"

StoreOption = Annotated[Path, typer.Option(
    "--store", help="Folder of <method>__<track>__<budget>.json submissions (default: the repository's store).")]
DbOption = Annotated[str, typer.Option(
    "--db", help="SQLAlchemy database URL, e.g. sqlite:///leaderboard.sqlite3 or "
                 "postgresql+psycopg://user@host/dbname.")]
ReferencesOption = Annotated[Optional[Path], typer.Option(
    "--references", help="Reference-score file (default: the shipped assets/reference_scores.json).")]


@leaderboard_app.command("submit")
def submit_command(
    runs_dir: Annotated[Path, typer.Argument(help="Folder holding one evaluated run folder (evaluation.json) "
                                                  "per core-suite task.")],
    method: Annotated[str, typer.Option(help="Method name: lower-case letters, digits and . _ + - (max 48).")],
    out: Annotated[Path, typer.Option(help="Submission file to write.")],
    description: Annotated[str, typer.Option(help="One paragraph on the method.")] = "",
    code_url: Annotated[Optional[str], typer.Option(help="http(s) URL of the code that produced the runs.")] = None,
    commit: Annotated[Optional[str], typer.Option(help="Commit of --code-url (hex).")] = None,
    track: Annotated[Optional[str], typer.Option(help="Expected track; default: the evaluations' own.")] = None,
    budget: Annotated[Optional[str], typer.Option(help="Expected budget; default: the evaluations' own.")] = None,
    learning_curves: Annotated[bool, typer.Option(help="Include metrics.jsonl learning curves when present.")] = True,
    merge_seeds: Annotated[bool, typer.Option(
        help="Take one evaluation per training seed (a sweep's run folders, leaderboard/reference-runs/<budget>/"
             "<method>) and merge each task's, checked to be evaluated alike.")] = False,
    core_suite_only: Annotated[bool, typer.Option(
        help="Leave out evaluations of tasks outside the core suite (a sweep that also screened other tasks) "
             "instead of refusing them; each left-out task is listed.")] = False,
    force: Annotated[bool, typer.Option(help="Replace an existing --out file.")] = False,
) -> None:
    """Assemble a submission from the evaluation.json files under RUNS_DIR and validate it."""
    with exit_on_error():
        from leaderboard.assemble import assemble_submission
        from leaderboard.store import write_file_atomic
        from leaderboard.submission import SubmissionError, canonical_json

        if out.exists() and not force:
            raise SubmissionError(f"{out} exists; pass --force to replace it or choose another --out")
        submission = assemble_submission(runs_dir, method=method, description=description, code_url=code_url,
                                         commit=commit, track=track, budget=budget,
                                         learning_curves=learning_curves, merge_seeds=merge_seeds,
                                         core_suite_only=core_suite_only, echo=typer.echo)
        write_file_atomic(out, canonical_json(submission.document))
        seeds = len(next(iter(submission.tasks.values())).seeds)
        typer.echo(f"wrote {out}: {submission.method} on {submission.track}/{submission.budget}, "
                   f"{len(submission.tasks)} tasks x {seeds} seeds (valid under protocol {submission.protocol_version})")


@leaderboard_app.command("publish-runs")
def publish_runs_command(
    sweep_out: Annotated[Path, typer.Argument(help="Out folder of `offdyn-bench sweep` (it holds runs/).")],
    to: Annotated[Optional[Path], typer.Option(
        "--to", help="Destination (default: the repository's leaderboard/reference-runs).")] = None,
    method: Annotated[Optional[list[str]], typer.Option(
        "--method", help="Only this method's runs (repeatable; default every method in the sweep).")] = None,
    replace: Annotated[bool, typer.Option(
        help="Replace published records whose bytes differ (published numbers change only with this).")] = False,
) -> None:
    """Publish the finished runs' evaluation records of a sweep (both sides) and their learning curves, byte for byte."""
    with exit_on_error():
        from leaderboard.assemble import METRICS_FILE
        from leaderboard.reference_runs import REFERENCE_RUNS_DIR, publish_reference_runs

        dest = to if to is not None else REFERENCE_RUNS_DIR
        report = publish_reference_runs(sweep_out, dest, methods=method or (), replace=replace)
        curves = sum(path.name == METRICS_FILE for path in report.written)
        typer.echo(f"{dest}: wrote {len(report.written) - curves} record(s) and {curves} learning curve(s), "
                   f"{len(report.unchanged)} file(s) already published unchanged; {len(report.unfinished)} run(s) "
                   "of the sweep not evaluated yet")
        for path in report.written:
            typer.echo(f"  {path}")
        if report.reproduced:
            typer.echo(f"{len(report.reproduced)} published file(s) reproduced (the same numbers, policy hashes "
                       "and versions; only the run's folder, commands or timings differ), kept as published:")
            for path in report.reproduced:
                typer.echo(f"  {path}")
        for path in report.compute:
            typer.echo(f"compute per run: {path}")


@leaderboard_app.command("coverage")
def coverage_command(
    spec: Annotated[Path, typer.Argument(
        help="Sweep spec whose grid to check (e.g. examples/sweeps/reference-lite.yaml).")],
    reference_runs: Annotated[Optional[Path], typer.Option(
        "--reference-runs",
        help="Published reference runs (default: the repository's leaderboard/reference-runs).")] = None,
) -> None:
    """How many of a sweep spec's seed results the published reference runs hold, and the CPU the rest would take."""
    with exit_on_error():
        from leaderboard.coverage import coverage_lines, reference_coverage
        from leaderboard.reference_runs import REFERENCE_RUNS_DIR
        from offdyn_bench.sweep.spec import load_spec

        root = reference_runs if reference_runs is not None else REFERENCE_RUNS_DIR
        coverage = reference_coverage(load_spec(spec), root)
        for line in coverage_lines(coverage):
            typer.echo(line)


@leaderboard_app.command("validate")
def validate_command(
    files: Annotated[list[Path], typer.Argument(help="Submission files.")],
) -> None:
    """Validate submission files against the schema and the protocol (what the server accepts)."""
    with exit_on_error():
        from leaderboard.submission import read_submission_file

        for path in files:
            submission = read_submission_file(path)
            typer.echo(f"{path}: valid ({submission.method} on {submission.track}/{submission.budget})")


@leaderboard_app.command("build")
def build_command(
    out: Annotated[Path, typer.Option(help="Folder for leaderboard.md and index.html.")],
    store: StoreOption = _REPO_STORE,
    references: ReferencesOption = None,
    reference_runs: Annotated[Optional[Path], typer.Option(
        "--reference-runs", help="Published reference runs to show beside the submissions (default: the "
                                 "repository's leaderboard/reference-runs).")] = None,
    no_reference_runs: Annotated[bool, typer.Option(
        "--no-reference-runs", help="Show the submissions only.")] = False,
) -> None:
    """Render the store into leaderboard.md (README table) and a static, self-contained index.html."""
    with exit_on_error():
        from leaderboard.reference_runs import REFERENCE_RUNS_DIR
        from leaderboard.render import build_site

        runs = None if no_reference_runs else (reference_runs if reference_runs is not None else REFERENCE_RUNS_DIR)
        markdown, page = build_site(store, out, references=references, reference_runs=runs)
        typer.echo(f"wrote {markdown} and {page}")


@leaderboard_app.command("serve")
def serve_command(
    db: DbOption = DEFAULT_DB,
    store: StoreOption = _REPO_STORE,
    host: Annotated[str, typer.Option(help="Interface to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port.")] = 8000,
    references: ReferencesOption = None,
    max_body_bytes: Annotated[Optional[int], typer.Option(
        help="Largest accepted request body (default: the submission size limit, 8 MiB).")] = None,
) -> None:
    """Serve the board at / and accept POST /submissions from token holders."""
    with exit_on_error():
        if not 0 <= port <= 65535:
            raise OffdynError(f"--port {port}: expected a TCP port in [0, 65535]")
        if max_body_bytes is not None and max_body_bytes < 1:
            raise OffdynError(f"--max-body-bytes {max_body_bytes}: expected a positive number of bytes")
        import uvicorn

        from leaderboard.server import create_app
        from leaderboard.submission import MAX_SUBMISSION_BYTES

        app = create_app(db_url=db, store=store, references=references,
                         max_body_bytes=max_body_bytes or MAX_SUBMISSION_BYTES)
        uvicorn.run(app, host=host, port=port, log_level="info")


@token_app.command("create")
def token_create_command(
    name: Annotated[str, typer.Argument(help="Who the token is for (unique), e.g. a lab or a person.")],
    db: DbOption = DEFAULT_DB,
) -> None:
    """Create a submitter token; it is printed once and stored only as its sha256."""
    with exit_on_error():
        from leaderboard.database import Database

        token = Database(db).create_token(name)
        typer.echo(token)
        typer.echo(f"token for {name!r} created; it is shown only now. Submit with "
                   "`Authorization: Bearer <token>`.", err=True)


@token_app.command("revoke")
def token_revoke_command(
    name: Annotated[str, typer.Argument(help="The name the token was created for.")],
    db: DbOption = DEFAULT_DB,
) -> None:
    """Revoke a submitter token (its submissions stay)."""
    with exit_on_error():
        from leaderboard.database import Database

        Database(db).revoke_token(name)
        typer.echo(f"revoked the token of {name!r}")
