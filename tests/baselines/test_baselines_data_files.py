"""The dataset loader on corrupt and odd .npz files: every bad file is an OffdynError (one line,
`error:` with exit code 2 in the CLI), never a traceback; every file it accepts is a usable dataset.
Files come from hypothesis: random bytes, truncated and bit-flipped real datasets, and archives of
arrays with random names, dtypes, shapes and values."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from typer.testing import CliRunner

from baselines.data import ARRAYS, TransitionDataset, load_dataset
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import get_task

PENDULUM = "invertedpendulum-kinematic-slider-hard"  # observations (4,), actions (1,) in [-3, 3]
TASK = get_task(PENDULUM)
SETTINGS = settings(max_examples=int(__import__("os").environ.get("NPZ_EXAMPLES", 60)), deadline=None, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _valid_arrays(n: int = 6) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(n)
    return {"observations": rng.normal(size=(n, 4)), "actions": rng.uniform(-3, 3, size=(n, 1)).astype(np.float32),
            "rewards": rng.normal(size=n), "next_observations": rng.normal(size=(n, 4)),
            "terminations": np.arange(n) == n - 1, "truncations": np.zeros(n, bool)}


def _npz_bytes(arrays: dict[str, np.ndarray], compressed: bool = False) -> bytes:
    buffer = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buffer, **arrays)
    return buffer.getvalue()


def _load_or_error(tmp_path, content: bytes) -> TransitionDataset | None:
    """Load ``content`` as an .npz dataset: the dataset, or None after checking the error is ours
    and one line."""
    path = tmp_path / "data.npz"
    path.write_bytes(content)
    try:
        data, provenance = load_dataset(str(path), TASK)
    except OffdynError as error:
        assert "\n" not in str(error) and str(error)
        return None
    assert provenance["size"] == len(data) > 0
    for name in ARRAYS:
        assert len(getattr(data, name)) == len(data)
    for name in ("observations", "actions", "rewards", "next_observations"):
        assert np.isfinite(getattr(data, name)).all()
    batch = data.to_batch(TASK.make("target").action_space)
    assert batch.actions.abs().max() <= 1.0 + 1e-5
    return data


@SETTINGS
@given(content=st.binary(max_size=2000))
def test_random_bytes_are_refused(tmp_path, content):
    assert _load_or_error(tmp_path, content) is None


@SETTINGS
@given(compressed=st.booleans(), cut=st.floats(0.0, 1.0, exclude_max=True))
def test_a_truncated_dataset_is_refused(tmp_path, compressed, cut):
    content = _npz_bytes(_valid_arrays(), compressed)
    assert _load_or_error(tmp_path, content[: int(cut * len(content))]) is None


@SETTINGS
@given(compressed=st.booleans(), where=st.floats(0.0, 1.0, exclude_max=True), bit=st.integers(0, 7))
def test_a_flipped_bit_is_refused_or_loads_a_usable_dataset(tmp_path, compressed, where, bit):
    content = bytearray(_npz_bytes(_valid_arrays(), compressed))
    content[int(where * len(content))] ^= 1 << bit
    _load_or_error(tmp_path, bytes(content))  # a flip in e.g. a float's low bits is valid data


DTYPES = st.sampled_from([np.float64, np.float32, np.int64, np.uint8, np.bool_, np.complex64, np.str_, np.void])


@st.composite
def odd_archives(draw) -> dict[str, np.ndarray]:
    """Valid arrays with some replaced by arrays of another dtype, shape or length, dropped, or
    joined by extra ones; values may be NaN or huge."""
    arrays = _valid_arrays(draw(st.integers(1, 5)))
    for name in draw(st.lists(st.sampled_from(ARRAYS), unique=True, max_size=3)):
        action = draw(st.sampled_from(["replace", "drop", "nan"]))
        if action == "drop":
            del arrays[name]
        elif action == "nan":
            arrays[name] = arrays[name].astype(np.float64)
            arrays[name].flat[draw(st.integers(0, arrays[name].size - 1))] = draw(st.sampled_from([np.nan, np.inf]))
        else:
            dtype = draw(DTYPES)
            shape = draw(hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5))
            if dtype in (np.str_, np.void):
                arrays[name] = np.zeros(shape, dtype="U3" if dtype is np.str_ else "V2")
            else:
                arrays[name] = draw(hnp.arrays(dtype, shape))
    if draw(st.booleans()):
        arrays["extra"] = np.zeros(2)
    return arrays


@SETTINGS
@given(arrays=odd_archives())
def test_odd_arrays_are_refused_or_load_a_usable_dataset(tmp_path, arrays):
    _load_or_error(tmp_path, _npz_bytes(arrays))


def test_object_arrays_and_foreign_files_are_named(tmp_path):
    objects = _valid_arrays() | {"rewards": np.array([1, "a", None, 2, 3, 4], dtype=object)}
    cases = {
        b"": "is empty",
        _npz_bytes(_valid_arrays())[:100]: "is damaged or truncated",
        _npz_bytes(objects): "holds a Python object array, which is not loaded",
        b"\x93NUMPY" + _npz_bytes(_valid_arrays())[6:]: "cannot be read",
    }
    single = io.BytesIO()
    np.save(single, np.zeros(3))
    cases[single.getvalue()] = "holds a single array, not an .npz archive"
    for content, message in cases.items():
        (tmp_path / "d.npz").write_bytes(content)
        with pytest.raises(OffdynError, match=message):
            load_dataset(str(tmp_path / "d.npz"), TASK)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("notes.txt", "not a dataset")
    (tmp_path / "d.npz").write_bytes(buffer.getvalue())
    with pytest.raises(OffdynError, match="lacks arrays"):
        load_dataset(str(tmp_path / "d.npz"), TASK)
    (tmp_path / "folder.npz").mkdir()
    with pytest.raises(OffdynError, match="is not a file"):
        load_dataset(str(tmp_path / "folder.npz"), TASK)


@pytest.mark.parametrize("content, message", [
    (b"", "is empty"),
    (b"PK\x03\x04truncated", "is damaged or truncated"),
    (_npz_bytes(_valid_arrays() | {"rewards": np.array([None] * 6, dtype=object)}), "object array"),
])
def test_the_cli_shows_one_error_line_and_exits_2(tmp_path, content, message):
    (tmp_path / "d.npz").write_bytes(content)
    done = CliRunner().invoke(app, ["train", "cql", "--task", PENDULUM, "--steps", "10", "--dataset",
                                    str(tmp_path / "d.npz"), "--out", str(tmp_path / "run")])
    assert done.exit_code == 2, done.output
    assert done.output.startswith("error: dataset ") and message in done.output
    assert len(done.output.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()
