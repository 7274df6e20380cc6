"""Two things that hid the wheel-legged robot's gap from the diagnosis, on data nobody declared:

- sensors that do not read the state exactly (noise, a latency, an offset) drown small dynamics
  effects in every residual; with stored states the search compares the physics with them, and
  the sensors are read off the difference between the two recordings;
- a dead zone among small commands (a gentle behaviour policy) lies below every fixed trial value;
  the screen now also tries the recorded command magnitudes.
"""

from __future__ import annotations

import numpy as np
import pytest
from diagnose_target_data import record

from offdyn_bench.diagnose import DiagnosisSettings, Transitions, diagnose
from offdyn_bench.diagnose.candidates import candidate_library
from offdyn_bench.diagnose.data import DiagnosisInputError
from offdyn_bench.diagnose.residual import ResidualEvaluator
from offdyn_bench.diagnose.source import SourceSimulator
from offdyn_bench.effects import effects_from_dicts
from offdyn_bench.errors import InvalidParameterError

STEPS = 1000
FAST = {"screen_rows": 400, "fit_rows": 700}
# Noisy, late and offset sensors over a joint's dry friction: the friction moves a step's motion
# less than the sensor noise does.
NOISY_SENSORS = [{"kind": "obs_noise", "std": 0.05}, {"kind": "obs_bias", "target": 2, "value": 0.05},
                 {"kind": "obs_delay", "target": 8, "steps": 1}]
DRY_FRICTION = {"kind": "frictionloss", "target": "foot_joint", "value": 3.0}
DRY_FRICTION_EFFECT, = effects_from_dicts([DRY_FRICTION])


@pytest.fixture(scope="module")
def noisy_data() -> Transitions:
    return Transitions(**record([*NOISY_SENSORS, DRY_FRICTION], STEPS, seed=32))


def _found(result) -> dict[tuple[str, object], float]:
    return {(e["kind"], e["target"]): float(e["value"]) for e in result.effects_added}


def test_stored_states_separate_the_sensors_from_the_dynamics(noisy_data: Transitions) -> None:
    result = diagnose("Hopper-v5", noisy_data, DiagnosisSettings(**FAST))
    found = _found(result)
    # The sensors, read off the two recordings: the delay exactly, the offset within its interval.
    assert found[("obs_delay", 8)] == 1
    bias = next(e for e in result.effects_added if (e["kind"], e["target"]) == ("obs_bias", 2))
    assert bias["interval"][0] <= 0.05 <= bias["interval"][1]
    assert "stored states" in bias["interval_method"]
    # The dynamics, on the stored states: the friction the noise hid.
    assert found[("frictionloss", "foot_joint")] == pytest.approx(3.0, rel=0.10)
    assert set(found) == {("obs_delay", 8), ("obs_bias", 2), ("frictionloss", "foot_joint")}
    # Errors stay those of the recorded observations: the noise is the floor, and it is reached.
    assert result.noise_floor > 0.1
    assert result.error_after.heldout_trimmed_nrmse <= 1.1 * result.noise_floor + 1e-3
    assert not result.unexplained_residual
    assert any("stored states" in note for note in result.notes)
    # Constant effects: no drift between the earlier and the later episodes (test_drift.py).
    assert result.identifiability is not None and result.identifiability.drifts == ()


def test_on_the_recorded_observations_the_noise_hides_that_friction(noisy_data: Transitions) -> None:
    """The control: the same data searched on the recorded observations, as before. The noise
    floor is reached without the friction, so the search stops short of it."""
    result = diagnose("Hopper-v5", noisy_data, DiagnosisSettings(**FAST, search_target="observations"))
    assert ("frictionloss", "foot_joint") not in _found(result)


def test_the_search_on_stored_states_has_a_numerical_floor_and_needs_whole_windows(noisy_data: Transitions) -> None:
    evaluator = ResidualEvaluator(SourceSimulator("Hopper-v5"), noisy_data, screen_rows=400, fit_rows=700,
                                  search_horizon=3)
    assert evaluator.search_on_states
    floor, per_dim = evaluator.search_floor()
    assert floor <= 1e-6 and np.all(per_dim <= 1e-6)
    # Every window's end state is stored and in the start's episode.
    for starts in evaluator.search_starts.values():
        assert np.all(evaluator.episode[starts + 3] == evaluator.episode[starts])
    # The true dynamics predict the stored states to rounding, whatever the sensors did; the
    # source does not.
    exact, source = evaluator.search_residuals([(DRY_FRICTION_EFFECT,), ()], "heldout")
    assert np.sqrt(np.mean(exact**2)) < 1e-6 < np.sqrt(np.mean(source**2))


def test_exact_sensors_keep_the_search_on_the_observations() -> None:
    data = Transitions(**record([DRY_FRICTION], 400, seed=33))
    evaluator = ResidualEvaluator(SourceSimulator("Hopper-v5"), data, screen_rows=200, fit_rows=300)
    assert not evaluator.search_on_states


def test_search_target_is_checked() -> None:
    data = Transitions(**record([], 300, seed=34, with_state=False))
    with pytest.raises(DiagnosisInputError, match="stored qpos/qvel"):
        ResidualEvaluator(SourceSimulator("Hopper-v5"), data, search_target="states")
    with pytest.raises(DiagnosisInputError, match="search_target must be one of auto, observations, states"):
        ResidualEvaluator(SourceSimulator("Hopper-v5"), data, search_target="sensors")  # type: ignore[arg-type]
    with pytest.raises(InvalidParameterError, match="search_target"):
        DiagnosisSettings(search_target="sensors")  # type: ignore[arg-type]


def test_a_dead_zone_among_small_commands_is_found() -> None:
    """Commands within +-0.15 and a 0.05 dead zone on the thigh: the fixed trials (0.1, 0.3 and 0.5
    of the limit) zero nearly every command or all of them; the recorded magnitudes locate it."""
    data = Transitions(**record([{"kind": "action_deadzone", "target": "thigh_joint", "threshold": 0.05}], STEPS,
                                seed=31, command_scale=0.15))
    result = diagnose("Hopper-v5", data, DiagnosisSettings(**FAST))
    assert _found(result) == {("action_deadzone", "thigh_joint"): pytest.approx(0.05, rel=0.05)}
    assert not result.unexplained_residual
    # The screen's dead-zone trials now include values among the recorded commands.
    source = SourceSimulator("Hopper-v5")
    library = candidate_library(source, commands=data.actions)
    trials = next(c.trials for c in library if c.label == "action_deadzone on thigh_joint")
    assert sum(t < 0.15 for t in trials) >= 4
    blind = next(c.trials for c in candidate_library(source) if c.label == "action_deadzone on thigh_joint")
    assert blind == (0.1, 0.3, 0.5)

