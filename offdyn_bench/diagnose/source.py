"""The source simulator as diagnosis sees it: a compiled model, how a control step maps to physics
steps, and how an observation is read off the physics state.

Any Gymnasium MuJoCo environment works (``Hopper-v5``, this suite's ids, a user's own env): the
observation map is found by probing the env's own ``_get_obs`` rather than by knowing the robot.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import os
from collections.abc import Sequence
from typing import Any

import gymnasium
import mujoco
import mujoco.rollout
import numpy as np

from offdyn_bench.diagnose.data import DiagnosisInputError, Transitions
from offdyn_bench.effects import ChannelEffects, Effect
from offdyn_bench.effects.model import ModelEffect, apply_model_effects, compile_model
from offdyn_bench.errors import OffdynError
from offdyn_bench.robots import ROBOTS
from offdyn_bench.tasks import ENTRY_POINT

FULL_PHYSICS = mujoco.mjtState.mjSTATE_FULLPHYSICS


@dataclasses.dataclass(frozen=True)
class ObservationMap:
    """Which state coordinate (index into ``[qpos, qvel]``) each observation dimension reads, and
    the clipping the env applies. ``source[i] == -1``: dimension ``i`` is not a state coordinate
    (e.g. contact forces) and is left out of the residual."""

    source: np.ndarray
    low: np.ndarray
    high: np.ndarray
    names: tuple[str, ...]

    @property
    def mapped(self) -> np.ndarray:
        return np.flatnonzero(self.source >= 0)

    def observe(self, qpos_qvel: np.ndarray) -> np.ndarray:
        """Observation dimensions ``mapped`` read from ``[..., nq + nv]`` state rows."""
        dims = self.mapped
        return np.clip(qpos_qvel[..., self.source[dims]], self.low[dims], self.high[dims])


def _state_names(model: mujoco.MjModel) -> list[str]:
    """``qpos[<joint>]`` / ``qvel[<joint>]`` labels, with a component index for multi-dof joints."""
    names: list[str] = []
    for prefix, count, address in (("qpos", model.nq, model.jnt_qposadr), ("qvel", model.nv, model.jnt_dofadr)):
        labels = [f"{prefix}[{i}]" for i in range(count)]
        for j in range(model.njnt):
            joint = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"
            start = int(address[j])
            end = int(address[j + 1]) if j + 1 < model.njnt else count
            for k in range(start, end):
                labels[k] = f"{prefix}[{joint}]" if end - start == 1 else f"{prefix}[{joint}:{k - start}]"
        names.extend(labels)
    return names


def probe_observation_map(env: Any) -> ObservationMap:
    """Find, for each observation dimension, the qpos/qvel coordinate it equals (and its clip
    bounds) by setting random states and reading the env's own observation."""
    model, data = env.model, env.data
    saved = (data.qpos.copy(), data.qvel.copy())
    rng = np.random.default_rng(0)

    def observe(qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        data.qpos[:] = qpos
        data.qvel[:] = qvel
        mujoco.mj_forward(model, data)
        return np.asarray(env._get_obs(), dtype=float).ravel()

    probes = [(model.qpos0 + 0.05 * rng.standard_normal(model.nq), 0.3 * rng.standard_normal(model.nv))
              for _ in range(4)]
    states = np.array([np.concatenate(p) for p in probes])
    observations = np.array([observe(*p) for p in probes])
    size = observations.shape[1]
    source = np.full(size, -1)
    for i in range(size):
        match = np.flatnonzero(np.all(np.abs(states - observations[:, [i]]) < 1e-12, axis=0))
        if match.size == 1:
            source[i] = match[0]
    low, high = np.full(size, -np.inf), np.full(size, np.inf)
    for sign, bound in ((1.0, high), (-1.0, low)):
        qpos, qvel = model.qpos0.copy(), np.zeros(model.nv)
        for i in np.flatnonzero(source >= 0):
            j = source[i]
            if j >= model.nq:
                qvel[j - model.nq] = sign * 1e4
        extreme = observe(qpos, qvel)
        for i in np.flatnonzero(source >= model.nq):
            if abs(extreme[i]) < 1e4 - 1e-6:
                bound[i] = extreme[i]
    data.qpos[:], data.qvel[:] = saved
    mujoco.mj_forward(model, data)
    labels = _state_names(model)
    names = tuple(labels[j] if j >= 0 else f"obs[{i}]" for i, j in enumerate(source))
    return ObservationMap(source=source, low=low, high=high, names=names)


def _find(env: gymnasium.Env, kind: type) -> Any:
    while True:
        if isinstance(env, kind):
            return env
        if not hasattr(env, "env"):
            return None
        env = env.env


class SourceSimulator:
    """The source env's model, control step and observation map, with batched prediction."""

    def __init__(self, env_id: str, **env_kwargs: Any) -> None:
        try:
            env = gymnasium.make(env_id, **env_kwargs)
        except gymnasium.error.Error as error:
            raise DiagnosisInputError(f"cannot build source env {env_id!r}: {error}") from None
        except Exception as error:  # a user's env may fail in its own way; say which env
            raise DiagnosisInputError(f"cannot build source env {env_id!r}: {type(error).__name__}: {error}") from None
        unwrapped = env.unwrapped
        if not all(hasattr(unwrapped, a) for a in ("model", "data", "frame_skip", "_get_obs")):
            raise DiagnosisInputError(f"source env {env_id!r} is not a Gymnasium MuJoCo env "
                                      "(it needs model, data, frame_skip and _get_obs)")
        if isinstance(unwrapped.observation_space, gymnasium.spaces.Dict):
            # Restarts from AntMaze's stored states are exact (tests/datasets), but this diagnosis's
            # predictions on them were not checked: refuse rather than report unverified effects.
            raise DiagnosisInputError(f"source env {env_id!r} has goal-conditioned (Dict) observations; diagnosis "
                                      "supports envs with one Box observation (not AntMaze yet)")
        engine = getattr(unwrapped, "engine", "mujoco")
        if engine != "mujoco":  # e.g. a DART target: it carries a MuJoCo model, but never steps it
            raise DiagnosisInputError(f"source env {env_id!r} runs on {engine}; diagnosis predicts with MuJoCo "
                                      "(mujoco.rollout), so --env must be a MuJoCo env, e.g. the pair's source id")
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs)
        self.env = env
        self.base_model: mujoco.MjModel = unwrapped.model
        self.frame_skip = int(unwrapped.frame_skip)
        self.robot = self._robot_name(env)
        channel = _find(env, ChannelEffects)
        model_effects = tuple(getattr(unwrapped, "model_effects", ()))
        self.declared_effects: tuple[Effect, ...] = model_effects + (tuple(channel.effects) if channel else ())
        # Model effects are already compiled into base_model; channel ones are replayed on the data.
        self.declared_channel_effects: tuple[Effect, ...] = tuple(channel.effects) if channel else ()
        self.observation_map = probe_observation_map(unwrapped)
        self.observation_map_labels = _state_names(self.base_model)  # qpos/qvel coordinate names
        self.action_size = int(np.prod(env.action_space.shape))
        self.observation_size = int(np.prod(env.observation_space.shape))
        self.state_size = mujoco.mj_stateSize(self.base_model, FULL_PHYSICS)
        reference = mujoco.MjData(self.base_model)
        self.reference_state = np.empty(self.state_size)
        mujoco.mj_getState(self.base_model, reference, self.reference_state, FULL_PHYSICS)
        self.nthread = max(1, os.cpu_count() or 1)
        self._datas = [mujoco.MjData(self.base_model) for _ in range(self.nthread)]
        self._model_cache: dict[tuple[Effect, ...], mujoco.MjModel] = {}
        self._declared_model_effects = model_effects
        self.xml_path: str | None = getattr(unwrapped, "fullpath", None)

    @functools.cached_property
    def compiles_from_spec(self) -> bool:
        """Whether compiling the env's XML with its declared model effects gives its model: only
        then may geometry effects (which edit the XML's spec before compiling) be candidates.
        Checked on first use: it compiles the model once."""
        if not self.xml_path or not os.path.isfile(self.xml_path):
            return False
        try:
            model = compile_model(self.xml_path, list(self._declared_model_effects))  # type: ignore[arg-type]
        except (OffdynError, ValueError, OSError):  # an XML the env post-processes itself: not ours to rebuild
            return False
        base = self.base_model
        fields = ("body_mass", "body_inertia", "body_pos", "geom_size", "geom_friction", "actuator_gear",
                  "dof_damping", "jnt_range")
        return (model.nq == base.nq and model.nbody == base.nbody and model.ngeom == base.ngeom
                and all(np.allclose(getattr(model, f), getattr(base, f)) for f in fields)
                and model.opt.timestep == base.opt.timestep)

    @staticmethod
    def _robot_name(env: gymnasium.Env) -> str | None:
        spec = env.spec
        if spec is not None and spec.entry_point == ENTRY_POINT:
            return str(spec.kwargs.get("robot"))
        for robot in ROBOTS.values():
            if type(env.unwrapped) is robot.load_env_class() or isinstance(env.unwrapped, robot.load_env_class()):
                return robot.name
        return None

    @property
    def is_suite_env(self) -> bool:
        spec = self.env.spec
        return spec is not None and spec.entry_point == ENTRY_POINT

    # --- checks ---------------------------------------------------------------------------
    def check_data(self, data: Transitions) -> None:
        """Raise a :class:`DiagnosisInputError` when ``data`` cannot come from this env."""
        if data.actions.shape[1] != self.action_size:
            raise DiagnosisInputError(f"the data's actions have {data.actions.shape[1]} dimensions but {self.env_id} "
                                      f"takes {self.action_size}; is --env the env the data was recorded on?")
        if data.observations.shape[1] != self.observation_size:
            raise DiagnosisInputError(f"the data's observations have {data.observations.shape[1]} dimensions but "
                                      f"{self.env_id} observes {self.observation_size}; is --env the env the data "
                                      "was recorded on?")
        if data.qpos is not None and (data.qpos.shape[1] != self.base_model.nq or data.qvel.shape[1] != self.base_model.nv):  # type: ignore[union-attr]
            raise DiagnosisInputError(f"qpos/qvel have {data.qpos.shape[1]}/{data.qvel.shape[1]} columns but {self.env_id}'s "  # type: ignore[union-attr]
                                      f"model has nq={self.base_model.nq}, nv={self.base_model.nv}")
        if self.observation_map.mapped.size == 0:
            raise DiagnosisInputError(f"no observation dimension of {self.env_id} is a qpos/qvel coordinate; "
                                      "diagnosis compares observations read off the physics state")

    # --- models ---------------------------------------------------------------------------
    def model_with(self, effects: Sequence[ModelEffect]) -> mujoco.MjModel:
        """A copy of the source model with ``effects`` applied on top (cached)."""
        key = tuple(effects)
        if not key:
            return self.base_model
        model = self._model_cache.get(key)
        if model is None:
            if len(self._model_cache) > 512:
                self._model_cache.clear()
            if any(e.needs_spec for e in key):
                if not self.compiles_from_spec:
                    raise DiagnosisInputError(f"{self.env_id}'s model cannot be recompiled from its XML, so geometry "
                                              f"effects ({', '.join(e.kind for e in key if e.needs_spec)}) cannot "
                                              "be applied to it")
                model = compile_model(self.xml_path, [*self._declared_model_effects, *key])  # type: ignore[arg-type, list-item]
            else:
                model = copy.copy(self.base_model)
                apply_model_effects(model, list(key))
            self._model_cache[key] = model
        return model

    # --- states ---------------------------------------------------------------------------
    def full_states(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """Full-physics state rows from qpos/qvel rows (time and activations from the reset state)."""
        nq, nv = self.base_model.nq, self.base_model.nv
        states = np.repeat(self.reference_state[None], len(qpos), axis=0)
        states[:, 1:1 + nq] = qpos
        states[:, 1 + nq:1 + nq + nv] = qvel
        return states

    def qpos_qvel(self, states: np.ndarray) -> np.ndarray:
        nq, nv = self.base_model.nq, self.base_model.nv
        return states[..., 1:1 + nq + nv]

    def predict(self, models: mujoco.MjModel | Sequence[mujoco.MjModel], states: np.ndarray,
                controls: np.ndarray) -> np.ndarray:
        """Roll every state forward with its controls ``[batch, horizon, nu]`` held for
        ``frame_skip`` physics steps each; return the states after each control step
        ``[batch, horizon, nstate]``."""
        controls = np.repeat(controls, self.frame_skip, axis=1)
        result, _ = mujoco.rollout.rollout(models, self._datas, states, controls, persistent_pool=True)
        return result[:, self.frame_skip - 1::self.frame_skip]

    # --- the calibrated simulator ---------------------------------------------------------
    def calibrated_env(self, added: Sequence[Effect]) -> dict[str, Any]:
        """How to build the calibrated simulator: a registry call or ``make_robot_env`` arguments."""
        extra = [e.to_dict() for e in added]
        # The source's own constructor arguments are part of the source: without them the recipe
        # would rebuild a different simulator.
        kwargs = _json_safe(self.env_kwargs)
        if self.is_suite_env:
            return {"builder": "gymnasium.make", "env_id": self.env_id, "kwargs": {**kwargs, "extra_effects": extra}}
        if self.robot is not None and not set(kwargs) & _MAKE_ONLY_KWARGS:
            return {"builder": "offdyn_bench.make_robot_env", "robot": self.robot, "kwargs": {**kwargs, "effects": extra}}
        return {"builder": "apply to env.unwrapped.model", "env_id": self.env_id, "env_kwargs": kwargs,
                "effects": extra,
                "note": "unknown robot: apply model effects with offdyn_bench.effects.apply_model_effects("
                        "env.unwrapped.model, ...) and wrap channel effects in offdyn_bench.effects.ChannelEffects"}


# Arguments of gymnasium.make itself, not of the env's constructor.
_MAKE_ONLY_KWARGS = {"max_episode_steps", "autoreset", "apply_api_compatibility", "disable_env_checker"}


def _json_safe(kwargs: dict[str, Any]) -> dict[str, Any]:
    """Constructor arguments as JSON values (paths as strings, arrays as lists)."""
    out: dict[str, Any] = {}
    for key, value in kwargs.items():
        if isinstance(value, os.PathLike):
            value = os.fspath(value)
        elif isinstance(value, np.ndarray):
            value = value.tolist()
        elif isinstance(value, tuple):
            value = list(value)
        out[key] = value
    return out


def rebuild_states(source: SourceSimulator, observations: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Rebuild qpos/qvel rows from observations. Returns ``(qpos_qvel, usable_rows, notes)``:
    coordinates the observation lacks take their reference value (``qpos0`` / zero velocity) and
    rows where a clipped observation hides the true value are not usable."""
    model = source.base_model
    omap = source.observation_map
    n = len(observations)
    values = np.concatenate([np.repeat(model.qpos0[None], n, axis=0), np.zeros((n, model.nv))], axis=1)
    usable = np.ones(n, dtype=bool)
    covered = np.zeros(model.nq + model.nv, dtype=bool)
    for i in omap.mapped:
        j = omap.source[i]
        covered[j] = True
        values[:, j] = observations[:, i]
        at_bound = (observations[:, i] >= omap.high[i] - 1e-9) | (observations[:, i] <= omap.low[i] + 1e-9)
        usable &= ~at_bound
    labels = _state_names(model)
    notes: list[str] = []
    missing = [labels[j] for j in np.flatnonzero(~covered)]
    if missing:
        notes.append("not in the observation, set to the reference value: " + ", ".join(missing))
    clipped = [omap.names[i] for i in omap.mapped if np.isfinite(omap.high[i]) or np.isfinite(omap.low[i])]
    if clipped and (~usable).any():
        notes.append(f"{int((~usable).sum())} of {n} rows dropped: the observation clips "
                     + ", ".join(clipped) + " and the true value is unknown there")
    return values, usable, notes
