"""Channel effects: what sits between the agent and the physics.

Action effects transform the command before it reaches the actuators, observation effects the
observation before it reaches the agent. Each effect has a pure, vectorized ``transform`` on
arrays (gap diagnosis uses it on whole datasets) and, for delays, a buffer. At run time the
:class:`ChannelEffects` wrapper applies them in list order, seeded from the env's RNG, and
appends its buffers to the ``state`` vectors in ``info`` so a simulator can be restarted exactly.
"""

from __future__ import annotations

import dataclasses
import functools
from collections import deque
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import gymnasium
import numpy as np

from offdyn_bench.effects.base import Effect, Interval
from offdyn_bench.effects.model import actuator_ids
from offdyn_bench.errors import OffdynError
from offdyn_bench.state_rows import ReadOnlyRows

if TYPE_CHECKING:  # MuJoCo loads when a model is built (see effects.model), not on import
    import mujoco


def _own_float64(x: Any) -> np.ndarray:
    """``x`` as a float64 array of its own: a copy unless converting it made a new array already.
    (Not ``np.array(x, dtype=float)``: another library's ``__array__`` may not take its ``copy``.)"""
    out = np.asarray(x, dtype=float)
    return out.copy() if out is x or out.base is not None else out


@dataclasses.dataclass(frozen=True, kw_only=True)
class ChannelEffect(Effect):
    """An effect on the action or observation channel.

    ``transform(x, mask, rng)`` maps a batch ``x[..., dim]`` of commands (or observations) to
    what the physics (or agent) receives; ``mask`` selects the targeted dimensions (``None``: all
    of them, the fast path the per-step wrapper takes).
    """

    family: ClassVar[Literal["channel"]] = "channel"
    channel: ClassVar[Literal["action", "observation"]]
    delay_steps: ClassVar[bool] = False

    def transform(self, x: np.ndarray, mask: np.ndarray | None,
                  rng: np.random.Generator | None) -> np.ndarray:
        raise NotImplementedError

    def per_step(self, mask: np.ndarray | None, size: int) -> Callable[[Any], np.ndarray] | None:
        """A faster form of ``transform(x, mask, None)`` for the one vector ``x`` of ``size``
        numbers a step gives the run-time wrapper, or ``None`` (the wrapper then calls
        ``transform``). It must return a new float64 array with ``transform``'s very bits and
        take any array-like ``x`` (a list, float32, another library's array): it converts it."""
        return None

    def dimension_mask(self, size: int, model: mujoco.MjModel | None = None) -> np.ndarray:
        """Boolean mask over the channel's dimensions that this effect targets."""
        mask = np.zeros(size, dtype=bool)
        if self.target is None:
            mask[:] = True
        elif self.channel == "action":
            if model is None:
                raise OffdynError(f"effect {self.kind!r}: a model is needed to resolve actuator {self.target!r}")
            mask[actuator_ids(model, str(self.target))] = True
        else:
            index = int(self.target)  # type: ignore[arg-type]
            if index >= size:
                raise OffdynError(f"effect {self.kind!r}: observation index {index} is out of range; "
                                  f"the observation has {size} dimensions (0..{size - 1})")
            mask[index] = True
        return mask


