"""Dataset builds run on the manifest's OpenBLAS kernel, whatever kernel numpy loaded.

OpenBLAS fixes its kernel when numpy loads it, so every check of another kernel starts a fresh
Python process with ``OPENBLAS_CORETYPE`` set.
"""

from __future__ import annotations

import json
import os
import pathlib
import platform
import subprocess
import sys

import pytest

from offdyn_bench.datasets import BuildMismatchError, build_dataset, read_manifest
from offdyn_bench.datasets.kernel import (
    DATASET_BLAS_KERNEL,
    KERNEL_ENV,
    BlasInfo,
    KernelError,
    call_on_kernel,
    cpu_flags,
    numpy_blas,
    plan_kernel,
    requested_kernel,
)
from offdyn_bench.datasets.manifest import Entry

X86 = frozenset({"sse4_2", "avx", "avx2", "fma"})
AVX512 = X86 | {"avx512f", "avx512bw", "avx512vl", "avx512dq"}
ON_OPENBLAS_X86 = (numpy_blas().library == "openblas" and platform.machine() == "x86_64"
                   and {"sse4_2", "avx", "avx2", "fma"} <= cpu_flags())
needs_openblas_x86 = pytest.mark.skipif(not ON_OPENBLAS_X86, reason="needs numpy on OpenBLAS on an x86-64 CPU "
                                                                    "with AVX2 and FMA")
needs_avx512 = pytest.mark.skipif(not (ON_OPENBLAS_X86 and AVX512 <= cpu_flags()),
                                  reason="needs an AVX-512 CPU, where OpenBLAS runs its SkylakeX kernel")

# A few hundred Ant steps are enough for the SkylakeX and Haswell kernels' last bits to change the trajectory.
_BUILD_SCRIPT = """
import dataclasses, json, pathlib, sys, tempfile
from offdyn_bench.datasets import build_dataset, default_recipe
from offdyn_bench.datasets.kernel import numpy_blas
recipe = dataclasses.replace(default_recipe("ant-friction-5.0", "source-policy", num_transitions=1000),
                             reference_episodes=1)
result = build_dataset(recipe, root=pathlib.Path(tempfile.mkdtemp()), install=False)
print(json.dumps({"files": result.entry.files, "built_with": result.entry.built_with,
                  "process_kernel": numpy_blas().kernel}))
"""


