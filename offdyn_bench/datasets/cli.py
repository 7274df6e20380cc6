"""``offdyn-bench datasets list | build | verify | download``."""

from __future__ import annotations

import contextlib
import pathlib
from collections.abc import Iterator
from typing import Annotated, Optional

import typer
from tqdm import tqdm

from offdyn_bench.datasets.build import MissingPolicyError, build_dataset, record_in_manifest, repo_path
from offdyn_bench.datasets.download import download_dataset
from offdyn_bench.datasets.install import datasets_root, is_installed, verify_installed
from offdyn_bench.datasets.manifest import MANIFEST_PATH, Manifest, read_manifest
from offdyn_bench.datasets.recipes import QUALITIES, dataset_id
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import TASKS

datasets_app = typer.Typer(no_args_is_help=True, add_completion=False,
                           help="Target datasets (Minari format): list, build from recipes, verify, download.")

ManifestOption = Annotated[Optional[pathlib.Path], typer.Option(
    "--manifest", help="Manifest with the expected hashes (default: the shipped assets/datasets.json).")]


@contextlib.contextmanager
def _errors_exit() -> Iterator[None]:
    try:
        yield
    except OffdynError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(1) from None


def _behaviour_status(entry_recipe) -> str:  # noqa: ANN001 - a Recipe
    if entry_recipe.behaviour.kind != "policy":
        return entry_recipe.behaviour.kind
    return "policy" if repo_path(str(entry_recipe.behaviour.policy)).is_file() else "policy MISSING"


@datasets_app.command("list")
def list_command(
    buildable: Annotated[bool, typer.Option(help="Also list every id of the task grid that builds on demand.")] = False,
    manifest_path: ManifestOption = None,
) -> None:
    """Dataset ids of the manifest: size, whether hashes are recorded, installed, behaviour."""
    with _errors_exit():
        manifest = read_manifest(manifest_path)
        ids = sorted(manifest.entries)
        if buildable:
            ids += sorted({dataset_id(name, q) for name in TASKS for q in QUALITIES} - set(ids))
        root = datasets_root()
        width = max([len("dataset id"), *map(len, ids)])
        typer.echo(f"{'dataset id':{width}} {'transitions':>11}  {'hashes':6}  {'installed':9}  behaviour")
        for ident in ids:
            entry = manifest.entry_or_default(ident)
            typer.echo(f"{ident:{width}} {entry.recipe.num_transitions:>11}  {'yes' if entry.is_built else 'no':6}  "
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
    with _errors_exit():
        manifest = read_manifest(manifest_path)
        targets = sorted(manifest.entries) if all_ else list(ids or [])
        if not targets:
            raise OffdynError("name at least one dataset id, or pass --all; see `offdyn-bench datasets list`")
        failed: list[str] = []
        for ident in targets:
            entry = manifest.entry_or_default(ident)
            if ident not in manifest:
                typer.echo(f"{ident}: not in the manifest; building the default recipe (no hashes to compare)")
            # A rebuild with --update-manifest may change the bytes on purpose (e.g. a new policy).
            recorded = None if update_manifest else entry
            try:
                with tqdm(total=entry.recipe.num_transitions, desc=ident, unit="step") as bar:
                    result = build_dataset(entry.recipe, out_dir=out, recorded=recorded, install=install,
                                           replace=force, on_progress=bar.update)
            except MissingPolicyError as error:
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
            typer.echo(f"{len(failed)} of {len(targets)} datasets not built: {', '.join(failed)}", err=True)
            raise typer.Exit(1)


@datasets_app.command("verify")
def verify_command(ident: Annotated[str, typer.Argument(metavar="ID")], manifest_path: ManifestOption = None) -> None:
    """Check every file of an installed dataset against the manifest's sha256."""
    with _errors_exit():
        manifest = read_manifest(manifest_path)
        report = verify_installed(manifest.get(ident))
        if not report.ok:
            for problem in report.problems:
                typer.echo(f"{ident}: {problem}", err=True)
            typer.echo(f"{ident}: FAILED verification ({len(report.problems)} problems) at {report.path}", err=True)
            raise typer.Exit(1)
        typer.echo(f"{ident}: OK ({len(manifest.get(ident).files or {})} files verified) at {report.path}")


@datasets_app.command("download")
def download_command(
    ident: Annotated[str, typer.Argument(metavar="ID")],
    remote: Annotated[Optional[str], typer.Option(
        help="Remote URL (https://, http://, file://); default $OFFDYN_REMOTE.")] = None,
    force: Annotated[bool, typer.Option(help="Replace an installed copy.")] = False,
    manifest_path: ManifestOption = None,
) -> None:
    """Download an archive and its manifest entry, verify every sha256, install atomically."""
    with _errors_exit():
        manifest: Manifest = read_manifest(manifest_path)
        with tqdm(total=0, desc=ident, unit="B", unit_scale=True) as bar:
            def set_total(total: int) -> None:
                bar.total = total
                bar.refresh()

            path = download_dataset(ident, remote=remote, manifest=manifest, force=force, on_bytes=bar.update,
                                    on_total=set_total, say=lambda message: bar.write(message))
        typer.echo(f"{ident}: installed and verified at {path}")


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

    with _errors_exit():
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
