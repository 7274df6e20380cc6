"""Gymnasium's Hopper-v5 and Walker2d-v5 simulated by DART instead of MuJoCo: the engine gap.

The env classes subclass Gymnasium's own ``HopperEnv``/``Walker2dEnv`` and replace only the
simulation: observation, reward terms, termination, reset noise, spaces, timestep and frame skip are
Gymnasium's code running on the same MJCF file. MuJoCo's compiled model of that file stays
available as ``env.unwrapped.model`` (read-only reference: it holds the actuator table and the
initial pose; it is never stepped), and ``env.unwrapped.data`` mirrors DART's state after every
step (``qpos``, ``qvel``, ``time``, ``ctrl``), which is what Gymnasium's code reads.

What DART does differently from MuJoCo on these models (the engine gap):

- contacts are hard: DART solves a boxed LCP (Dantzig) for non-penetrating contact impulses with a
  four-sided (pyramidal) friction cone; MuJoCo's contacts are soft (``solref``/``solimp`` give a
  spring-damper with 0.02 s time constant and a 1 mm ``margin``) with a pyramidal cone of its own
  solver. DART has no equivalent of ``solref``, ``solimp`` or ``margin``;
- joint limits are hard constraints in DART, soft (``solreflimit``) in MuJoCo. DART removes a limit
  violation within one step: Gymnasium's reset noise (+-5 mrad) puts each thigh and leg joint of
  Hopper and Walker2d past its limit of 0 at half the resets, and DART pushes it back at up to
  2.5 rad/s where MuJoCo barely moves it;
- integration: DART steps semi-implicit Euler with implicit joint damping; the models ask MuJoCo
  for RK4;
- frictionless contacts: Hopper's robot geoms declare ``condim=1`` (frictionless among themselves);
  DART applies friction to every contact, so a self-contact of Hopper's limbs has friction in DART;
- the floor is a 400 m wide, 1 m thick box (MuJoCo: an infinite plane).

Not a difference: joint ``armature`` (1.0 on Hopper's actuated joints, 0.01 on Walker2d's), which
DART lacks, is emulated exactly within DART's step (see :class:`DartWorld`); pass
``emulate_armature=False`` to study that gap too (the actuated joints are then far lighter).

Every ``reset`` info carries ``state`` and every ``step`` info ``prev_state`` and ``state``, like the
MuJoCo envs of this suite: ``[time, qpos (nq), qvel (nv)]``. DART's generalized coordinates are
MuJoCo's, so this is DART's full state for these models (its contact solver keeps nothing between
steps) *and* the layout of MuJoCo's ``mjSTATE_FULLPHYSICS`` for them (no actuator activations):
:meth:`set_full_state` restores a DART env exactly (a recorded step replays bit for bit), and a DART
state restarts the MuJoCo source at the same place, which is what gap diagnosis does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import gymnasium
import mujoco
import numpy as np
from gymnasium import utils

from offdyn_bench.effects import ChannelEffects, Effect, effects_from_dicts, split_effects
from offdyn_bench.engines.dart_world import COLLISION_DETECTORS, DartWorld, build_dart_world
from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.robots import get_robot

DART_ROBOTS = ("Hopper", "Walker2d")

EffectsLike = Sequence[Effect | dict[str, Any]]


def _on_dart(base: type) -> type:
    """Subclass a Gymnasium MuJoCo locomotion env so that DART simulates it."""

    class DartEnv(base):  # type: ignore[misc, valid-type]
        engine = "dart"

        def __init__(self, collision_detector: str = "ode", emulate_armature: bool = True, **kwargs: Any) -> None:
            if collision_detector not in COLLISION_DETECTORS:
                raise OffdynError(f"unknown DART collision detector {collision_detector!r}; expected one of "
                                  f"{', '.join(COLLISION_DETECTORS)} (FCL and DART's own detector lack capsules)")
            self.collision_detector = collision_detector
            self.emulate_armature = bool(emulate_armature)
            self.model_effects: tuple = ()  # DART targets take no model effects: the engine is the shift
            self.state_size = 0
            self.dart: DartWorld
            self._last_state: np.ndarray | None = None
            self._last_time = math.nan
            base.__init__(self, **kwargs)
            utils.EzPickle.__init__(self, collision_detector=collision_detector,
                                    emulate_armature=self.emulate_armature, **kwargs)

        def _initialize_simulation(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
            model = mujoco.MjModel.from_xml_path(self.fullpath)
            model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
            model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
            self.dart = build_dart_world(self.fullpath, model, self.collision_detector, self.emulate_armature)
            self.state_size = 1 + model.nq + model.nv
            return model, mujoco.MjData(model)

        # --- the simulation: DART steps, MuJoCo's data mirrors it for Gymnasium's code -------------

        def _mirror(self) -> None:
            data, dart = self.data, self.dart
            data.qpos[:] = dart.qpos()
            data.qvel[:] = dart.qvel()
            data.time = dart.time

        def _step_mujoco_simulation(self, ctrl: np.ndarray, n_frames: int) -> None:
            self.data.ctrl[:] = ctrl
            self.dart.step(np.asarray(ctrl, dtype=float), n_frames)
            self._mirror()

        def _write_state(self, time: float, qpos: np.ndarray, qvel: np.ndarray) -> None:
            self.dart.world.setTime(float(time))
            self.dart.set_qpos_qvel(qpos, qvel)
            self._mirror()
            self._last_state, self._last_time = None, math.nan

        def set_state(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
            qpos, qvel = np.asarray(qpos, dtype=float), np.asarray(qvel, dtype=float)
            if qpos.shape != (self.model.nq,) or qvel.shape != (self.model.nv,):
                raise OffdynError(f"expected qpos of shape ({self.model.nq},) and qvel of shape ({self.model.nv},), "
                                  f"got {qpos.shape} and {qvel.shape}")
            self._write_state(self.dart.time, qpos, qvel)

        def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
            self.dart.world.setTime(0.0)  # mj_resetData zeroes MuJoCo's clock; DART's follows
            obs, info = super().reset(seed=seed, options=options)
            info["state"] = self._read_state()
            return obs, info

        def step(self, action):
            prev = self._last_state
            if self._last_time != self.data.time:
                prev = self._read_state()
            result = super().step(action)
            info = result[4]
            info["prev_state"] = prev
            info["state"] = self._read_state()
            return result

        def _read_state(self) -> np.ndarray:
            state = np.concatenate(([self.dart.time], self.data.qpos, self.data.qvel))
            state.flags.writeable = False  # one array is this step's state and the next's prev_state
            self._last_state, self._last_time = state, self.data.time
            return state

        def set_full_state(self, state: np.ndarray) -> None:
            """Restore a ``[time, qpos, qvel]`` state taken from this env's ``info``."""
            state = np.asarray(state, dtype=float)
            if state.shape != (self.state_size,):
                raise OffdynError(f"expected a state [time, qpos ({self.model.nq}), qvel ({self.model.nv})] of shape "
                                  f"({self.state_size},) for {type(self).__name__}, got {state.shape}")
            nq = self.model.nq
            self._write_state(state[0], state[1:1 + nq], state[1 + nq:])

        def current_observation(self) -> np.ndarray:
            return self._get_obs()

        def render(self):
            mujoco.mj_kinematics(self.model, self.data)  # the renderer draws MuJoCo's mirror of DART's pose
            return super().render()

    name = f"Dart{base.__name__}"
    DartEnv.__name__ = DartEnv.__qualname__ = name
    DartEnv.__module__ = __name__
    return DartEnv


