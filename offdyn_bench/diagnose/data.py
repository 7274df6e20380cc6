"""Measured transitions: the input of gap diagnosis, loaded from a ``.npz`` file or a Minari dataset.

Rows are in time order within episodes; a new episode starts after a row that terminated or
truncated (and the last row always ends one). ``qpos``/``qvel`` are the physics state *before*
each step; when a dataset lacks them, :mod:`offdyn_bench.diagnose.source` rebuilds them from the
observations where the observation determines them.
"""

from __future__ import annotations

import dataclasses
import math
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from offdyn_bench.errors import OffdynError

NPZ_REQUIRED = ("observations", "actions", "next_observations", "terminations", "truncations")
NPZ_OPTIONAL = ("qpos", "qvel")


class DiagnosisInputError(OffdynError):
    """Data or an env id that gap diagnosis cannot work with; the message says what to fix."""


@dataclasses.dataclass(frozen=True)
class Transitions:
    """One row per control step: ``observations[t]``, ``actions[t]`` -> ``next_observations[t]``."""

    observations: np.ndarray
    actions: np.ndarray
    next_observations: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray
    qpos: np.ndarray | None = None
    qvel: np.ndarray | None = None
    origin: str = ""
    recorded_env_id: str | None = None  # the env a Minari dataset says it was recorded with

    def __post_init__(self) -> None:
        for name in ("terminations", "truncations"):
            object.__setattr__(self, name, _as_flags(getattr(self, name), name))
        for name in ("observations", "actions", "next_observations", "qpos", "qvel"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _as_numbers(getattr(self, name), name))
        _validate(self)

    @property
    def size(self) -> int:
        return len(self.actions)

    @property
    def has_state(self) -> bool:
        return self.qpos is not None

    @property
    def episode_ends(self) -> np.ndarray:
        ends = self.terminations | self.truncations
        ends = ends.copy()
        ends[-1] = True
        return ends

    @property
    def episode_index(self) -> np.ndarray:
        """The episode each row belongs to (0, 1, ...)."""
        ends = self.episode_ends
        return np.concatenate([[0], np.cumsum(ends[:-1])]).astype(int)

    @property
    def step_in_episode(self) -> np.ndarray:
        """How many rows of the same episode precede each row."""
        index = self.episode_index
        starts = np.flatnonzero(np.r_[True, index[1:] != index[:-1]])
        return np.arange(self.size) - starts[index]


def _validate(data: Transitions) -> None:
    arrays = {"observations": data.observations, "actions": data.actions,
              "next_observations": data.next_observations}
    for name, array in arrays.items():
        if array.ndim != 2:
            raise DiagnosisInputError(f"{name} must be a 2-D array (rows x dimensions), got shape {array.shape}")
    n = len(data.actions)
    if n == 0:
        where = f" {data.origin}" if data.origin else ""
        raise DiagnosisInputError(f"the dataset{where} is empty: no transitions to diagnose")
    for name, array in {**arrays, "terminations": data.terminations, "truncations": data.truncations}.items():
        if len(array) != n:
            raise DiagnosisInputError(f"{name} has {len(array)} rows but actions has {n}; every array needs one row per transition")
    if data.observations.shape[1] != data.next_observations.shape[1]:
        raise DiagnosisInputError(f"observations have {data.observations.shape[1]} dimensions but next_observations "
                                  f"{data.next_observations.shape[1]}; both must have the observation's size")
    if (data.qpos is None) != (data.qvel is None):
        raise DiagnosisInputError("give both qpos and qvel, or neither")
    if data.qpos is not None:
        for name, array in {"qpos": data.qpos, "qvel": data.qvel}.items():
            if array.ndim != 2 or len(array) != n:  # type: ignore[union-attr]
                raise DiagnosisInputError(f"{name} must have one row per transition ({n}), got shape {array.shape}")  # type: ignore[union-attr]
    for name, array in {**arrays, "qpos": data.qpos, "qvel": data.qvel}.items():
        if array is None:
            continue
        bad = np.flatnonzero(~np.isfinite(array).all(axis=1))
        if bad.size:
            shown = ", ".join(str(i) for i in bad[:5]) + (" ..." if bad.size > 5 else "")
            raise DiagnosisInputError(f"{name} has NaN or infinite values in {bad.size} row(s) ({shown}); "
                                      "remove those transitions (and keep episodes contiguous) before diagnosis")


