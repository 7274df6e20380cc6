"""Manifest entries from any JSON a remote could serve: an entry or a one-line ManifestError /
DownloadError naming what was expected, never another exception (fuzzed with hypothesis)."""

from __future__ import annotations

import copy
import json
from typing import Any

import hypothesis
import hypothesis.strategies as st
import pytest

from offdyn_bench.datasets.download import DownloadError, parse_entry
from offdyn_bench.datasets.manifest import MANIFEST_FORMAT, ArchiveRecord, Entry, Manifest, ManifestError
from offdyn_bench.datasets.recipes import default_recipe

DATASET_ID = "offdyn/hopper-gravity-0p5/random-v0"

JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=12,
)


def valid_entry() -> dict[str, Any]:
    files = {"data/main_data.hdf5": "a" * 64, "data/metadata.json": "b" * 64}
    return Entry(recipe=default_recipe("hopper-gravity-0.5", "random"), files=files,
                 file_sizes={"data/main_data.hdf5": 1000, "data/metadata.json": 10},
                 total_steps=20_000, total_episodes=3, reference_scores={"random": {"value": 1.0}},
                 built_with={"mujoco": "3.17.0"},
                 archive=ArchiveRecord(f"{DATASET_ID}.tar.gz", "c" * 64, 1234)).to_dict()


# Every place in an entry a value can sit: the fuzzer puts arbitrary JSON at one of them.
FIELD_PATHS = [(), ("recipe",), ("files",), ("file_sizes",), ("archive",), ("total_steps",), ("total_episodes",),
               ("reference_scores",), ("built_with",), ("recipe", "behaviour"), ("archive", "size"),
               ("archive", "sha256"), ("archive", "name"), ("files", "data/metadata.json"),
               ("file_sizes", "data/metadata.json"), ("unknown-key",)] + \
              [("recipe", key) for key in valid_entry()["recipe"]] + \
              [("recipe", "behaviour", key) for key in valid_entry()["recipe"]["behaviour"]]


def with_value_at(data: dict[str, Any], path: tuple[str, ...], value: Any) -> Any:
    if not path:
        return value
    changed = copy.deepcopy(data)
    holder = changed
    for key in path[:-1]:
        holder = holder[key]
    holder[path[-1]] = value
    return changed


def test_a_valid_entry_round_trips() -> None:
    entry = Entry.from_dict(valid_entry())
    assert Entry.from_dict(entry.to_dict()) == entry
    assert entry.file_sizes == {"data/main_data.hdf5": 1000, "data/metadata.json": 10}


@pytest.mark.parametrize("value, expected", [
    ([1, 2, 3], "must be a JSON object with keys .*got a list"),
    ("entry", "must be a JSON object .*got a string"),
    (None, "must be a JSON object .*got null"),
    ({"recipe": [1]}, "a recipe must be a JSON object, got a list"),
    ({"recipe": {}}, "unknown fields|missing field 'dataset_id'"),
])
def test_non_objects_name_what_was_expected(value: Any, expected: str) -> None:
    with pytest.raises(ManifestError, match=expected):
        Entry.from_dict(value, where="http://remote/x.json")


@pytest.mark.parametrize("path, value, expected", [
    (("files",), ["data/x"], "'files' must map file names to sha256"),
    (("files", "data/metadata.json"), "xyz", "must be 64 lowercase hex digits"),
    (("archive", "size"), True, "'archive size' must be a non-negative integer"),
    (("archive", "size"), -1, "'archive size' must be a non-negative integer"),
    (("recipe", "num_transitions"), "20000", "field 'num_transitions' must be an integer, got a string"),
    (("recipe", "behaviour", "action_noise_std"), None, "'action_noise_std' must be an integer or a number"),
    (("file_sizes", "data/metadata.json"), 1.5, "non-negative integer"),
])
def test_mistyped_fields_are_named(path: tuple[str, ...], value: Any, expected: str) -> None:
    with pytest.raises(ManifestError, match=expected):
        Entry.from_dict(with_value_at(valid_entry(), path, value))


@pytest.mark.parametrize("name", ["../escape", "/etc/passwd", "data/../../x", "data//x", "a\\b", ""])
def test_file_names_that_leave_the_dataset_folder_are_refused(name: str) -> None:
    data = valid_entry()
    data["files"] = {name: "a" * 64}
    data["file_sizes"] = {name: 1}
    with pytest.raises(ManifestError, match="not a relative path inside the dataset folder"):
        Entry.from_dict(data)


