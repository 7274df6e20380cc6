"""The diagnosis names effects that nothing declares to it, fits their values and closes the gap."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from diagnose_target_data import assert_diagnosed, record

import offdyn_bench  # noqa: F401  (registers the task ids)
from offdyn_bench import make_robot_env
from offdyn_bench.diagnose import DiagnosisSettings, Transitions, diagnose

# Small data and subsets keep the default run quick; test_slow.py runs the defaults on more data.
STEPS = 1000
FAST = DiagnosisSettings(screen_rows=400, fit_rows=700)


# The single dead zone, mass and gear cases run in `make test-slow`: the default run finds each of
# those kinds elsewhere (a dead zone beside a heavier torso below; a weaker motor in four checks).
@pytest.mark.parametrize(
    ("hidden", "expected"),
    [
        pytest.param([{"kind": "action_deadzone", "target": "thigh_joint", "threshold": 0.3}],
                     [("action_deadzone", "thigh_joint", 0.3)], id="deadzone-one-actuator", marks=pytest.mark.slow),
        pytest.param([{"kind": "frictionloss", "target": "leg_joint", "value": 8.0},
                      {"kind": "frictionloss", "target": "foot_joint", "value": 5.0}],
                     [("frictionloss", "leg_joint", 8.0), ("frictionloss", "foot_joint", 5.0)],
                     id="frictionloss-two-joints"),
        pytest.param([{"kind": "action_delay", "target": None, "steps": 1}],
                     [("action_delay", None, 1)], id="one-step-action-delay"),
        pytest.param([{"kind": "mass", "target": "leg", "scale": 1.5}],
                     [("mass", "leg", 1.5)], id="heavier-body", marks=pytest.mark.slow),
        pytest.param([{"kind": "gear", "target": "foot_joint", "scale": 0.6}],
                     [("gear", "foot_joint", 0.6)], id="weaker-actuator", marks=pytest.mark.slow),
        pytest.param([{"kind": "action_deadzone", "target": "leg_joint", "threshold": 0.25},
                      {"kind": "mass", "target": "torso", "scale": 1.3}],
                     [("action_deadzone", "leg_joint", 0.25), ("mass", "torso", 1.3)], id="two-effects"),
    ],
)
def test_names_fits_and_closes_an_undeclared_effect(hidden, expected) -> None:
    result = diagnose("Hopper-v5", Transitions(**record(hidden, STEPS, seed=1)), FAST)
    assert_diagnosed(result, expected)


def test_declared_shift_plus_undeclared_effect() -> None:
    """The source declares the gravity shift; only the undeclared weaker motor is added."""
    hidden = [{"kind": "gravity", "scale": 0.5}, {"kind": "gear", "target": "thigh_joint", "scale": 0.7}]
    result = diagnose("offdyn/Hopper-gravity-0.5-target-v0", Transitions(**record(hidden, STEPS, seed=2)), FAST)
    assert_diagnosed(result, [("gear", "thigh_joint", 0.7)])
    calibrated = result.calibrated_env
    assert calibrated["builder"] == "gymnasium.make"
    env = gymnasium.make(calibrated["env_id"], **calibrated["kwargs"])
    assert env.unwrapped.model.actuator_gear[0, 0] == pytest.approx(0.7 * 200, rel=0.01)


def test_calibrated_effect_list_rebuilds_the_target() -> None:
    """The calibrated list from a plain Hopper-v5 source builds a simulator that reproduces the data."""
    hidden = [{"kind": "action_delay", "target": None, "steps": 1}]
    arrays = record(hidden, 600, seed=3)
    result = diagnose("Hopper-v5", Transitions(**arrays), FAST)
    calibrated = result.calibrated_env
    assert calibrated["builder"] == "offdyn_bench.make_robot_env"
    env = make_robot_env(calibrated["robot"], **calibrated["kwargs"])
    target = make_robot_env("Hopper", effects=hidden)
    env.reset(seed=5)
    target.reset(seed=5)
    rng = np.random.default_rng(0)
    for _ in range(20):
        action = rng.uniform(-1, 1, 3)
        obs, *_ = env.step(action)
        expected, *_ = target.step(action)
        np.testing.assert_allclose(obs, expected, atol=1e-9)


def test_observation_noise_only_adds_nothing() -> None:
    """A control dataset: the source is right, the sensors are noisy. No false positive."""
    hidden = [{"kind": "obs_noise", "std": 0.01}]
    result = diagnose("Hopper-v5", Transitions(**record(hidden, STEPS, seed=4)), FAST)
    assert result.effects_added == ()
    assert not result.unexplained_residual
    assert result.noise_floor > 1e-3  # the noise is measured, not assumed away
    assert result.error_after.heldout_one_step_nrmse == pytest.approx(result.noise_floor, rel=0.2)


def test_contact_model_swap_leaves_an_honest_residual() -> None:
    """An engine-level difference the vocabulary cannot express, plus a weaker motor it can:
    the tool adds the motor, and says a residual remains."""
    hidden = [{"kind": "integrator", "integrator": "Euler"}, {"kind": "contact_solref", "timeconst": 0.05},
              {"kind": "friction_cone", "cone": "elliptic"}, {"kind": "gear", "target": "thigh_joint", "scale": 0.7}]
    result = diagnose("Hopper-v5", Transitions(**record(hidden, STEPS, seed=5)), FAST)
    assert ("gear", "thigh_joint") in {(e["kind"], e["target"]) for e in result.effects_added}
    assert result.error_after.heldout_one_step_nrmse < 0.7 * result.error_before.heldout_one_step_nrmse
    assert result.unexplained_residual
    assert result.error_after.heldout_trimmed_nrmse > 10 * result.noise_floor


def test_state_rebuilt_from_observations() -> None:
    """Without stored qpos/qvel the state comes from the observation; clipped rows are dropped and said."""
    hidden = [{"kind": "gear", "target": "leg_joint", "scale": 0.75}]
    result = diagnose("Hopper-v5", Transitions(**record(hidden, STEPS, seed=6, with_state=False)), FAST)
    assert result.state_source == "rebuilt from observations"
    assert any("rootx" in note for note in result.notes)
    assert_diagnosed(result, [("gear", "leg_joint", 0.75)])


def test_action_noise_is_read_off_the_residual_spread() -> None:
    """No deterministic effect explains a noisy command; a per-step command correction does."""
    result = diagnose("Hopper-v5", Transitions(**record([{"kind": "action_noise", "std": 0.1}], STEPS, seed=7)), FAST)
    assert [(e["kind"], e["target"]) for e in result.effects_added] == [("action_noise", None)]
    assert result.effects_added[0]["value"] == pytest.approx(0.1, rel=0.10)
    assert result.steps[-1].stochastic
    assert result.action_channel_share > 0.9
    assert not result.unexplained_residual


def test_observation_channel_effects() -> None:
    """A biased sensor and a late one, on two observation dimensions."""
    hidden = [{"kind": "obs_bias", "target": 2, "value": 0.05}, {"kind": "obs_delay", "target": 8, "steps": 1}]
    result = diagnose("Hopper-v5", Transitions(**record(hidden, STEPS, seed=8)), FAST)
    assert_diagnosed(result, [("obs_bias", 2, 0.05), ("obs_delay", 8, 1)])


def test_a_fit_on_its_bound_is_flagged() -> None:
    """A torso six times heavier lies beyond the mass candidate's bound (x5): the fit says so."""
    hidden = [{"kind": "mass", "target": "torso", "scale": 6.0}]
    settings = DiagnosisSettings(screen_rows=400, fit_rows=700, max_effects=1)
    result = diagnose("Hopper-v5", Transitions(**record(hidden, STEPS, seed=9)), settings)
    first = result.effects_added[0]
    assert (first["kind"], first["target"], first["on_bound"]) == ("mass", "torso", True)
    assert any("sits on its bound" in note for note in result.notes)


def test_effect_under_sensor_noise() -> None:
    """A weaker motor seen through noisy sensors: found, and the interval covers the true value."""
    hidden = [{"kind": "obs_noise", "std": 0.005}, {"kind": "gear", "target": "foot_joint", "scale": 0.7}]
    result = diagnose("Hopper-v5", Transitions(**record(hidden, STEPS, seed=3)), FAST)
    assert [(e["kind"], e["target"]) for e in result.effects_added] == [("gear", "foot_joint")]
    found = result.effects_added[0]
    assert found["value"] == pytest.approx(0.7, rel=0.10)
    assert found["interval"][0] <= 0.7 <= found["interval"][1]
    assert not result.unexplained_residual
    assert result.error_after.heldout_trimmed_nrmse <= 1.1 * result.noise_floor
