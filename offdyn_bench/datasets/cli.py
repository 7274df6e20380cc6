"""``offdyn-bench datasets list | build | verify | download``."""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Annotated, Optional

import typer
from tqdm import tqdm

from offdyn_bench.datasets.build import (
    BuildMismatchError,
    MissingPolicyError,
    build_dataset,
    check_buildable,
    record_in_manifest,
    repo_path,
)
from offdyn_bench.datasets.ensure import ensure_dataset
from offdyn_bench.datasets.install import datasets_root, is_installed, verify_installed
from offdyn_bench.datasets.staging import clean_stale_staging
from offdyn_bench.datasets.transfer import TransferLimits
from offdyn_bench.datasets.manifest import MANIFEST_PATH, Manifest, read_manifest
from offdyn_bench.datasets.recipes import POLICY_KINDS, dataset_id, qualities_of
from offdyn_bench.errors import OffdynError, exit_on_error
from offdyn_bench.protocol import official_dataset
from offdyn_bench.tasks import TASKS

datasets_app = typer.Typer(no_args_is_help=True, add_completion=False,
                           help="Target datasets (Minari format): list, build from recipes, verify, download.")

ManifestOption = Annotated[Optional[pathlib.Path], typer.Option(
    "--manifest", help="Manifest with the expected hashes (default: the shipped assets/datasets.json).")]


def _behaviour_status(entry_recipe) -> str:  # noqa: ANN001 - a Recipe
    kind = entry_recipe.behaviour.kind
    if kind not in POLICY_KINDS:
        return kind
    return kind if repo_path(str(entry_recipe.behaviour.policy)).is_file() else f"{kind} MISSING"


@datasets_app.command("list")
def list_command(
    buildable: Annotated[bool, typer.Option(help="Also list every id of the task grid that builds on demand.")] = False,
    manifest_path: ManifestOption = None,
) -> None:
    """Dataset ids of the manifest: transitions, archive size, hashes recorded?, installed?, behaviour.
    Reads only: creates no folder (not even the datasets root)."""
    with exit_on_error():
        manifest = read_manifest(manifest_path)
        ids = sorted(manifest.entries)
        if buildable:
            ids += sorted({dataset_id(pair, q) for pair in TASKS.values() for q in qualities_of(pair)} - set(ids))
        root = datasets_root()
        clean_stale_staging(root)  # so a replace killed midway shows as installed again
        width = max([len("dataset id"), *map(len, ids)])
        typer.echo(f"{'dataset id':{width}} {'transitions':>11}  {'archive MB':>10}  {'hashes':6}  {'installed':9}  "
                   "behaviour")
        for ident in ids:
            entry = manifest.entry_or_default(ident)
            # What the data holds once built; the recipe's target before.
            steps = entry.total_steps if entry.total_steps is not None else entry.recipe.num_transitions
            archive = f"{entry.archive.size / 1e6:.1f}" if entry.archive is not None else "-"
            typer.echo(f"{ident:{width}} {steps:>11}  {archive:>10}  {'yes' if entry.is_built else 'no':6}  "
                       f"{'yes' if is_installed(ident, root) else 'no':9}  {_behaviour_status(entry.recipe)}")
        typer.echo(f"{len(ids)} datasets; installed under {root}; manifest {manifest_path or MANIFEST_PATH}")


