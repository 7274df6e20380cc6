"""The wheel-legged balancer's task pairs: the clean model as source, the "real robot" as target.

H2O (Section 6.1) names what its simulator missed on the real robot: motor dead zones, sliding
friction the simulator could not model, and a wheel-ground friction coefficient (and its wear)
that could not be set as in reality. The target expresses each with the suite's effects, plus
the sensing of a real robot (a one-step latency and noise), so gap diagnosis can look for them:

| effect | value | stands for |
|---|---|---|
| ``action_deadzone`` on ``wheel_motors`` | 0.05 (of the 3 N m peak: 0.15 N m summed) | the motors' dead zone: small torque commands do nothing |
| ``frictionloss`` on ``wheel_axle`` | 0.04 N m | dry (sliding) friction in the wheel drive that the clean model lacks |
| ``friction`` on the ``wheels`` | x0.4 (0.9 -> 0.36) | a worn tyre on a smooth floor: the wheels slip above about 0.27 of peak torque |
| ``obs_delay`` on every observation | 1 control step (5 ms) | sensor and bus latency |
| ``obs_noise`` per observation | tilt 0.002 rad, displacement 0.002 m, tilt rate 0.02 rad/s, velocity 0.01 m/s | IMU and encoder noise |

The target has the worn coefficient, constant: every effect of the vocabulary is constant, and a
recording of a few minutes wears a real tyre negligibly. Data whose tyres do wear within the
recording are what gap diagnosis reports as drift (``tests/wheel_legged/test_wheel_legged_diagnosis.py``).
"""

from __future__ import annotations

from offdyn_bench.effects import Effect, effects_from_dicts

ROBOT = "WheelLegged"
TASK_NAMES = ("standstill", "movestraight")
CONTROL_HZ = 200
EPISODE_STEPS = {"standstill": 30 * CONTROL_HZ, "movestraight": 20 * CONTROL_HZ}  # 30 s and 20 s, as in the paper

# Observation layout per task (see env.py): which index holds which quantity.
OBSERVATION_NAMES = {"standstill": ("tilt", "displacement", "tilt_rate", "velocity"),
                     "movestraight": ("tilt", "tilt_rate", "velocity")}
SENSOR_NOISE_STD = {"tilt": 0.002, "displacement": 0.002, "tilt_rate": 0.02, "velocity": 0.01}

MOTOR_DEADZONE = 0.05
DRIVE_FRICTIONLOSS = 0.04
WHEEL_FRICTION_SCALE = 0.4
SENSOR_DELAY_STEPS = 1


def real_robot_effects(task: str) -> tuple[Effect, ...]:
    """The target's effects for ``task``: the real robot's dynamics and sensing."""
    dynamics = [
        {"kind": "action_deadzone", "target": "wheel_motors", "threshold": MOTOR_DEADZONE},
        {"kind": "frictionloss", "target": "wheel_axle", "value": DRIVE_FRICTIONLOSS},
        {"kind": "friction", "target": "wheels", "scale": WHEEL_FRICTION_SCALE},
    ]
    sensing = [{"kind": "obs_delay", "target": None, "steps": SENSOR_DELAY_STEPS}]
    sensing += [{"kind": "obs_noise", "target": i, "std": SENSOR_NOISE_STD[name]}
                for i, name in enumerate(OBSERVATION_NAMES[task])]
    return effects_from_dicts(dynamics + sensing)
