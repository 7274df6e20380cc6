"""``offdyn-bench protocol gap``: the source-target gap per task against hand-computed returns,
fractions kept, normalized scores and Mann-Whitney probabilities."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from offdyn_bench import protocol
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError
from offdyn_bench.protocol.gap import gaps_markdown, measure_gaps
from offdyn_bench.protocol.references import FORMAT as REFERENCE_FORMAT

HOPPER = "hopper-gravity-0.5"
WALKER = "walker2d-gravity-2.0"


def record(method: str, task: str, seed_returns: dict[int, list[float]], *, budget: str = "lite",
           side: str = "target") -> dict:
    """An evaluation record with the fields the gap reads, as `offdyn-bench evaluate` writes them."""
    return {"format": "offdyn-bench/evaluation", "format_version": 1, "protocol_version": "1.0", "task": task,
            "side": side, "budget": budget, "method": method,
            "seeds": [{"seed": s, "returns": r} for s, r in seed_returns.items()]}


@pytest.fixture
def reference_file(tmp_path):
    """Hopper: random 25, an oracle at lite with seed means 300 and 625 (2 episodes each). Walker:
    a random reference (1) and the zero command's (2)."""
    data = {"format": REFERENCE_FORMAT, "format_version": 1, "protocol_version": protocol.PROTOCOL_VERSION,
            "tasks": {HOPPER: {"random": {"mean_return": 25.0, "returns": [25.0], "provenance": {}},
                               "oracle": {"lite": {"mean_return": 462.5, "returns": [250.0, 350.0, 600.0, 650.0],
                                                   "provenance": {"episodes_per_seed": 2}}}},
                      WALKER: {"random": {"mean_return": 1.0, "returns": [1.0], "provenance": {}},
                               "zero_command": {"mean_return": 2.0, "returns": [2.0], "provenance": {}}}}}
    path = tmp_path / "reference_scores.json"
    path.write_text(json.dumps(data))
    return path


def both_sides(task=HOPPER, source=None, target=None, **kwargs):
    return [record("sac-source", task, source or {0: [1000.0], 1: [800.0]}, side="source", **kwargs),
            record("sac-source", task, target or {0: [100.0, 200.0], 1: [300.0]}, **kwargs)]


def test_gap_against_hand_computed_values(reference_file):
    [gap] = measure_gaps(both_sides(), str(reference_file))
    # Seed means: source 1000, 800 -> 900; target 150, 300 -> 225; kept 225 / 900.
    assert (gap.source_return, gap.target_return, gap.kept) == (900.0, 225.0, 0.25)
    # Oracle seed means 300 and 625: mean 462.5; 100 x (225 - 25) / (462.5 - 25).
    assert gap.oracle_seed_means == (300.0, 625.0) and gap.oracle_return == 462.5
    assert gap.normalized_target == pytest.approx(100 * 200 / 437.5)
    # Oracle against RL on source over seed pairs: 300>150, 300=300 (1/2), 625>150, 625>300.
    assert gap.oracle_better_probability == 0.875
    text = gaps_markdown([gap])
    assert "| hopper-gravity-0.5 | sac-source | 900.0 (2) | 225.0 (2) | 0.25 | 462.5 (2) | 45.7 | 0.88 |" in text


def test_missing_references_and_a_non_positive_source_give_no_invented_numbers(reference_file):
    walker = both_sides(WALKER, source={0: [-10.0]}, target={0: [5.0]})
    hopper_target_only = [record("sac-source", HOPPER, {0: [50.0]})]
    gaps = {g.task: g for g in measure_gaps(walker + hopper_target_only, str(reference_file))}
    assert gaps[WALKER].kept is None  # a fraction of a negative source return means nothing
    assert gaps[WALKER].oracle_return is None and gaps[WALKER].normalized_target is None
    assert gaps[WALKER].oracle_better_probability is None
    assert gaps[HOPPER].source_return is None and gaps[HOPPER].kept is None
    assert gaps[HOPPER].normalized_target == pytest.approx(100 * 25 / 437.5)
    assert "| walker2d-gravity-2.0 | sac-source | -10.0 (1) | 5.0 (1) | - | - | - | - |" in gaps_markdown(
        list(gaps.values()))


