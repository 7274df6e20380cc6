"""What a diagnosis writes: the JSON contract, a table of the steps and per-dimension plots."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from offdyn_bench.diagnose.loop import Diagnosis


def _nrmse(value: float | None) -> str:
    """An error as the table prints it; ``n/a`` where it was not measured (no H-step window)."""
    return "n/a" if value is None else f"{value:.4g}"


def _value(effect: dict[str, Any]) -> str:
    value = effect["value"]
    return str(value) if isinstance(value, (int, str)) else f"{value:.4g}"


def _bound(value: Any) -> str:
    return str(value) if isinstance(value, str) else f"{value:.4g}"


def steps_table(diagnosis: Diagnosis) -> str:
    """A Markdown table: one row per added effect, errors before -> after."""
    lines = [
        "| step | effect added | value (95% interval) | one-step train | one-step held-out | H-step all "
        "| H-step held-out |",
        "|---|---|---|---|---|---|---|",
    ]
    for i, step in enumerate(diagnosis.steps, 1):
        e = step.effect
        target = "all" if e["target"] is None else e["target"]
        qualifier = "".join(f" ({k} {e[k]})" for k in ("side", "axis") if k in e)
        low, high = step.interval
        bound = " on its bound" if step.on_bound else (" (stochastic: explains the spread)" if step.stochastic else "")
        lines.append(
            f"| {i} | {e['kind']}{qualifier} on {target} | {_value(e)} ({_bound(low)}..{_bound(high)}){bound} "
            f"| {step.before.one_step_nrmse:.4g} -> {step.after.one_step_nrmse:.4g} "
            f"| {step.before.heldout_one_step_nrmse:.4g} -> {step.after.heldout_one_step_nrmse:.4g} "
            f"| {_nrmse(step.before.horizon_nrmse)} -> {_nrmse(step.after.horizon_nrmse)} "
            f"| {_nrmse(step.before.heldout_horizon_nrmse)} -> {_nrmse(step.after.heldout_horizon_nrmse)} |")
    if not diagnosis.steps:
        lines.append("| - | nothing added | | | | | |")
    return "\n".join(lines)


def summary_text(diagnosis: Diagnosis) -> str:
    """What a person reads in the terminal."""
    before, after = diagnosis.error_before, diagnosis.error_after
    verdict = ("an unexplained residual remains" if diagnosis.unexplained_residual
               else "the remaining residual is at the noise floor")
    lines = [
        f"Gap diagnosis of {diagnosis.env_id} on {diagnosis.dataset} ({diagnosis.transitions} transitions, "
        f"state {diagnosis.state_source})",
        "",
        steps_table(diagnosis),
        "",
        f"held-out one-step NRMSE {before.heldout_one_step_nrmse:.4g} -> {after.heldout_one_step_nrmse:.4g}; "
        f"noise floor {diagnosis.noise_floor:.4g}; {verdict} ({diagnosis.stop_reason}).",
    ]
    if diagnosis.effects_added:
        lines += ["", "| effect | final value | 95% interval | interval from |", "|---|---|---|---|"]
        for effect in diagnosis.effects_added:
            target = "all" if effect["target"] is None else effect["target"]
            qualifier = "".join(f" ({k} {effect[k]})" for k in ("side", "axis") if k in effect)
            low, high = effect["interval"]
            lines.append(f"| {effect['kind']}{qualifier} on {target} | {_value(effect)} "
                         f"| {_bound(low)}..{_bound(high)} "
                         f"| {effect.get('interval_method', '')} |")
        lines.append("")
    identified = diagnosis.identifiability
    if identified is not None:
        for direction in identified.unresolved:
            combination = ", ".join(f"{label} {component:+.2f}" for label, component in direction.items())
            lines.append(f"not resolved by the data (the prediction barely changes along): {combination}")
    predictability = diagnosis.residual_predictability
    if predictability is not None:
        lines.append(f"remaining residual: held-out R^2 {predictability.heldout_r2:.2f} from state and command "
                     f"({'systematic: a model error' if predictability.systematic else 'no structure found'})")
    if diagnosis.effects_added:
        env = diagnosis.calibrated_env
        effects = env.get("kwargs", {}).get("extra_effects", env.get("kwargs", {}).get("effects", env.get("effects")))
        where = env.get("env_id") or env.get("robot")
        lines.append(f"calibrated simulator ({env['builder']} {where}): {json.dumps(effects)}")
    lines.extend(f"note: {note}" for note in diagnosis.notes)
    return "\n".join(lines)


def plot_residuals(diagnosis: Diagnosis, path: Path) -> None:
    """Per-dimension held-out one-step NRMSE before and after, with the noise floor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = diagnosis.dimension_names
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.6 * len(names) + 2), 4))
    width = 0.4
    ax.bar(x - width / 2, diagnosis.error_before.heldout_per_dimension, width, label="source model")
    ax.bar(x + width / 2, diagnosis.error_after.heldout_per_dimension, width, label="calibrated")
    ax.plot(x, diagnosis.noise_floor_per_dimension, "k_", markersize=14, label="noise floor")
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("held-out one-step NRMSE")
    ax.set_yscale("symlog", linthresh=1e-4)
    top = max([*diagnosis.error_before.heldout_per_dimension, *diagnosis.noise_floor_per_dimension, 1e-3])
    ax.set_ylim(0, 3 * top)
    ax.set_title(f"Residual per observation dimension: {diagnosis.env_id}")
    ax.legend(loc="upper left", fontsize=8, ncols=3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Write through a temporary file in the same folder, then rename: a reader never sees half
    a file, and a failed write leaves nothing behind."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(handle)
    try:
        write(Path(temporary))
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def write_report(diagnosis: Diagnosis, out_dir: str | Path) -> dict[str, Path]:
    """Write ``diagnosis.json``, ``report.md`` and ``residual_per_dimension.png`` into ``out_dir``."""
    out = Path(out_dir)
    paths = {"json": out / "diagnosis.json", "report": out / "report.md", "plot": out / "residual_per_dimension.png"}
    write_json(diagnosis, paths["json"])
    report = summary_text(diagnosis) + "\n\n![residual per dimension](residual_per_dimension.png)\n"
    _write_atomically(paths["report"], lambda p: p.write_text(report))
    _write_atomically(paths["plot"], lambda p: plot_residuals(diagnosis, p))
    return paths


def write_json(diagnosis: Diagnosis, path: str | Path) -> None:
    text = json.dumps(diagnosis.to_json(), indent=2, default=float) + "\n"
    _write_atomically(Path(path), lambda p: p.write_text(text))


def unwritable_reason(path: Path, *, directory: bool) -> str | None:
    """Why ``path`` (a folder to create or fill, or a file to write) cannot be written, or
    ``None``. Checked before a diagnosis runs, without creating anything."""
    if path.exists():
        if directory and not path.is_dir():
            return f"{path} exists and is not a folder"
        if not directory and path.is_dir():
            return f"{path} is a folder; expected a file path"
        folder = path if directory else path.parent
        if not os.access(folder, os.W_OK | os.X_OK) or (not directory and not os.access(path, os.W_OK)):
            return f"{path} is not writable"
        return None
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        return f"{path} cannot be created: {ancestor} is not a folder"
    if not os.access(ancestor, os.W_OK | os.X_OK):
        return f"{path} cannot be created: {ancestor} is not writable"
    return None