@dataclasses.dataclass(frozen=True, kw_only=True)
class _Noise(ChannelEffect):
    value_field: ClassVar[str] = "std"
    ranges: ClassVar = {"std": Interval(0.0, 1e3)}  # in the units of the command or observation
    std: float

    def transform(self, x, mask, rng):
        if rng is None:
            raise OffdynError(f"effect {self.kind!r} is stochastic and needs a random generator")
        return x + self.noise_term(rng.standard_normal(np.shape(x)), mask)

    def noise_term(self, z: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        """What the effect adds given standard normal draws ``z``: ``std * z`` on the masked
        dimensions. ``+ 0.0`` makes the values exactly ``rng.normal(0.0, std)``'s (signed zeros
        included), which recorded datasets were built with."""
        noise = z * self.std + 0.0
        return noise if mask is None else noise * mask


@dataclasses.dataclass(frozen=True, kw_only=True)
class _Bias(ChannelEffect):
    value_field: ClassVar[str] = "value"
    ranges: ClassVar = {"value": Interval(-1e3, 1e3)}  # in the units of the command or observation
    value: float

    def transform(self, x, mask, rng):
        return x + (self.value if mask is None else self.value * mask)


@dataclasses.dataclass(frozen=True, kw_only=True)
class _Delay(ChannelEffect):
    value_field: ClassVar[str] = "steps"
    delay_steps: ClassVar[bool] = True
    # The run-time buffer holds `steps` past values: the bound keeps it small.
    ranges: ClassVar = {"steps": Interval(0, 1000, integer=True, unit="control steps")}
    steps: int

    def transform(self, x, mask, rng):
        """Delay a time series ``x[t, dim]`` of one episode (first axis is time)."""
        out = np.array(x, dtype=float, copy=True)
        if self.steps == 0 or len(x) == 0:
            return out
        k = min(self.steps, len(x))
        shifted = np.empty_like(out)
        shifted[k:] = x[: len(x) - k]
        shifted[:k] = self.initial_fill(np.asarray(x[0], dtype=float))
        return shifted if mask is None else np.where(mask, shifted, out)

    def initial_fill(self, first: np.ndarray) -> np.ndarray:
        raise NotImplementedError


@dataclasses.dataclass(frozen=True, kw_only=True)
class ActionNoise(_Noise):
    """Add Gaussian noise ``N(0, std^2)`` to the command: the joint-noise shift."""

    kind: ClassVar[str] = "action_noise"
    channel: ClassVar = "action"
    target_type: ClassVar = "actuator"


@dataclasses.dataclass(frozen=True, kw_only=True)
class ActionBias(_Bias):
    """Add a constant offset to the command (a miscalibrated motor driver)."""

    kind: ClassVar[str] = "action_bias"
    channel: ClassVar = "action"
    target_type: ClassVar = "actuator"


@dataclasses.dataclass(frozen=True, kw_only=True)
class ActionGain(ChannelEffect):
    """Multiply the command by ``scale`` (negative flips the motor's direction)."""

    kind: ClassVar[str] = "action_gain"
    channel: ClassVar = "action"
    target_type: ClassVar = "actuator"
    value_field: ClassVar[str] = "scale"
    ranges: ClassVar = {"scale": Interval(-100.0, 100.0)}
    scale: float

    def transform(self, x, mask, rng):
        return x * self.scale if mask is None else np.where(mask, x * self.scale, x)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ActionDeadzone(ChannelEffect):
    """Commands with ``|a| <= threshold`` produce zero; larger ones pass unchanged."""

    kind: ClassVar[str] = "action_deadzone"
    channel: ClassVar = "action"
    target_type: ClassVar = "actuator"
    value_field: ClassVar[str] = "threshold"
    ranges: ClassVar = {"threshold": Interval(0.0, 1e3, unit="command units")}
    threshold: float

    # Up to this many numbers a per-step loop over Python floats beats numpy's calls on tiny arrays.
    PER_STEP_MAX_SIZE: ClassVar[int] = 64

    def transform(self, x, mask, rng):
        small = np.abs(x) <= np.asarray(self.threshold)  # a 0-d array compares faster than a float
        out = np.array(x, dtype=float)
        np.copyto(out, 0.0, where=small if mask is None else mask & small)  # np.where's values, cheaper
        return out

    def per_step(self, mask, size):
        """One command as Python floats: a comparison and a store per targeted number, where
        ``transform`` makes five numpy calls (each costs more than the whole loop on a few numbers).
        The same numbers: converting to float64, ``abs`` and ``<=`` are exact on both sides."""
        if size > self.PER_STEP_MAX_SIZE:
            return None
        targeted = tuple(range(size) if mask is None else np.flatnonzero(mask).tolist())
        return functools.partial(_dead_zone, float(self.threshold), targeted)  # a partial pickles; a closure not


def _dead_zone(threshold: float, targeted: tuple[int, ...], x: Any) -> np.ndarray:
    out = _own_float64(x)  # the caller's action stays as it was
    values = out.tolist()
    for i in targeted:
        if abs(values[i]) <= threshold:
            out[i] = 0.0
    return out


@dataclasses.dataclass(frozen=True, kw_only=True)
class ActionSaturation(ChannelEffect):
    """Clip the command to ``[-limit, limit]`` (a driver that cannot deliver full torque)."""

    kind: ClassVar[str] = "action_saturation"
    channel: ClassVar = "action"
    target_type: ClassVar = "actuator"
    value_field: ClassVar[str] = "limit"
    ranges: ClassVar = {"limit": Interval(0.0, 1e3, low_open=True, unit="command units")}
    limit: float

    def transform(self, x, mask, rng):
        clipped = np.clip(x, -self.limit, self.limit)
        return clipped if mask is None else np.where(mask, clipped, x)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ActionDelay(_Delay):
    """Apply each command ``steps`` control steps late; before that the actuators get zero."""

    kind: ClassVar[str] = "action_delay"
    channel: ClassVar = "action"
    target_type: ClassVar = "actuator"

    def initial_fill(self, first: np.ndarray) -> np.ndarray:
        return np.zeros_like(first)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ObsNoise(_Noise):
    """Add Gaussian sensor noise ``N(0, std^2)`` to the observation."""

    kind: ClassVar[str] = "obs_noise"
    channel: ClassVar = "observation"
    target_type: ClassVar = "observation"


@dataclasses.dataclass(frozen=True, kw_only=True)
class ObsBias(_Bias):
    """Add a constant offset to the observation (a miscalibrated sensor)."""

    kind: ClassVar[str] = "obs_bias"
    channel: ClassVar = "observation"
    target_type: ClassVar = "observation"


@dataclasses.dataclass(frozen=True, kw_only=True)
class ObsDelay(_Delay):
    """Return the observation from ``steps`` control steps ago (the first one until then)."""

    kind: ClassVar[str] = "obs_delay"
    channel: ClassVar = "observation"
    target_type: ClassVar = "observation"

    def initial_fill(self, first: np.ndarray) -> np.ndarray:
        return first


# --- run time -------------------------------------------------------------------------------

class _Stage:
    """One effect at run time: its mask; for noise, the noise term of each step of the current
    block (one array per step, filled by :class:`_NoiseBlocks`); for a delay, its past inputs.

    A short delay (up to ``RING_STEPS``) keeps its last ``steps`` inputs as separate arrays,
    oldest first, none ever written in place: a step hands out the oldest (no copy) and appends the
    new input, which must be an array of the stage's own (``keeps_input``): the wrapper copies what
    it gives a first stage, and a later delay (``copy_input``) copies what the stage before it
    made. A longer one shifts one contiguous buffer, so its state is one part, not ``steps`` parts.
    ``past`` is the stage's state in parts, oldest first.
    """

    RING_STEPS = 16

    def __init__(self, effect: ChannelEffect, mask: np.ndarray) -> None:
        self.effect = effect
        self.mask: np.ndarray | None = None if mask.all() else mask
        self.size = mask.size
        self.noise_size = mask.size if isinstance(effect, _Noise) else 0
        self.noise_block = np.zeros((0, mask.size))
        self.noise_rows: list[np.ndarray] = []
        self.grouped = False  # its noise is added by a _NoiseGroup (which keeps the rows)
        self.memoryless = not effect.delay_steps
        self.transform = effect.transform  # bound once: called every step
        self.steps: int = effect.steps if effect.delay_steps else 0  # type: ignore[attr-defined]
        self.keeps_input = 0 < self.steps <= self.RING_STEPS
        self.buffer = np.zeros((0 if self.keeps_input else self.steps, mask.size))
        self.past: deque[np.ndarray] | tuple[np.ndarray, ...] = (
            deque(np.zeros(mask.size) for _ in range(self.steps)) if self.keeps_input
            else (self.buffer.reshape(-1),) if self.steps else ())
        self.copy_input = True
        per_step = effect.per_step(self.mask, mask.size) if self.memoryless and not self.noise_size else None
        self.step_function = per_step
        # Whether `apply` takes the caller's action as it came (it converts it itself).
        self.converts_input = per_step is not None
        # What one step runs, chosen once: the per-step cost of tiny arrays is all call overhead.
        if self.noise_size:
            self.apply = self._add_noise
        elif per_step is not None:
            self.apply = self._per_step
        elif self.memoryless:
            self.apply = self._memoryless
        elif self.keeps_input:
            self.apply = self._delay
        elif self.steps:
            self.apply = self._shift
        else:
            self.apply = self._unchanged

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        if self.steps and not self.keeps_input:  # pickled, the view became an array of its own
            self.past = (self.buffer.reshape(-1),)

    @property
    def state_size(self) -> int:
        """How many numbers of the state vector are this stage's (its past inputs)."""
        return self.steps * self.size

    def reset(self, first: np.ndarray) -> None:
        if self.keeps_input:
            fill = np.asarray(self.effect.initial_fill(first), dtype=float)  # type: ignore[attr-defined]
            self.past = deque(np.array(np.broadcast_to(fill, (self.size,))) for _ in range(self.steps))
        elif self.steps:
            self.buffer[:] = self.effect.initial_fill(first)  # type: ignore[attr-defined]

    def restore(self, values: np.ndarray) -> None:
        """Take past inputs back from a state vector's part (copied: the vector stays the caller's)."""
        if self.keeps_input:
            self.past = deque(np.array(row, dtype=float) for row in values.reshape(self.steps, self.size))
        else:
            self.buffer[:] = values.reshape(self.buffer.shape)

    def _add_noise(self, x: np.ndarray, row: int) -> np.ndarray:
        return x + self.noise_rows[row]

    def _per_step(self, x: Any, row: int) -> np.ndarray:
        return self.step_function(x)  # type: ignore[misc]

    def _memoryless(self, x: np.ndarray, row: int) -> np.ndarray:
        return self.transform(x, self.mask, None)

    def _delay(self, x: np.ndarray, row: int) -> np.ndarray:
        past: deque[np.ndarray] = self.past  # type: ignore[assignment]
        out = past.popleft()  # no longer kept: handed out as it is
        if self.mask is not None:
            out = np.where(self.mask, out, x)
        past.append(np.array(x, dtype=float) if self.copy_input else x)
        return out

    def _shift(self, x: np.ndarray, row: int) -> np.ndarray:
        buffer = self.buffer
        out = buffer[0].copy() if self.mask is None else np.where(self.mask, buffer[0], x)
        buffer[:-1] = buffer[1:]
        buffer[-1] = x
        return out

    @staticmethod
    def _unchanged(x: np.ndarray, row: int) -> np.ndarray:
        return x


class _NoiseGroup:
    """Consecutive noise stages on disjoint dimensions, applied as one addition.

    Off its dimensions a stage's noise is a zero, so per dimension at most one stage adds a
    nonzero number and ``x + (n1 + n2 + ...)`` is ``((x + n1) + n2) + ...``: the stages' sum is
    that one number, and adding a zero to a nonzero sum changes nothing. (The one exception, a
    sum that is exactly zero, may differ in the sign of that zero.) The sensor noise of four
    single-dimension stages thus costs one addition a step, not four.
    """

    def __init__(self, stages: Sequence[_Stage]) -> None:
        self.stages = tuple(stages)
        self.noise_rows: list[np.ndarray] = []
        for stage in self.stages:
            stage.grouped = True

    @staticmethod
    def can_join(group: Sequence[_Stage], stage: _Stage) -> bool:
        if not (stage.noise_size and stage.mask is not None and group):
            return False
        if any(member.mask is None or not member.noise_size for member in group):
            return False
        return not any(np.any(member.mask & stage.mask) for member in group)

    def refresh(self) -> None:
        total = self.stages[0].noise_block
        for stage in self.stages[1:]:
            total = total + stage.noise_block
        self.noise_rows = list(total)

    def apply(self, x: np.ndarray, row: int) -> np.ndarray:
        return x + self.noise_rows[row]


class _NoiseBlocks:
    """The Gaussian noise of every noise stage, drawn for many steps at once.

    Per step, noise stages consume standard normals from one generator in a fixed order (action
    stages, then observation stages, each in list order; a reset draws only its observation
    stages' noise). ``standard_normal((k, n))`` holds exactly the numbers of ``k`` successive
    ``standard_normal(n)`` calls, so a block of ``k`` steps gives each stage the noise it would
    draw step by step: recorded datasets stay byte for byte the same. Blocks start small and double
    up to ``MAX_ROWS`` steps, so a short episode (a new generator each) does not pay for a long one.
    """

    FIRST_ROWS = 16
    MAX_ROWS = 1024

    def __init__(self, action_stages: Sequence[_Stage], obs_stages: Sequence[_Stage]) -> None:
        self.step_stages = [stage for stage in (*action_stages, *obs_stages) if stage.noise_size]
        self.reset_stages = [stage for stage in obs_stages if stage.noise_size]
        self.rng = np.random.default_rng(0)
        self.next_rows = self.FIRST_ROWS
        self.groups: list[_NoiseGroup] = []  # refreshed after each draw of their stages

    def restart(self, rng: np.random.Generator) -> None:
        """Take a new generator (the episode's); the next block is a small one again."""
        self.rng = rng
        self.next_rows = self.FIRST_ROWS

    def draw_reset(self) -> None:
        """One row of noise for the observation stages, as a reset draws it."""
        self._draw(self.reset_stages, 1)

    def draw_block(self) -> int:
        """Noise for the next steps of every stage; returns how many steps (rows) it covers."""
        rows = self.next_rows
        self._draw(self.step_stages, rows)
        self.next_rows = min(2 * rows, self.MAX_ROWS)
        return rows

    def _draw(self, stages: Sequence[_Stage], rows: int) -> None:
        z = self.rng.standard_normal((rows, sum(stage.noise_size for stage in stages)))
        start = 0
        for stage in stages:
            end = start + stage.noise_size
            stage.noise_block = stage.effect.noise_term(z[:, start:end], stage.mask)  # type: ignore[attr-defined]
            # One array per step, made here in bulk: cheaper than indexing the block every step.
            # A grouped stage's rows go into its group's sum instead.
            stage.noise_rows = [] if stage.grouped else list(stage.noise_block)
            start = end
        for group in self.groups:
            if group.stages[0] in stages:
                group.refresh()


ControlCostOn = Literal["applied", "commanded"]
"""Which action a robot's control cost is charged on where action-channel effects change it: the
``applied`` one (what reached the motors; Gymnasium's own reward) or the ``commanded`` one (the
policy's; ``offdyn_bench.envs.CommandedControlCost``)."""
CONTROL_COST_ON: tuple[ControlCostOn, ...] = ("applied", "commanded")


class ChannelEffects(gymnasium.Wrapper):
    """Apply channel effects to an env's actions and observations.

    Noise is drawn from a generator spawned from the env's own RNG at every ``reset``, so the
    same seed gives the same noise. ``info["state"]`` (and ``info["prev_state"]`` on ``step``)
    gain the delay buffers at their end; :meth:`set_full_state` takes such a vector back.
    """

    # How a step turns the caller's action into the first stage's input.
    _AS_FLOAT64, _OWN_COPY, _AS_GIVEN, _NUMPY_AS_GIVEN = range(4)

    def __init__(self, env: gymnasium.Env, effects: Sequence[ChannelEffect]) -> None:
        super().__init__(env)
        self.effects = tuple(effects)
        model = getattr(env.unwrapped, "model", None)
        action_size = int(np.prod(env.action_space.shape))
        obs_size = int(np.prod(env.observation_space.shape))
        self._action_stages = [_Stage(e, e.dimension_mask(action_size, model))
                               for e in self.effects if e.channel == "action"]
        self._obs_stages = [_Stage(e, e.dimension_mask(obs_size, None))
                            for e in self.effects if e.channel == "observation"]
        self._stages = self._action_stages + self._obs_stages
        self._noise = _NoiseBlocks(self._action_stages, self._obs_stages)
        self._action_steps = self._step_functions(self._action_stages)
        self._obs_steps = self._step_functions(self._obs_stages)
        first = self._action_stages[0] if self._action_stages else None
        if first is not None and first.noise_size:
            # A first stage that adds noise to a numpy action makes the float64 array itself
            # (float64 noise + the action); anything else (a list, another library's array) is
            # converted first.
            self._action_entry = self._NUMPY_AS_GIVEN
        elif first is not None and first.converts_input:
            self._action_entry = self._AS_GIVEN
        elif first is not None and first.keeps_input:
            self._action_entry = self._OWN_COPY  # a delay keeps it: not the caller's array
        else:
            self._action_entry = self._AS_FLOAT64
        # The observation as the first stage gets it: a copy of its own when a delay keeps it.
        self._obs_copy = bool(self._obs_stages) and self._obs_stages[0].keeps_input
        # Every stage makes float64: a float64 space needs no final cast.
        self._obs_dtype = None if self.observation_space.dtype == np.float64 else self.observation_space.dtype
        self._buffered = [stage for stage in self._stages if stage.steps]
        self._state_rows_extra = sum(stage.state_size for stage in self._buffered)
        self._state_rows = ReadOnlyRows(0, -1)  # sized on first use: physics state plus buffers
        # The stage whose one part is all of the channel state (one delay of one step, or a long one), if any.
        self._only_past = self._buffered[0] if len(self._buffered) == 1 and len(self._buffered[0].past) == 1 else None
        self._row = 0  # this step's row of the noise block
        self._block_rows = 0 if self._noise.step_stages else -1  # rows in the block; -1: no noise
        # The full state vector given last (physics + buffers) and the physics part it was made
        # from: the next step's prev_state is that same vector when the physics part is unchanged.
        self._last_state: tuple[np.ndarray, np.ndarray] | None = None

    def _step_functions(self, stages: Sequence[_Stage]) -> list:
        """What each step applies, in order: a stage's own function, or one per noise group."""
        for i, stage in enumerate(stages):
            stage.copy_input = i > 0  # the first stage's input is made for it by step and reset
        runs: list[list[_Stage]] = []
        for stage in stages:
            if runs and _NoiseGroup.can_join(runs[-1], stage):
                runs[-1].append(stage)
            else:
                runs.append([stage])
        functions = []
        for run in runs:
            if len(run) == 1:
                functions.append(run[0].apply)
            else:
                group = _NoiseGroup(run)
                self._noise.groups.append(group)
                functions.append(group.apply)
        return functions

    @property
    def channel_state_size(self) -> int:
        return self._state_rows_extra

    def channel_state(self) -> np.ndarray:
        if not self._buffered:
            return np.zeros(0)
        return np.concatenate([past for stage in self._buffered for past in stage.past])

    def _with_channel_state(self, physics_state: np.ndarray) -> np.ndarray:
        rows = self._state_rows
        if rows.split != physics_state.size:
            rows = self._state_rows = ReadOnlyRows(physics_state.size + self._state_rows_extra, physics_state.size)
        _, state, physics_part, channel_part = (rows.free or rows.refill()).pop()
        physics_part[...] = physics_state
        only = self._only_past
        if only is not None:
            channel_part[...] = only.past[0]
        else:
            np.concatenate([past for stage in self._buffered for past in stage.past], out=channel_part)
        self._last_state = (physics_state, state)
        return state

    def _observe(self, obs: Any, row: int) -> np.ndarray:
        obs = _own_float64(obs) if self._obs_copy else np.asarray(obs, dtype=float)
        for apply in self._obs_steps:
            obs = apply(obs, row)
        return obs if self._obs_dtype is None else obs.astype(self._obs_dtype, copy=False)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        # A fresh generator per episode, drawn from the env's RNG: the same seed, the same noise.
        self._noise.restart(np.random.default_rng(int(self.env.unwrapped.np_random.integers(2**63))))
        self._row = 0
        if self._noise.step_stages:
            self._block_rows = 0  # the first step draws a block from the new generator
        if self._noise.reset_stages:
            self._noise.draw_reset()
        zero_action = np.zeros(self.action_space.shape)
        for stage in self._action_stages:
            stage.reset(zero_action)
        for stage in self._obs_stages:
            stage.reset(np.asarray(obs, dtype=float))
        obs = self._observe(obs, 0)
        self._last_state = None
        if "state" in info and self._buffered:
            info["state"] = self._with_channel_state(info["state"])
        return obs, info

    def step(self, action):
        buffered = self._buffered
        if buffered:
            last = self._last_state
            prev_channel = self.channel_state() if last is None else None
        row = self._row
        if row == self._block_rows:  # noise block used up: draw the next one
            row, self._block_rows = 0, self._noise.draw_block()
        self._row = row + 1
        entry = self._action_entry
        if entry == 0 or (entry == 3 and type(action) is not np.ndarray):  # _AS_FLOAT64, _NUMPY_AS_GIVEN
            command = np.asarray(action, dtype=float)
        elif entry == 1:  # _OWN_COPY
            command = _own_float64(action)
        else:  # _AS_GIVEN, or _NUMPY_AS_GIVEN of a numpy array
            command = action
        for apply in self._action_steps:
            command = apply(command, row)
        obs, reward, terminated, truncated, info = self.env.step(command)
        info["applied_action"] = command
        if self._obs_steps:
            obs = _own_float64(obs) if self._obs_copy else np.asarray(obs, dtype=float)
            for apply in self._obs_steps:
                obs = apply(obs, row)
            if self._obs_dtype is not None:
                obs = obs.astype(self._obs_dtype, copy=False)
        if buffered and "state" in info:
            prev_physics = info["prev_state"]
            if last is not None and last[0] is prev_physics:
                info["prev_state"] = last[1]
            else:  # the physics was moved since the last state given (or none was given yet)
                if prev_channel is None:  # the buffers were not: only step, reset and set_full_state move them
                    prev_channel = last[1][last[0].size:]
                info["prev_state"] = np.concatenate([prev_physics, prev_channel])
            info["state"] = self._with_channel_state(info["state"])
        return obs, reward, terminated, truncated, info

    def set_full_state(self, state: np.ndarray) -> None:
        """Restore physics and delay buffers from a ``state`` vector taken from ``info``."""
        state = np.asarray(state, dtype=float)
        n = self.channel_state_size
        inner = state[: state.size - n]
        self.env.get_wrapper_attr("set_full_state")(inner)
        offset = inner.size
        for stage in self._buffered:
            stage.restore(state[offset: offset + stage.state_size])
            offset += stage.state_size
        self._last_state = None