@pytest.mark.parametrize("records, message", [
    ([], "no evaluations given"),
    (both_sides(target={0: [1.0], 2: [1.0]}), r"source side has training seeds \[0, 1\], the target side \[0, 2\]"),
    (both_sides() + [record("sac-source", HOPPER, {1: [5.0]})], r"training seed\(s\) \[1\] of task"),
    (both_sides() + [record("sac-source", WALKER, {0: [1.0]}, budget="full")], "mix budgets"),
    ([record("sac-source", HOPPER, {0: [1.0]}, side="sideways")], "side 'sideways'; expected one of source, target"),
    ([{"task": HOPPER, "seeds": "many"}], "'seeds' is not a non-empty list"),
])
def test_bad_evaluations_are_refused_with_what_was_expected(records, message, reference_file):
    with pytest.raises(OffdynError, match=message):
        measure_gaps(records, str(reference_file))


def write_records(folder, records) -> list[str]:
    """Each record as its own evaluation file, as the commands read them; their paths."""
    paths = []
    for i, one in enumerate(records):
        path = folder / f"evaluation-{i}.json"
        path.write_text(json.dumps(one))
        paths.append(str(path))
    return paths


def test_gap_command_reads_evaluation_files(tmp_path, reference_file):
    paths = write_records(tmp_path, both_sides())
    runner = CliRunner()
    result = runner.invoke(app, ["protocol", "gap", *paths, "--reference-file", str(reference_file)])
    assert result.exit_code == 0, result.output
    assert "| hopper-gravity-0.5 | sac-source | 900.0 (2) | 225.0 (2) | 0.25 |" in result.output
    rows = json.loads(runner.invoke(app, ["protocol", "gap", *paths, "--json", "--reference-file",
                                          str(reference_file)]).output)
    assert rows[0]["kept"] == 0.25 and rows[0]["p_oracle_better"] == 0.875 and rows[0]["source_seeds"] == 2
    (tmp_path / "not.json").write_text("{}")
    refused = runner.invoke(app, ["protocol", "gap", str(tmp_path / "not.json")])
    assert refused.exit_code == 2 and "is not an offdyn-bench/evaluation file" in refused.output


def test_sac_target_records_are_the_oracle_where_the_reference_file_has_none(reference_file):
    """Walker has no recorded oracle: the sac-target records given beside sac-source's are its oracle
    (seed means 40 and 101 against RL on source's 5), marked as such, and no row of their own."""
    oracle_runs = [record("sac-target", WALKER, {0: [30.0, 50.0], 1: [101.0]})]
    walker = both_sides(WALKER, source={0: [50.0]}, target={0: [5.0]})
    [gap] = measure_gaps(walker + oracle_runs, str(reference_file))
    assert (gap.method, gap.oracle_from, gap.oracle_seed_means) == ("sac-source", "records", (40.0, 101.0))
    assert gap.normalized_target == pytest.approx(100 * (5.0 - 1.0) / (70.5 - 1.0))
    assert gap.oracle_better_probability == 1.0
    text = gaps_markdown([gap])
    assert "| walker2d-gravity-2.0 | sac-source | 50.0 (1) | 5.0 (1) | 0.10 | 70.5* (2) | 5.8 | 1.00 |" in text
    assert "* an oracle from the sac-target records given" in text
    # Hopper has a recorded oracle: it is the protocol's, and records given beside it change nothing.
    [hopper] = measure_gaps(both_sides() + [record("sac-target", HOPPER, {0: [1.0], 1: [2.0]})], str(reference_file))
    assert hopper.oracle_from == "reference file" and hopper.oracle_seed_means == (300.0, 625.0)
    assert "*" not in gaps_markdown([hopper])


def test_oracle_records_alone_are_no_gap(reference_file):
    with pytest.raises(OffdynError, match=r"only sac-target target-side records given; pass the method's records"):
        measure_gaps([record("sac-target", WALKER, {0: [1.0]})], str(reference_file))


# The core suite's same-budget test (PROTOCOL.md §9, decision 1): P(oracle > RL on source) >= 0.9
# over 5 training seeds each side.

FIVE_RL_ON_SOURCE = {s: [float(s + 1)] for s in range(5)}  # seed means 1..5


def _admission(oracle_means, rl_on_source=FIVE_RL_ON_SOURCE, reference_file=None):
    from offdyn_bench.protocol.gap import admit

    oracle = [record("sac-target", WALKER, {s: [m] for s, m in enumerate(oracle_means)})] if oracle_means else []
    [gap] = measure_gaps([record("sac-source", WALKER, rl_on_source)] + oracle, str(reference_file))
    return admit(gap)


