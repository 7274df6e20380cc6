"""Loading measured data: whatever bytes an .npz file holds, the loader returns valid transitions
or raises the suite's error with one line that says what to fix; the CLI shows it as ``error:``
with exit code 2, before any diagnosis runs."""

from __future__ import annotations

import io
import json
import tracemalloc
import zipfile

import hypothesis
import hypothesis.extra.numpy as hnp
import hypothesis.strategies as st
import numpy as np
import pytest
from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.diagnose import DiagnosisInputError, DiagnosisSettings, Transitions, diagnose, load_npz
from offdyn_bench.diagnose.data import NPZ_REQUIRED
from offdyn_bench.errors import OffdynError

runner = CliRunner()
ROWS = 40


def _valid_arrays(rows: int = ROWS) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    ends = np.zeros(rows, dtype=bool)
    ends[: rows][rows // 2 - 1 : rows // 2] = True
    return {"observations": rng.normal(size=(rows, 11)), "actions": rng.uniform(-1, 1, (rows, 3)),
            "next_observations": rng.normal(size=(rows, 11)), "terminations": ends,
            "truncations": np.zeros(rows, dtype=bool), "qpos": rng.normal(size=(rows, 6)),
            "qvel": rng.normal(size=(rows, 6))}


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _diagnose_cli(path, *extra: str):
    return runner.invoke(app, ["diagnose", "--env", "Hopper-v5", "--data", str(path), *extra])


def _assert_one_line_error(result, fragment: str) -> None:
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit)
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert fragment in lines[0]


# --- broken files on the command line --------------------------------------------------------

def test_empty_file(tmp_path):
    path = tmp_path / "empty.npz"
    path.write_bytes(b"")
    _assert_one_line_error(_diagnose_cli(path), "is empty (0 bytes); expected an .npz archive")


