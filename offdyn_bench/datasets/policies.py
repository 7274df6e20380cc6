"""Behaviour policies: anything that maps an observation to an action.

A trained policy ships as two files side by side, never as a pickle:

- ``<name>.safetensors``: the actor's weights (``<layer>.weight`` of shape ``(out, in)`` and
  ``<layer>.bias``, the layout of ``torch.nn.Linear``);
- ``<name>.json``: the sidecar, which says how to read them (layer names, activation, action
  bounds), where the policy came from (training config) and how good it is (score).

The actor is a SAC tanh-Gaussian actor used deterministically: ``action = tanh(mean(obs))``
scaled to the action space. The log-std head, if present in the file, is ignored. Inference is
plain numpy in float64 so that dataset builds do not depend on torch's kernels.
"""

from __future__ import annotations

import hashlib
import json
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from offdyn_bench.datasets.archive import sha256_file
from offdyn_bench.errors import OffdynError

POLICY_FORMAT = "offdyn-policy/1"
ACTIVATIONS = {
    "relu": lambda x: np.maximum(x, 0.0),
    "tanh": np.tanh,
}


class PolicyError(OffdynError):
    """A policy file that is missing, malformed or not the one a recipe expects."""


@runtime_checkable
class Policy(Protocol):
    """Anything that can act: one observation in, one action out."""

    def __call__(self, obs: np.ndarray) -> np.ndarray: ...


def derived_seed(entropy: Sequence[int]) -> int:
    """One seed from a list of integers (``[recipe seed, stream]``): the first word of their
    ``SeedSequence``, so each stream of a recipe draws from its own generator."""
    return int(np.random.SeedSequence(list(entropy)).generate_state(1)[0])


class UniformRandomPolicy:
    """Uniform actions inside the box, from its own seeded generator (reproducible)."""

    def __init__(self, low: np.ndarray, high: np.ndarray, seed: int) -> None:
        self.low = np.asarray(low, dtype=np.float64)
        self.high = np.asarray(high, dtype=np.float64)
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.rng.uniform(self.low, self.high)


class MLPPolicy:
    """A deterministic tanh-squashed MLP actor (the mean of a SAC tanh-Gaussian actor)."""

    def __init__(self, layers: Sequence[tuple[np.ndarray, np.ndarray]], activation: str,
                 action_low: np.ndarray, action_high: np.ndarray) -> None:
        if activation not in ACTIVATIONS:
            raise PolicyError(f"unknown activation {activation!r}; expected one of {sorted(ACTIVATIONS)}")
        self.layers = [(np.asarray(w, dtype=np.float64), np.asarray(b, dtype=np.float64)) for w, b in layers]
        self.activation = ACTIVATIONS[activation]
        low = np.asarray(action_low, dtype=np.float64)
        high = np.asarray(action_high, dtype=np.float64)
        self.action_scale = (high - low) / 2.0
        self.action_bias = (high + low) / 2.0

    @property
    def observation_dim(self) -> int:
        return int(self.layers[0][0].shape[1])

    @property
    def action_dim(self) -> int:
        return int(self.layers[-1][0].shape[0])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        x = np.asarray(obs, dtype=np.float64)
        for weight, bias in self.layers[:-1]:
            x = self.activation(weight @ x + bias)
        weight, bias = self.layers[-1]
        return np.tanh(weight @ x + bias) * self.action_scale + self.action_bias


def sidecar_path(weights_path: str | pathlib.Path) -> pathlib.Path:
    """``foo.safetensors`` -> ``foo.json``."""
    return pathlib.Path(weights_path).with_suffix(".json")


def policy_sha256(weights_path: str | pathlib.Path) -> str:
    """The hash a recipe pins: weights and sidecar together (the sidecar decides how the
    weights act, e.g. the action bounds)."""
    weights_path = pathlib.Path(weights_path)
    digest = hashlib.sha256()
    digest.update(sha256_file(weights_path).encode())
    digest.update(sha256_file(sidecar_path(weights_path)).encode())
    return digest.hexdigest()


