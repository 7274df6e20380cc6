"""Target datasets for the offline-target methods, and source datasets for the offline-source
tracks, behind one loader (:func:`load_dataset`).

A dataset spec is one of:

* ``collect:<policy>:<N>`` -- collected on the spot in the task's target (the source, for a source
  dataset: ``load_dataset(..., side="source")``): ``N`` transitions by
  ``<policy>``, which is ``random`` (uniform actions) or a training run folder (its latest
  checkpoint's deployed action, seed 0, plus Gaussian noise of std 0.1 in [-1, 1] action units so
  the data is sub-optimal and covers more than one trajectory, as a behaviour policy's would);
* a path to an ``.npz`` holding the arrays of :class:`TransitionDataset`;
* a Minari dataset id (``offdyn/hopper-gravity-0p5/source-policy-v0``), loaded with
  ``minari.load_dataset`` when it is installed locally.
"""

from __future__ import annotations

import dataclasses
import hashlib
import struct
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import gymnasium
import numpy as np
import torch

from baselines.sac import Batch
from offdyn_bench.envs import flat_observations, flatten_observation_rows
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import TaskPair

ARRAYS = ("observations", "actions", "rewards", "next_observations", "terminations", "truncations")
PER_STEP_VECTORS = ("observations", "actions", "next_observations")
"""Arrays with one row per step (``[N, ...]``); the others are ``[N]``."""
BEHAVIOUR_NOISE_STD = 0.1
Policy = Callable[[np.ndarray], np.ndarray]
"""Observation (environment units) -> action (environment units)."""
Side = Literal["source", "target"]


@dataclasses.dataclass(frozen=True)
class TransitionDataset:
    """Transitions as numpy arrays, actions in environment units; row i is one step."""

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_observations: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray

    def __post_init__(self) -> None:
        for name in ARRAYS:
            array = getattr(self, name)
            if not isinstance(array, np.ndarray):
                raise OffdynError(f"dataset {name} is a {type(array).__name__}; expected a numpy array")
            if array.dtype.kind not in "biuf":
                raise OffdynError(f"dataset {name} has dtype {array.dtype}; expected real numbers or booleans")
            expected_ndim = "at least 2 dimensions" if name in PER_STEP_VECTORS else "1 dimension"
            if (array.ndim < 2) if name in PER_STEP_VECTORS else (array.ndim != 1):
                raise OffdynError(f"dataset {name} has shape {array.shape}; expected {expected_ndim} "
                                  "(one row per step)")
            if array.dtype.kind == "f" and not np.isfinite(array).all():
                row = int(np.flatnonzero(~np.isfinite(array.reshape(len(array), -1)).all(axis=1))[0])
                raise OffdynError(f"dataset {name} holds NaN or infinite values (first in row {row}); expected "
                                  "finite numbers")
        n = len(self.rewards)
        for name in ARRAYS:
            if len(getattr(self, name)) != n:
                raise OffdynError(f"dataset arrays differ in length: {name} has {len(getattr(self, name))} "
                                  f"rows, rewards has {n}")
        for name in ("terminations", "truncations"):
            flags = getattr(self, name)
            if flags.dtype.kind != "b" and not np.isin(flags, (0, 1)).all():
                raise OffdynError(f"dataset {name} holds values other than 0 and 1; expected booleans")

    def __len__(self) -> int:
        return len(self.rewards)

    def save_npz(self, path: str | Path) -> None:
        np.savez(path, **{name: getattr(self, name) for name in ARRAYS})

    @classmethod
    def from_npz(cls, path: str | Path) -> TransitionDataset:
        """Read an ``.npz`` of :data:`ARRAYS`; anything else (an empty, truncated or foreign file,
        pickled objects) is an :class:`OffdynError` saying so."""
        expected = f"expected an .npz written by numpy.savez with arrays {', '.join(ARRAYS)}"
        arrays = {}
        try:
            # allow_pickle stays off: loading pickled objects from a dataset file can run code.
            data = np.load(path, allow_pickle=False)
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise OffdynError(f"dataset {str(path)!r} holds a single array, not an .npz archive; {expected}")
            with data:
                missing = [name for name in ARRAYS if name not in data.files]
                if missing:
                    raise OffdynError(f"dataset {str(path)!r} lacks arrays {missing}; {expected}")
                for name in ARRAYS:
                    arrays[name] = data[name]
        except OffdynError:
            raise
        except EOFError:
            raise OffdynError(f"dataset {str(path)!r} is empty; {expected}") from None
        except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, NotImplementedError, RuntimeError,
                struct.error) as error:
            # zipfile answers damaged flag or method fields with NotImplementedError ("unsupported
            # compression") and RuntimeError ("encrypted, password required").
            raise OffdynError(f"dataset {str(path)!r} is damaged or truncated ({_one_line(error)}); "
                              f"{expected}") from None
        except MemoryError:
            raise OffdynError(f"dataset {str(path)!r} declares arrays too large to load (a damaged header?); "
                              f"{expected}") from None
        except ValueError as error:
            if "allow_pickle" in str(error):
                raise OffdynError(f"dataset {str(path)!r} holds a Python object array, which is not loaded "
                                  f"(it could run code); {expected}") from None
            raise OffdynError(f"dataset {str(path)!r} cannot be read ({_one_line(error)}); {expected}") from None
        except OSError as error:
            raise OffdynError(f"dataset {str(path)!r} cannot be read ({error.strerror or _one_line(error)}); "
                              f"{expected}") from None
        try:
            return cls(**arrays)
        except OffdynError as error:
            raise OffdynError(f"{str(path)!r}: {error}") from None

    def sha256(self) -> str:
        digest = hashlib.sha256()
        for name in ARRAYS:
            digest.update(np.ascontiguousarray(getattr(self, name)).tobytes())
        return digest.hexdigest()

    def check_spaces(self, observation_space: gymnasium.Space, action_space: gymnasium.Space, task: str) -> None:
        """Raise if the arrays do not fit the task's spaces."""
        for name, space in (("observations", observation_space), ("next_observations", observation_space),
                            ("actions", action_space)):
            shape = getattr(self, name).shape[1:]
            if shape != space.shape:
                raise OffdynError(f"dataset {name} have shape {shape} per step but task {task!r} expects "
                                  f"{space.shape}; was the dataset collected on another robot?")
        if len(self) == 0:
            raise OffdynError("the dataset is empty")
        low, high = action_space.low, action_space.high
        if np.any(self.actions < low - 1e-6) or np.any(self.actions > high + 1e-6):
            raise OffdynError(f"dataset actions leave task {task!r}'s action bounds [{low}, {high}]")

    def to_batch(self, action_space: gymnasium.spaces.Box) -> Batch:
        """Float tensors with actions scaled to [-1, 1], for the samplers."""
        def tensor(x: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x, dtype=np.float32))

        scaled = 2.0 * (self.actions - action_space.low) / (action_space.high - action_space.low) - 1.0
        return Batch(tensor(self.observations), tensor(scaled), tensor(self.rewards),
                     tensor(self.next_observations), tensor(self.terminations))


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__