@datasets_app.command("build")
def build_command(
    ids: Annotated[Optional[list[str]], typer.Argument(help="Dataset ids, e.g. offdyn/hopper-gravity-0p5/random-v0.")] = None,
    all_: Annotated[bool, typer.Option("--all", help="Every dataset of the manifest.")] = False,
    out: Annotated[Optional[pathlib.Path], typer.Option(
        help="Also write archives and manifest entries here, in the layout a remote serves.")] = None,
    update_manifest: Annotated[bool, typer.Option(
        help="Record the hashes, scores and pinned policy hash in the manifest.")] = False,
    install: Annotated[bool, typer.Option(help="Install into $MINARI_DATASETS_PATH.")] = True,
    force: Annotated[bool, typer.Option(help="Replace an installed dataset with other bytes.")] = False,
    manifest_path: ManifestOption = None,
) -> None:
    """Regenerate datasets from their recipes (identical bytes on the same platform and MuJoCo)."""
    with exit_on_error():
        manifest = read_manifest(manifest_path)
        targets = sorted(manifest.entries) if all_ else list(ids or [])
        if not targets:
            raise OffdynError("name at least one dataset id, or pass --all; see `offdyn-bench datasets list`")
        if out is not None:
            try:  # before any build: a build takes minutes, and its archive goes here last
                out.mkdir(parents=True, exist_ok=True)
            except OSError as error:
                raise OffdynError(f"--out {str(out)!r}: cannot create it ({error.strerror or error}); expected a "
                                  "folder this user can write") from None
        failed: list[str] = []
        for ident in targets:
            entry = manifest.entry_or_default(ident)
            if ident not in manifest:
                typer.echo(f"{ident}: not in the manifest; building the default recipe (no hashes to compare)")
            # A rebuild with --update-manifest may change the bytes on purpose (e.g. a new policy).
            recorded = None if update_manifest else entry
            try:
                check_buildable(entry.recipe)  # before the bar: no empty bar above the error
                with tqdm(total=entry.recipe.num_transitions, desc=ident, unit="step") as bar:
                    result = build_dataset(entry.recipe, out_dir=out, recorded=recorded, install=install,
                                           replace=force, on_progress=bar.update)
            except (MissingPolicyError, BuildMismatchError) as error:
                # The others still build: `build --all --no-install` checks the whole manifest.
                typer.echo(f"error: {error}", err=True)
                failed.append(ident)
                continue
            matched = " (matches the manifest)" if (entry.files is not None and not update_manifest) else ""
            where = result.installed_at or "not installed"
            typer.echo(f"{ident}: {result.entry.total_steps} transitions in {result.seconds:.1f} s "
                       f"({result.transitions_per_second:.0f}/s){matched}; installed at {where}"
                       + (f"; archive {result.archive_path}" if result.archive_path else ""))
            if update_manifest:
                path = record_in_manifest(result.entry, manifest_path)
                manifest = manifest.with_entry(result.entry)
                typer.echo(f"recorded {ident} in {path}")
        if failed:
            typer.echo(f"{len(failed)} of {len(targets)} datasets not built (missing policy or other bytes than the "
                       f"manifest's): {', '.join(failed)}", err=True)
            raise typer.Exit(1)


@datasets_app.command("verify")
def verify_command(ident: Annotated[str, typer.Argument(metavar="ID")], manifest_path: ManifestOption = None) -> None:
    """Check every file of an installed dataset against the manifest's sha256."""
    with exit_on_error():
        manifest = read_manifest(manifest_path)
        report = verify_installed(manifest.get(ident))
        if not report.ok:
            for problem in report.problems:
                typer.echo(f"{ident}: {problem}", err=True)
            typer.echo(f"{ident}: FAILED verification ({len(report.problems)} problems) at {report.path}; to "
                       f"replace it with a verified copy, run: offdyn-bench datasets download {ident} --force",
                       err=True)
            raise typer.Exit(1)
        typer.echo(f"{ident}: OK ({len(manifest.get(ident).files or {})} files verified) at {report.path}")


@datasets_app.command("returns")
def returns_command(ident: Annotated[str, typer.Argument(metavar="ID")]) -> None:
    """What an installed dataset's behaviour earns: its episodes' returns (count, mean, min, max),
    the level an offline method trained on it is read against."""
    import numpy as np

    from offdyn_bench.datasets.ensure import load_installed

    with exit_on_error():
        returns = [float(np.sum(episode.rewards)) for episode in load_installed(ident).iterate_episodes()]
        if not returns:
            raise OffdynError(f"{ident} holds no episode")
        typer.echo(f"{ident}: {len(returns)} episodes; return mean {np.mean(returns):.1f}, "
                   f"min {min(returns):.1f}, max {max(returns):.1f}")


@datasets_app.command("download")
def download_command(
    ident: Annotated[Optional[str], typer.Argument(
        metavar="[ID]", help="Dataset id, e.g. offdyn/hopper-gravity-0p5/source-policy-v0 (or give --task).")] = None,
    task: Annotated[Optional[str], typer.Option(
        help="Instead of ID: the official target dataset of this task on --track, the one `train --task "
             "TASK --track TRACK` trains on.")] = None,
    track: Annotated[str, typer.Option(help="With --task: the protocol track whose official dataset to install.")]
        = "offline-target",
    quality: Annotated[Optional[str], typer.Option(
        help="With --task: the task's dataset of this quality (random, source-policy, medium, medium-replay, "
             "medium-expert, ...) instead of the track's official one.")] = None,
    print_id: Annotated[bool, typer.Option(
        "--print-id", help="For scripts: print only the dataset id on stdout (the messages go to stderr).")] = False,
    remote: Annotated[Optional[str], typer.Option(
        help="Remote URL (https://, http://, file://); default $OFFDYN_REMOTE. With neither, the dataset is "
             "rebuilt from its recipe.")] = None,
    force: Annotated[bool, typer.Option(help="Replace an installed copy.")] = False,
    deadline: Annotated[Optional[float], typer.Option(
        help="Longest time one remote file may take, in seconds (default $OFFDYN_DOWNLOAD_DEADLINE or 3600).")] = None,
    min_rate: Annotated[Optional[float], typer.Option(
        help="Slowest accepted transfer, bytes/s averaged over 30 s (default $OFFDYN_DOWNLOAD_MIN_RATE or 1024; "
             "0 turns it off).")] = None,
    manifest_path: ManifestOption = None,
) -> None:
    """Install a dataset and verify every sha256: from the remote when one is configured,
    otherwise rebuilt from its recipe. Says which it did."""
    with exit_on_error():
        ident = _dataset_to_download(ident, task, track, quality)
        manifest: Manifest = read_manifest(manifest_path)
        limits = TransferLimits.from_environment()
        overrides = {"deadline_s": deadline, "min_rate_bytes_per_s": min_rate}
        limits = dataclasses.replace(limits, **{k: v for k, v in overrides.items() if v is not None})
        ensure_dataset(ident, remote=remote, manifest=manifest, force=force, limits=limits,
                       echo=lambda line: typer.echo(line, err=print_id), progress=not print_id)
        if print_id:
            typer.echo(ident)