def read_sidecar(weights_path: str | pathlib.Path) -> dict[str, Any]:
    weights_path = pathlib.Path(weights_path)
    sidecar = sidecar_path(weights_path)
    if not weights_path.is_file():
        raise PolicyError(f"policy weights not found at {weights_path} (expected a .safetensors file with "
                          f"a .json sidecar beside it)")
    if not sidecar.is_file():
        raise PolicyError(f"policy sidecar not found at {sidecar}; a policy is a .safetensors file plus a "
                          f".json sidecar with its architecture, training config and score")
    try:
        meta = json.loads(sidecar.read_text())
    except json.JSONDecodeError as error:
        raise PolicyError(f"policy sidecar {sidecar} is not valid JSON: {error}") from error
    if meta.get("format") != POLICY_FORMAT:
        raise PolicyError(f"policy sidecar {sidecar}: format {meta.get('format')!r}, expected {POLICY_FORMAT!r}")
    return meta


def load_policy(weights_path: str | pathlib.Path) -> MLPPolicy:
    """Load a policy from ``<name>.safetensors`` and its ``<name>.json`` sidecar (no pickle)."""
    from safetensors.numpy import load_file

    weights_path = pathlib.Path(weights_path)
    meta = read_sidecar(weights_path)
    arch = meta.get("architecture") or {}
    names = list(arch.get("hidden_layers", [])) + [arch.get("mean_layer")]
    if names[-1] is None:
        raise PolicyError(f"policy sidecar {sidecar_path(weights_path)}: architecture.mean_layer is missing")
    try:
        tensors = load_file(str(weights_path))
    except Exception as error:  # safetensors raises its own error types for corrupt headers
        raise PolicyError(f"cannot read policy weights {weights_path}: {error}") from error
    layers = []
    for name in names:
        missing = [key for key in (f"{name}.weight", f"{name}.bias") if key not in tensors]
        if missing:
            raise PolicyError(f"policy {weights_path}: tensors {missing} missing; file has {sorted(tensors)}")
        layers.append((tensors[f"{name}.weight"], tensors[f"{name}.bias"]))
    for i, (name, (weight, bias)) in enumerate(zip(names, layers)):
        if weight.ndim != 2 or bias.shape != (weight.shape[0],):
            raise PolicyError(f"policy {weights_path}: layer {name!r} has weight {weight.shape} and bias "
                              f"{bias.shape}; expected (out, in) and (out,)")
        if i and weight.shape[1] != layers[i - 1][0].shape[0]:
            raise PolicyError(f"policy {weights_path}: layer {name!r} takes {weight.shape[1]} inputs but the "
                              f"layer before it gives {layers[i - 1][0].shape[0]}")
    policy = MLPPolicy(layers, arch.get("activation", "relu"), meta["action_low"], meta["action_high"])
    if policy.observation_dim != int(meta["observation_dim"]) or policy.action_dim != int(meta["action_dim"]):
        raise PolicyError(f"policy {weights_path}: weights map {policy.observation_dim} -> {policy.action_dim} "
                          f"but the sidecar says {meta['observation_dim']} -> {meta['action_dim']}")
    return policy


def save_policy(weights_path: str | pathlib.Path, layers: Mapping[str, tuple[np.ndarray, np.ndarray]],
                *, action_low: Sequence[float], action_high: Sequence[float], trained_on: str,
                training: Mapping[str, Any], score: Mapping[str, Any] | None,
                activation: str = "relu") -> pathlib.Path:
    """Write an MLP actor in this module's format. ``layers`` maps layer name to ``(weight,
    bias)`` in order, the last one being the mean head. ``training`` is its config and
    ``score`` its evaluation (with provenance); write ``None`` only for untrained policies."""
    from safetensors.numpy import save_file

    weights_path = pathlib.Path(weights_path)
    names = list(layers)
    tensors = {}
    for name, (weight, bias) in layers.items():
        tensors[f"{name}.weight"] = np.ascontiguousarray(weight, dtype=np.float32)
        tensors[f"{name}.bias"] = np.ascontiguousarray(bias, dtype=np.float32)
    first_weight = layers[names[0]][0]
    last_weight = layers[names[-1]][0]
    sidecar = {
        "format": POLICY_FORMAT,
        "kind": "tanh-gaussian-actor-mean",
        "trained_on": trained_on,
        "observation_dim": int(first_weight.shape[1]),
        "action_dim": int(last_weight.shape[0]),
        "action_low": [float(x) for x in action_low],
        "action_high": [float(x) for x in action_high],
        "architecture": {"hidden_layers": names[:-1], "mean_layer": names[-1], "activation": activation},
        "training": dict(training),
        "score": None if score is None else dict(score),
    }
    weights_path.parent.mkdir(parents=True, exist_ok=True)
    save_file(tensors, str(weights_path))
    sidecar_path(weights_path).write_text(json.dumps(sidecar, indent=2, sort_keys=True) + "\n")
    return weights_path