def collect_target_dataset(task: TaskPair, policy: Policy | str, n_transitions: int, seed: int
                           ) -> TransitionDataset:
    """``n_transitions`` steps of ``policy`` in ``task``'s target (episode k reset with seed
    ``[seed, k]``). ``policy`` is a callable, ``"random"`` or a training run folder."""
    return collect_dataset(task, policy, n_transitions, seed, side="target")


def collect_dataset(task: TaskPair, policy: Policy | str, n_transitions: int, seed: int,
                    side: Side = "target") -> TransitionDataset:
    """:func:`collect_target_dataset` in ``task``'s ``side`` environment (``source`` for the
    offline-source tracks' source data)."""
    if n_transitions <= 0:
        raise OffdynError(f"cannot collect {n_transitions} transitions; expected a positive number")
    env = flat_observations(task.make(side))
    rng = np.random.default_rng(seed)
    act = _resolve_policy(policy, env.action_space, rng)
    rows: dict[str, list[Any]] = {name: [] for name in ARRAYS}
    episode = 0
    obs, _ = env.reset(seed=_episode_seed(seed, episode))
    while len(rows["rewards"]) < n_transitions:
        action = np.asarray(act(obs), dtype=env.action_space.dtype)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for name, value in zip(ARRAYS, (obs, action, reward, next_obs, terminated, truncated)):
            rows[name].append(value)
        obs = next_obs
        if terminated or truncated:
            episode += 1
            obs, _ = env.reset(seed=_episode_seed(seed, episode))
    # The last row ends the dataset mid-episode: mark it truncated so nothing bootstraps across it.
    rows["truncations"][-1] = True
    env.close()
    return TransitionDataset(
        observations=np.asarray(rows["observations"], dtype=np.float64),
        actions=np.asarray(rows["actions"], dtype=np.float32),
        rewards=np.asarray(rows["rewards"], dtype=np.float64),
        next_observations=np.asarray(rows["next_observations"], dtype=np.float64),
        terminations=np.asarray(rows["terminations"], dtype=bool),
        truncations=np.asarray(rows["truncations"], dtype=bool))


def _episode_seed(seed: int, episode: int) -> int:
    return int(np.random.SeedSequence([int(seed), episode]).generate_state(1)[0])


