"""``offdyn-bench train``: the command line of the baselines.

Imports nothing heavy at module level (torch loads when ``train`` runs), so attaching the command
keeps the rest of ``offdyn-bench`` quick to start.
"""

from __future__ import annotations

from pathlib import Path

import typer

from offdyn_bench.errors import OffdynError

# The registry's names, for the help text (a test checks they match baselines.algorithms.ALGORITHMS).
ALGORITHM_NAMES = ("sac-source", "sac-target", "cql", "darc", "darc-online", "h2o", "dap", "dap-u", "matl",
                   "matl-u", "matl-f", "independent", "direct-transfer", "fine-tuning", "dara", "h2o-offline-source")


def train_command(
    algo: str = typer.Argument(..., help="Algorithm: " + ", ".join(ALGORITHM_NAMES) + "."),
    task: str | None = typer.Option(None, "--task", help="Task pair, e.g. hopper-gravity-0.5 (required to train)."),
    steps: int | None = typer.Option(None, "--steps", help="Environment steps (gradient updates for cql, dara, "
                                                           "h2o-offline-source); "
                                                           "or pass --budget."),
    out: Path | None = typer.Option(None, "--out", help="Run folder; run the same command again to resume it "
                                                        "(required to train)."),
    seed: int = typer.Option(0, "--seed", help="First training seed."),
    n_seeds: int = typer.Option(1, "--n-seeds", help="Seeds seed..seed+n-1, trained together in one process."),
    dataset: str | None = typer.Option(None, "--dataset",
                                       help="Target dataset: collect:<random|run folder>:<N>, an .npz path, "
                                            "or a Minari id."),
    source_dataset: str | None = typer.Option(
        None, "--source-dataset", help="Source dataset of the offline-source methods (dara, h2o-offline-source): "
                                       "collect:<random|run folder>:<N> (collected in the source), an .npz path, or "
                                       "a Minari id; default: the task's official source dataset."),
    overrides: list[str] = typer.Option([], "--set", help="Config override key=value, e.g. sac.batch_size=128 "
                                                          "(repeatable)."),
    eval_every: int | None = typer.Option(None, "--eval-every", help="Steps between target evaluations "
                                                                     "(default steps/20)."),
    eval_episodes: int = typer.Option(10, "--eval-episodes", help="Target episodes per evaluation."),
    checkpoint_every: int | None = typer.Option(None, "--checkpoint-every", help="Default steps/10."),
    threads: int = typer.Option(1, "--threads", help="torch threads (1: best on a small shared CPU)."),
    progress: bool = typer.Option(True, "--progress/--no-progress"),
    track: str | None = typer.Option(None, "--track", help="Protocol track: offline-target, online-target, "
                                                           "offline-source-offline-target or "
                                                           "offline-source-online-target (default: the method's "
                                                           "own); checked against the method."),
    budget: str | None = typer.Option(None, "--budget", help="Protocol budget: lite (100k steps) or full (1M); "
                                                             "sets --steps."),
    device: str = typer.Option("cpu", "--device", help="cpu, cuda, cuda:N or auto (CUDA when there is one); "
                                                       "runs are deterministic per device."),
    eval_on_device: bool = typer.Option(False, "--eval-on-device", help="On an accelerator, run the in-training "
                                        "evaluations' policy there too (default: a CPU copy of it, which waits on "
                                        "no device each episode step)."),
    print_config: bool = typer.Option(False, "--print-config", help="Print the method's settings (its defaults "
                                      "with the --set overrides applied and checked) as the JSON a run's "
                                      "config.json records under \"config\", and exit: nothing is trained or "
                                      "written, and no task or folder is needed."),
) -> None:
    """Train a reference baseline and write config.json, metrics.jsonl, result.json and checkpoints."""
    from baselines.train import train

    parsed = {}
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep or not key:
            typer.echo(f"error: --set expects key=value, got {item!r}", err=True)
            raise typer.Exit(2)
        parsed[key.strip()] = value.strip()
    if print_config:
        _print_config(algo, parsed)
        return
    missing = [what for what, value in (("--task (the task pair, e.g. hopper-gravity-0.5)", task),
                                        ("--out (the run folder to write)", out)) if value is None]
    if missing:
        typer.echo(f"error: training needs {' and '.join(missing)}; to see the method's settings only, pass "
                   "--print-config", err=True)
        raise typer.Exit(2)
    assert task is not None and out is not None
    try:
        result = train(algo, task, steps=steps, out=out, seed=seed, n_seeds=n_seeds, dataset=dataset,
                       source_dataset=source_dataset,
                       overrides=parsed, eval_every=eval_every, eval_episodes=eval_episodes,
                       checkpoint_every=checkpoint_every, threads=threads, progress=progress, track=track,
                       budget=budget, device=device, eval_on_device=eval_on_device)
    except OffdynError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(2) from None
    if result is not None:
        typer.echo(f"mean target return {result['mean_return']:.1f}; wrote {out}/result.json")


def _print_config(algo: str, overrides: dict[str, str]) -> None:
    """``--print-config``: the settings a run of ``algo`` with these overrides would record."""
    import json

    from baselines.algorithms import apply_overrides, config_to_dict, get_algorithm

    try:
        config = apply_overrides(get_algorithm(algo).default_config(), overrides, algo)
    except OffdynError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(2) from None
    typer.echo(json.dumps(config_to_dict(config), indent=2))
