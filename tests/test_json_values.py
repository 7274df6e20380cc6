"""A boolean is never a number: ``true`` in a file or ``--set`` is refused where an integer is expected."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from baselines.algorithms import apply_overrides, get_algorithm
from baselines.limits import integer, number
from offdyn_bench.diagnose.loop import DiagnosisSettings
from offdyn_bench.errors import OffdynError
from offdyn_bench.json_values import is_finite_number, is_integer, is_number
from offdyn_bench.sweep.spec import SpecError, parse_spec
from offdyn_bench.wheel_legged.operator import OperatorSettings


@given(st.integers())
def test_every_int_is_an_integer_and_a_finite_number(value):
    assert is_integer(value) and is_number(value) and is_finite_number(value)


@given(st.floats(allow_nan=True, allow_infinity=True))
def test_a_float_is_a_number_never_an_integer_and_finite_only_when_math_says_so(value):
    assert not is_integer(value) and is_number(value)
    assert is_finite_number(value) == math.isfinite(value)


@pytest.mark.parametrize("value", [True, False])
def test_booleans_are_not_numbers(value):
    assert not is_integer(value) and not is_number(value) and not is_finite_number(value)


@pytest.mark.parametrize("value", ["3", None, [1], {"a": 1}, 2j, b"1"])
def test_other_json_and_python_values_are_not_numbers(value):
    assert not is_integer(value) and not is_number(value) and not is_finite_number(value)


def test_limits_refuse_a_boolean_that_would_pass_the_range_check():
    assert integer(0).accepts(0) and not integer(0).accepts(False)
    assert number(0.0, 1.0).accepts(1) and not number(0.0, 1.0).accepts(True)
    assert not number().accepts(math.inf) and not number().accepts(math.nan)


def _spec(**changes):
    data = {"methods": ["sac-source"], "tasks": ["hopper-gravity-0.5"], "seeds": [0], "track": "offline-target",
            "budget": "lite", "out": "runs/x"}
    return parse_spec({**data, **changes})


@pytest.mark.parametrize("refuse, expected", [
    (lambda: _spec(seeds=[0, True]), "seeds: got [0, true]; expected a count >= 1"),
    (lambda: _spec(max_retries=True), "max_retries: got true; expected an integer in"),
    (lambda: _spec(cpus_per_run=True), "cpus_per_run: got true"),
    (lambda: DiagnosisSettings(horizon=True), "an integer in [1,"),
    (lambda: DiagnosisSettings(min_z=False), "a number in [0, 100]"),
    (lambda: OperatorSettings(loop_delay_steps=True), "an integer in [0, 1000]"),
    (lambda: OperatorSettings(trim_std=True), "a number in [0, 10]"),
    (lambda: apply_overrides(get_algorithm("sac-source").default_config(), {"batch_size": "true"}, "sac-source"),
     "batch_size"),
])
def test_entry_points_refuse_a_boolean_with_a_message(refuse, expected):
    with pytest.raises((OffdynError, SpecError)) as caught:
        refuse()
    assert expected in str(caught.value)
