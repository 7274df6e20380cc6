"""Candidates search only values their effect accepts: a fit can never produce an effect that
construction refuses (which would end a diagnosis in an error halfway)."""

from __future__ import annotations

import pytest

from offdyn_bench.diagnose.candidates import Candidate, _within_effect_range
from offdyn_bench.effects import EFFECT_KINDS


def test_bounds_beyond_the_effect_range_are_clipped():
    strong_motor_damping = Candidate("damping", None, 2.0, 0.0, 5e4, 500.0, "smooth", trials=(10.0, 2e4))
    clipped = _within_effect_range(strong_motor_damping)
    assert (clipped.low, clipped.high, clipped.nominal, clipped.trials) == (0.0, 1e4, 2.0, (10.0,))
    bias = _within_effect_range(Candidate("action_bias", None, 0.0, -4000.0, 4000.0, 400.0, "smooth"))
    assert (bias.low, bias.high) == (-1000.0, 1000.0)
    EFFECT_KINDS["damping"](value=clipped.high)  # the extremes construct
    for value in (bias.low, bias.high):
        EFFECT_KINDS["action_bias"](value=value)


def test_a_candidate_inside_its_range_is_unchanged_and_one_outside_is_dropped():
    gear = Candidate("gear", None, 1.0, 0.1, 3.0, 0.05, "smooth")
    assert _within_effect_range(gear) is gear
    assert _within_effect_range(Candidate("action_saturation", None, 0.0, 0.0, 0.0, 0.0, "threshold")) is None
    assert _within_effect_range(Candidate("action_delay", None, 0, 2000, 3000, 1, "integer")) is None


@pytest.mark.parametrize("env_id", ["Hopper-v5", "HalfCheetah-v5"])
def test_every_library_candidate_builds_at_both_bounds(env_id):
    from offdyn_bench.diagnose.candidates import candidate_library
    from offdyn_bench.diagnose.source import SourceSimulator

    for candidate in candidate_library(SourceSimulator(env_id)):
        candidate.effect(candidate.low)
        candidate.effect(candidate.high)