def _as_numbers(array: object, name: str) -> np.ndarray:
    """A float array of ``array``; text, objects and complex numbers are refused, not converted."""
    out = np.asarray(array)
    if out.dtype.kind not in "biuf":
        raise DiagnosisInputError(f"{name} must hold real numbers, got an array of dtype {out.dtype}")
    return out.astype(float, copy=False)


def _as_float(array: np.ndarray, name: str) -> np.ndarray:
    out = _as_numbers(array, name)
    return out[:, None] if out.ndim == 1 else out


def _as_flags(array: object, name: str) -> np.ndarray:
    """One boolean per row. 0/1 numbers are booleans; any other value (0.5, NaN) is an error,
    never silently cast to True."""
    flags = np.asarray(array)
    if flags.ndim == 2 and flags.shape[1] == 1:
        flags = flags[:, 0]
    if flags.ndim != 1:
        raise DiagnosisInputError(f"{name} must be a 1-D array with one flag per transition, got shape {flags.shape}")
    if flags.dtype.kind == "b":
        return flags
    if flags.dtype.kind not in "iuf":
        raise DiagnosisInputError(f"{name} must be booleans (True/False or 0/1), got an array of dtype {flags.dtype}")
    bad = np.flatnonzero((flags != 0) & (flags != 1))
    if bad.size:
        raise DiagnosisInputError(f"{name} must be booleans (True/False or 0/1), got {flags[bad[0]].item()!r} in row "
                                  f"{bad[0]} ({bad.size} row(s) are neither 0 nor 1)")
    return flags.astype(bool)


# What a broken archive raises while it is read: a truncated or corrupt zip, a bad .npy header,
# a compressed stream that ends early, a compression method zipfile lacks.
_ARCHIVE_ERRORS = (OSError, EOFError, ValueError, zipfile.BadZipFile, zlib.error, NotImplementedError)


def _read_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, name: str, path: str) -> np.ndarray:
    """Read one ``.npy`` member, checking its header against the bytes the archive holds before
    allocating anything: a corrupt header cannot make numpy allocate what is not there."""
    with archive.open(info) as stream:
        version = np.lib.format.read_magic(stream)
        if version == (1, 0):
            shape, fortran_order, dtype = np.lib.format.read_array_header_1_0(stream)
        elif version == (2, 0):
            shape, fortran_order, dtype = np.lib.format.read_array_header_2_0(stream)
        else:
            raise DiagnosisInputError(f"{name} in {path} uses .npy format version {version}; "
                                      "save the arrays with numpy.savez")
        if dtype.hasobject:
            raise DiagnosisInputError(f"{name} in {path} holds Python objects (dtype {dtype}); diagnosis reads "
                                      "plain numeric or boolean arrays only (objects would need unpickling)")
        needed = math.prod(shape) * dtype.itemsize
        available = info.file_size - stream.tell()
        if needed > available:
            raise DiagnosisInputError(f"{name} in {path} is cut short: its header declares shape {shape} "
                                      f"({needed} bytes) but the archive holds {max(available, 0)}; "
                                      "the file was not fully written")
        data = bytearray(stream.read(needed))
    if len(data) != needed:
        raise DiagnosisInputError(f"{name} in {path} is cut short: {len(data)} of {needed} bytes of array data")
    array = np.frombuffer(data, dtype=dtype)
    return array.reshape(shape[::-1]).T if fortran_order else array.reshape(shape)


def _read_npz(path: str) -> dict[str, np.ndarray]:
    """The arrays of the diagnosis contract in an ``.npz`` archive (others are not read)."""
    if os.path.getsize(path) == 0:
        raise DiagnosisInputError(f"{path} is empty (0 bytes); expected an .npz archive written by numpy.savez")
    try:
        with zipfile.ZipFile(path) as archive:
            members = {info.filename[:-4]: info for info in archive.infolist() if info.filename.endswith(".npy")}
            missing = [k for k in NPZ_REQUIRED if k not in members]
            if missing:
                raise DiagnosisInputError(f"{path} lacks the array(s) {missing}; an .npz dataset needs "
                                          f"{list(NPZ_REQUIRED)} and optionally {list(NPZ_OPTIONAL)}")
            return {name: _read_member(archive, members[name], name, path)
                    for name in (*NPZ_REQUIRED, *NPZ_OPTIONAL) if name in members}
    except DiagnosisInputError:
        raise
    except _ARCHIVE_ERRORS as error:
        reason = " ".join(f"{type(error).__name__}: {error}".split())  # one line
        raise DiagnosisInputError(f"cannot read {path} as an .npz archive ({reason}); expected a complete "
                                  "file written by numpy.savez") from None