def test_sizes_must_name_the_same_files_as_hashes() -> None:
    data = valid_entry()
    del data["file_sizes"]["data/metadata.json"]
    with pytest.raises(ManifestError, match="'file_sizes' must name exactly the files of 'files'"):
        Entry.from_dict(data)


@hypothesis.settings(max_examples=300, deadline=None)
@hypothesis.given(value=JSON_VALUES)
def test_fuzz_any_json_value_as_an_entry(value: Any) -> None:
    try:
        entry = Entry.from_dict(value, where="fuzz")
    except ManifestError as error:
        assert "\n" not in str(error) and str(error).startswith("fuzz")
    else:
        assert Entry.from_dict(entry.to_dict()) == entry


@hypothesis.settings(max_examples=500, deadline=None)
@hypothesis.given(path=st.sampled_from(FIELD_PATHS), value=JSON_VALUES)
def test_fuzz_any_json_value_in_any_field(path: tuple[str, ...], value: Any) -> None:
    data = with_value_at(valid_entry(), path, value)
    try:
        entry = Entry.from_dict(data, where="fuzz")
    except ManifestError as error:
        assert "\n" not in str(error)
    else:
        assert Entry.from_dict(entry.to_dict()) == entry


@hypothesis.settings(max_examples=300, deadline=None)
@hypothesis.given(body=st.binary(max_size=64) | JSON_VALUES.map(lambda v: json.dumps(v).encode()))
def test_fuzz_remote_entry_bytes_give_only_download_errors(body: bytes) -> None:
    with pytest.raises(DownloadError):  # none of these is a built entry for DATASET_ID
        parse_entry(body, DATASET_ID, "http://remote/entry.json")


@pytest.mark.parametrize("body", [b"[" * 100_000, b"9" * 10_000, b"\xff\xfe", b'{"recipe": NaN}'])
def test_pathological_json_is_a_download_error(body: bytes) -> None:
    with pytest.raises(DownloadError, match="entry.json"):
        parse_entry(body, DATASET_ID, "http://remote/entry.json")


def test_a_valid_remote_entry_parses_and_must_name_the_requested_id() -> None:
    body = json.dumps(valid_entry()).encode()
    assert parse_entry(body, DATASET_ID, "remote").dataset_id == DATASET_ID
    with pytest.raises(DownloadError, match="describes 'offdyn/hopper-gravity-0p5/random-v0', not"):
        parse_entry(body, "offdyn/hopper-gravity-0p5/random-v1", "remote")


@hypothesis.settings(max_examples=200, deadline=None)
@hypothesis.given(datasets=JSON_VALUES)
def test_fuzz_manifest_datasets_field(datasets: Any) -> None:
    try:
        Manifest.from_dict({"format": MANIFEST_FORMAT, "datasets": datasets}, where="fuzz")
    except ManifestError as error:
        assert "\n" not in str(error)


@hypothesis.settings(max_examples=200, deadline=None)
@hypothesis.given(data=JSON_VALUES | st.fixed_dictionaries({"format": st.just(MANIFEST_FORMAT)}, optional={
    "datasets": st.dictionaries(st.text(max_size=8), JSON_VALUES | st.just(valid_entry()), max_size=3)}))
def test_fuzz_whole_manifests(data: Any) -> None:
    try:
        manifest = Manifest.from_dict(data, where="fuzz")
    except ManifestError as error:
        assert "\n" not in str(error)
    else:
        assert Manifest.from_dict(manifest.to_dict()) == manifest


@hypothesis.settings(max_examples=200, deadline=None)
@hypothesis.given(values=st.dictionaries(st.sampled_from(["OFFDYN_DOWNLOAD_DEADLINE", "OFFDYN_DOWNLOAD_MIN_RATE",
                                                          "OFFDYN_DOWNLOAD_RATE_WINDOW"]),
                                         st.text(max_size=12) | st.floats().map(str)))
def test_fuzz_transfer_limits_from_the_environment(values: dict[str, str]) -> None:
    from offdyn_bench.datasets.transfer import TransferError, TransferLimits

    try:
        limits = TransferLimits.from_environment(values)
    except TransferError as error:
        assert "\n" not in str(error) and any(name in str(error) for name in values)
    else:
        assert limits.deadline_s > 0 and limits.rate_window_s > 0 and limits.min_rate_bytes_per_s >= 0
