"""``scripts/gpu_reference_sweep.sh``: prepare a GPU lease's reference sweep here, run it there, and
bring the finished runs back. Checked on the CPU (``DEVICE=cpu``, no wheels): the same spec, sweep
and archive as on the device, where it ran on an H200 (README, "Devices")."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "gpu_reference_sweep.sh"


def _script(*args: str, tmp_path: Path, **env: str) -> subprocess.CompletedProcess:
    # No remote: --prepare rebuilds each dataset from its recipe into this test's Minari root.
    environment = {k: v for k, v in os.environ.items() if k != "OFFDYN_REMOTE"} | {"DEVICE_SWEEP_DIR": str(tmp_path / "device-sweep"),
                                "SWEEP_ROOT": str(tmp_path / "sweep-root"), "SKIP_WHEELS": "1",
                                # the checks here run the project's interpreter as python3
                                "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"} | env
    return subprocess.run(["bash", str(SCRIPT), *args], cwd=REPO, env=environment, capture_output=True, text=True,
                          timeout=900)


@pytest.mark.parametrize(("args", "message"), [
    (["--prepare", "cql"], "usage: "),
    (["--prepare", "cql", "ten", "hopper-gravity-0.5"], "error: budget ten: expected lite or a number of steps"),
    (["--prepare", "cql", "lite", "hopper-gravity-9"], "error: unknown task 'hopper-gravity-9'; closest valid names"),
    (["--prepare", "cq1", "lite", "hopper-gravity-0.5"], "methods: unknown algorithm 'cq1'; closest valid names: 'cql'"),
    (["--prepare", "cql", "0", "hopper-gravity-0.5"], "steps: got 0; expected an integer >= 1"),
    # RL on target's lite records of this task are in leaderboard/reference-runs: no lease time for them
    (["--prepare", "sac-target", "lite", "hopper-friction-0.5", "hopper-gravity-0.5"],
     "error: published already (leaderboard/reference-runs/lite), leave out their tasks: "
     "sac-target/hopper-friction-0.5/seeds-0-4 sac-target/hopper-gravity-0.5/seeds-0-4"),
])
def test_a_bad_prepare_says_what_was_wrong_and_leaves_no_folder(args, message, tmp_path):
    result = _script(*args, tmp_path=tmp_path)
    assert result.returncode != 0 and message in result.stderr
    assert not any(tmp_path.glob("device-sweep*"))


def test_running_without_a_prepared_folder_is_refused(tmp_path):
    result = _script(tmp_path=tmp_path, OUT=str(tmp_path / "out"))
    assert result.returncode == 2 and "run --prepare here first" in result.stderr


def test_more_lite_cql_tasks_than_a_lease_finishes_are_prepared_with_a_note(tmp_path):
    tasks = ["hopper-gravity-0.5", "hopper-friction-0.5", "walker2d-gravity-2.0"]
    prepared = _script("--prepare", "cql", "lite", *tasks, tmp_path=tmp_path, DEVICE="cpu")
    assert prepared.returncode == 0, prepared.stderr
    assert "note: 3 lite CQL tasks: the measured lease would finish about two" in prepared.stderr
    assert f"tasks: [{', '.join(tasks)}]" in (tmp_path / "device-sweep" / "spec.yaml").read_text()
    [travels] = [line for line in prepared.stdout.splitlines() if line.startswith("travels: ")]
    assert f", {tmp_path / 'device-sweep'} " in travels  # the folder to carry, not the one it was built in


@pytest.mark.parametrize("method", ["cql", "sac-target", "darc"])
def test_a_cuda_sweep_replays_the_graph_update_for_exactly_the_methods_whose_config_has_it(method, tmp_path):
    from baselines.algorithms import get_algorithm

    prepared = _script("--prepare", method, "40", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cuda")
    assert prepared.returncode == 0, prepared.stderr
    spec = (tmp_path / "device-sweep" / "spec.yaml").read_text()
    has_graph = hasattr(get_algorithm(method).default_config(), "cuda_graph")
    assert has_graph == (method != "darc")  # the premise: DARC has no graph update
    assert (f'overrides: {{{method}: {{cuda_graph: "true"}}}}' in spec) == has_graph, spec


@pytest.mark.slow
def test_a_prepared_sweep_runs_and_comes_back_as_one_archive_without_checkpoints(tmp_path):
    prepared = _script("--prepare", "cql", "40", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cpu")
    assert prepared.returncode == 0, prepared.stderr
    assert "note:" not in prepared.stderr  # a smoke test's steps, not lite: nothing to warn about
    spec = (tmp_path / "device-sweep" / "spec.yaml").read_text()
    assert "device: cpu" in spec and "seeds_per_run: 5" in spec and "cuda_graph" not in spec

    # A stand-in nvidia-smi: the load the script samples once a minute comes back in gpu.log.
    fake = tmp_path / "bin" / "nvidia-smi"
    fake.parent.mkdir()
    fake.write_text('#!/bin/sh\ncase "$*" in *utilization*) echo "37 %, 1234 MiB";; *) echo "Stand-in GPU";; esac\n')
    fake.chmod(0o755)
    ran = _script("600", tmp_path=tmp_path, OUT=str(tmp_path / "out"),
                  PATH=f"{fake.parent}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    assert ran.returncode == 0, ran.stderr
    assert "the sweep has ended" in ran.stdout and "1/1 runs done, 0 failed" in ran.stdout
    # the status table: steps, and the share of the time the evaluations took
    assert re.search(r"cql/hopper-gravity-0\.5/seeds-0-4 +done +100% +\d+% +1 ", ran.stdout), ran.stdout
    with tarfile.open(tmp_path / "out" / "sweep.tar.xz") as archive:
        names = archive.getnames()
        run = "gpu-reference/runs/cql/hopper-gravity-0.5/seeds-0-4"
        evaluation = json.load(archive.extractfile(f"{run}/evaluation.json"))
    assert f"{run}/result.json" in names and f"{run}/metrics.jsonl" in names
    assert not [name for name in names if "checkpoints" in name]
    assert [seed["seed"] for seed in evaluation["seeds"]] == [0, 1, 2, 3, 4]
    assert all(len(seed["returns"]) == 20 for seed in evaluation["seeds"])  # the protocol's 20 episodes
    assert (tmp_path / "out" / "sweep.log").stat().st_size > 0
    assert re.fullmatch(r"(\d\d:\d\d:\d\d GPU busy, memory: 37 %, 1234 MiB\n)+", (tmp_path / "out" / "gpu.log").read_text())
