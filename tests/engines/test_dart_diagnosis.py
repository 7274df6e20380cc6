"""Gap diagnosis of DART target data against the MuJoCo source: part of the gap is explained by
effects, an engine gap remains, and the JSON and report say so."""

from __future__ import annotations

import json

import pytest

from offdyn_bench.datasets.build import build_dataset
from offdyn_bench.datasets.recipes import default_recipe
from offdyn_bench.diagnose.loop import DiagnosisSettings, diagnose
from offdyn_bench.diagnose.report import summary_text, write_json
from offdyn_bench.engines.gap import engine_gap_note


def test_engine_note_only_for_pairs_whose_target_runs_on_another_engine():
    assert "runs on DART, not MuJoCo" in engine_gap_note("offdyn/Hopper-dart-source-v0")
    assert engine_gap_note("offdyn/Hopper-contact-soft-source-v0") is None  # another MuJoCo model, no engine gap
    assert engine_gap_note("Hopper-v5") is None
    assert engine_gap_note(None) is None


@pytest.mark.slow
def test_diagnosis_of_dart_data_explains_part_and_reports_the_engine_gap(tmp_path):
    recipe = default_recipe("hopper-dart", "source-policy", num_transitions=3000)
    build_dataset(recipe)
    result = diagnose("Hopper-v5", recipe.dataset_id, DiagnosisSettings(max_effects=2))
    before, after = result.error_before.heldout_one_step_nrmse, result.error_after.heldout_one_step_nrmse
    # Measured on these 3,000 transitions: 0.75 -> 0.56 one step, H10 2.13 -> 0.87, noise floor 1e-6.
    assert after < before  # effects explain part of the gap ...
    assert result.unexplained_residual and after > 1000 * result.noise_floor  # ... and a residual remains
    assert result.effects_added
    # The checks of a real model gap: the stored states show exact sensors, so no observation
    # effect; the H10 error at least halves; what remains is systematic (an engine gap), not noise.
    assert not [e for e in result.effects_added if e["kind"].startswith("obs_")]
    assert result.error_after.heldout_horizon_nrmse <= 0.5 * result.error_before.heldout_horizon_nrmse
    assert result.residual_predictability is not None and result.residual_predictability.systematic
    assert "action_noise" not in {e["kind"] for e in result.effects_added}
    write_json(result, tmp_path / "diagnosis.json")
    saved = json.loads((tmp_path / "diagnosis.json").read_text())
    assert saved["unexplained_residual"] is True
    assert any("runs on DART, not MuJoCo" in note and "engine gap" in note for note in saved["notes"])
    text = summary_text(result)
    assert "an unexplained residual remains" in text and "engine gap that no effect can explain" in text


def test_a_dart_env_as_diagnosis_source_is_a_clear_error_before_any_data_is_read(tmp_path):
    from offdyn_bench.diagnose.data import DiagnosisInputError

    missing = tmp_path / "never-read.npz"
    with pytest.raises(DiagnosisInputError, match="runs on dart; diagnosis predicts with MuJoCo"):
        diagnose("offdyn/Hopper-dart-target-v0", missing)
