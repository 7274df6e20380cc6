"""The wheel-legged balancer: a body on two legs with a driven wheel at each foot.

## Description

The simulated counterpart of the real wheel-legged robot on which H2O (Niu et al., 2022,
Section 6.1 and Appendix B.2) was validated: the robot balances on its two wheels like an
inverted pendulum on a cart. Two tasks, as in the paper: ``standstill`` (stay upright at the
start position) and ``movestraight`` (roll forward at 0.2 m/s while balanced). The model is
``assets/robots/wheel_legged.xml``; it is planar (x, z, pitch, the wheel axle), because the
paper's action is the *sum* of the two wheel torques and its observation has no yaw: the two
wheels always turn together, so they share one axle joint.

Physical numbers (a small real robot of this class; the paper does not give its robot's
dimensions, and the per-motor torque is missing from the published text):

| part | value | why |
|---|---|---|
| body (battery, computer, drivers) | 2.6 kg, 12 x 16 x 8 cm box, 0.2 m above the axle | a 3-4 kg hobby/research balancer |
| legs | 2 x 0.15 kg, 16 cm, fixed stance | carbon tube with knee assembly; the action moves only the wheels |
| wheels | 2 x 0.35 kg, radius 6.5 cm, 2.5 cm wide | hub-motor wheels (rotor and tyre) |
| whole robot | 3.6 kg, centre of mass 0.15 m above the axle | uncontrolled, it falls in under a second |
| motors | 1.5 N m peak each, 3 N m summed (the actuator's gear) | small geared BLDC hub drives; a push of 46 N at the tyre, about 1.3 g |
| tyre-floor friction | 0.9 (sliding), 0.005 (torsional), 0.0001 (rolling) | rubber on a hard floor |
| control | 200 Hz (5 physics steps of 1 ms, implicitfast integrator) | the paper's control rate |

## Action Space

``Box(-1, 1, (1,), float32)``: the summed wheel torque as a fraction of its peak (3 N m), as in
the paper. A command of 1 puts 1.5 N m on each wheel.

## Observation Space

As on the real robot, read from the body's IMU and the wheel odometry:

| index | standstill | movestraight | unit | MuJoCo coordinate |
|---|---|---|---|---|
| 0 | tilt angle (forward positive) | tilt angle | rad | ``qpos[rooty]`` |
| 1 | displacement from the start | tilt angular velocity | m / rad/s | ``qpos[rootx]`` / ``qvel[rooty]`` |
| 2 | tilt angular velocity | linear velocity | rad/s / m/s | ``qvel[rooty]`` / ``qvel[rootx]`` |
| 3 | linear velocity | - | m/s | ``qvel[rootx]`` |

``movestraight`` leaves out the displacement, as the paper does (only the velocity matters there).

## Rewards

Positive by construction (the constant offsets are the paper's, 30 and 15), bounded below by 1:

- ``standstill``: ``30 - 20 min(|tilt| / 0.6, 1) - 5 min(|x| / 0.5, 1) - 4 u^2``; highest (30) at zero
  tilt and displacement with no torque.
- ``movestraight``: ``15 - 10 min(|v - 0.2| / 0.2, 1) - 4 u^2``.

``u`` is the torque command the motors received (after any dead zone of the target): the torque
penalty stands for motor life, as in the paper. ``info`` carries each term.

## Starting State

Upright at the origin, tilt ``U(-0.02, 0.02)`` rad, tilt rate and velocity ``U(-0.02, 0.02)``.

## Episode End

Terminated when the robot falls (``|tilt| > 0.6`` rad, about 34 degrees, where a real robot of this
build no longer recovers). Truncated after 30 s (6000 steps, ``standstill``) or 20 s (4000 steps,
``movestraight``) by the registration's ``max_episode_steps``.

## Arguments

| argument | default | meaning |
|---|---|---|
| ``task`` | ``"standstill"`` | ``standstill`` or ``movestraight`` (registered pairs pass it) |
| ``xml_file`` | ``assets/robots/wheel_legged.xml`` | the MJCF |
| ``frame_skip`` | 5 | physics steps (1 ms) per control step |
| ``reset_noise_scale`` | 0.02 | half-width of the uniform reset noise on tilt, tilt rate and velocity |

## Version History

- v0: first version.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import mujoco
import numpy as np
from gymnasium import utils
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv
from gymnasium.spaces import Box

from offdyn_bench.errors import UnknownNameError
from offdyn_bench.wheel_legged.pairs import CONTROL_HZ, TASK_NAMES

WheelLeggedTask = Literal["standstill", "movestraight"]
MODEL_PATH = Path(__file__).resolve().parents[2] / "assets" / "robots" / "wheel_legged.xml"

FALL_TILT = 0.6  # rad
TARGET_VELOCITY = 0.2  # m/s, the paper's

# Indices into qpos / qvel of the planar model (rootx, rootz, rooty, wheel_axle).
X, TILT, WHEEL = 0, 2, 3  # (1 is rootz)
# The observation as [qpos, qvel] coordinates, per task.
OBSERVED = {"standstill": (TILT, X, 4 + TILT, 4 + X), "movestraight": (TILT, 4 + TILT, 4 + X)}


class WheelLeggedEnv(MujocoEnv, utils.EzPickle):
    """The wheel-legged balancer (see the module docstring for spaces, rewards and numbers)."""

    metadata = {"render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"], "render_fps": CONTROL_HZ}

    def __init__(self, task: WheelLeggedTask = "standstill", xml_file: str | None = None,
                 frame_skip: int = 5, reset_noise_scale: float = 0.02, **kwargs: Any) -> None:
        if task not in TASK_NAMES:
            raise UnknownNameError("wheel-legged task", task, TASK_NAMES)
        utils.EzPickle.__init__(self, task, xml_file, frame_skip, reset_noise_scale, **kwargs)
        self.task: WheelLeggedTask = task
        self._reset_noise_scale = reset_noise_scale
        self._applied = 0.0
        observation_space = Box(low=-np.inf, high=np.inf, shape=(len(OBSERVED[task]),), dtype=np.float64)
        MujocoEnv.__init__(self, str(xml_file or MODEL_PATH), frame_skip, observation_space=observation_space,
                           default_camera_config={"trackbodyid": 1, "distance": 1.5, "elevation": -10.0}, **kwargs)
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.dt))}

    def _get_obs(self) -> np.ndarray:
        qpos, qvel = self.data.qpos, self.data.qvel
        if self.task == "standstill":
            return np.array((qpos[TILT], qpos[X], qvel[TILT], qvel[X]))
        return np.array((qpos[TILT], qvel[TILT], qvel[X]))

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        # Plain floats and no temporaries: on this small model the physics of a control step costs
        # about 60 us, so every microsecond here shows in the env/bare ratio (benchmarks/).
        self.do_simulation(action, self.frame_skip)
        qpos, qvel = self.data.qpos, self.data.qvel
        tilt, x, tilt_rate, velocity = float(qpos[TILT]), float(qpos[X]), float(qvel[TILT]), float(qvel[X])
        torque = self._applied  # the command the motors got, clipped to [-1, 1]
        torque_cost = 4.0 * torque * torque
        if self.task == "standstill":
            tilt_cost = 20.0 * min(abs(tilt) / FALL_TILT, 1.0)
            displacement_cost = 5.0 * min(abs(x) * 2.0, 1.0)  # full penalty 0.5 m from the start
            reward = 30.0 - tilt_cost - displacement_cost - torque_cost
            info: dict[str, Any] = {"reward_tilt": -tilt_cost, "reward_displacement": -displacement_cost,
                                    "reward_torque": -torque_cost, "tilt": tilt, "x_position": x,
                                    "x_velocity": velocity}
            obs = np.array((tilt, x, tilt_rate, velocity))
        else:
            velocity_cost = 10.0 * min(abs(velocity - TARGET_VELOCITY) / TARGET_VELOCITY, 1.0)
            reward = 15.0 - velocity_cost - torque_cost
            info = {"reward_velocity": -velocity_cost, "reward_torque": -torque_cost, "tilt": tilt,
                    "x_position": x, "x_velocity": velocity}
            obs = np.array((tilt, tilt_rate, velocity))
        # A NaN tilt or velocity (a blown-up simulation) fails both comparisons: it ends the episode.
        terminated = not (abs(tilt) <= FALL_TILT and abs(tilt_rate) < 1e6 and abs(velocity) < 1e6)
        if self.render_mode == "human":
            self.render()
        return obs, reward, terminated, False, info

    def do_simulation(self, ctrl: np.ndarray, n_frames: int) -> None:
        # An array's own shape: np.shape() costs a function dispatch more (a list still goes through it).
        if (ctrl.shape if type(ctrl) is np.ndarray else np.shape(ctrl)) != (1,):
            raise ValueError(f"expected an action of shape (1,) (the summed wheel torque), got {np.shape(ctrl)}")
        command = float(ctrl[0])
        # Clipped here so that the reward's torque term sees what the motors got.
        self._applied = command if -1.0 <= command <= 1.0 else (1.0 if command > 1.0 else -1.0)
        self.data.ctrl[0] = self._applied
        # No mj_rnePostConstraint: nothing here reads contact forces or cacc.
        mujoco.mj_step(self.model, self.data, n_frames)

    def reset_model(self) -> np.ndarray:
        noise = self._reset_noise_scale
        qpos = self.init_qpos.copy()
        qvel = self.init_qvel.copy()
        qpos[TILT] += self.np_random.uniform(-noise, noise)
        qvel[TILT] += self.np_random.uniform(-noise, noise)
        qvel[X] += self.np_random.uniform(-noise, noise)
        self.set_state(qpos, qvel)
        return self._get_obs()
