"""The undeclared-effect checks with the default settings on more data (`make test-slow`)."""

from __future__ import annotations

import pytest
from diagnose_target_data import assert_diagnosed, record

from offdyn_bench.diagnose import Transitions, diagnose

STEPS = 4000

CASES = [
    ([{"kind": "action_deadzone", "target": "foot_joint", "threshold": 0.15}], [("action_deadzone", "foot_joint", 0.15)]),
    ([{"kind": "frictionloss", "target": "thigh_joint", "value": 6.0},
      {"kind": "frictionloss", "target": "foot_joint", "value": 4.0}],
     [("frictionloss", "thigh_joint", 6.0), ("frictionloss", "foot_joint", 4.0)]),
    ([{"kind": "action_delay", "target": None, "steps": 2}], [("action_delay", None, 2)]),
    ([{"kind": "mass", "target": "thigh", "scale": 1.4}], [("mass", "thigh", 1.4)]),
    ([{"kind": "gear", "target": "leg_joint", "scale": 0.5}], [("gear", "leg_joint", 0.5)]),
    ([{"kind": "action_bias", "target": "thigh_joint", "value": 0.1},
      {"kind": "damping", "target": "leg_joint", "value": 5.0}],
     [("action_bias", "thigh_joint", 0.1), ("damping", "leg_joint", 5.0)]),
    ([{"kind": "action_saturation", "target": "leg_joint", "limit": 0.6}], [("action_saturation", "leg_joint", 0.6)]),
]


@pytest.mark.slow
@pytest.mark.parametrize(("hidden", "expected"), CASES, ids=[c[1][0][0] + "-" + str(len(c[1])) for c in CASES])
def test_undeclared_effects_with_default_settings(hidden, expected) -> None:
    result = diagnose("Hopper-v5", Transitions(**record(hidden, STEPS, seed=21)))
    assert_diagnosed(result, expected)


@pytest.mark.slow
def test_noise_control_with_default_settings() -> None:
    result = diagnose("Hopper-v5", Transitions(**record([{"kind": "obs_noise", "std": 0.02}], STEPS, seed=22)))
    assert result.effects_added == ()
    assert not result.unexplained_residual


@pytest.mark.slow
@pytest.mark.parametrize(
    ("robot", "env_id", "hidden", "expected"),
    [
        ("Walker2d", "Walker2d-v5", [{"kind": "gear", "target": "thigh_left_joint", "scale": 0.6}],
         [("gear", "thigh_left_joint", 0.6)]),
        ("HalfCheetah", "HalfCheetah-v5", [{"kind": "mass", "target": "bthigh", "scale": 1.5}],
         [("mass", "bthigh", 1.5)]),
        ("Ant", "Ant-v5", [{"kind": "frictionloss", "target": "hip_1", "value": 20.0}],
         [("frictionloss", "hip_1", 20.0)]),
    ],
    ids=["walker2d", "halfcheetah", "ant"],
)
def test_other_robots(robot, env_id, hidden, expected) -> None:
    result = diagnose(env_id, Transitions(**record(hidden, 1500, robot=robot, seed=23)))
    assert_diagnosed(result, expected)
