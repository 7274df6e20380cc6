"""``offdyn-bench evaluate`` and ``offdyn-bench protocol ...``: score anything under the protocol.

Heavy libraries (gymnasium, torch, mujoco) load inside the commands, so attaching them keeps
``offdyn-bench --help`` quick.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from offdyn_bench.errors import OffdynError, exit_on_error

if TYPE_CHECKING:
    from offdyn_bench.protocol.gap import TaskGap
    from offdyn_bench.protocol.references import ReferenceScore

protocol_app = typer.Typer(no_args_is_help=True, add_completion=False,
                           help="The fixed evaluation protocol: show it, record reference scores, score results.")
reference_app = typer.Typer(no_args_is_help=True, add_completion=False,
                            help="Record reference scores (random policy, zero command, sac-target oracle) with provenance.")
protocol_app.add_typer(reference_app, name="reference")


def _parse_seeds(text: str | None) -> list[int] | None:
    if text is None:
        return None
    try:
        seeds = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise OffdynError(f"--seeds {text!r}: expected comma-separated integers, e.g. 0,1,2,3,4") from None
    if not seeds or len(set(seeds)) != len(seeds) or any(s < 0 for s in seeds):
        raise OffdynError(f"--seeds {text!r}: expected distinct non-negative integers, e.g. 0,1,2,3,4")
    return seeds


def _parse_references(items: list[str]) -> dict[str, tuple[float, float]]:
    out = {}
    for item in items:
        task, sep, values = item.partition("=")
        parts = values.split(",")
        try:
            j_random, j_oracle = (float(parts[0]), float(parts[1])) if sep and len(parts) == 2 else (None, None)
        except ValueError:
            j_random = j_oracle = None
        if j_random is None or j_oracle is None or not j_oracle > j_random:
            raise OffdynError(f"--reference {item!r}: expected TASK=J_RANDOM,J_ORACLE with J_ORACLE > J_RANDOM, "
                              "e.g. hopper-gravity-0.5=18.4,2500")
        out[task] = (j_random, j_oracle)
    return out


def evaluate_command(
    agent: str = typer.Option(..., "--agent", help="A run folder of `offdyn-bench train`, or package.module:factory "
                                                   "returning an object with act(observation) -> action."),
    task: str | None = typer.Option(None, "--task", help="Task pair (default: the run's task)."),
    track: str | None = typer.Option(None, "--track", help="offline-target, online-target, "
                                                           "offline-source-offline-target or "
                                                           "offline-source-online-target (default: the "
                                                           "method's track)."),
    budget: str | None = typer.Option(None, "--budget", help="full or lite (default: read from the run's steps)."),
    seeds: str | None = typer.Option(None, "--seeds", help="Training seeds of a module:factory agent, e.g. 0,1,2,3,4."),
    episodes: int = typer.Option(20, "--episodes", help="Episodes per seed (the protocol uses 20)."),
    method: str | None = typer.Option(None, "--method", help="Method name recorded for a module:factory agent."),
    out: Path | None = typer.Option(None, "--out", help="Where to write the record (default: the run folder's "
                                                        "evaluation.json, or evaluation[-<task>][-source].json for "
                                                        "another task or the source side; required to keep a "
                                                        "factory's record)."),
    progress: bool = typer.Option(True, "--progress/--no-progress"),
    side: str = typer.Option("target", "--side", help="target (the protocol) or source (the task's source-target "
                                                      "gap: the same policies in the source)."),
) -> None:
    """Evaluate the final policy of every training seed on the task's target under the protocol:
    deterministic actions, fixed episode seeds; writes raw per-episode returns with versions."""
    from offdyn_bench.evaluate import default_evaluation_path, evaluate
    from offdyn_bench.protocol.scoring import method_scores, seed_means

    with exit_on_error():
        record = evaluate(agent, task, track=track, budget=budget, seeds=_parse_seeds(seeds), episodes=episodes,
                          out=out, method=method, progress=progress, side=side)
        # A source-side record is no score: its per-seed returns only (protocol gap compares the sides).
        scores = method_scores(record["method"] or "agent", [record], record["budget"]) if side == "target" else None
    truncated = {entry["seed"]: entry["truncated"] for entry in record["seeds"]}
    for seed, mean in seed_means(record).items():
        line = f"seed {seed}: mean {side} return {mean:.1f}"
        if scores is not None and scores.normalized is not None:
            line += f", normalized {scores.normalized[scores.seeds.index(seed), 0]:.1f}"
        ran_out = truncated[seed]
        typer.echo(line + f" ({sum(ran_out)}/{len(ran_out)} episodes ran to the time limit)")
    if scores is not None and scores.missing_references:
        typer.echo(f"no normalized score: {record['task']} has no random and oracle reference"
                   + (f" at budget {record['budget']!r}" if record["budget"] else " (no protocol budget)"))
    for note in record["notes"]:
        typer.echo(f"not a protocol result: {note}")
    where = out if out is not None else (
        default_evaluation_path(Path(agent), str(record["agent"].get("trained_task", record["task"])),
                                record["task"], side) if Path(agent).is_dir() else None)
    if where is not None:
        typer.echo(f"wrote {where}")


@protocol_app.command("show")
def show(as_json: bool = typer.Option(False, "--json", help="Print the protocol as JSON.")) -> None:
    """Print the protocol: version, tracks, budgets, evaluation, core suite, references present."""
    from offdyn_bench.protocol import definition
    from offdyn_bench.protocol.references import reference_scores

    with exit_on_error():
        references = reference_scores()
    summary = definition.summary()
    summary["references"] = {task: sorted(kinds) for task, kinds in references.items()}
    if as_json:
        typer.echo(json.dumps(summary, indent=1))
        return
    typer.echo(f"protocol {summary['protocol_version']} (PROTOCOL.md)")
    for track in definition.TRACKS.values():
        typer.echo(f"track {track.name}: {track.description}; methods {', '.join(track.methods)}")
    for name, text in definition.REFERENCE_METHODS.items():
        typer.echo(f"reference {name}: {text}")
    for budget in definition.BUDGETS.values():
        typer.echo(f"budget {budget.name}: {budget.source_steps:,} source steps ({budget.description})")
    typer.echo(f"evaluation: final policy, deterministic actions, {definition.EVAL_EPISODES} target episodes "
               f"(seeds {definition.EPISODE_SEEDS[0]}..{definition.EPISODE_SEEDS[-1]}), "
               f"at least {definition.MIN_SEEDS} training seeds")
    typer.echo("core suite (reference mean returns; an oracle's per-seed means in brackets):")
    for task in definition.CORE_SUITE:
        scores = references.get(task, {})
        shown = [_describe_reference(kind, scores[kind]) for kind in sorted(scores)]
        typer.echo(f"  {task:36s} references: {'; '.join(shown) if shown else 'none yet'}")


def _describe_reference(kind: str, score: ReferenceScore) -> str:
    text = f"{kind} {score.mean_return:.1f}"
    means = score.seed_means()
    return text + (f" [{', '.join(f'{m:.1f}' for m in means)}]" if means else "")


def _record_trivial_references(kind: str, task: list[str], core_suite: bool) -> None:
    from offdyn_bench.protocol.definition import CORE_SUITE
    from offdyn_bench.protocol.references import (REFERENCE_FILE, record_random_reference,
                                                  record_zero_command_reference)
    from offdyn_bench.tasks import get_task

    record = record_random_reference if kind == "random" else record_zero_command_reference
    with exit_on_error():
        tasks = list(CORE_SUITE) if core_suite else [get_task(t).name for t in task]
        if not tasks:
            raise OffdynError("name a task with --task, or pass --core-suite")
        for name in tasks:
            score = record(name)
            typer.echo(f"{name}: {kind} {score.mean_return:.1f} over {len(score.returns)} episodes")
    typer.echo(f"wrote {REFERENCE_FILE}")


@reference_app.command("random")
def reference_random(task: list[str] = typer.Option([], "--task", help="Task pair (repeatable)."),
                     core_suite: bool = typer.Option(False, "--core-suite", help="Every core-suite task.")) -> None:
    """Measure the uniform-random policy on the protocol's episode seeds and record it."""
    _record_trivial_references("random", task, core_suite)


