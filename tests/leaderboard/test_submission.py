"""The one validation function: schema, protocol rules, strict JSON, and the shipped store."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from leaderboard.store import DEFAULT_STORE, load_store
from leaderboard.submission import (
    SCHEMA_PATH,
    SubmissionError,
    parse_json_strict,
    submission_schema,
    validate_submission,
)

TASK = "hopper-gravity-0.5"


def test_published_schema_is_valid_draft_2020_12() -> None:
    schema = json.loads(SCHEMA_PATH.read_text())
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)


def test_every_submission_in_the_repository_store_validates() -> None:
    """The canonical store under the real protocol (and its file names match their contents)."""
    submissions = load_store(DEFAULT_STORE)
    assert [s.file_name for s in submissions] == sorted(p.name for p in DEFAULT_STORE.glob("*.json"))


def test_valid_submission_round_trips(make_submission) -> None:
    submission = validate_submission(make_submission("alpha"))
    assert submission.key == ("alpha", "offline-target", "lite")
    assert submission.file_name == "alpha__offline-target__lite.json"
    assert submission.tasks[TASK].seeds == (0, 1, 2)
    np.testing.assert_allclose(submission.tasks[TASK].returns.mean(axis=1), [10.0, 20.0, 30.0])


def _reject(document: object, *fragments: str) -> str:
    with pytest.raises(SubmissionError) as caught:
        validate_submission(document)
    message = str(caught.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, message
    return message


def test_a_submitted_score_is_refused(make_submission) -> None:
    document = make_submission()
    document["iqm"] = 99.0
    _reject(document, "'iqm' was unexpected")
    document = make_submission()
    document["tasks"][TASK]["normalized_score"] = 100.0
    _reject(document, "normalized_score", "computes every score itself")


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_returns_are_refused(make_submission, value: float) -> None:
    document = make_submission()
    document["tasks"][TASK]["seeds"][1]["returns"][2] = value
    _reject(document, f"$.tasks.{TASK}.seeds[1].returns[2]", "finite")


def test_nan_token_is_not_json() -> None:
    with pytest.raises(SubmissionError, match="NaN is not valid JSON"):
        parse_json_strict(b'{"returns": [1.0, NaN]}', source="body")
    with pytest.raises(SubmissionError, match="Infinity is not valid JSON"):
        parse_json_strict(b'[-Infinity]', source="body")


def test_strict_json_refuses_repeated_keys_bad_text_and_size() -> None:
    with pytest.raises(SubmissionError, match="key 'a' appears twice"):
        parse_json_strict('{"a": 1, "a": 2}', source="body")
    with pytest.raises(SubmissionError, match=r"not valid JSON: Expecting value at line 1 column 1"):
        parse_json_strict("}{", source="body")
    with pytest.raises(SubmissionError, match="not UTF-8"):
        parse_json_strict(b"\xff\xfe", source="body")
    with pytest.raises(SubmissionError, match="at most 10 bytes"):
        parse_json_strict(b"[" + b"1," * 10 + b"1]", source="body", max_bytes=10)


def test_unknown_and_missing_tasks(make_submission) -> None:
    document = make_submission()
    document["tasks"]["hopper-gravity-0.7"] = copy.deepcopy(document["tasks"][TASK])
    _reject(document, "'hopper-gravity-0.7' is not in the core suite", "expected exactly")
    document = make_submission()
    del document["tasks"]["ant-gravity-0.1"]
    _reject(document, "missing core-suite task(s) ant-gravity-0.1")


def test_seed_and_episode_counts(make_submission) -> None:
    _reject(make_submission(seeds=(0, 1), seed_means={t: (1.0, 2.0) for t in
                                                      ("hopper-gravity-0.5", "walker2d-gravity-2.0",
                                                       "ant-gravity-0.1")}),
            "2 training seed(s)", "at least 3")
    document = make_submission()
    document["tasks"][TASK]["seeds"][0]["returns"].append(1.0)
    _reject(document, "seeds[0] (seed 0) has 5 returns", "exactly 4 episodes")
    document = make_submission()
    document["tasks"][TASK]["seeds"][2]["seed"] = 0
    _reject(document, "repeats a seed")
    document = make_submission()
    document["tasks"][TASK]["seeds"][2]["seed"] = 7
    _reject(document, "same training seeds")
    document = make_submission()
    document["tasks"][TASK]["episode_seeds"][0] = 1
    _reject(document, "episode_seeds differ from the protocol's 4 episode seeds")


def test_protocol_track_budget_and_versions(make_submission) -> None:
    document = make_submission()
    document["protocol_version"] = "0.9"
    _reject(document, "protocol_version '0.9'", "scores protocol '1.0'")
    _reject(make_submission(track="offline"), "$.track", "is not one of")
    _reject(make_submission(budget="huge"), "$.budget")
    document = make_submission()
    document["versions"]["mujoco"] = "3.3.0"
    _reject(document, "MuJoCo 3.3.0", "pins MuJoCo 3.17.0")
    document = make_submission()
    del document["versions"]["torch"]
    _reject(document, "$.versions", "'torch' is a required property")


def test_task_identity_is_checked_against_the_registry(make_submission) -> None:
    document = make_submission()
    document["tasks"][TASK]["task_version"] = 3
    _reject(document, "task_version is 3", "version 0")
    document = make_submission()
    document["tasks"][TASK]["target_env_id"] = "offdyn/Hopper-gravity-0.7-target-v0"
    _reject(document, "target_env_id", "offdyn/Hopper-gravity-0.5-target-v0")


@pytest.mark.parametrize("name", ["../x", "/etc/x", "a/b", "A", "", ".hidden", "x" * 49, "a b", "a\\b"])
def test_method_names_that_could_leave_the_store_are_refused(make_submission, name: str) -> None:
    _reject(make_submission(name), "$.method.name")


def test_string_and_size_bounds(make_submission) -> None:
    document = make_submission()
    document["method"]["description"] = "x" * 2001
    _reject(document, "$.method.description", "is too long")
    document = make_submission()
    document["method"]["code_url"] = "javascript:alert(1)"
    _reject(document, "$.method.code_url")
    document = make_submission()
    document["tasks"][TASK]["seeds"] = document["tasks"][TASK]["seeds"] * 40
    _reject(document, f"$.tasks.{TASK}.seeds", "too long")
    document = make_submission()
    document["tasks"][TASK]["seeds"][0]["returns"][0] = 1e12
    _reject(document, "greater than the maximum")


def test_learning_curve_shape(make_submission) -> None:
    document = make_submission(curves=True)
    assert validate_submission(document).tasks[TASK].learning_curve[-1].step == 2000
    document["tasks"][TASK]["learning_curve"][1]["target_return"].pop()
    _reject(document, "learning_curve[1] has 2 values", "one per training seed (3)")
    document = make_submission(curves=True)
    document["tasks"][TASK]["learning_curve"][2]["step"] = 500
    _reject(document, "learning_curve[2].step 500 does not increase")


def test_not_an_object_and_wrong_format() -> None:
    _reject([1, 2], "expected a JSON object")
    assert submission_schema()["properties"]["format"]["const"] == "offdyn-bench/submission"


def test_schema_errors_are_short(make_submission) -> None:
    document = make_submission()
    document["tasks"][TASK]["dataset"] = {"id": "x" * 5000, "sha256": "0"}
    message = _reject(document, "$.tasks.hopper-gravity-0.5.dataset")
    assert len(message) < 400


def test_read_submission_file_reports_the_path(tmp_path: Path) -> None:
    from leaderboard.submission import read_submission_file

    path = tmp_path / "broken.json"
    path.write_text("{")
    with pytest.raises(SubmissionError, match=f"{path}: not valid JSON"):
        read_submission_file(path)