def _dataset_to_download(ident: str | None, task: str | None, track: str, quality: str | None = None) -> str:
    """The dataset id a download names: ``ident``, or ``task``'s dataset of ``quality``, or
    ``task``'s official dataset on ``track``."""
    if (ident is None) == (task is None):
        raise OffdynError("give a dataset ID or --task TASK, one of the two: e.g. `offdyn-bench datasets download "
                          "--task hopper-gravity-0.5` installs the dataset `train --task hopper-gravity-0.5 "
                          "--track offline-target` trains on")
    if ident is not None:
        if quality is not None:
            raise OffdynError(f"--quality {quality} picks one of --task's datasets; with a dataset ID ({ident}) "
                              "leave it out")
        return ident
    assert task is not None
    if quality is not None:
        return dataset_id(task, quality)
    dataset = official_dataset(task, track)
    if dataset is None:
        raise OffdynError(f"track {track!r} trains on no target dataset; --task needs a track that does, "
                          "e.g. offline-target")
    return dataset


def _checkpoint_state_file(path: pathlib.Path) -> tuple[pathlib.Path, pathlib.Path | None]:
    """The state file of a checkpoint given as a file, a ``step_<N>`` folder or a run folder,
    and the run folder (where config.json and result.json are) when there is one."""
    if path.is_dir() and (path / "checkpoints").is_dir():
        steps = sorted(p for p in (path / "checkpoints").glob("step_*") if (p / "state.safetensors").is_file())
        if not steps:
            raise OffdynError(f"{path}/checkpoints holds no complete checkpoint")
        return steps[-1] / "state.safetensors", path
    if path.is_dir():
        path = path / "state.safetensors"
    if not path.is_file():
        raise OffdynError(f"no checkpoint at {path}; expected a run folder, a checkpoints/step_<N> folder or a "
                          "state.safetensors file")
    run = path.parent.parent.parent if path.parent.parent.name == "checkpoints" else None
    return path, run


@datasets_app.command("import-policy")
def import_policy_command(
    checkpoint: Annotated[pathlib.Path, typer.Argument(help="Run folder, checkpoints/step_<N> folder or state.safetensors of a baselines SAC run.")],
    trained_on: Annotated[str, typer.Option(help="Env id the policy was trained in, e.g. offdyn/Hopper-gravity-0.5-source-v0.")],
    out: Annotated[pathlib.Path, typer.Option(help="Where to write <name>.safetensors (+ .json), e.g. assets/policies/sac-source/hopper-nominal.safetensors.")],
    member: Annotated[int, typer.Option(help="Which training seed of the checkpoint to keep.")] = 0,
    eval_episodes: Annotated[int, typer.Option(help="Episodes (seeds 1000000, ...) to score it in --trained-on.")] = 10,
    note: Annotated[Optional[str], typer.Option(help="A remark kept in the sidecar's training record.")] = None,
) -> None:
    """Extract one seed's actor from a SAC checkpoint into a behaviour/oracle policy file."""
    import json

    from offdyn_bench.datasets.archive import sha256_file
    from offdyn_bench.datasets.policies import evaluate_policy, import_sac_actor, update_sidecar

    with exit_on_error():
        state_file, run = _checkpoint_state_file(checkpoint)
        training: dict = {"checkpoint": "/".join(state_file.parts[-3:]), "checkpoint_sha256": sha256_file(state_file)}
        if note:
            training["note"] = note
        run_result = None
        if run is not None and (run / "config.json").is_file():
            training["config"] = json.loads((run / "config.json").read_text())
        if run is not None and (run / "result.json").is_file():
            run_result = json.loads((run / "result.json").read_text())
        path = import_sac_actor(state_file, out, member=member, trained_on=trained_on, training=training,
                                score=None)
        score = {"evaluation": evaluate_policy(path, trained_on, eval_episodes), "run_result": run_result}
        update_sidecar(path, score=score)
        typer.echo(f"wrote {path} and {path.with_suffix('.json')}; mean return in {trained_on}: "
                   f"{score['evaluation']['mean_return']:.1f} over {eval_episodes} episodes")
