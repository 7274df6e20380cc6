"""Diagnosis on gaps that are not one declared effect: observation effects only where the data show
them, a floor no hypothesis moves, systematic residuals never called noise, what the data cannot
resolve, and a recipe that rebuilds the exact source."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import mujoco
import numpy as np
import pytest
from diagnose_target_data import record

from offdyn_bench import make_robot_env
from offdyn_bench.diagnose import DiagnosisInputError, DiagnosisSettings, Transitions, diagnose
from offdyn_bench.diagnose.candidates import candidate_library
from offdyn_bench.diagnose.identifiability import UNRESOLVED_RATIO, identifiability
from offdyn_bench.diagnose.loop import _fix_gauge
from offdyn_bench.diagnose.residual import ResidualEvaluator
from offdyn_bench.diagnose.source import SourceSimulator
from offdyn_bench.errors import InvalidParameterError
from offdyn_bench.diagnose.systematic import (
    SYSTEMATIC_R2,
    horizon_under_action_noise,
    residual_predictability,
)

STEPS = 1000
FAST = DiagnosisSettings(screen_rows=400, fit_rows=700)


def _evaluator(hidden: list[dict], seed: int, **record_kwargs) -> ResidualEvaluator:
    data = Transitions(**record(hidden, STEPS, seed=seed, **record_kwargs))
    return ResidualEvaluator(SourceSimulator("Hopper-v5"), data, screen_rows=400, fit_rows=700)


def _thigh_spring(model: mujoco.MjModel) -> None:
    """A spring on the thigh: a torque that depends on the joint angle, which no effect of the
    vocabulary adds (an effect nobody declared, and outside what diagnosis can name)."""
    joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "thigh_joint")
    model.jnt_stiffness[joint] = 60.0
    model.qpos_spring[model.jnt_qposadr[joint]] = -0.4


def test_exact_sensors_admit_no_observation_effect() -> None:
    """The observations equal those of the stored states: a badly wrong model must not be
    'improved' by delaying or biasing a sensor (a delayed velocity predicts no change)."""
    evaluator = _evaluator([{"kind": "mass", "target": "torso", "scale": 3.0},
                            {"kind": "gear", "target": "foot_joint", "scale": 0.4}], seed=11)
    check = evaluator.observation_check
    assert check.bias_allowed == () and check.delay_allowed == ()
    assert check.max_discrepancy is not None and check.max_discrepancy < 1e-9
    library = candidate_library(evaluator.source, obs_bias_dims=check.bias_allowed,
                                obs_delay_dims=check.delay_allowed)
    assert not [c for c in library if c.kind.startswith("obs_")]
    assert any("equal those read off the stored states" in note for note in evaluator.notes)


def test_observation_effects_are_candidates_only_where_the_sensors_disagree() -> None:
    evaluator = _evaluator([{"kind": "obs_bias", "target": 2, "value": 0.05},
                            {"kind": "obs_delay", "target": 8, "steps": 1}], seed=12)
    check = evaluator.observation_check
    assert 2 in check.bias_allowed and set(check.bias_allowed) <= {2, 8}
    assert check.delay_allowed == (8,)


def test_the_floor_is_the_measured_sensor_noise() -> None:
    """Sensor noise of std 0.01 on every dimension: the floor of each dimension is that noise in
    the residual's units, measured from the data, whatever hypothesis is judged."""
    std = 0.01
    evaluator = _evaluator([{"kind": "obs_noise", "std": std}], seed=13)
    floor, per_dim = evaluator.noise_floor()
    np.testing.assert_allclose(per_dim, std / evaluator.spread, rtol=0.1)
    assert floor == pytest.approx(float(np.sqrt(np.mean((std / evaluator.spread) ** 2))), rel=0.1)
    assert evaluator.observation_check.bias_allowed == () and evaluator.observation_check.delay_allowed == ()


def test_a_residual_the_state_predicts_is_systematic_and_noise_is_not() -> None:
    missing_mass = _evaluator([{"kind": "mass", "target": "torso", "scale": 1.5}], seed=14)
    assert residual_predictability(missing_mass, ()).heldout_r2 > 0.5
    noisy_command = _evaluator([{"kind": "action_noise", "std": 0.1}], seed=15)
    noise = residual_predictability(noisy_command, ())
    assert noise.heldout_r2 < SYSTEMATIC_R2 and not noise.systematic