def test_admission_is_the_mann_whitney_test_at_its_threshold(reference_file):
    # Oracle 3 against 1..5: beats 2, ties 1 (1/2); 6..9 beat all five: (2.5 + 20) / 25 = 0.90 exactly.
    passes = _admission([3.0, 6.0, 7.0, 8.0, 9.0], reference_file=reference_file)
    # RL on source's mean 3 against random 1 and the oracle's mean 6.6: 100 x 2 / 5.6 = 35.7.
    assert (passes.verdict, passes.probability, passes.reason) == (
        "passes", 0.9, "P = 0.90 >= 0.90; RL on source scores 35.7 <= 50 normalized")
    assert passes.rl_on_source_score == pytest.approx(200 / 5.6)
    assert (passes.rl_on_source_seeds, passes.oracle_seeds, passes.in_core_suite) == (5, 5, True)
    # 2.5 beats 2 and ties none: 22 / 25 = 0.88, one half-win short.
    fails = _admission([2.5, 6.0, 7.0, 8.0, 9.0], reference_file=reference_file)
    assert (fails.verdict, fails.probability, fails.reason) == ("fails", 0.88, "P = 0.88 < 0.90")


def test_admission_never_passes_on_too_few_seeds_or_without_an_oracle(reference_file):
    # Four oracle seeds that beat every RL-on-source seed: P = 1, but four is not the protocol's five.
    short = _admission([10.0, 11.0, 12.0, 13.0], reference_file=reference_file)
    assert (short.verdict, short.probability) == ("undecided", 1.0)
    assert short.reason == "4 oracle seeds; the test needs 5 on each side"
    few = _admission([10.0] * 5, rl_on_source={0: [1.0]}, reference_file=reference_file)
    assert (few.verdict, few.reason) == ("undecided", "1 RL-on-source seed; the test needs 5 on each side")
    none = _admission([], reference_file=reference_file)
    assert none.verdict == "undecided" and none.reason.startswith("no lite oracle") and none.probability is None


def test_too_few_seeds_fail_already_when_no_missing_seed_could_lift_p(reference_file):
    """PROTOCOL §9: `hopper-morph-thigh-hard` at P = 0.50 on 4 oracle seeds could reach at most
    15/25 = 0.60 with a fifth; such a pair fails on the seeds given, and its missing runs need not
    be trained. A pair that the missing seeds could still lift to the threshold stays undecided."""
    from offdyn_bench.protocol.gap import best_reachable_probability

    # RL on source 1..5. Oracle 3 beats 2 and ties 1 (2.5 of 5), oracle 1.5 beats 1 (1 of 5): P = 3.5 / 10.
    # Three more oracle seeds above all five at best: (3.5 + 3 x 5) / 25 = 0.74.
    hopeless = _admission([3.0, 1.5], reference_file=reference_file)
    assert (hopeless.verdict, hopeless.probability) == ("fails", 0.35)
    assert hopeless.reason == ("P = 0.35 on 2 oracle seeds; even if every missing seed went the oracle's way, "
                               "P would reach at most 0.74 < 0.90 with 5 on each side")
    # Oracle 3 and 10: (2.5 + 5) / 10 = 0.75, at best (7.5 + 15) / 25 = 0.90: still open.
    still_open = _admission([3.0, 10.0], reference_file=reference_file)
    assert (still_open.verdict, still_open.probability) == ("undecided", 0.75)
    # Missing RL-on-source seeds count the same way: the oracle (10) loses to both seeds given (20);
    # three more RL-on-source seeds below every oracle seed give at best 3 x 5 / 25 = 0.60.
    short_source = _admission([10.0] * 5, rl_on_source={0: [20.0], 1: [20.0]}, reference_file=reference_file)
    assert short_source.verdict == "fails" and "at most 0.60 < 0.90" in short_source.reason
    # The published hand computations (PROTOCOL §9): the hard thigh's 0.60, joint noise 1.0's 0.80.
    assert best_reachable_probability(0.5, 4, 5, 5) == pytest.approx(0.6)
    assert best_reachable_probability(0.0, 1, 5, 5) == pytest.approx(0.8)
    assert best_reachable_probability(27 / 42, 7, 6, 5) == pytest.approx(27 / 42)  # nothing missing: P as it is
    # P stands for a count of half-wins: a P a hair under 7.5 of 10 is 7.5, whose bound is the threshold itself.
    assert best_reachable_probability(0.75 - 1e-9, 2, 5, 5) == pytest.approx(0.9, abs=1e-15)
    with pytest.raises(OffdynError, match="a seed on each side"):
        best_reachable_probability(1.0, 0, 5, 5)


