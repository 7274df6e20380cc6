"""Safetensors checkpoints that a killed run can resume from.

A checkpoint is a folder ``checkpoints/step_<N>/`` holding ``state.safetensors`` (every tensor:
parameters, optimizer moments, replay buffers, random generator states) and ``trainer.json``
(counters). It is written to a temporary folder and renamed into place, so a kill leaves either
the whole checkpoint or none of it; the newest complete one is the one a run resumes from.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

CHECKPOINT_DIR = "checkpoints"
STATE_FILE = "state.safetensors"
TRAINER_FILE = "trainer.json"


def optimizer_tensors(optimizer: torch.optim.Optimizer, prefix: str) -> dict[str, torch.Tensor]:
    """An optimizer's per-parameter state as flat named tensors (the hyperparameters live in the
    config, so they are not saved)."""
    out = {}
    for index, state in optimizer.state_dict()["state"].items():
        for key, value in state.items():
            out[f"{prefix}.{index}.{key}"] = torch.as_tensor(value)
    return out


def load_optimizer_tensors(optimizer: torch.optim.Optimizer, tensors: dict[str, torch.Tensor],
                           prefix: str) -> None:
    current = optimizer.state_dict()
    state: dict[int, dict[str, torch.Tensor]] = {}
    for name, value in tensors.items():
        if name.startswith(prefix + "."):
            index, key = name[len(prefix) + 1:].split(".", 1)
            state.setdefault(int(index), {})[key] = value.clone()
    optimizer.load_state_dict({"state": state, "param_groups": current["param_groups"]})


def _contiguous(tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach().contiguous() for k, v in tensors.items()}


def save_checkpoint(run_dir: Path, step: int, tensors: dict[str, torch.Tensor], trainer: dict[str, Any]) -> Path:
    """Write checkpoint ``step`` atomically and drop the older ones."""
    root = run_dir / CHECKPOINT_DIR
    root.mkdir(exist_ok=True)
    final = root / f"step_{step:09d}"
    partial = root / f".partial_step_{step:09d}"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    save_file(_contiguous(tensors), str(partial / STATE_FILE))
    (partial / TRAINER_FILE).write_text(json.dumps(trainer, indent=1))
    if final.exists():
        shutil.rmtree(final)
    os.replace(partial, final)
    for old in root.glob("step_*"):
        if old != final:
            shutil.rmtree(old, ignore_errors=True)
    return final


def latest_checkpoint(run_dir: Path) -> Path | None:
    root = run_dir / CHECKPOINT_DIR
    done = sorted(p for p in root.glob("step_*") if (p / TRAINER_FILE).exists()) if root.exists() else []
    return done[-1] if done else None


def load_checkpoint(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    return load_file(str(path / STATE_FILE)), json.loads((path / TRAINER_FILE).read_text())