def test_an_effect_outside_the_vocabulary_is_never_called_noise() -> None:
    """A joint spring lives in the action channel (a per-step command correction explains it)
    but is a function of the state: the diagnosis must say a residual remains, not fit a noise."""
    data = Transitions(**record([], STEPS, seed=16, edit_model=_thigh_spring))
    result = diagnose("Hopper-v5", data, FAST)
    assert "action_noise" not in {e["kind"] for e in result.effects_added}
    if result.unexplained_residual:
        assert result.residual_predictability is not None and result.residual_predictability.systematic
        assert "systematic" in result.stop_reason
    else:  # explained only if some vocabulary effect truly brings the held-out error to the floor
        assert result.error_after.heldout_trimmed_nrmse <= 1.1 * result.noise_floor + 1e-3
    assert result.noise_floor < 1e-5  # the sensors are exact: the floor stays where the data put it


def test_unresolved_direction_is_reported_and_a_gauge_fixed() -> None:
    """A weaker motor driven by a weaker command: only the product of gear and command gain acts
    (commands stay inside their range), so the data cannot resolve the two."""
    evaluator = _evaluator([{"kind": "gear", "target": "thigh_joint", "scale": 0.7}], seed=17)
    library = {c.label: c for c in candidate_library(evaluator.source)}
    gear, gain = library["gear on thigh_joint"], library["action_gain on thigh_joint"]
    hypothesis = (gear.effect(0.7 / 0.8), gain.effect(0.8))
    found = identifiability(evaluator, hypothesis, [(0, gear, 0.7 / 0.8), (1, gain, 0.8)])
    assert found is not None and len(found.unresolved) == 1
    assert set(found.unresolved[0]) == {gear.label, gain.label}
    assert min(found.singular_values) < UNRESOLVED_RATIO * max(found.singular_values)
    # A control: a motor and a body mass are told apart by the same data.
    mass = library["mass on torso"]
    distinct = identifiability(evaluator, (gear.effect(0.7), mass.effect(1.0)), [(0, gear, 0.7), (1, mass, 1.0)])
    assert distinct is not None and distinct.unresolved == ()
    chosen = [(gear, 0.7 / 0.8, (0.0, 0.0), False), (gain, 0.8, (0.0, 0.0), False)]
    kept, kept_chosen, notes = _fix_gauge(evaluator, hypothesis, chosen, found, FAST)
    assert len(kept) == 1 and len(notes) == 1 and "gauge" in notes[0]
    # With one of the two held at the source's value (1.0), the other carries the whole product.
    (candidate, value, _, _), = kept_chosen
    assert candidate in (gear, gain)
    assert value == pytest.approx(0.7, rel=0.02)


def test_resolved_effects_have_episode_bootstrap_intervals_that_cover_the_truth() -> None:
    hidden = [{"kind": "obs_noise", "std": 0.005}, {"kind": "mass", "target": "torso", "scale": 1.3},
              {"kind": "gear", "target": "foot_joint", "scale": 0.7}]
    result = diagnose("Hopper-v5", Transitions(**record(hidden, STEPS, seed=18)), FAST)
    found = {(e["kind"], e["target"]): e for e in result.effects_added}
    assert set(found) == {("mass", "torso"), ("gear", "foot_joint")}
    for key, truth in ((("mass", "torso"), 1.3), (("gear", "foot_joint"), 0.7)):
        effect = found[key]
        assert effect["interval"][0] <= truth <= effect["interval"][1], effect
        assert "episode bootstrap" in effect["interval_method"]
        assert effect["values_during_search"]
    assert result.identifiability is not None and not result.identifiability.unresolved


