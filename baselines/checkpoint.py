"""Safetensors checkpoints that a killed run can resume from, verified before they are trusted.

A checkpoint is a folder ``checkpoints/step_<N>/`` holding ``state.safetensors`` (every tensor:
parameters, optimizer moments, replay buffers, random generator states), ``trainer.json``
(counters) and ``checksums.json`` (the sha256 of the other two, written last). It is written to a
temporary folder and renamed into place, so a kill leaves either the whole checkpoint or none of
it. Disks and copies still damage files afterwards (a truncated copy, a flipped bit), so a
checkpoint counts as complete only when every file it needs is there and matches its checksum:
:func:`load_checkpoint` verifies before it returns anything, and the two newest checkpoints are
kept so a damaged newest one still leaves one to resume from.

Checkpoints written before checksums existed (no ``checksums.json``) are accepted when both files
parse; they cannot be checked for flipped bytes.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_safetensors_bytes
from safetensors.torch import save_file

from offdyn_bench.errors import OffdynError

CHECKPOINT_DIR = "checkpoints"
STATE_FILE = "state.safetensors"
TRAINER_FILE = "trainer.json"
CHECKSUMS_FILE = "checksums.json"
KEEP = 2
"""Checkpoints kept: the newest and one before it, the fallback when the newest is damaged."""


class DamagedCheckpointError(OffdynError):
    """A checkpoint whose files are missing, unreadable or do not match their checksums."""

    def __init__(self, path: Path, reason: str) -> None:
        self.path, self.reason = path, reason
        super().__init__(f"checkpoint {path.name} is damaged ({reason})")


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


def _file_sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def checkpoint_step(path: Path) -> int:
    return int(path.name.removeprefix("step_"))


def save_checkpoint(run_dir: Path, step: int, tensors: dict[str, torch.Tensor], trainer: dict[str, Any]) -> Path:
    """Write checkpoint ``step`` atomically (checksums last), then keep only the newest ``KEEP``."""
    root = run_dir / CHECKPOINT_DIR
    root.mkdir(exist_ok=True)
    final = root / f"step_{step:09d}"
    partial = root / f".partial_step_{step:09d}"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    save_file(_contiguous(tensors), str(partial / STATE_FILE))
    (partial / TRAINER_FILE).write_text(json.dumps(trainer, indent=1))
    checksums = {name: _file_sha256(partial / name) for name in (STATE_FILE, TRAINER_FILE)}
    (partial / CHECKSUMS_FILE).write_text(json.dumps(checksums, indent=1))
    # The data must be on disk before the rename makes the checkpoint visible, or a power cut can
    # leave a complete-looking folder of empty files.
    for name in (STATE_FILE, TRAINER_FILE, CHECKSUMS_FILE):
        _fsync(partial / name)
    if final.exists():
        shutil.rmtree(final)
    os.replace(partial, final)
    _fsync(root)
    for old in checkpoints(run_dir)[:-KEEP]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def checkpoints(run_dir: Path) -> list[Path]:
    """Every ``step_<N>`` folder of a run, oldest first, whether complete or not."""
    root = run_dir / CHECKPOINT_DIR
    if not root.is_dir():
        return []
    found = [p for p in root.glob("step_*") if p.is_dir() and p.name.removeprefix("step_").isdigit()]
    return sorted(found, key=checkpoint_step)


def load_checkpoint(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The tensors and counters of checkpoint ``path``, after checking every file against its
    checksum; raises :class:`DamagedCheckpointError` saying what is wrong."""
    expected = _read_checksums(path)
    contents = {}
    for name in (STATE_FILE, TRAINER_FILE):
        try:
            contents[name] = (path / name).read_bytes()
        except FileNotFoundError:
            raise DamagedCheckpointError(path, f"{name} is missing") from None
        except OSError as error:
            raise DamagedCheckpointError(path, f"{name} cannot be read: {error.strerror}") from None
        if not contents[name]:
            raise DamagedCheckpointError(path, f"{name} is empty")
        if expected is not None:
            digest = hashlib.sha256(contents[name]).hexdigest()
            if digest != expected.get(name):
                raise DamagedCheckpointError(path, f"{name} does not match its sha256 in {CHECKSUMS_FILE}")
    try:
        tensors = load_safetensors_bytes(contents[STATE_FILE])
    except (SafetensorError, ValueError, RuntimeError) as error:
        raise DamagedCheckpointError(path, f"{STATE_FILE} is not a readable safetensors file: {error}") from None
    try:
        trainer = json.loads(contents[TRAINER_FILE])
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DamagedCheckpointError(path, f"{TRAINER_FILE} is not valid JSON: {error}") from None
    if not isinstance(trainer, dict) or trainer.get("step") != checkpoint_step(path):
        raise DamagedCheckpointError(path, f"{TRAINER_FILE} does not record step {checkpoint_step(path)}")
    return tensors, trainer


def _read_checksums(path: Path) -> dict[str, str] | None:
    """The recorded sha256 per file; None for a checkpoint written before checksums existed."""
    checksums_path = path / CHECKSUMS_FILE
    if not checksums_path.exists():
        if not (path / STATE_FILE).exists() and not (path / TRAINER_FILE).exists():
            raise DamagedCheckpointError(path, "it holds none of its files")
        return None
    try:
        checksums = json.loads(checksums_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, OSError) as error:
        raise DamagedCheckpointError(path, f"{CHECKSUMS_FILE} is unreadable: {error}") from None
    if not isinstance(checksums, dict) or any(not isinstance(checksums.get(n), str) for n in (STATE_FILE, TRAINER_FILE)):
        raise DamagedCheckpointError(path, f"{CHECKSUMS_FILE} does not list {STATE_FILE} and {TRAINER_FILE}")
    return checksums


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The newest checkpoint that verifies, or None."""
    for path in reversed(checkpoints(run_dir)):
        try:
            load_checkpoint(path)
        except DamagedCheckpointError:
            continue
        return path
    return None