def _resolve_policy(policy: Policy | str, action_space: gymnasium.spaces.Box, rng: np.random.Generator) -> Policy:
    if callable(policy):
        return policy
    if policy == "random":
        return lambda obs: rng.uniform(action_space.low, action_space.high)
    run_dir = Path(policy)
    if not run_dir.is_dir():
        raise OffdynError(f"unknown behaviour policy {policy!r}; expected 'random' or a training run folder "
                          "(one holding config.json and checkpoints/)")
    from baselines.train import load_trained_policy

    deployed = load_trained_policy(run_dir)
    low, high = action_space.low, action_space.high

    def noisy(obs: np.ndarray) -> np.ndarray:
        scaled = 2.0 * (deployed(obs) - low) / (high - low) - 1.0
        scaled = np.clip(scaled + rng.normal(0.0, BEHAVIOUR_NOISE_STD, size=scaled.shape), -1.0, 1.0)
        return low + (scaled + 1.0) * 0.5 * (high - low)

    return noisy


def load_dataset(spec: str, task: TaskPair, seed: int = 0, side: Side = "target"
                 ) -> tuple[TransitionDataset, dict[str, Any]]:
    """The dataset named by ``spec`` (see the module docstring) and its provenance, checked against
    ``task``'s spaces. The one place dataset kinds are told apart. ``side``: the environment a
    ``collect:`` spec steps, and, for a Minari id, the side its data must come from (a source
    dataset passed as a target one, or the reverse, is refused)."""
    if spec.startswith("collect:"):
        parts = spec.split(":")
        policy, count = ":".join(parts[1:-1]), parts[-1]
        if len(parts) < 3 or not policy or not count.isdigit():
            raise OffdynError(f"bad dataset spec {spec!r}; expected collect:<policy>:<N>, e.g. collect:random:5000 "
                              "or collect:runs/sac-source:5000")
        dataset = collect_dataset(task, policy, int(count), seed, side)
        provenance = {"kind": "collected", "policy": policy, "n_transitions": int(count), "seed": seed,
                      "behaviour_noise_std": None if policy == "random" else BEHAVIOUR_NOISE_STD}
        if side == "source":
            provenance["side"] = "source"
    elif spec.endswith(".npz"):
        if not Path(spec).exists():
            raise OffdynError(f"dataset file {spec!r} does not exist")
        if not Path(spec).is_file():
            raise OffdynError(f"dataset {spec!r} is not a file; expected an .npz file")
        dataset = TransitionDataset.from_npz(spec)
        provenance = {"kind": "npz", "path": str(Path(spec).resolve())}
    elif spec.count("/") >= 2:
        _check_minari_side(spec, side)
        dataset, provenance = _load_minari(spec)
    else:
        raise OffdynError(f"unrecognised dataset {spec!r}; expected collect:<policy>:<N>, a path to an .npz "
                          "file, or a Minari dataset id like offdyn/hopper-gravity-0p5/source-policy-v0")
    env = flat_observations(task.make("target"))
    dataset.check_spaces(env.observation_space, env.action_space, task.name)
    env.close()
    provenance |= {"spec": spec, "task_version": task.version, "size": len(dataset), "sha256": dataset.sha256()}
    return dataset, provenance


def _check_minari_side(dataset_id: str, side: Side) -> None:
    """The suite's own ids say their side: ``source`` datasets come from the source, the other
    qualities from the target."""
    from offdyn_bench.datasets.recipes import parse_dataset_id

    try:
        _, quality, _ = parse_dataset_id(dataset_id)
    except OffdynError:
        return  # not one of the suite's ids: loading says what is wrong with it
    if (quality == "source") != (side == "source"):
        flag, other = ("--source-dataset", "--dataset") if side == "source" else ("--dataset", "--source-dataset")
        raise OffdynError(f"{dataset_id} holds {'source' if quality == 'source' else 'target'} transitions; "
                          f"{flag} expects {side} ones (pass it as {other})")


def _load_minari(dataset_id: str) -> tuple[TransitionDataset, dict[str, Any]]:
    import minari

    from offdyn_bench.datasets.ensure import load_installed

    # A missing dataset names the suite's own install command, not Minari's "download=True".
    data = load_installed(dataset_id)
    rows: dict[str, list[np.ndarray]] = {name: [] for name in ARRAYS}
    for episode in data.iterate_episodes():
        obs = episode.observations
        # Dict observations (AntMaze's) as envs.flat_observations gives them to the learner.
        obs = flatten_observation_rows(obs, data.observation_space) if isinstance(obs, dict) else np.asarray(obs)
        rows["observations"].append(obs[:-1])
        rows["next_observations"].append(obs[1:])
        rows["actions"].append(np.asarray(episode.actions))
        rows["rewards"].append(np.asarray(episode.rewards))
        rows["terminations"].append(np.asarray(episode.terminations, dtype=bool))
        rows["truncations"].append(np.asarray(episode.truncations, dtype=bool))
    dataset = TransitionDataset(**{name: np.concatenate(rows[name]) for name in ARRAYS})
    return dataset, {"kind": "minari", "dataset_id": dataset_id,
                     "minari_version": getattr(minari, "__version__", None)}
