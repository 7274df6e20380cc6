"""The human operator of the wheel-legged robot, whose recordings are its target datasets.

H2O recorded 100,000 "human controlled" transitions per task on its real robot, mostly near the
balanced state. A person cannot close a 200 Hz balance loop by hand: on robots of this kind the
operator steers a balancing controller with a remote. So the operator here is two layers:

- the **balancing loop**: an LQR on the clean model, linearized about the upright state with
  MuJoCo's ``mjd_transitionFD`` (one control step = 5 physics steps, ctrl held) and solved as a
  discrete algebraic Riccati equation with scipy. ``standstill`` regulates (tilt, displacement,
  tilt rate, velocity) to a position set-point; ``movestraight`` regulates (tilt, tilt rate,
  velocity) to a velocity set-point, without the displacement it does not observe.
- the **person** on top, with human imperfections (all seeded, per episode):
  a loop latency (the command acts on the observation ``loop_delay_steps`` old); a set-point that
  drifts as a random walk (the stick is never held perfectly still); noisy commands (white
  jitter) and a slowly drifting torque offset (an Ornstein-Uhlenbeck process: trim that wanders);
  and occasional corrections: when the person notices the robot has wandered off (after a
  reaction delay of ``reaction_delay_steps``), or at random moments (a Poisson rate), the set-point
  goes back to the nominal one and the trim is re-zeroed.

:class:`BalancingController` is the clean loop alone (the tests' reference controller).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
from typing import Any

import mujoco
import numpy as np
import scipy.linalg

from offdyn_bench.errors import InvalidParameterError, UnknownNameError
from offdyn_bench.json_values import is_integer, is_number
from offdyn_bench.wheel_legged.env import CONTROL_HZ, MODEL_PATH, TARGET_VELOCITY, TASK_NAMES, TILT, WHEEL, X

# LQR weights on (tilt [rad], displacement [m], tilt rate [rad/s], velocity [m/s]) and on the
# normalized torque command. Tilt dominates (a fall ends everything); the displacement weight is
# low so a push is absorbed by rolling, not by large torques. The torque weight keeps the loop
# slow enough to tolerate 10-15 ms of latency (at 1 it oscillates with 10 ms: measured).
STATE_WEIGHTS = (100.0, 10.0, 1.0, 5.0)
TORQUE_WEIGHT = 10.0
# Reduced coordinates per task, as indices into (tilt, displacement, tilt rate, velocity); they are
# also the task's observation, in the same order.
REDUCED = {"standstill": (0, 1, 2, 3), "movestraight": (0, 2, 3)}


def _upright_equilibrium(model: mujoco.MjModel) -> mujoco.MjData:
    """The robot upright and at rest, its wheels settled into the floor contact."""
    data = mujoco.MjData(model)
    for _ in range(300):  # 0.3 s holding the body upright: the contact settles
        data.qpos[TILT] = 0.0
        data.qvel[:] = 0.0
        mujoco.mj_step(model, data)
    data.qpos[TILT] = 0.0
    data.qvel[:] = 0.0
    data.ctrl[:] = 0.0
    mujoco.mj_forward(model, data)
    return data


def linearized_control_step(frame_skip: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """``(A, B)`` of one control step about the upright state, in the coordinates (tilt,
    displacement, tilt rate, velocity) and the normalized torque command."""
    model = mujoco.MjModel.from_xml_path(str(MODEL_PATH))
    data = _upright_equilibrium(model)
    nv = model.nv
    a = np.zeros((2 * nv, 2 * nv))
    b = np.zeros((2 * nv, model.nu))
    mujoco.mjd_transitionFD(model, data, 1e-6, True, a, b, None, None)
    # One control step holds ctrl for frame_skip physics steps.
    a_step = np.linalg.matrix_power(a, frame_skip)
    b_step = sum((np.linalg.matrix_power(a, k) @ b for k in range(frame_skip)), np.zeros_like(b))
    # Reduced coordinates: project the tangent state [dq, dv] onto (tilt, x, tilt rate, velocity)
    # and lift back with the rolling constraint (the wheel turns at v / r relative to the ground;
    # the wheel angle and the contact height do not enter the dynamics).
    radius = float(model.geom_size[model.geom("left_wheel").id, 0])
    project = np.zeros((4, 2 * nv))
    project[0, TILT], project[1, X], project[2, nv + TILT], project[3, nv + X] = 1, 1, 1, 1
    lift = np.zeros((2 * nv, 4))
    lift[TILT, 0], lift[X, 1], lift[nv + TILT, 2], lift[nv + X, 3] = 1, 1, 1, 1
    lift[nv + WHEEL, 3], lift[nv + WHEEL, 2] = 1.0 / radius, -1.0
    return project @ a_step @ lift, project @ b_step


@functools.cache
def lqr_gain(task: str) -> np.ndarray:
    """The LQR gain row ``K`` of ``task`` (``u = -K (s - s_ref)`` on its reduced coordinates)."""
    if task not in TASK_NAMES:
        raise UnknownNameError("wheel-legged task", task, TASK_NAMES)
    a, b = linearized_control_step()
    keep = list(REDUCED[task])
    a, b = a[np.ix_(keep, keep)], b[keep]
    q = np.diag([STATE_WEIGHTS[i] for i in keep])
    r = np.array([[TORQUE_WEIGHT]])
    x = scipy.linalg.solve_discrete_are(a, b, q, r)
    gain = np.linalg.solve(r + b.T @ x @ b, b.T @ x @ a)[0]
    gain.flags.writeable = False
    return gain


class BalancingController:
    """The clean balancing loop: ``u = clip(-K (obs - reference))``; deterministic, stateless."""

    def __init__(self, task: str) -> None:
        self.task = task
        self.gain = lqr_gain(task)
        self.reference = _nominal_reference(task)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        u = -float(self.gain @ (np.asarray(obs, dtype=float) - self.reference))
        return np.array([min(max(u, -1.0), 1.0)])

    act = __call__  # the protocol's agent interface (offdyn-bench evaluate --agent module:factory)


def balancing_agent(task: str) -> BalancingController:
    """``offdyn-bench evaluate --agent offdyn_bench.wheel_legged.operator:balancing_agent --task
    wheellegged-standstill``: the clean LQR as a reference point under the protocol."""
    return BalancingController(task.removeprefix("wheellegged-"))


def _nominal_reference(task: str) -> np.ndarray:
    """Standstill: upright at the origin, at rest. Movestraight: upright at 0.2 m/s."""
    return np.zeros(4) if task == "standstill" else np.array([0.0, 0.0, TARGET_VELOCITY])


@dataclasses.dataclass(frozen=True)
class OperatorSettings:
    """The operator's imperfections. The defaults are the datasets' (changing one is a new
    dataset version); times are in control steps of 5 ms or in seconds as named."""

    loop_delay_steps: int = 1
    """The balancing loop acts on the observation this many control steps old (5 ms)."""
    command_noise_std: float = 0.02
    """White jitter on the torque command (normalized units)."""
    trim_std: float = 0.02
    """Stationary std of the slowly drifting torque offset."""
    trim_time_constant_s: float = 2.0
    setpoint_drift: float = 0.03
    """Random-walk rate of the set-point, per sqrt(second): m (standstill) or m/s (movestraight)."""
    notice_threshold: float = 0.1
    """How far the robot may wander before the person notices: m (standstill) or m/s (movestraight: half this)."""
    reaction_delay_steps: int = 50
    """From noticing to correcting: 0.25 s, a person's reaction time."""
    random_correction_rate_hz: float = 0.1
    """Corrections at random moments, as a Poisson process (once per 10 s on average)."""

    def __post_init__(self) -> None:
        for name in ("loop_delay_steps", "reaction_delay_steps"):
            value = getattr(self, name)
            if not is_integer(value) or not 0 <= value <= 1000:
                raise InvalidParameterError("operator settings", name, value, "an integer in [0, 1000]")
        for name in ("command_noise_std", "trim_std", "setpoint_drift", "random_correction_rate_hz"):
            value = getattr(self, name)
            if not is_number(value) or not 0.0 <= value <= 10.0:
                raise InvalidParameterError("operator settings", name, value, "a number in [0, 10]")
        for name in ("trim_time_constant_s", "notice_threshold"):
            value = getattr(self, name)
            if not is_number(value) or not 0.0 < value <= 100.0:
                raise InvalidParameterError("operator settings", name, value, "a number in (0, 100]")


