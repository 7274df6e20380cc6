"""Environments with effects applied, and the entry point every registered id uses.

``make_robot_env(robot, effects)`` builds the robot's Gymnasium v5 environment on a model
compiled with the model effects, and wraps it in :class:`ChannelEffects` when channel effects are
present. The effects travel as plain dicts in the env spec's kwargs, so specs serialize to JSON
(Minari stores them) and pickling rebuilds the same dynamics.

Every ``reset`` info carries ``state`` and every ``step`` info ``prev_state`` and ``state``: MuJoCo's
full-physics state vector (``mjSTATE_FULLPHYSICS``: time, qpos, qvel, act, ...) followed by any
channel delay buffers. The arrays are read-only: the state after one step is the next step's
``prev_state``, the same array. They are rows of blocks of 64 states (one allocation per 64 steps),
so a state kept alone keeps its block alive: ``.copy()`` one to keep it on its own. Move the
simulation between steps with ``set_state`` or :func:`set_full_state` (direct writes to ``data``
that leave the clock unchanged are not seen by the next ``prev_state``). :func:`set_full_state`
restores an env exactly there.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import gymnasium
import mujoco
import numpy as np
from gymnasium import utils
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

from offdyn_bench.effects import (CONTROL_COST_ON, ChannelEffects, ControlCostOn, Effect, effects_from_dicts,
                                  split_effects)
from offdyn_bench.effects.model import ModelEffect, compile_model
from offdyn_bench.errors import OffdynError, UnknownNameError
from offdyn_bench.robots import ROBOTS, Robot, get_robot
from offdyn_bench.state_rows import ReadOnlyRows

FULL_PHYSICS = mujoco.mjtState.mjSTATE_FULLPHYSICS
_FULL_PHYSICS_BITS = int(FULL_PHYSICS)  # pybind converts a plain int faster than the enum (hot path)
_get_state = mujoco.mj_getState
_step = mujoco.mj_step
_rne_post_constraint = mujoco.mj_rnePostConstraint

EffectsLike = Sequence[Effect | dict[str, Any]]


class _SuiteState:
    """What the suite keeps on an env besides Gymnasium's own attributes, behind one attribute.

    CPython 3.11 keeps an object's attributes in its fast shared-key layout only up to 30 names;
    Gymnasium's MuJoCo envs have 23 to 30 already. Five names of our own pushed Hopper and Walker2d
    over, and every ``self.x`` in Gymnasium's own step became a slower dict lookup: several percent
    of a Hopper step, more than the state capture itself. One slotted object adds one name.
    """

    __slots__ = ("model_effects", "state_size", "last_state", "last_time", "rows", "ctrl", "ctrl_shape", "option")

    def __init__(self, model_effects: tuple[ModelEffect, ...]) -> None:
        self.model_effects = model_effects
        self.state_size = 0  # set once the model exists; reset() runs inside base.__init__
        self.last_state: np.ndarray | None = None
        self.last_time = math.nan  # the clock at last_state; NaN: read the state afresh
        self.rows = ReadOnlyRows(0)  # sized once the model exists
        self.ctrl = np.zeros(0)
        self.ctrl_shape: tuple[int, ...] = (0,)
        self.option: mujoco.MjOption | None = None

    def attach(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Size the state; keep the views and objects the step reads (each read of ``data.ctrl``
        or ``model.opt`` makes a new Python object)."""
        self.state_size = mujoco.mj_stateSize(model, FULL_PHYSICS)
        self.rows = ReadOnlyRows(self.state_size)
        self.ctrl, self.ctrl_shape, self.option = data.ctrl, (model.nu,), model.opt

    def forget_state(self) -> None:
        """The simulation was moved: the next step reads its state before afresh."""
        self.last_state, self.last_time = None, math.nan

    def capture(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """The physics state now, as a new read-only row; remembered as the next step's state before."""
        rows = self.rows
        destination, state = (rows.free or rows.refill()).pop()
        _get_state(model, data, destination, _FULL_PHYSICS_BITS)
        self.last_state = state
        self.last_time = destination[0]  # the state's own clock: no second read of data.time
        return state


def _with_model_effects(base: type) -> type:
    """Subclass a Gymnasium MuJoCo env so its model is compiled with model effects and its
    info carries the physics state. A subclass (not a wrapper) keeps the per-step cost to one
    state copy: the benchmark compares it with the vanilla env."""
    base_step = base.step

    class EnvWithEffects(base):  # type: ignore[misc, valid-type]
        def __init__(self, model_effects: EffectsLike = (), **kwargs: Any) -> None:
            effects = effects_from_dicts(model_effects)
            for effect in effects:
                if not isinstance(effect, ModelEffect):
                    raise TypeError(f"{type(self).__name__} takes model effects only, got {effect.kind!r}; "
                                    "use make_robot_env() for channel effects")
            self._suite = _SuiteState(effects)  # type: ignore[arg-type]  # one name: see _SuiteState
            base.__init__(self, **kwargs)
            # Pickling rebuilds from these arguments: the effects must be among them.
            utils.EzPickle.__init__(self, model_effects=[e.to_dict() for e in effects], **kwargs)

        @property
        def model_effects(self) -> tuple[ModelEffect, ...]:
            return self._suite.model_effects

        @property
        def state_size(self) -> int:
            """Length of the physics state vectors in ``info``."""
            return self._suite.state_size

        def _initialize_simulation(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
            model = compile_model(self.fullpath, self._suite.model_effects)
            model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
            model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
            data = mujoco.MjData(model)
            self._suite.attach(model, data)
            return model, data

        def _read_state(self) -> np.ndarray:
            return self._suite.capture(self.model, self.data)

        def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
            obs, info = super().reset(seed=seed, options=options)
            info["state"] = self._read_state()
            return obs, info

        def step(self, action):
            # The state after the last step is this step's state before, unless the simulation was
            # moved since (set_state / set_full_state clear it; a changed clock shows other writes).
            suite = self._suite
            prev = suite.last_state
            if suite.last_time != self.data.time:
                prev = suite.capture(self.model, self.data)
            result = base_step(self, action)  # not super(): one call layer less per step
            # suite.capture() inlined: a call layer costs about 1% of a HalfCheetah step.
            rows = suite.rows
            destination, state = (rows.free or rows.refill()).pop()
            _get_state(self.model, self.data, destination, _FULL_PHYSICS_BITS)
            suite.last_state = state
            suite.last_time = destination[0]
            info = result[4]
            info["state"] = state
            info["prev_state"] = prev
            return result

        def set_state(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
            super().set_state(qpos, qvel)
            self._suite.forget_state()

        def set_full_state(self, state: np.ndarray) -> None:
            """Restore the full physics state (``mjSTATE_FULLPHYSICS``) and recompute derived
            quantities, including the contact forces some observations read."""
            state = np.asarray(state, dtype=float)
            if state.shape != (self.state_size,):
                raise ValueError(f"expected a physics state of shape ({self.state_size},), got {state.shape}")
            mujoco.mj_setState(self.model, self.data, state, FULL_PHYSICS)
            mujoco.mj_forward(self.model, self.data)
            mujoco.mj_rnePostConstraint(self.model, self.data)
            self._suite.forget_state()

        def current_observation(self) -> np.ndarray:
            return self._get_obs()

    # Faster copies of two of Gymnasium's MujocoEnv members, for bases that keep Gymnasium's own
    # (the wheel-legged env has its own do_simulation): the same physics, about 3 us less per step.
    if (base.do_simulation is MujocoEnv.do_simulation
            and base._step_mujoco_simulation is MujocoEnv._step_mujoco_simulation):
        def do_simulation(self, ctrl, n_frames) -> None:
            # Gymnasium's shape check copies the command (np.array(ctrl)); the ctrl view is kept.
            suite = self._suite
            if np.shape(ctrl) != suite.ctrl_shape:
                raise ValueError(f"Action dimension mismatch. Expected {suite.ctrl_shape}, found {np.shape(ctrl)}")
            suite.ctrl[:] = ctrl
            model, data = self.model, self.data
            _step(model, data, nstep=n_frames)
            _rne_post_constraint(model, data)  # as Gymnasium: contact forces for the observations

        EnvWithEffects.do_simulation = do_simulation
    if base.dt is MujocoEnv.dt:
        EnvWithEffects.dt = property(lambda self: self._suite.option.timestep * self.frame_skip,
                                     doc="Gymnasium's dt, less a new model.opt object per read.")

    name = f"{base.__name__.removesuffix('Env')}WithEffects"
    EnvWithEffects.__name__ = EnvWithEffects.__qualname__ = name
    EnvWithEffects.__module__ = __name__
    EnvWithEffects.__doc__ = (f"{base.__module__}.{base.__name__} compiled with model effects; "
                              "info carries the full physics state.")
    return EnvWithEffects


def _class_name(robot: Robot) -> str:
    """The module-level name of ``robot``'s class with effects, known without importing its env."""
    return f"{robot.env_class.partition(':')[2].removesuffix('Env')}WithEffects"


class _EnvClasses(Mapping[str, type]):
    """Robot name -> its env class with model effects, built when first asked for: importing this
    module loads no robot's env, so a HalfCheetah run never imports Gymnasium-Robotics (the Adroit
    robots' package) and needs it installed only for the Adroit tasks."""

    def __init__(self) -> None:
        self._built: dict[str, type] = {}

    def __getitem__(self, robot: str) -> type:
        if robot not in self._built:
            cls = _with_model_effects(ROBOTS[robot].load_env_class())
            assert cls.__name__ == _class_name(ROBOTS[robot])
            globals()[cls.__name__] = cls  # module-level, so instances pickle by reference
            self._built[robot] = cls
        return self._built[robot]

    def __iter__(self) -> Iterator[str]:
        return iter(ROBOTS)

    def __len__(self) -> int:
        return len(ROBOTS)


ENV_CLASSES: Mapping[str, type] = _EnvClasses()


def __getattr__(name: str) -> type:
    # Unpickling looks an env class up by its module-level name before anything built it.
    for robot in ROBOTS.values():
        if _class_name(robot) == name:
            return ENV_CLASSES[robot.name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class CommandedControlCost(gymnasium.Wrapper):
    """Charge the robot's control cost on the action the policy commanded, not on the one that
    reached the motors after the action-channel effects (joint noise, bias, gain, ...).

    Gymnasium's locomotion envs charge ``ctrl_cost_weight * |a|^2`` on the action they are stepped
    with. Behind :class:`ChannelEffects` that is the *applied* action, so a joint-noise target also
    charges for noise nobody commanded: a reward shift on top of the dynamics shift (on the Ant
    at noise std 0.5, about 1.0 per step, as much as it earns for staying up). Off-dynamics RL
    assumes one reward on both sides; this wrapper restores it: the reward is the robot's own,
    less the cost it charged on the applied action, plus the cost of the commanded one.
    ``info["reward_ctrl"]`` becomes the commanded action's term and
    ``info["reward_ctrl_applied"]`` keeps the robot's.
    """

    def __init__(self, env: gymnasium.Env) -> None:
        super().__init__(env)
        robot = env.unwrapped
        control_cost, weight = getattr(robot, "control_cost", None), getattr(robot, "_ctrl_cost_weight", None)
        if not callable(control_cost) or not isinstance(weight, (int, float)):
            raise OffdynError(f"{type(robot).__name__} has no control_cost(action) with a _ctrl_cost_weight to "
                              "charge on the commanded action; control_cost_on='commanded' needs one of the "
                              "Gymnasium locomotion robots (Ant, HalfCheetah, Hopper, Walker2d)")
        # The cost is recomputed here as weight x a.a (a third of the time of the robot's own
        # np.sum(np.square(a))): refuse a robot whose cost has another form.
        probe = np.linspace(-1.0, 1.0, int(np.prod(env.action_space.shape)))
        if not math.isclose(float(control_cost(probe)), weight * float(probe @ probe), rel_tol=1e-12):
            raise OffdynError(f"{type(robot).__name__}.control_cost is not ctrl_cost_weight x |a|^2; "
                              "control_cost_on='commanded' cannot recompute it")
        self._weight = float(weight)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        command = np.asarray(action, dtype=np.float64).ravel()
        commanded_term = -self._weight * float(command @ command)
        try:
            applied_term = info["reward_ctrl"]  # the robot's own: -cost(applied action)
        except KeyError:
            raise OffdynError(f"{type(self.env.unwrapped).__name__}.step gave no info['reward_ctrl']: the applied "
                              "action's control cost cannot be taken back out of its reward") from None
        info["reward_ctrl_applied"] = applied_term
        info["reward_ctrl"] = commanded_term
        return obs, reward - applied_term + commanded_term, terminated, truncated, info


def make_robot_env(robot: str, effects: EffectsLike = (), extra_effects: EffectsLike = (),
                   control_cost_on: ControlCostOn = "applied", **env_kwargs: Any) -> gymnasium.Env:
    """Build ``robot``'s environment with ``effects`` (then ``extra_effects``) applied.

    ``extra_effects`` lets a registered task be extended without re-listing its effects, e.g.
    ``gymnasium.make("offdyn/Hopper-gravity-0.5-source-v0", extra_effects=calibrated)``.
    ``control_cost_on="commanded"`` charges the robot's control cost on the policy's action
    rather than on the action the channel effects made of it (:class:`CommandedControlCost`).
    """
    get_robot(robot)
    if control_cost_on not in CONTROL_COST_ON:
        raise UnknownNameError("control_cost_on", control_cost_on, CONTROL_COST_ON)
    all_effects = effects_from_dicts(effects) + effects_from_dicts(extra_effects)
    model_effects, channel_effects = split_effects(all_effects)
    env = ENV_CLASSES[robot](model_effects=model_effects, **env_kwargs)
    if channel_effects:
        env = ChannelEffects(env, channel_effects)  # type: ignore[arg-type]
    if control_cost_on == "commanded":
        env = CommandedControlCost(env)
    return env


def set_full_state(env: gymnasium.Env, state: np.ndarray) -> None:
    """Restore an env built by this suite to a ``state`` vector taken from its ``info``."""
    env.get_wrapper_attr("set_full_state")(state)


def flat_observations(env: gymnasium.Env) -> gymnasium.Env:
    """``env`` with a ``Dict`` observation (AntMaze's goal-conditioned ``observation``,
    ``achieved_goal``, ``desired_goal``) flattened into one ``Box`` by Gymnasium's
    ``FlattenObservation``, the form the baselines and evaluation take; any other env unchanged.
    :func:`flatten_observation_rows` flattens stored dict observations the same way."""
    if isinstance(env.observation_space, gymnasium.spaces.Dict):
        return gymnasium.wrappers.FlattenObservation(env)
    return env


def flatten_observation_rows(observations: np.ndarray | dict, space: gymnasium.Space) -> np.ndarray:
    """Rows of observations as :func:`flat_observations` gives them: a ``Dict`` space's parts
    concatenated in the space's key order (``gymnasium.spaces.flatten``'s), other arrays as they are."""
    if not isinstance(observations, dict):
        return np.asarray(observations)
    if not isinstance(space, gymnasium.spaces.Dict) or set(observations) != set(space.spaces):
        raise ValueError(f"dict observations with keys {sorted(observations)} do not match the env's "
                         f"observation space {space}")
    return np.concatenate([flatten_observation_rows(observations[key], space.spaces[key]).reshape(
        len(observations[key]), -1) for key in space.spaces], axis=1)
