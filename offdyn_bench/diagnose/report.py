"""What a diagnosis writes: the JSON contract, a table of the steps and per-dimension plots."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from offdyn_bench.diagnose.loop import Diagnosis


def _value(effect: dict[str, Any]) -> str:
    value = effect["value"]
    return str(value) if isinstance(value, int) else f"{value:.4g}"


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
        low, high = step.interval
        bound = " on its bound" if step.on_bound else (" (stochastic: explains the spread)" if step.stochastic else "")
        lines.append(
            f"| {i} | {e['kind']} on {target} | {_value(e)} ({low:.4g}..{high:.4g}){bound} "
            f"| {step.before.one_step_nrmse:.4g} -> {step.after.one_step_nrmse:.4g} "
            f"| {step.before.heldout_one_step_nrmse:.4g} -> {step.after.heldout_one_step_nrmse:.4g} "
            f"| {step.before.horizon_nrmse:.4g} -> {step.after.horizon_nrmse:.4g} "
            f"| {step.before.heldout_horizon_nrmse:.4g} -> {step.after.heldout_horizon_nrmse:.4g} |")
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


def write_report(diagnosis: Diagnosis, out_dir: str | Path) -> dict[str, Path]:
    """Write ``diagnosis.json``, ``report.md`` and ``residual_per_dimension.png`` into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "diagnosis.json", "report": out / "report.md", "plot": out / "residual_per_dimension.png"}
    write_json(diagnosis, paths["json"])
    paths["report"].write_text(summary_text(diagnosis) + "\n\n![residual per dimension](residual_per_dimension.png)\n")
    plot_residuals(diagnosis, paths["plot"])
    return paths


def write_json(diagnosis: Diagnosis, path: str | Path) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(diagnosis.to_json(), indent=2, default=float) + "\n")