def test_an_undecided_pair_says_what_its_missing_oracle_seeds_must_average(reference_file, tmp_path):
    """PROTOCOL §9: `hopper-friction-5.0` on 2 oracle seeds (254.8, 226.8) could pass only if the 3
    missing ones averaged at least 495.6; the command now says so instead of leaving it to a reader."""
    # Walker: random 1, zero command 2; RL on source 1..5 (mean 3). (c) needs the oracle's mean at
    # least 1 + 100 x (3 - 1) / 50 = 5, (a) above 2: the five seeds must sum to 25, and 4.5 + 4.5 are
    # given (P = 8 / 10, at best 23 / 25: open), so the other three must average 16 / 3.
    open_pair = _admission([4.5, 4.5], reference_file=reference_file)
    assert (open_pair.verdict, open_pair.probability) == ("undecided", 0.8)
    assert open_pair.missing_oracle_mean_needed == pytest.approx(16 / 3)
    assert open_pair.reason == ("2 oracle seeds; the test needs 5 on each side; to pass, the 3 missing oracle seeds "
                                "must average above 5.3 (the 2 given: 4.5)")
    # RL on source at the random policy's return: (c) holds for any oracle above random, so (a) binds:
    # a mean above 2, a sum above 10 over five seeds, 6 given: the other four above 1.0.
    at_random = _admission([3.0, 3.0], rl_on_source={s: [1.0] for s in range(5)}, reference_file=reference_file)
    assert at_random.missing_oracle_mean_needed == pytest.approx(4 / 3)
    # Below the given seeds' own mean it is no news, so the reason leaves it out (the field keeps it).
    assert at_random.reason == "2 oracle seeds; the test needs 5 on each side"
    # Not computable: RL-on-source seeds missing too (their mean would move), or no zero-command reference.
    assert _admission([3.0, 10.0], rl_on_source={0: [1.0], 1: [2.0]},
                      reference_file=reference_file).missing_oracle_mean_needed is None
    data = json.loads(reference_file.read_text())
    del data["tasks"][WALKER]["zero_command"]
    bare = tmp_path / "no-zero.json"
    bare.write_text(json.dumps(data))
    unknown = _admission([3.0, 10.0], reference_file=bare)
    assert (unknown.verdict, unknown.missing_oracle_mean_needed) == ("undecided", None)
    assert unknown.reason == "2 oracle seeds; the test needs 5 on each side"
    # A decided pair carries none.
    assert _admission([3.0, 6.0, 7.0, 8.0, 9.0], reference_file=reference_file).missing_oracle_mean_needed is None


def test_an_oracle_below_the_zero_command_fails_whatever_rl_on_source_does(reference_file, tmp_path):
    """PROTOCOL §9: the Ant standing still earns 994.5 under friction x5, its lite oracle 164.0. An
    oracle that doing nothing beats is no oracle: on its scale doing nothing scores above 100."""
    # Walker: random 1, zero command 2. Oracle seeds 1.5-2.5 (mean 2.0) against RL on source 0.1-0.5.
    low = _admission([1.5, 1.75, 2.0, 2.25, 2.5], rl_on_source={s: [0.1 * (s + 1)] for s in range(5)},
                     reference_file=reference_file)
    assert low.probability == 1.0 and low.verdict == "fails"
    assert low.reason == "the oracle (2.0) does not beat the zero command (2.0): doing nothing would score 100 normalized"
    above = _admission([1.6, 1.85, 2.1, 2.35, 2.6], rl_on_source={s: [0.1 * (s + 1)] for s in range(5)},
                       reference_file=reference_file)
    assert (above.verdict, above.reason) == ("passes", "P = 1.00 >= 0.90; RL on source scores -63.6 <= 50 normalized")
    # No zero-command reference: undecided, never a pass, and the command that records one is named.
    data = json.loads(reference_file.read_text())
    del data["tasks"][WALKER]["zero_command"]
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps(data))
    missing = _admission([10.0, 11.0, 12.0, 13.0, 14.0], reference_file=bare)
    assert (missing.verdict, missing.probability) == ("undecided", 1.0)
    assert missing.reason == ("no zero-command reference: record one (offdyn-bench protocol reference zero-command "
                              "--task walker2d-gravity-2.0)")