def test_truncated_file(tmp_path):
    whole = _npz_bytes(_valid_arrays())
    path = tmp_path / "truncated.npz"
    path.write_bytes(whole[: len(whole) // 2])
    _assert_one_line_error(_diagnose_cli(path), "cannot read")


def test_object_array_is_refused_without_unpickling(tmp_path):
    path = tmp_path / "objects.npz"
    np.savez(path, **{**_valid_arrays(), "actions": np.array([{"a": 1}] * ROWS, dtype=object)})
    _assert_one_line_error(_diagnose_cli(path), "actions in")
    assert "holds Python objects (dtype object)" in _diagnose_cli(path).output


def test_non_boolean_terminations_are_refused(tmp_path):
    path = tmp_path / "half.npz"
    np.savez(path, **{**_valid_arrays(), "terminations": np.full(ROWS, 0.5)})
    _assert_one_line_error(_diagnose_cli(path), "terminations must be booleans (True/False or 0/1), got 0.5 in row 0")


def test_zero_one_integers_are_booleans():
    arrays = _valid_arrays()
    data = Transitions(**{**arrays, "terminations": arrays["terminations"].astype(int),
                          "truncations": np.zeros(ROWS, dtype=np.uint8)})
    np.testing.assert_array_equal(data.terminations, arrays["terminations"])
    assert data.terminations.dtype == bool
    with pytest.raises(DiagnosisInputError, match="truncations must be booleans .* got 2 in row 3"):
        Transitions(**{**arrays, "truncations": np.where(np.arange(ROWS) == 3, 2, 0)})


def test_text_is_not_read_as_numbers(tmp_path):
    path = tmp_path / "text.npz"
    np.savez(path, **{**_valid_arrays(), "actions": np.full((ROWS, 3), "0.5")})
    with pytest.raises(DiagnosisInputError, match="actions must hold real numbers, got an array of dtype <U3"):
        load_npz(path)


def test_a_header_that_claims_a_huge_array_allocates_nothing(tmp_path):
    """A corrupt header declaring 10^12 rows is refused from the sizes alone (numpy's own loader
    would allocate the declared array before finding the data missing)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, array in _valid_arrays().items():
            member = io.BytesIO()
            np.lib.format.write_array(member, array)
            raw = member.getvalue()
            if name == "observations":
                raw = raw.replace(f"({ROWS}, 11)".encode(), b"(10**12, 11)".replace(b"10**12", b"1" + b"0" * 12), 1)
            archive.writestr(f"{name}.npy", raw)
    path = tmp_path / "huge.npz"
    path.write_bytes(buffer.getvalue())
    tracemalloc.start()
    try:
        with pytest.raises(DiagnosisInputError, match=r"observations in .* is cut short: its header declares shape \(1000000000000, 11\)"):
            load_npz(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 50 * 2**20


# --- the horizon and the output paths ---------------------------------------------------------

@pytest.mark.parametrize("horizon", ["0", "1001", "100000000000000000000"])
def test_horizon_out_of_range_fails_before_anything_runs(tmp_path, monkeypatch, horizon):
    monkeypatch.setattr("offdyn_bench.diagnose.loop.diagnose", _must_not_run)
    path = tmp_path / "data.npz"
    np.savez(path, **_valid_arrays())
    _assert_one_line_error(_diagnose_cli(path, "--horizon", horizon),
                           f"invalid horizon={horizon}; expected an integer in [1, 1000]")


def _must_not_run(*args, **kwargs):
    raise AssertionError("the diagnosis ran although its output cannot be written")


@pytest.mark.parametrize("option", ["--out", "--json"])
def test_unwritable_output_fails_before_the_diagnosis_runs(tmp_path, monkeypatch, option):
    monkeypatch.setattr("offdyn_bench.diagnose.loop.diagnose", _must_not_run)
    data = tmp_path / "data.npz"
    np.savez(data, **_valid_arrays())
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    result = _diagnose_cli(data, option, str(blocker / "sub" / "result.json"))
    _assert_one_line_error(result, f"{option}: {blocker / 'sub' / 'result.json'} cannot be created: "
                                   f"{blocker} is not a folder; nothing was run")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "data.npz"]


def test_out_that_is_a_file_and_json_that_is_a_folder(tmp_path, monkeypatch):
    monkeypatch.setattr("offdyn_bench.diagnose.loop.diagnose", _must_not_run)
    data = tmp_path / "data.npz"
    np.savez(data, **_valid_arrays())
    _assert_one_line_error(_diagnose_cli(data, "--out", str(data)), "exists and is not a folder")
    _assert_one_line_error(_diagnose_cli(data, "--json", str(tmp_path)), "is a folder; expected a file path")


def test_settings_are_validated_in_the_api_too():
    with pytest.raises(OffdynError, match=r"diagnosis settings: invalid horizon=0; expected an integer in \[1, 1000\]"):
        DiagnosisSettings(horizon=0)
    with pytest.raises(OffdynError, match=r"invalid heldout_fraction=1.0; expected a number in \[0.05, 0.95\]"):
        DiagnosisSettings(heldout_fraction=1.0)


def test_an_h_step_error_that_cannot_be_measured_is_null_not_zero(tmp_path):
    """Episodes of 20 steps hold no window of 50: the H-step error is not measured."""
    from diagnose_target_data import record

    arrays = record([], 400, seed=21)
    ends = np.zeros(len(arrays["actions"]), dtype=bool)
    ends[19::20] = True  # cut every episode at 20 steps
    arrays = {**arrays, "truncations": ends & ~arrays["terminations"]}
    result = diagnose("Hopper-v5", Transitions(**arrays),
                      DiagnosisSettings(horizon=50, max_effects=0, screen_rows=300, fit_rows=500))
    assert result.error_before.horizon_nrmse is None
    assert result.error_before.heldout_horizon_nrmse is None
    assert result.error_before.heldout_one_step_nrmse < 1e-3  # measured, and the model is exact
    payload = json.loads(json.dumps(result.to_json()))
    assert payload["error_before"]["horizon_nrmse"] is None
    assert payload["error_after"]["heldout_horizon_nrmse"] is None
    assert any("H-step error is not measured (reported as null)" in note for note in result.notes)


# --- property tests on generated files ---------------------------------------------------------

_DTYPES = st.sampled_from([np.float64, np.float32, np.int64, np.uint8, np.bool_, np.complex128, "U4", "S3"])


@st.composite
def _mutated_arrays(draw: st.DrawFn) -> dict[str, np.ndarray]:
    """The contract's arrays with some replaced by arrays of any shape, dtype and values, some
    left out and some extra ones added."""
    arrays = _valid_arrays(draw(st.integers(min_value=0, max_value=ROWS)))
    for name in draw(st.lists(st.sampled_from(sorted(arrays)), unique=True, max_size=3)):
        shape = draw(hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=6))
        arrays[name] = draw(hnp.arrays(draw(_DTYPES), shape))
    for name in draw(st.lists(st.sampled_from(sorted(arrays)), unique=True, max_size=2)):
        del arrays[name]
    if draw(st.booleans()):
        arrays["extra"] = np.array([object()], dtype=object)  # never read: only the contract's arrays are
    return arrays


def _load_or_error(path) -> Transitions | None:
    try:
        return load_npz(path)
    except OffdynError as error:
        assert "\n" not in str(error)
        return None


@hypothesis.settings(max_examples=150, deadline=None)
@hypothesis.given(arrays=_mutated_arrays())
def test_any_arrays_load_as_valid_transitions_or_a_clear_error(tmp_path_factory, arrays):
    path = tmp_path_factory.mktemp("npz") / "data.npz"
    np.savez(path, **arrays)
    data = _load_or_error(path)
    if data is not None:
        assert set(NPZ_REQUIRED) <= set(arrays)
        assert data.terminations.dtype == bool and data.truncations.dtype == bool
        assert data.observations.ndim == 2 and data.observations.dtype == float
        assert len(data.observations) == len(data.actions) == len(data.terminations) > 0
        assert np.isfinite(data.observations).all() and np.isfinite(data.actions).all()


@hypothesis.settings(max_examples=150, deadline=None)
@hypothesis.given(cut=st.floats(min_value=0.0, max_value=1.0), flips=st.lists(
    st.tuples(st.floats(min_value=0.0, max_value=1.0, exclude_max=True), st.integers(1, 255)), max_size=4))
def test_truncated_or_corrupted_bytes_load_or_give_a_clear_error(tmp_path_factory, cut, flips):
    raw = bytearray(_npz_bytes(_valid_arrays()))
    for where, xor in flips:
        raw[int(where * len(raw))] ^= xor
    path = tmp_path_factory.mktemp("npz") / "data.npz"
    path.write_bytes(bytes(raw[: int(cut * len(raw))]) if cut < 1.0 else bytes(raw))
    _load_or_error(path)