@reference_app.command("zero-command")
def reference_zero_command(task: list[str] = typer.Option([], "--task", help="Task pair (repeatable)."),
                           core_suite: bool = typer.Option(False, "--core-suite",
                                                           help="Every core-suite task.")) -> None:
    """Measure the zero command (the centre of the action box, every step) on the protocol's
    episode seeds and record it: the core suite's admission test refuses an oracle below it."""
    _record_trivial_references("zero-command", task, core_suite)


@reference_app.command("oracle")
def reference_oracle(evaluations: list[Path] = typer.Argument(..., help="evaluation.json of sac-target runs of one "
                                                                       "task at one budget.")) -> None:
    """Record sac-target evaluations as a task's oracle at their budget."""
    from offdyn_bench.evaluate import read_evaluation
    from offdyn_bench.protocol.references import REFERENCE_FILE, record_oracle_reference

    with exit_on_error():
        score = record_oracle_reference([read_evaluation(path) for path in evaluations])
    typer.echo(f"{score.task}: oracle at budget {score.budget} = {score.mean_return:.1f} "
               f"({len(score.provenance['seeds'])} seeds x {score.provenance['episodes_per_seed']} episodes); "
               f"wrote {REFERENCE_FILE}")


@protocol_app.command("score")
def score(evaluations: list[Path] = typer.Argument(..., help="evaluation.json files (any methods and tasks)."),
          budget: str | None = typer.Option(None, "--budget", help="Normalize against this budget's oracle "
                                                                   "(default: the evaluations' budget)."),
          reference: list[str] = typer.Option([], "--reference", help="TASK=J_RANDOM,J_ORACLE: normalize TASK "
                                                                        "against these returns instead of the "
                                                                        "reference file (repeatable)."),
          as_json: bool = typer.Option(False, "--json")) -> None:
    """Score evaluations: per-task raw returns, normalized scores, IQM with a 95% stratified-bootstrap
    interval, optimality gap, and the probability of improvement between methods."""
    from offdyn_bench.evaluate import read_evaluation
    from offdyn_bench.protocol.report import score_report

    with exit_on_error():
        records = [read_evaluation(path) for path in evaluations]
        report = score_report(records, budget, _parse_references(reference) if reference else None)
    typer.echo(json.dumps(report.to_dict(), indent=1) if as_json else report.to_text())