class HumanOperator:
    """The balancing loop steered by an imperfect person; call :meth:`start_episode` after each
    reset (the dataset builder does), then call it with each observation.

    Every random draw comes from a generator seeded by ``(seed, episode seed)``: the same recipe
    gives the same commands, byte for byte; nothing reads the clock.
    """

    def __init__(self, task: str, seed: int, settings: OperatorSettings | None = None) -> None:
        self.task = task
        self.seed = int(seed)
        self.settings = settings or OperatorSettings()
        self.gain = lqr_gain(task)
        self.nominal = _nominal_reference(task)
        # Which coordinate the person steers: displacement (standstill) or velocity (movestraight).
        self._steered = 1 if task == "standstill" else 2
        self._threshold = self.settings.notice_threshold * (1.0 if task == "standstill" else 0.5)
        self.start_episode(0)

    def start_episode(self, episode_seed: int) -> None:
        s = self.settings
        self.rng = np.random.default_rng([self.seed, int(episode_seed)])
        self.reference = self.nominal.copy()
        self.trim = 0.0
        self._seen: collections.deque[np.ndarray] = collections.deque(maxlen=s.loop_delay_steps + 1)
        self._noticed_at: int | None = None
        self._step = 0
        dt = 1.0 / CONTROL_HZ
        self._trim_decay = float(np.exp(-dt / s.trim_time_constant_s))
        self._trim_kick = s.trim_std * float(np.sqrt(1.0 - self._trim_decay**2))
        self._drift_step = s.setpoint_drift * float(np.sqrt(dt))
        self._correction_probability = 1.0 - float(np.exp(-s.random_correction_rate_hz * dt))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        s = self.settings
        obs = np.asarray(obs, dtype=float)
        self._seen.append(obs)
        delayed = self._seen[0]  # loop_delay_steps old (the first observation until then)
        # One fixed draw order per step keeps the stream reproducible: jitter, trim, drift, chance.
        jitter, trim_noise, drift, chance = self.rng.standard_normal(3).tolist() + [float(self.rng.random())]
        self.trim = self._trim_decay * self.trim + self._trim_kick * trim_noise
        self.reference[self._steered] += self._drift_step * drift
        wandered = abs(obs[self._steered] - self.nominal[self._steered]) > self._threshold
        if wandered and self._noticed_at is None:
            self._noticed_at = self._step
        due = self._noticed_at is not None and self._step - self._noticed_at >= s.reaction_delay_steps
        if due or chance < self._correction_probability:
            self.reference = self.nominal.copy()
            self.trim = 0.0
            self._noticed_at = None
        self._step += 1
        u = -float(self.gain @ (delayed - self.reference)) + self.trim + s.command_noise_std * jitter
        return np.array([min(max(u, -1.0), 1.0)])

    def describe(self) -> dict[str, Any]:
        """The operator's full definition, for a dataset's provenance."""
        return {"kind": "human-operator", "task": self.task, "seed": self.seed,
                "settings": dataclasses.asdict(self.settings),
                "lqr": {"gain": self.gain.tolist(), "state_weights": [STATE_WEIGHTS[i] for i in REDUCED[self.task]],
                        "torque_weight": TORQUE_WEIGHT,
                        "linearization": "mujoco.mjd_transitionFD about the upright state of the clean model, "
                                         "5 physics steps per control step, scipy.linalg.solve_discrete_are"}}