def test_rl_on_source_that_the_oracle_beats_by_a_little_is_no_clear_failure(reference_file, tmp_path):
    """PROTOCOL §9, decision 1's third condition: the oracle beats every RL-on-source seed (P = 1) but
    RL on source closes more than half of the way from random to the oracle: not well below it."""
    twos = {s: [2.0] for s in range(5)}  # RL on source: 2 on every seed; random 1.
    # Oracle 3: 100 x (2 - 1) / (3 - 1) = 50, the bound itself, passes.
    at_bound = _admission([3.0] * 5, rl_on_source=twos, reference_file=reference_file)
    assert (at_bound.verdict, at_bound.probability, at_bound.rl_on_source_score) == ("passes", 1.0, 50.0)
    # Oracle 2.9: 1 / 1.9 = 52.6, above the bound, fails whatever P says.
    above = _admission([2.9] * 5, rl_on_source=twos, reference_file=reference_file)
    assert (above.verdict, above.probability) == ("fails", 1.0)
    assert above.reason == "RL on source scores 52.6 normalized, above 50: not well below the oracle (P = 1.00)"
    # Without a random reference there is no normalized score: undecided, never a pass.
    data = json.loads(reference_file.read_text())
    del data["tasks"][WALKER]["random"]
    bare = tmp_path / "no-random.json"
    bare.write_text(json.dumps(data))
    unscored = _admission([3.0] * 5, rl_on_source=twos, reference_file=bare)
    assert (unscored.verdict, unscored.rl_on_source_score) == ("undecided", None)
    assert unscored.reason == ("no random reference, so no normalized score: record one (offdyn-bench protocol "
                               "reference random --task walker2d-gravity-2.0)")


def test_coverage_lists_every_robot_and_shift_of_the_core_suite_with_its_passing_pairs(reference_file):
    from offdyn_bench.protocol.gap import Admission, admission_coverage

    def one(task, verdict):
        return Admission(task, "lite", 5, 5, 1.0, verdict, "", False, 10.0)

    coverage = admission_coverage([one("halfcheetah-gravity-5.0", "passes"), one("walker2d-gravity-2.0", "fails"),
                                   one("hopper-morph-thigh-hard", "passes"), one("ant-friction-5.0", "undecided")])
    assert coverage.passing == ("halfcheetah-gravity-5.0", "hopper-morph-thigh-hard")
    assert dict(coverage.robots) == {"Ant": (), "HalfCheetah": ("halfcheetah-gravity-5.0",),
                                     "Hopper": ("hopper-morph-thigh-hard",), "Walker2d": ()}
    assert dict(coverage.shifts) == {"friction": (), "gravity": ("halfcheetah-gravity-5.0",), "joint-noise": (),
                                     "kinematic": (), "morph": ("hopper-morph-thigh-hard",)}
    assert coverage.uncovered == ("Ant", "Walker2d", "friction", "joint-noise", "kinematic")
    assert coverage.to_dict()["uncovered"] == list(coverage.uncovered)


def test_admission_refuses_another_methods_records(tmp_path, reference_file):
    from offdyn_bench.protocol.gap import admit

    [gap] = measure_gaps([record("dap", HOPPER, {0: [1.0]})], str(reference_file))
    with pytest.raises(OffdynError, match=r"compares the oracle with RL on source \(sac-source\); got records of "
                                          r"'dap' on hopper-gravity-0.5"):
        admit(gap)
    paths = write_records(tmp_path, [record("dap", HOPPER, {0: [1.0]})])
    refused = CliRunner().invoke(app, ["protocol", "admission", *paths, "--reference-file", str(reference_file)])
    assert refused.exit_code == 2 and "error: the admission test compares the oracle with RL on source" in refused.output


def test_admission_command_reports_each_task_and_the_core_suite_count(tmp_path, reference_file):
    paths = write_records(tmp_path, [
        record("sac-source", WALKER, FIVE_RL_ON_SOURCE),
        record("sac-target", WALKER, {s: [m] for s, m in enumerate([3.0, 6.0, 7.0, 8.0, 9.0])}),
        record("sac-source", "hopper-gravity-5.0", FIVE_RL_ON_SOURCE)])
    runner = CliRunner()
    result = runner.invoke(app, ["protocol", "admission", *paths, "--reference-file", str(reference_file)])
    assert result.exit_code == 0, result.output
    assert ("| walker2d-gravity-2.0 | yes | 5 | 5 | 0.90 | 35.7 | passes: P = 0.90 >= 0.90; RL on source scores "
            "35.7 <= 50 normalized |") in result.output
    assert "| hopper-gravity-5.0 | no | 5 | 0 | - | - | undecided: no lite oracle" in result.output
    assert "Core-suite pairs given: 1 (1 passes, 0 fails, 0 undecided)." in result.output
    # What a suite of the passing pairs would cover, against the robots and shifts of the current one.
    assert ("Passing pairs: 1; robots covered: Walker2d, without a passing pair: Ant, HalfCheetah, Hopper; shift "
            "families covered: gravity, without one: friction, joint-noise, kinematic, morph.") in result.output
    rows = json.loads(runner.invoke(app, ["protocol", "admission", *paths, "--json", "--reference-file",
                                          str(reference_file)]).output)
    assert [(r["task"], r["verdict"]) for r in rows] == [("hopper-gravity-5.0", "undecided"),
                                                         ("walker2d-gravity-2.0", "passes")]