def test_calibrated_recipe_keeps_the_source_constructor_arguments(tmp_path: Path) -> None:
    """A source built from its own XML file: the recipe must rebuild that source, not the stock one."""
    stock = Path(gymnasium.make("Hopper-v5").unwrapped.fullpath).read_text()
    assert 'name="torso_geom" size="0.05 ' in stock
    xml = tmp_path / "hopper_thick_torso.xml"
    xml.write_text(stock.replace('name="torso_geom" size="0.05 ', 'name="torso_geom" size="0.08 '))
    hidden = [{"kind": "gear", "target": "thigh_joint", "scale": 0.7}]
    data = Transitions(**record(hidden, 600, seed=19, xml_file=str(xml)))
    result = diagnose("Hopper-v5", data, FAST, xml_file=str(xml))
    assert [(e["kind"], e["target"]) for e in result.effects_added] == [("gear", "thigh_joint")]
    recipe = result.calibrated_env
    assert recipe["kwargs"]["xml_file"] == str(xml)
    calibrated = make_robot_env(recipe["robot"], **recipe["kwargs"])
    target = make_robot_env("Hopper", effects=hidden, xml_file=str(xml))
    calibrated.reset(seed=3)
    target.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(20):
        action = rng.uniform(-1, 1, 3)
        np.testing.assert_allclose(calibrated.step(action)[0], target.step(action)[0], atol=1e-6)


def test_a_command_miscalibrated_per_episode_is_not_called_noise() -> None:
    """Every episode's motors carry their own constant offset (a driver recalibrated between
    runs): zero mean over the data and unrelated to the command or the state, so a per-step
    correction looks like noise at one step. But an offset keeps pushing, while independent kicks
    add up like a random walk: over 10 steps the error grows far beyond what that noise gives."""
    rng = np.random.default_rng(0)
    parts = [record([{"kind": "action_bias", "target": None, "value": float(b)}], 200, seed=100 + k)
             for k, b in enumerate(rng.normal(0.0, 0.15, 12))]
    data = Transitions(**{key: np.concatenate([p[key] for p in parts]) for key in parts[0]})
    evaluator = ResidualEvaluator(SourceSimulator("Hopper-v5"), data, screen_rows=400, fit_rows=700)
    growth = horizon_under_action_noise(evaluator, (), 0.12)
    assert growth is not None and not growth.consistent and growth.ratio > 2.0
    result = diagnose("Hopper-v5", data, FAST)
    assert "action_noise" not in {e["kind"] for e in result.effects_added}
    assert result.unexplained_residual and "not noise" in result.stop_reason
    # Real command noise predicts its own growth.
    noisy = _evaluator([{"kind": "action_noise", "std": 0.1}], seed=15)
    real = horizon_under_action_noise(noisy, (), 0.1)
    assert real is not None and real.consistent and 0.7 < real.ratio < 1.3


def test_a_longer_search_horizon_finds_effects_and_keeps_the_floor_in_its_units() -> None:
    """The search can compare predictions several steps ahead (for high-rate data whose one-step
    change is below the sensor noise): it still names the effect, and its floor is the same sensor
    noise measured against the larger change over the search horizon. (On the recorded
    observations: data without stored states have nothing else; test_stored_state_search.py
    covers the search on stored states.)"""
    hidden = [{"kind": "obs_noise", "std": 0.005}, {"kind": "gear", "target": "foot_joint", "scale": 0.7}]
    data = Transitions(**record(hidden, STEPS, seed=3))
    result = diagnose("Hopper-v5", data, DiagnosisSettings(screen_rows=400, fit_rows=700, search_horizon=5,
                                                           search_target="observations"))
    assert [(e["kind"], e["target"]) for e in result.effects_added] == [("gear", "foot_joint")]
    assert result.effects_added[0]["value"] == pytest.approx(0.7, rel=0.10)
    assert not result.unexplained_residual and result.to_json()["search_horizon"] == 5
    evaluator = ResidualEvaluator(SourceSimulator("Hopper-v5"), data, screen_rows=400, fit_rows=700, search_horizon=5,
                                  search_target="observations")
    _, one_step = evaluator.noise_floor()
    _, five_steps = evaluator.search_floor()
    np.testing.assert_allclose(five_steps, np.maximum(one_step * evaluator.spread / evaluator.search_spread, 1e-6))
    assert np.all(evaluator.search_spread > evaluator.spread)  # the state moves further in five steps


def test_a_search_horizon_longer_than_the_episodes_is_a_clear_error() -> None:
    data = Transitions(**record([], 300, seed=4))
    with pytest.raises(DiagnosisInputError, match="too few windows of 400 steps"):
        diagnose("Hopper-v5", data, DiagnosisSettings(search_horizon=400))
    with pytest.raises(InvalidParameterError, match="search_horizon"):
        DiagnosisSettings(search_horizon=0)