def load_npz(path: str | os.PathLike) -> Transitions:
    """Load the plain ``.npz`` format (see the README for the contract)."""
    arrays = _read_npz(str(path))
    state = {k: _as_float(arrays[k], k) for k in NPZ_OPTIONAL if k in arrays}
    return Transitions(observations=_as_float(arrays["observations"], "observations"),
                       actions=_as_float(arrays["actions"], "actions"),
                       next_observations=_as_float(arrays["next_observations"], "next_observations"),
                       terminations=_as_flags(arrays["terminations"], "terminations"),
                       truncations=_as_flags(arrays["truncations"], "truncations"),
                       qpos=state.get("qpos"), qvel=state.get("qvel"), origin=str(path))


def load_minari(dataset: str | os.PathLike, nq: int | None = None, nv: int | None = None) -> Transitions:
    """Load a Minari dataset by id or by path. The physics state before each step is read from
    the step infos' ``state`` (``mjSTATE_FULLPHYSICS``: time, qpos, qvel, ...) when present and
    ``nq``/``nv`` are known."""
    import minari

    try:
        path = Path(dataset)
        if path.is_dir():
            data_dir = path / "data" if (path / "data").is_dir() else path
            loaded = minari.MinariDataset(data_dir)
        else:
            from offdyn_bench.datasets.ensure import load_installed

            # A missing dataset names the suite's install command, not Minari's "download=True".
            loaded = load_installed(str(dataset))
    except OffdynError as error:
        raise DiagnosisInputError(str(error)) from None
    except Exception as error:  # Minari raises several types for a missing or broken dataset
        raise DiagnosisInputError(f"cannot load Minari dataset {str(dataset)!r}: {error}") from None
    columns: dict[str, list[np.ndarray]] = {k: [] for k in (*NPZ_REQUIRED, *NPZ_OPTIONAL)}
    for episode in loaded.iterate_episodes():
        obs = np.asarray(episode.observations, dtype=float)
        if obs.ndim != 2:
            raise DiagnosisInputError(f"Minari dataset {str(dataset)!r}: diagnosis needs flat Box observations, "
                                      f"got an observation array of shape {obs.shape}")
        steps = len(episode.actions)
        columns["observations"].append(obs[:-1])
        columns["next_observations"].append(obs[1:])
        columns["actions"].append(np.asarray(episode.actions, dtype=float).reshape(steps, -1))
        terminations = np.asarray(episode.terminations, dtype=bool)
        truncations = np.asarray(episode.truncations, dtype=bool).copy()
        truncations[-1] = not terminations[-1]  # an episode cut short by the recording ends here too
        columns["terminations"].append(terminations)
        columns["truncations"].append(truncations)
        state = (episode.infos or {}).get("state")
        if state is not None and nq is not None and nv is not None:
            state = np.asarray(state, dtype=float)
            before = state[:steps]  # infos hold the reset state then one state per step
            columns["qpos"].append(before[:, 1:1 + nq])
            columns["qvel"].append(before[:, 1 + nq:1 + nq + nv])
    if not columns["actions"]:
        raise DiagnosisInputError(f"Minari dataset {str(dataset)!r} has no episodes")
    full_state = len(columns["qpos"]) == len(columns["actions"])
    env_spec = getattr(loaded.spec, "env_spec", None)
    return Transitions(
        observations=np.concatenate(columns["observations"]),
        actions=np.concatenate(columns["actions"]),
        next_observations=np.concatenate(columns["next_observations"]),
        terminations=np.concatenate(columns["terminations"]),
        truncations=np.concatenate(columns["truncations"]),
        qpos=np.concatenate(columns["qpos"]) if full_state else None,
        qvel=np.concatenate(columns["qvel"]) if full_state else None,
        origin=str(dataset), recorded_env_id=getattr(env_spec, "id", None))


def load_transitions(dataset: str | os.PathLike, nq: int | None = None, nv: int | None = None) -> Transitions:
    """Load ``dataset``: a path ending in ``.npz``, or a Minari dataset id or directory."""
    text = str(dataset)
    if text.endswith(".npz"):
        if not Path(text).is_file():
            raise DiagnosisInputError(f"no such file: {text}")
        return load_npz(text)
    return load_minari(dataset, nq=nq, nv=nv)