@protocol_app.command("claims")
def claims(evaluations: list[Path] = typer.Argument(..., help="evaluation.json files of one budget (any methods, "
                                                              "tasks and datasets; a sweep's per-seed records)."),
           as_json: bool = typer.Option(False, "--json"),
           out: Path | None = typer.Option(None, "--out", help="Also write the markdown report here.")) -> None:
    """Check the papers' headline claims task by task: DAP at least doubles RL on source and DAP+U
    beats DAP (DAP, Section 5.2); H2O beats DARC and CQL on the HalfCheetah H2O settings (H2O, Table 1)."""
    from offdyn_bench.evaluate import read_evaluation
    from offdyn_bench.protocol.claims import check_claims, claims_markdown

    with exit_on_error():
        checks = check_claims([read_evaluation(path) for path in evaluations])
        text = claims_markdown(checks)
        if out is not None:
            from baselines.run_folder import write_lines_atomic

            try:
                write_lines_atomic(out, text.splitlines())
            except OSError as error:
                raise OffdynError(f"--out {str(out)!r}: cannot write the report ({error.strerror}); nothing was "
                                  "written") from None
    typer.echo(json.dumps([c.to_dict() for c in checks], indent=1) if as_json else text.rstrip("\n"))


@protocol_app.command("gap")
def gap(evaluations: list[Path] = typer.Argument(..., help="evaluation.json files of one budget: sac-source's "
                                                           "target-side and source-side (evaluate --side source) "
                                                           "records; sac-target records beside them are the "
                                                           "oracle of a task without a recorded one."),
        as_json: bool = typer.Option(False, "--json"),
        reference_file: Path | None = typer.Option(None, "--reference-file", help="Reference scores (default: "
                                                   "assets/reference_scores.json).")) -> None:
    """The source-target gap per task: the return in the source and in the target, the fraction kept,
    and how far below the task's oracle it stays (normalized score, P(oracle > method))."""
    from offdyn_bench.protocol.gap import gaps_markdown

    gaps = _measured_gaps(evaluations, reference_file)
    typer.echo(json.dumps([g.to_dict() for g in gaps], indent=1) if as_json else gaps_markdown(gaps).rstrip("\n"))


def _measured_gaps(evaluations: list[Path], reference_file: Path | None) -> list[TaskGap]:
    """The gap per (method, task) of the evaluation files, errors as one line each (exit code 2)."""
    from offdyn_bench.evaluate import read_evaluation
    from offdyn_bench.protocol.gap import measure_gaps

    with exit_on_error():
        return measure_gaps([read_evaluation(path) for path in evaluations],
                            str(reference_file) if reference_file is not None else None)


@protocol_app.command("admission")
def admission(evaluations: list[Path] = typer.Argument(..., help="evaluation.json files of one budget: sac-source's "
                                                                 "target-side records (source-side ones may be "
                                                                 "given too); sac-target records beside them are "
                                                                 "the oracle of a task without a recorded one."),
              as_json: bool = typer.Option(False, "--json"),
              reference_file: Path | None = typer.Option(None, "--reference-file", help="Reference scores "
                                                         "(default: assets/reference_scores.json).")) -> None:
    """The core suite's same-budget test per task: does the oracle beat RL on source in the target with
    P(oracle > RL on source) >= 0.9 over 5 training seeds on each side (PROTOCOL.md §9)?"""
    from offdyn_bench.protocol.gap import admissions_markdown, admit

    gaps = _measured_gaps(evaluations, reference_file)
    with exit_on_error():
        results = [admit(g) for g in gaps]
    typer.echo(json.dumps([a.to_dict() for a in results], indent=1) if as_json
               else admissions_markdown(results).rstrip("\n"))


@protocol_app.command("curves")
def curves(paths: list[Path] = typer.Argument(..., help="metrics.jsonl files of trained runs, each with its "
                                                        "evaluation.json beside it (a sweep's run folders or "
                                                        "leaderboard/reference-runs)."),
           as_json: bool = typer.Option(False, "--json")) -> None:
    """How far each budget carried learning: per method and task, the seeds' mean learning curve at
    each quarter of the budget, its late plateau, the step from which it stays above 90% of it, and its
    late slope."""
    from offdyn_bench.protocol.curves import curves_markdown, read_curves

    with exit_on_error():
        summaries = read_curves(paths)
    typer.echo(json.dumps([s.to_dict() for s in summaries], indent=1) if as_json
               else curves_markdown(summaries).rstrip("\n"))
