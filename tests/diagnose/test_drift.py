"""A value that changes over the recording (a tyre wearing, a motor warming up) is reported as
such, not averaged away: every effect of the vocabulary is constant, so no calibrated model fits
those data, and the diagnosis says which effect moves and by how much."""

from __future__ import annotations

import numpy as np
import pytest
from diagnose_target_data import record

from offdyn_bench.diagnose import DiagnosisSettings, Transitions, diagnose

FAST = DiagnosisSettings(screen_rows=400, fit_rows=700)


def test_a_motor_weakening_over_the_recording_is_reported_as_drift() -> None:
    # Ten episodes in recording order, the foot's motor weaker in each: gear x0.85 down to x0.55.
    gears = np.linspace(0.85, 0.55, 10)
    parts = [record([{"kind": "gear", "target": "foot_joint", "scale": float(g)}], 200, seed=200 + k)
             for k, g in enumerate(gears)]
    data = Transitions(**{key: np.concatenate([p[key] for p in parts]) for key in parts[0]})
    result = diagnose("Hopper-v5", data, FAST)
    assert [(e["kind"], e["target"]) for e in result.effects_added] == [("gear", "foot_joint")]
    assert result.effects_added[0]["value"] == pytest.approx(gears.mean(), rel=0.05)
    assert result.identifiability is not None
    drift, = result.identifiability.drifts
    assert drift.label == "gear on foot_joint"
    # Each half's value is about that half's mean gear.
    assert drift.earlier == pytest.approx(gears[:5].mean(), abs=0.03)
    assert drift.later == pytest.approx(gears[5:].mean(), abs=0.03)
    assert any("earlier half of the episodes" in note and "gear on foot_joint" in note for note in result.notes)
    assert result.unexplained_residual  # no constant gear explains every episode
    assert result.to_json()["identifiability"]["drifts"][0]["effect"] == "gear on foot_joint"
