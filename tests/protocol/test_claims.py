"""``offdyn-bench protocol claims``: the papers' headline claims checked task by task, against
hand-computed verdicts and Mann-Whitney probabilities."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError
from offdyn_bench.protocol import ProtocolError
from offdyn_bench.protocol.claims import PAPER_CLAIMS, check_claims, claims_markdown, training_caveats

HOPPER = "hopper-gravity-0.5"
CHEETAH_H2O = "halfcheetah-h2o-gravity-2.0"


def record(method: str, task: str, seed_returns: dict[int, list[float]], *, dataset: str | None = None,
           budget: str = "lite", side: str = "target") -> dict:
    """An evaluation record as `offdyn-bench evaluate` writes it (the fields the claims read)."""
    return {"format": "offdyn-bench/evaluation", "format_version": 1, "protocol_version": "1.0", "task": task,
            "side": side, "budget": budget, "method": method,
            "dataset": None if dataset is None else {"dataset_id": dataset, "sha256": "0" * 64},
            "seeds": [{"seed": s, "returns": r} for s, r in seed_returns.items()]}


def by_claim(checks, name, task=HOPPER):
    return [c for c in checks if c.claim.name == name and c.task == task]


def test_dap_claims_against_hand_computed_values():
    records = [record("sac-source", HOPPER, {0: [90.0, 110.0], 1: [200.0, 200.0]}),  # seed means 100, 200
               record("dap", HOPPER, {0: [310.0], 1: [290.0]}, dataset="offdyn/hopper-gravity-0p5/source-policy-v0"),
               record("dap-u", HOPPER, {0: [250.0], 1: [350.0]}, dataset="offdyn/hopper-gravity-0p5/source-policy-v0")]
    checks = check_claims(records)
    [double] = by_claim(checks, "dap >= 2x rl-on-source")
    # mean 300 against 2 x 150: holds at exactly twice; DAP beats RL on source on all 4 seed pairs.
    assert (double.better_return, double.worse_return, double.holds) == (300.0, 150.0, True)
    assert double.probability_of_improvement == 1.0 and double.claimed_on_task
    [u] = by_claim(checks, "dap-u > dap")
    # 300 is not above 300; seed pairs (250|310, 250|290, 350|310, 350|290) -> 2 of 4.
    assert (u.better_return, u.worse_return, u.holds, u.probability_of_improvement) == (300.0, 300.0, False, 0.5)
    assert u.dataset == "offdyn/hopper-gravity-0p5/source-policy-v0"
    assert not by_claim(checks, "h2o > darc")  # no H2O run: nothing claimed, nothing invented
    text = claims_markdown(checks)
    assert "| hopper-gravity-0.5 | offdyn/hopper-gravity-0p5/source-policy-v0 | 300.0 (2 seeds) | 150.0 (2 seeds) " \
           "| holds | 1.00 |" in text
    assert "| does not hold | 0.50 |" in text
    assert text.count("holds on 1 of 1") == 1 and text.count("holds on 0 of 1") == 1


def test_doubling_is_undefined_where_rl_on_source_has_no_positive_return():
    checks = check_claims([record("sac-source", HOPPER, {0: [-50.0]}), record("dap", HOPPER, {0: [10.0]})])
    [double] = by_claim(checks, "dap >= 2x rl-on-source")
    assert double.holds is None
    assert "undefined (sac-source return <= 0)" in claims_markdown(checks)
    assert "holds on 0 of 0" in claims_markdown(checks)


def test_h2o_claims_are_checked_per_dataset_and_only_claimed_on_the_halfcheetah_h2o_settings():
    medium, expert = "offdyn/halfcheetah-h2o-gravity-2p0/medium-v0", "offdyn/halfcheetah-h2o-gravity-2p0/medium-expert-v0"
    records = [record("h2o", CHEETAH_H2O, {0: [500.0]}, dataset=medium),
               record("darc", CHEETAH_H2O, {0: [400.0]}, dataset=medium),
               record("cql", CHEETAH_H2O, {0: [600.0]}, dataset=medium),
               record("h2o", CHEETAH_H2O, {0: [900.0]}, dataset=expert),
               record("darc", CHEETAH_H2O, {0: [950.0]}, dataset=expert),
               record("h2o", HOPPER, {0: [1.0]}, dataset="x"), record("darc", HOPPER, {0: [0.0]}, dataset="x")]
    checks = check_claims(records)
    darc = {c.dataset: c for c in by_claim(checks, "h2o > darc", CHEETAH_H2O)}
    assert (darc[medium].holds, darc[expert].holds) == (True, False)
    [cql] = by_claim(checks, "h2o > cql", CHEETAH_H2O)  # CQL ran on medium only
    assert (cql.dataset, cql.holds, cql.probability_of_improvement) == (medium, False, 0.0)
    [hopper] = by_claim(checks, "h2o > darc")
    assert hopper.holds and not hopper.claimed_on_task
    text = claims_markdown(checks)
    assert "| hopper-gravity-0.5 (not claimed here) | x |" in text
    assert "holds on 1 of 2 (task, dataset) rows" in text  # the Hopper row is not counted


def test_a_verdict_against_a_training_too_short_for_its_method_says_so():
    """DARC's published schedule starts its reward correction at step 100,000: at lite (100,000
    steps) the runs never apply it, so "H2O beats DARC" there is a verdict against SAC on the
    source; the row says so. The same runs with the correction from step 10,000 carry no caveat."""
    medium = "offdyn/halfcheetah-h2o-gravity-2p0/medium-v0"
    h2o = record("h2o", CHEETAH_H2O, {0: [500.0]}, dataset=medium) | {"steps": 100_000}
    command = f"offdyn-bench train darc --task {CHEETAH_H2O} --steps 100000 --seed 0 --n-seeds 1 --out runs/darc"
    darc = record("darc", CHEETAH_H2O, {0: [400.0]}, dataset=medium) | {"steps": 100_000, "train_command": command}
    assert training_caveats(h2o) == ()  # no train command: nothing to recompute
    assert training_caveats(darc) == (("--steps 100000 is not above warmup_steps=100000: this darc run never "
                                       "applies its reward correction and trains plain SAC"),)
    [check] = by_claim(check_claims([h2o, darc]), "h2o > darc", CHEETAH_H2O)
    assert check.holds and check.caveats == ("darc: " + training_caveats(darc)[0],)
    assert check.to_dict()["caveats"] == list(check.caveats)
    text = claims_markdown([check])
    assert f"- {CHEETAH_H2O}, {medium}: darc: --steps 100000 is not above warmup_steps=100000" in text

    shorter = darc | {"train_command": command.replace(" --out", " --set warmup_steps=10000 --out")}
    [check] = by_claim(check_claims([h2o, shorter]), "h2o > darc", CHEETAH_H2O)
    assert check.caveats == () and "too short" not in claims_markdown([check])
    # A method this version does not know, or a setting it does not have: nothing is claimed of it.
    assert training_caveats(darc | {"method": "my-method"}) == ()
    assert training_caveats(darc | {"train_command": command + " --set no_such_setting=1"}) == ()


def test_a_sweeps_per_seed_records_merge_and_a_seed_twice_is_refused():
    split = [record("sac-source", HOPPER, {0: [100.0]}), record("sac-source", HOPPER, {1: [300.0]}),
             record("dap", HOPPER, {0: [500.0]}), record("dap", HOPPER, {1: [300.0]})]
    [double] = by_claim(check_claims(split), "dap >= 2x rl-on-source")
    assert (double.better_return, double.worse_return, double.better_seeds) == (400.0, 200.0, 2)
    assert double.probability_of_improvement == 0.875  # 500 beats both, 300 beats 100 and ties 300
    with pytest.raises(ProtocolError, match=r"sac-source: training seed\(s\) \[0\] of task 'hopper-gravity-0.5' "
                                            r"\(dataset -\) are in two evaluations"):
        check_claims(split + [record("sac-source", HOPPER, {0: [1.0]})])


@pytest.mark.parametrize("records, message", [
    ([], "no evaluations to check the claims on"),
    ([record("dap", HOPPER, {0: [1.0]}), record("sac-source", HOPPER, {0: [1.0]}, budget="full")],
     r"mix budgets \['full', 'lite'\]"),
    ([record("dap", HOPPER, {0: [1.0]}, side="source")], "a source-side evaluation"),
    ([record("dap", HOPPER, {0: [float("nan")]})], "non-finite"),
    ([["not", "a", "record"]], "evaluation 1: not a JSON object"),
    ([{"format": "offdyn-bench/evaluation", "method": "dap", "task": HOPPER, "seeds": [{"seed": 0}]}],
     r"the evaluation of 'dap' on 'hopper-gravity-0.5': seeds\[0\].returns is not a non-empty list of numbers"),
])
def test_bad_records_get_a_clear_error(records, message):
    with pytest.raises(OffdynError, match=message):
        check_claims(records)


def test_every_claim_names_its_paper_and_a_method_of_the_suite():
    from baselines.cli import ALGORITHM_NAMES

    for claim in PAPER_CLAIMS:
        assert {claim.better, claim.worse} <= set(ALGORITHM_NAMES) and claim.paper and claim.factor >= 1


def test_cli_writes_the_report_and_refuses_an_unwritable_path(tmp_path):
    paths = []
    for i, r in enumerate([record("sac-source", HOPPER, {0: [100.0]}), record("dap", HOPPER, {0: [250.0]})]):
        paths.append(tmp_path / f"e{i}.json")
        paths[-1].write_text(json.dumps(r))
    runner = CliRunner()
    result = runner.invoke(app, ["protocol", "claims", *map(str, paths), "--out", str(tmp_path / "claims.md")])
    assert result.exit_code == 0, result.output
    assert "| hopper-gravity-0.5 | - | 250.0 (1 seed) | 100.0 (1 seed) | holds | 1.00 |" in result.output
    assert (tmp_path / "claims.md").read_text().rstrip("\n") == result.output.rstrip("\n")
    as_json = json.loads(runner.invoke(app, ["protocol", "claims", *map(str, paths), "--json"]).output)
    assert as_json[0] | {"probability_of_improvement": 1.0} == as_json[0] and as_json[0]["holds"] is True
    result = runner.invoke(app, ["protocol", "claims", *map(str, paths), "--out", str(tmp_path / "no" / "x.md")])
    assert result.exit_code == 2 and "cannot write the report" in result.output
    assert not (tmp_path / "no").exists()
