"""The protocol's aggregate statistics against values worked out by hand, scipy where it defines
the convention, and the properties a reader relies on (reproducible bytes, stratification)."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import scipy.stats
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from offdyn_bench.errors import OffdynError
from offdyn_bench.protocol.statistics import (
    AGGREGATE_STATISTICS,
    Interval,
    StatisticsError,
    aggregate,
    iqm,
    mean,
    median,
    method_seed,
    optimality_gap,
    performance_profile,
    performance_profile_ci,
    probability_of_improvement,
    probability_of_improvement_ci,
    stratified_bootstrap_ci,
)


def normal_scores(runs: int, tasks: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(50.0, 15.0, size=(runs, tasks))


def interval_bytes(interval: Interval) -> bytes:
    return np.array([interval.point, interval.low, interval.high]).tobytes()


# ---------------------------------------------------------------- point estimates by hand


def test_iqm_of_eight_values_is_the_mean_of_the_middle_four() -> None:
    # Pooled and sorted: 1 2 | 3 4 5 6 | 7 100
    scores = [[1, 2], [3, 4], [5, 6], [7, 100]]
    assert iqm(scores) == 4.5


def test_iqm_cuts_whole_scores_rounding_the_quarter_down() -> None:
    # 10 scores: 0.25 * 10 = 2.5 -> 2 cut from each end (scipy.stats.trim_mean), the middle 6 kept:
    # 1 2 | 3 4 5 6 7 8 | 9 1000
    scores = np.array([[1, 1000], [2, 9], [3, 8], [4, 7], [5, 6]])
    assert iqm(scores) == 5.5
    assert iqm(scores) == pytest.approx(scipy.stats.trim_mean(scores.ravel(), 0.25), abs=1e-12)


def test_iqm_of_fewer_than_four_scores_cuts_nothing() -> None:
    assert iqm([[1.0, 2.0, 6.0]]) == 3.0


def test_iqm_pools_runs_and_tasks() -> None:
    # Per-task IQMs would be 2.5 and 25; pooled, the 8 scores' middle four are 3, 4, 10, 20.
    scores = [[1, 10], [2, 20], [3, 30], [4, 40]]
    assert iqm(scores) == (3 + 4 + 10 + 20) / 4


def test_mean_and_median_follow_rliable() -> None:
    # Task means 10, 20, 50: median 20 (the pooled median would be 15), mean 80 / 3.
    scores = [[0, 10, 100], [20, 30, 0]]
    assert median(scores) == 20.0
    assert mean(scores) == pytest.approx(80 / 3, abs=1e-12)


def test_optimality_gap_by_hand() -> None:
    # Shortfalls from 100: 50, 0 (120 earns no credit above the oracle), 0, 20.
    scores = [[50, 120], [100, 80]]
    assert optimality_gap(scores) == 17.5
    # Against 60: 10, 0, 0, 0.
    assert optimality_gap(scores, threshold=60) == 2.5


@pytest.mark.parametrize(
    ("x", "y", "expected"),
    [
        ([[1], [2]], [[0], [3]], 0.5),  # 1>0, 1<3, 2>0, 2<3
        ([[1], [1]], [[1], [1]], 0.5),  # every pair ties
        ([[2], [2]], [[1], [2]], 0.75),  # (1 + 1/2 + 1 + 1/2) / 4
        ([[5, 0], [6, 1]], [[1, 5], [2, 6]], 0.5),  # task 0: 1, task 1: 0
        ([[3], [4], [5]], [[1], [10]], 0.5),  # 3 of 6 pairs won
    ],
)
def test_probability_of_improvement_by_hand(x: list, y: list, expected: float) -> None:
    assert probability_of_improvement(x, y) == expected


def test_probability_of_improvement_is_mann_whitney_u_over_pairs() -> None:
    rng = np.random.default_rng(3)
    x = rng.integers(0, 5, size=(7, 3)).astype(float)  # many ties
    y = rng.integers(0, 5, size=(4, 3)).astype(float)
    per_task = [scipy.stats.mannwhitneyu(x[:, t], y[:, t]).statistic / (7 * 4) for t in range(3)]
    assert probability_of_improvement(x, y) == pytest.approx(np.mean(per_task), abs=1e-12)


def test_performance_profile_by_hand() -> None:
    scores = [[10, 50], [30, 70]]
    # tau 0: all; 20: task 0 1/2, task 1 all; 50: task 0 none, task 1 1/2 (50 is not above 50); 100: none
    profile = performance_profile(scores, [0, 20, 50, 100])
    np.testing.assert_array_equal(profile, [1.0, 0.75, 0.25, 0.0])


def test_performance_profile_averages_tasks_not_runs_pooled() -> None:
    # Unequal per-task fractions: task 0 has 1 of 2 runs above 5, task 1 has 2 of 2.
    assert performance_profile([[0, 10], [10, 10]], [5])[0] == 0.75


# ---------------------------------------------------------------- bootstrap intervals


@pytest.mark.parametrize("statistic", [iqm, mean, median, optimality_gap])
def test_interval_contains_the_point_estimate(statistic) -> None:
    interval = stratified_bootstrap_ci(normal_scores(10, 8), statistic, reps=500)
    assert interval.low <= interval.point <= interval.high
    assert interval.low < interval.high
    assert interval.point == statistic(normal_scores(10, 8))


def test_interval_shrinks_with_more_runs() -> None:
    few = stratified_bootstrap_ci(normal_scores(5, 6), iqm, reps=500)
    many = stratified_bootstrap_ci(normal_scores(80, 6), iqm, reps=500)
    assert many.width < few.width / 2


def test_interval_widens_with_confidence() -> None:
    scores = normal_scores(10, 5)
    narrow = stratified_bootstrap_ci(scores, mean, reps=500, confidence=0.5)
    wide = stratified_bootstrap_ci(scores, mean, reps=500, confidence=0.99)
    assert wide.low < narrow.low < narrow.high < wide.high


def test_same_seed_same_bytes_other_seed_other_interval() -> None:
    scores = normal_scores(10, 5)
    first = stratified_bootstrap_ci(scores, iqm, reps=300, seed=7)
    again = stratified_bootstrap_ci(scores.copy(), iqm, reps=300, seed=7)
    other = stratified_bootstrap_ci(scores, iqm, reps=300, seed=8)
    assert interval_bytes(first) == interval_bytes(again)
    assert (other.low, other.high) != (first.low, first.high)
    assert other.point == first.point


def test_seed_is_independent_of_global_numpy_state() -> None:
    scores = normal_scores(6, 4)
    np.random.seed(1)
    first = stratified_bootstrap_ci(scores, iqm, reps=100, seed=0)
    np.random.seed(2)
    np.random.random(10)
    assert interval_bytes(stratified_bootstrap_ci(scores, iqm, reps=100, seed=0)) == interval_bytes(first)


def test_all_equal_scores_give_a_zero_width_interval() -> None:
    scores = np.full((6, 4), 42.0)
    for statistic in (iqm, mean, median):
        assert stratified_bootstrap_ci(scores, statistic, reps=200) == Interval(42.0, 42.0, 42.0)
    assert stratified_bootstrap_ci(scores, optimality_gap, reps=200) == Interval(58.0, 58.0, 58.0)


def test_resampling_is_stratified_per_task() -> None:
    # Task 0 is constant; tasks 1 and 2 hold values no other task has.
    scores = np.array([[7.0, 1.0, 100.0], [7.0, 2.0, 200.0], [7.0, 3.0, 300.0], [7.0, 4.0, 400.0]])
    samples: list[np.ndarray] = []

    def record(sample: np.ndarray) -> float:
        samples.append(sample.copy())
        return float(np.ptp(sample[:, 0]))  # the spread of task 0: zero unless tasks were mixed

    interval = stratified_bootstrap_ci(scores, record, reps=300, seed=1)
    assert interval == Interval(0.0, 0.0, 0.0)
    assert len(samples) == 1 + 300  # the point estimate, then each sample
    for sample in samples:
        assert sample.shape == scores.shape
        for task in range(3):
            assert set(sample[:, task]) <= set(scores[:, task])
    # The runs are drawn independently per task: rows of the sample are not whole original rows.
    resampled = samples[1:]
    assert any(not any((row == scores).all(axis=1).any() for row in sample) for sample in resampled)
    # ...and with replacement: some sample repeats a run.
    assert any(len(set(sample[:, 1])) < 4 for sample in resampled)


def test_custom_statistic_per_sample_and_vectorized_agree() -> None:
    scores = normal_scores(8, 5)

    def spread(sample: np.ndarray) -> float:
        return float(sample.max() - sample.min())

    def spread_batch(batch: np.ndarray) -> np.ndarray:
        return batch.max(axis=(1, 2)) - batch.min(axis=(1, 2))

    looped = stratified_bootstrap_ci(scores, spread, reps=600, seed=4)
    vectorized = stratified_bootstrap_ci(scores, spread_batch, reps=600, seed=4, vectorized=True)  # type: ignore[arg-type]
    assert interval_bytes(looped) == interval_bytes(vectorized)


def test_builtin_statistics_match_a_per_sample_evaluation() -> None:
    # The vectorised path of each built-in against calling the statistic sample by sample on the
    # same draws (a lambda hides the built-in, so the per-sample loop is taken).
    scores = normal_scores(7, 4)
    for statistic in (iqm, mean, median, functools.partial(optimality_gap, threshold=60.0)):
        fast = stratified_bootstrap_ci(scores, statistic, reps=300, seed=2)
        slow = stratified_bootstrap_ci(scores, lambda s, f=statistic: f(s), reps=300, seed=2)
        assert fast.low == pytest.approx(slow.low, abs=1e-12)
        assert fast.high == pytest.approx(slow.high, abs=1e-12)
        assert fast.point == pytest.approx(slow.point, abs=1e-12)


def test_partial_optimality_gap_uses_its_threshold() -> None:
    scores = normal_scores(6, 3)
    interval = stratified_bootstrap_ci(scores, functools.partial(optimality_gap, threshold=60.0), reps=100)
    assert interval.point == optimality_gap(scores, threshold=60.0)


def test_a_single_rep_gives_that_sample_as_the_interval() -> None:
    interval = stratified_bootstrap_ci(normal_scores(5, 3), mean, reps=1, seed=3)
    assert interval.low == interval.high


def test_probability_of_improvement_interval() -> None:
    x = normal_scores(10, 6, seed=1) + 10.0
    y = normal_scores(10, 6, seed=2)
    interval = probability_of_improvement_ci(x, y, reps=400, seed=5)
    assert interval.point == probability_of_improvement(x, y)
    assert 0.5 < interval.low <= interval.point <= interval.high <= 1.0
    assert interval_bytes(interval) == interval_bytes(probability_of_improvement_ci(x, y, reps=400, seed=5))
    # Identical methods: P = 1/2 exactly, and the interval straddles it.
    same = probability_of_improvement_ci(y, y, reps=400, seed=5)
    assert same.point == 0.5
    assert same.low < 0.5 < same.high


def test_probability_of_improvement_interval_with_constant_methods_has_zero_width() -> None:
    assert probability_of_improvement_ci(np.full((4, 2), 3.0), np.full((5, 2), 1.0), reps=50) == Interval(1.0, 1.0, 1.0)


def test_performance_profile_band_brackets_the_profile() -> None:
    scores = normal_scores(10, 5)
    taus = np.linspace(0, 100, 21)
    low, high = performance_profile_ci(scores, taus, reps=400, seed=1)
    profile = performance_profile(scores, taus)
    assert low.shape == high.shape == taus.shape
    assert np.all(low <= profile) and np.all(profile <= high)
    assert np.all(np.diff(low) <= 0) and np.all(np.diff(high) <= 0)  # profiles fall as tau rises
    assert (low[0], high[0]) == (1.0, 1.0) and (low[-1], high[-1]) == (0.0, 0.0)
    again = performance_profile_ci(scores, taus, reps=400, seed=1)
    assert low.tobytes() == again[0].tobytes() and high.tobytes() == again[1].tobytes()


# ---------------------------------------------------------------- aggregate


def test_aggregate_reports_every_statistic_with_its_interval() -> None:
    scores = {"dap": normal_scores(5, 4, seed=1), "darc": normal_scores(5, 4, seed=2)}
    result = aggregate(scores, reps=200, seed=3)
    assert list(result) == ["dap", "darc"]
    for method, matrix in scores.items():
        assert tuple(result[method]) == AGGREGATE_STATISTICS
        for name, statistic in zip(AGGREGATE_STATISTICS, (iqm, mean, median, optimality_gap)):
            expected = stratified_bootstrap_ci(matrix, statistic, reps=200, seed=method_seed(3, method))
            assert interval_bytes(result[method][name]) == interval_bytes(expected)


def test_aggregate_interval_of_a_method_does_not_depend_on_the_others() -> None:
    dap = normal_scores(5, 4, seed=1)
    alone = aggregate({"dap": dap}, reps=200)
    with_others = aggregate({"a-first": normal_scores(3, 4), "dap": dap, "zz": normal_scores(6, 4)}, reps=200)
    assert alone["dap"] == with_others["dap"]
    # Two methods with equal scores still get their own draws.
    twins = aggregate({"a": dap, "b": dap}, reps=200)
    assert twins["a"]["iqm"].point == twins["b"]["iqm"].point
    assert twins["a"]["iqm"] != twins["b"]["iqm"]


def test_aggregate_optimality_threshold() -> None:
    scores = [[50.0, 120.0], [100.0, 80.0]]
    assert aggregate({"m": scores}, reps=10, optimality_threshold=60)["m"]["optimality_gap"].point == 2.5


def test_method_seed_is_stable() -> None:
    # Fixed by sha256, not Python's salted hash: the same in every process and release.
    assert method_seed(0, "dap") == method_seed(0, "dap")
    assert method_seed(0, "dap") != method_seed(1, "dap") != method_seed(0, "darc")
    assert 0 <= method_seed(0, "dap") < 2**64


def test_inputs_are_left_unchanged() -> None:
    x, y = normal_scores(5, 3, seed=1), normal_scores(4, 3, seed=2)
    x_before, y_before = x.copy(), y.copy()
    aggregate({"x": x, "y": y}, reps=50)
    probability_of_improvement_ci(x, y, reps=50)
    performance_profile_ci(x, [10.0, 50.0], reps=50)
    np.testing.assert_array_equal(x, x_before)
    np.testing.assert_array_equal(y, y_before)


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("scores", "message"),
    [
        ([1.0, 2.0, 3.0], "expected a 2-D array of shape (n_runs, n_tasks), got 1-D shape (3,)"),
        (np.zeros((2, 2, 2)), "got 3-D shape (2, 2, 2)"),
        (np.zeros((0, 3)), "expected at least one run and one task, got shape (n_runs=0, n_tasks=3)"),
        (np.zeros((3, 0)), "n_tasks=0"),
        ([[1.0, np.nan], [2.0, 3.0]], "expected finite scores, got nan at run 0, task 1 (1 non-finite in all)"),
        ([[1.0, 2.0], [np.inf, 3.0]], "got inf at run 1, task 0"),
        ([["a", "b"]], "expected a numeric array of shape (n_runs, n_tasks)"),
    ],
)
def test_malformed_scores_are_refused(scores: object, message: str) -> None:
    for call in (
        lambda: iqm(scores),
        lambda: optimality_gap(scores),
        lambda: stratified_bootstrap_ci(scores, iqm),
        lambda: performance_profile(scores, [0.0]),
    ):
        with pytest.raises(StatisticsError) as error:
            call()
        assert message in str(error.value)
        assert isinstance(error.value, OffdynError)


def test_mismatched_task_counts_are_refused() -> None:
    with pytest.raises(StatisticsError, match=r"x has 2 tasks but y has 3; methods are compared on the same tasks"):
        probability_of_improvement(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(StatisticsError, match="x has 2 tasks but y has 3"):
        probability_of_improvement_ci(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(StatisticsError, match=r"method 'dap' has 2 tasks but method 'darc' has 3"):
        aggregate({"dap": np.zeros((4, 2)), "darc": np.zeros((5, 3))})
    with pytest.raises(StatisticsError, match=r"scores of 'darc': expected finite scores"):
        aggregate({"dap": np.zeros((4, 2)), "darc": [[0.0, np.nan]]})


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"confidence": 0.0}, "invalid confidence=0.0; expected a number strictly between 0 and 1"),
        ({"confidence": 1.0}, "invalid confidence=1.0"),
        ({"confidence": 95}, "invalid confidence=95"),
        ({"confidence": float("nan")}, "invalid confidence=nan"),
        ({"reps": 0}, "invalid reps=0; expected an integer >= 1"),
        ({"reps": 2.5}, "invalid reps=2.5"),
        ({"seed": -1}, "invalid seed=-1; expected an integer >= 0"),
        ({"seed": 1.5}, "invalid seed=1.5"),
    ],
)
def test_bootstrap_parameters_out_of_range_are_refused(keywords: dict, message: str) -> None:
    scores = normal_scores(4, 2)
    for call in (
        lambda: stratified_bootstrap_ci(scores, iqm, **keywords),
        lambda: probability_of_improvement_ci(scores, scores, **keywords),
        lambda: performance_profile_ci(scores, [50.0], **keywords),
        lambda: aggregate({"m": scores}, **keywords),
    ):
        with pytest.raises(StatisticsError) as error:
            call()
        assert message in str(error.value)


def test_other_bad_arguments_are_refused() -> None:
    scores = normal_scores(4, 2)
    with pytest.raises(StatisticsError, match="expected a non-empty mapping"):
        aggregate({})
    with pytest.raises(StatisticsError, match="method names must be non-empty strings"):
        aggregate({1: scores})  # type: ignore[dict-item]
    with pytest.raises(StatisticsError, match=r"invalid threshold=nan; expected a finite number"):
        optimality_gap(scores, threshold=float("nan"))
    with pytest.raises(StatisticsError, match="taus: expected a non-empty 1-D array"):
        performance_profile(scores, [[1.0, 2.0]])
    with pytest.raises(StatisticsError, match="taus: expected finite score thresholds"):
        performance_profile_ci(scores, [np.inf])
    with pytest.raises(StatisticsError, match=r"statistic returned shape \(\) on the input scores, a stack of shape \(1, 4, 2\); "
                                          r"expected shape \(1,\)"):
        stratified_bootstrap_ci(scores, lambda batch: 1.0, vectorized=True, reps=300)
    with pytest.raises(StatisticsError, match="statistic returned a non-finite value on the bootstrap samples"):
        stratified_bootstrap_ci(scores, lambda s: float("nan") if s[0, 0] != scores[0, 0] else 0.0, reps=50)


# ---------------------------------------------------------------- properties

score_values = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, allow_infinity=False)
score_matrices = hnp.arrays(
    np.float64, hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=8), elements=score_values
)


@settings(max_examples=200, deadline=None)
@given(score_matrices)
def test_iqm_lies_between_min_and_max(scores: np.ndarray) -> None:
    value = iqm(scores)
    slack = 1e-12 * max(1.0, float(np.abs(scores).max()))
    assert scores.min() - slack <= value <= scores.max() + slack


@settings(max_examples=200, deadline=None)
@given(score_matrices, st.randoms(use_true_random=False))
def test_iqm_is_invariant_to_permuting_runs_within_tasks(scores: np.ndarray, random) -> None:
    permuted = scores.copy()
    for task in range(scores.shape[1]):
        column = list(permuted[:, task])
        random.shuffle(column)
        permuted[:, task] = column
    assert iqm(permuted) == iqm(scores)  # exactly: the kept scores are summed in sorted order


@settings(max_examples=200, deadline=None)
@given(score_matrices, st.floats(min_value=-1e3, max_value=1e3))
def test_iqm_shifts_with_the_scores(scores: np.ndarray, shift: float) -> None:
    assert iqm(scores + shift) == pytest.approx(iqm(scores) + shift, rel=1e-9, abs=1e-8)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 6).flatmap(
        lambda tasks: st.tuples(
            hnp.arrays(np.float64, st.tuples(st.integers(1, 7), st.just(tasks)), elements=score_values),
            hnp.arrays(np.float64, st.tuples(st.integers(1, 7), st.just(tasks)), elements=score_values),
        )
    )
)
def test_improvement_of_x_over_y_and_y_over_x_sum_to_one(pair: tuple[np.ndarray, np.ndarray]) -> None:
    x, y = pair
    forward = probability_of_improvement(x, y)
    assert 0.0 <= forward <= 1.0
    assert forward + probability_of_improvement(y, x) == pytest.approx(1.0, abs=1e-12)