def import_sac_actor(state_file: str | pathlib.Path, out_path: str | pathlib.Path, *, member: int,
                     trained_on: str, training: Mapping[str, Any], score: Mapping[str, Any] | None,
                     prefix: str = "actor") -> pathlib.Path:
    """Extract one seed's actor from a ``baselines`` SAC checkpoint into this module's format.

    A ``baselines`` checkpoint (``checkpoints/step_<N>/state.safetensors``) stacks every training
    seed: ``actor.<2i>`` is ``[members, in, out]``, ``actor.<2i+1>`` is ``[members, 1, out]``,
    and the last layer gives the Gaussian's mean and log-std side by side. Only the chosen
    member's mean path is kept (the critics, optimizer moments and replay buffers stay behind),
    and the action bounds come from ``trained_on``'s action space.
    """
    import gymnasium
    from safetensors.numpy import load_file

    try:
        state = load_file(str(state_file))
    except Exception as error:
        raise PolicyError(f"cannot read checkpoint {state_file}: {error}") from error
    indices = sorted(int(key.split(".")[1]) for key in state if key.startswith(prefix + ".")
                     and key.split(".")[1].isdigit())
    if not indices or len(indices) % 2 or indices != list(range(len(indices))):
        raise PolicyError(f"checkpoint {state_file} has no {prefix}.0 .. {prefix}.<2L-1> tensors "
                          f"(found {sorted(k for k in state if k.startswith(prefix))[:6]})")
    members = state[f"{prefix}.0"].shape[0]
    if not 0 <= member < members:
        raise PolicyError(f"checkpoint {state_file} holds {members} seeds; member {member} is out of range")
    env = gymnasium.make(trained_on)
    space = env.action_space
    env.close()
    action_dim = int(space.shape[0])  # type: ignore[index]
    n_layers = len(indices) // 2
    layers: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for i in range(n_layers):
        weight = state[f"{prefix}.{2 * i}"][member].T  # [in, out] -> nn.Linear's [out, in]
        bias = state[f"{prefix}.{2 * i + 1}"][member].reshape(-1)
        if i == n_layers - 1:
            if weight.shape[0] != 2 * action_dim:
                raise PolicyError(f"checkpoint {state_file}: last actor layer has {weight.shape[0]} outputs, "
                                  f"expected mean and log-std of {action_dim} actions ({2 * action_dim})")
            weight, bias = weight[:action_dim], bias[:action_dim]
        layers["mean" if i == n_layers - 1 else f"hidden{i}"] = (weight, bias)
    return save_policy(out_path, layers, action_low=space.low, action_high=space.high,  # type: ignore[attr-defined]
                       trained_on=trained_on, training={**training, "checkpoint_member": member}, score=score)


def update_sidecar(weights_path: str | pathlib.Path, **fields: Any) -> None:
    """Set top-level fields of a policy's sidecar (e.g. its score once measured)."""
    meta = read_sidecar(weights_path)
    meta.update(fields)
    sidecar_path(weights_path).write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")


def evaluate_policy(weights_path: str | pathlib.Path, env_id: str, episodes: int,
                    first_seed: int = 1_000_000) -> dict[str, Any]:
    """Mean undiscounted return of the deterministic policy over fixed episode seeds, with the
    provenance a sidecar records."""
    import gymnasium

    from offdyn_bench.datasets.collect import episode_returns
    from offdyn_bench.versions import versions

    env = gymnasium.make(env_id)
    returns = episode_returns(env, load_policy(weights_path), episodes=episodes, seed=first_seed)
    env.close()
    return {"env_id": env_id, "mean_return": float(np.mean(returns)), "std_return": float(np.std(returns)),
            "returns": returns, "episode_seeds": list(range(first_seed, first_seed + episodes)),
            "policy": "deterministic: tanh(mean)", "versions": versions()}