def _fresh_process(script: str, **environment: str) -> dict:
    env = {key: value for key, value in os.environ.items() if key not in ("OPENBLAS_CORETYPE", KERNEL_ENV)}
    done = subprocess.run([sys.executable, "-c", script], env=env | environment, capture_output=True, text=True,
                          timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize(("blas", "wanted", "machine", "flags", "where", "words"), [
    (BlasInfo("openblas", "Haswell"), "Haswell", "x86_64", X86, "here", "already"),
    (BlasInfo("openblas", "SkylakeX"), "Haswell", "x86_64", AVX512, "child", "SkylakeX"),
    (BlasInfo("openblas", "Zen"), "Haswell", "x86_64", X86, "child", "Zen"),
    (BlasInfo("openblas", "NeoverseN1"), "Haswell", "aarch64", frozenset(), "here", "aarch64"),
    (BlasInfo("openblas", "Sandybridge"), "Haswell", "x86_64", frozenset({"sse4_2", "avx"}), "here", "avx2, fma"),
    (BlasInfo("mkl", None), "Haswell", "x86_64", X86, "here", "not OpenBLAS"),
    (BlasInfo(None, None), "Haswell", "x86_64", X86, "here", "no BLAS that threadpoolctl recognises"),
    (BlasInfo("openblas", "SkylakeX"), "native", "x86_64", AVX512, "here", "native"),
])
def test_plan_says_where_a_build_runs_and_why(blas: BlasInfo, wanted: str, machine: str, flags: frozenset[str],
                                              where: str, words: str) -> None:
    plan = plan_kernel(blas, wanted, machine=machine, flags=flags)
    assert plan.where == where
    assert words in plan.reason
    if where == "child":
        assert plan.kernel == wanted


def test_requested_kernel_defaults_to_the_manifests_and_rejects_unknown_names() -> None:
    assert requested_kernel({}) == DATASET_BLAS_KERNEL == "Haswell"
    assert requested_kernel({KERNEL_ENV: " "}) == "Haswell"
    assert requested_kernel({KERNEL_ENV: "native"}) == "native"
    assert requested_kernel({KERNEL_ENV: "SkylakeX"}) == "SkylakeX"
    with pytest.raises(KernelError, match=r"OFFDYN_BLAS_KERNEL='skylake' is not a kernel .*'SkylakeX'.*'native'"):
        requested_kernel({KERNEL_ENV: "skylake"})


def _another_kernel() -> str:
    return "Nehalem" if numpy_blas().kernel != "Nehalem" else "Sandybridge"


@needs_openblas_x86
def test_a_build_on_another_kernel_runs_in_a_child_reports_progress_and_installs(
        tiny_recipe, monkeypatch: pytest.MonkeyPatch, tmp_path: pathlib.Path) -> None:
    kernel = _another_kernel()
    monkeypatch.setenv(KERNEL_ENV, kernel)
    steps: list[int] = []
    result = build_dataset(tiny_recipe(task="ant-friction-5.0", quality="source-policy", transitions=300),
                           root=tmp_path / "root", on_progress=steps.append)
    assert sum(steps) == 300 == result.entry.total_steps
    assert result.entry.built_with is not None and result.entry.built_with["blas_kernel"] == kernel
    assert result.installed_at is not None and (result.installed_at / "data" / "main_data.hdf5").is_file()
    assert numpy_blas().kernel != kernel  # this process kept its own


@needs_openblas_x86
def test_a_child_build_equals_a_process_started_on_that_kernel() -> None:
    kernel = _another_kernel()
    in_child = _fresh_process(_BUILD_SCRIPT, **{KERNEL_ENV: kernel})
    started_on_it = _fresh_process(_BUILD_SCRIPT, OPENBLAS_CORETYPE=kernel, **{KERNEL_ENV: kernel})
    assert in_child["process_kernel"] != kernel and started_on_it["process_kernel"] == kernel
    assert in_child["files"] == started_on_it["files"]
    assert in_child["built_with"]["blas_kernel"] == started_on_it["built_with"]["blas_kernel"] == kernel


@needs_avx512
def test_ant_bytes_do_not_depend_on_the_kernel_numpy_loaded() -> None:
    on_skylake = _fresh_process(_BUILD_SCRIPT, OPENBLAS_CORETYPE="SkylakeX")
    on_haswell = _fresh_process(_BUILD_SCRIPT, OPENBLAS_CORETYPE="Haswell")
    unpinned = _fresh_process(_BUILD_SCRIPT, OPENBLAS_CORETYPE="SkylakeX", **{KERNEL_ENV: "native"})
    assert on_skylake["process_kernel"] == "SkylakeX" and on_haswell["process_kernel"] == "Haswell"
    assert on_skylake["files"] == on_haswell["files"]
    assert on_skylake["built_with"]["blas_kernel"] == "Haswell"
    # Without the pin the kernels give other bytes: the equality above is the pin's doing.
    assert unpinned["files"]["data/main_data.hdf5"] != on_haswell["files"]["data/main_data.hdf5"]
    assert unpinned["built_with"]["blas_kernel"] == "SkylakeX"


@needs_avx512
def test_a_manifest_ant_dataset_rebuilds_to_its_recorded_bytes_from_an_avx512_process() -> None:
    dataset = "offdyn/ant-friction-5p0/source-policy-v0"
    script = f"""
import json, pathlib, tempfile
from offdyn_bench.datasets import build_dataset, read_manifest
from offdyn_bench.datasets.kernel import numpy_blas
entry = read_manifest().entries[{dataset!r}]
result = build_dataset(entry.recipe, root=pathlib.Path(tempfile.mkdtemp()), recorded=entry, install=False)
print(json.dumps({{"files": result.entry.files, "process_kernel": numpy_blas().kernel}}))
"""
    rebuilt = _fresh_process(script, OPENBLAS_CORETYPE="SkylakeX")
    assert rebuilt["process_kernel"] == "SkylakeX"
    assert rebuilt["files"] == read_manifest().entries[dataset].files


@needs_openblas_x86
def test_a_mismatch_in_the_child_is_raised_here_naming_both_kernels(tiny_recipe,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    kernel = _another_kernel()
    monkeypatch.setenv(KERNEL_ENV, kernel)
    recipe = tiny_recipe()
    wrong = Entry(recipe=recipe, files={"data/main_data.hdf5": "0" * 64, "data/metadata.json": "0" * 64},
                  built_with={"numpy": "2.4.6"})
    with pytest.raises(BuildMismatchError, match=rf"built with .*'blas_kernel': 'Haswell'.*this build uses "
                                                 rf".*'blas_kernel': '{kernel}'.*child process on {kernel}"):
        build_dataset(recipe, recorded=wrong)


@needs_openblas_x86
def test_an_unexpected_failure_in_the_child_comes_back_with_its_traceback() -> None:
    with pytest.raises(KernelError, match=r"(?s)child process on the Nehalem kernel.*TypeError.*on_progress"):
        call_on_kernel(json.loads, {"s": "{}"}, "Nehalem")


def raise_unknown_task(name: str, on_progress: object = None) -> None:
    """Runs in the child: a bad-input error whose constructor takes more than its message."""
    from offdyn_bench.errors import UnknownNameError

    raise UnknownNameError("task", name, ["hopper-gravity-0.5", "hopper-friction-5.0"])


@needs_openblas_x86
def test_a_bad_input_error_in_the_child_comes_back_as_its_message(monkeypatch: pytest.MonkeyPatch) -> None:
    here = str(pathlib.Path(__file__).resolve().parent)  # where the child finds this module
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [here, os.environ.get("PYTHONPATH")])))
    with pytest.raises(KernelError) as raised:
        call_on_kernel(raise_unknown_task, {"name": "hoper-gravity-0.5"}, "Nehalem")
    assert "unknown task 'hoper-gravity-0.5'; closest valid names: 'hopper-gravity-0.5'" in str(raised.value)
    assert "Traceback" not in str(raised.value)


def exit_at_once(code: int, on_progress: object = None) -> None:
    """Runs in the child: it ends without sending a result."""
    os._exit(code)


@needs_openblas_x86
def test_a_child_that_ends_without_a_result_is_an_error_with_its_exit_code(monkeypatch: pytest.MonkeyPatch) -> None:
    here = str(pathlib.Path(__file__).resolve().parent)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [here, os.environ.get("PYTHONPATH")])))
    with pytest.raises(KernelError, match=r"child process on the Nehalem kernel ended \(exit code 3\) without a "
                                          r"result"):
        call_on_kernel(exit_at_once, {"code": 3}, "Nehalem")