DartHopperEnv = _on_dart(get_robot("Hopper").load_env_class())
DartWalker2dEnv = _on_dart(get_robot("Walker2d").load_env_class())
DART_ENV_CLASSES: dict[str, type] = {"Hopper": DartHopperEnv, "Walker2d": DartWalker2dEnv}


def make_dart_env(robot: str, effects: EffectsLike = (), extra_effects: EffectsLike = (),
                  **env_kwargs: Any) -> gymnasium.Env:
    """Build ``robot``'s environment on DART. Channel effects (action/observation noise, delay, ...)
    wrap it as on MuJoCo; model effects are refused: they edit a compiled MuJoCo model, which DART
    does not simulate."""
    if robot not in DART_ENV_CLASSES:
        raise UnknownNameError("DART robot", robot, DART_ENV_CLASSES)
    all_effects = effects_from_dicts(effects) + effects_from_dicts(extra_effects)
    model_effects, channel_effects = split_effects(all_effects)
    if model_effects:
        kinds = ", ".join(sorted({e.kind for e in model_effects}))
        raise OffdynError(f"DART envs take channel effects only, got model effects ({kinds}); model effects edit "
                          "a compiled MuJoCo model, which DART does not simulate")
    env = DART_ENV_CLASSES[robot](**env_kwargs)
    if channel_effects:
        env = ChannelEffects(env, channel_effects)  # type: ignore[arg-type]
    return env
