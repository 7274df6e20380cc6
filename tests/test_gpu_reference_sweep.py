"""``scripts/gpu_reference_sweep.sh``: prepare a GPU lease's reference sweep here, run it there, and
bring the finished runs back. Checked on the CPU (``DEVICE=cpu``, no wheels): the same spec, sweep
and archive as on the device, where it ran on an H200 (README, "Devices")."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest
from cut_short_runs import TASK, pack_unfinished, train_tiny_source

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


@pytest.fixture(scope="module")
def rebuilt_datasets(tmp_path_factory) -> dict[str, str]:
    """One Minari root for the prepares that get as far as the datasets: each task's dataset is
    rebuilt from its recipe (and checked against the manifest) once for the module, not per test.
    Checks that something is refused before any dataset keep their own, empty, root."""
    return {"MINARI_DATASETS_PATH": str(tmp_path_factory.mktemp("minari"))}


@pytest.mark.parametrize(("args", "message"), [
    (["--prepare", "cql"], "usage: "),
    (["--prepare", "cql", "ten", "hopper-gravity-0.5"], "error: budget ten: expected lite or a number of steps"),
    (["--prepare", "cql", "lite", "hopper-gravity-9"], "tasks: unknown task 'hopper-gravity-9'; closest valid names"),
    (["--prepare", "cq1", "lite", "hopper-gravity-0.5"], "methods: unknown algorithm 'cq1'; closest valid names: 'cql'"),
    (["--prepare", "cql", "0", "hopper-gravity-0.5"], "steps: got 0; expected an integer >= 1"),
    # RL on target's lite records of this task are in leaderboard/reference-runs: no lease time for them
    (["--prepare", "sac-target", "lite", "hopper-friction-0.5", "hopper-gravity-0.5"],
     ("error: published already (leaderboard/reference-runs/lite), leave out their tasks: "
      "sac-target/hopper-friction-0.5/seeds-0-4 sac-target/hopper-gravity-0.5/seeds-0-4")),
])
def test_a_bad_prepare_says_what_was_wrong_and_leaves_no_folder(args, message, tmp_path):
    result = _script(*args, tmp_path=tmp_path)
    assert result.returncode != 0 and message in result.stderr
    assert not any(tmp_path.glob("device-sweep*"))


@pytest.mark.parametrize(("env", "message"), [
    ({"SEEDS": "1,,2"}, "error: SEEDS=1,,2: expected training seeds separated by commas, e.g. SEEDS=1,2,3,4"),
    ({"SEEDS": "0-4"}, "error: SEEDS=0-4: expected training seeds separated by commas"),
    ({"DATASETS": "Medium"}, "error: DATASETS=Medium: expected dataset qualities separated by commas"),
    ({"DATASETS": "medum"}, "datasets: unknown quality 'medum'; expected qualities from"),
    ({"DATASETS": "medium"}, "hopper-gravity-0.5 has no medium dataset"),
    # CQL's seed 0 on the H2O gravity setting's medium data is published (a CPU run): a lease
    # training it again beside seed 1 could not publish the pair.
    ({"SEEDS": "0,1"}, "cql/halfcheetah-h2o-gravity-2.0/medium-v0.seeds-0-1 (seed(s) 0 published)"),
])
def test_seeds_and_datasets_that_name_no_publishable_run_are_refused_before_anything_is_packed(env, message, tmp_path):
    task = "halfcheetah-h2o-gravity-2.0" if env.get("SEEDS") == "0,1" else "hopper-gravity-0.5"
    result = _script("--prepare", "cql", "lite", task, tmp_path=tmp_path, DEVICE="cpu",
                     **({"DATASETS": "medium"} | env if task != "hopper-gravity-0.5" else env))
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert "rebuilding it from its recipe" not in result.stderr  # refused before any dataset
    assert not any(tmp_path.glob("device-sweep*"))


@pytest.mark.slow
def test_a_lease_trains_the_seeds_and_dataset_qualities_it_is_given(tmp_path):
    """The H2O paper's Table 1 cells: seeds 1-4 beside a published seed 0, on the medium data."""
    prepared = _script("--prepare", "cql", "40", "halfcheetah-h2o-gravity-2.0", tmp_path=tmp_path, DEVICE="cpu",
                       SEEDS="1,2,3,4", DATASETS="medium")
    assert prepared.returncode == 0, prepared.stderr
    spec = (tmp_path / "device-sweep" / "spec.yaml").read_text()
    assert "seeds: [1, 2, 3, 4]\nseeds_per_run: 4\ndatasets: [medium]\n" in spec
    with tarfile.open(tmp_path / "device-sweep" / "payload.tar.xz") as payload:
        datasets = {Path(name).parts[2:4] for name in payload.getnames() if len(Path(name).parts) > 3}
    assert datasets == {("halfcheetah-h2o-gravity-2p0", "medium-v0")}
    assert (tmp_path / "device-sweep" / "workers").read_text().strip() == "1"


def test_running_without_a_prepared_folder_is_refused(tmp_path):
    result = _script(tmp_path=tmp_path, OUT=str(tmp_path / "out"))
    assert result.returncode == 2 and "run --prepare here first" in result.stderr


def test_more_lite_cql_tasks_than_a_lease_finishes_are_prepared_with_a_note(tmp_path, rebuilt_datasets):
    # Pairs outside the core suite: the reference grid publishes no CQL run of them, so at lite
    # they stay preparable however far the grid gets.
    tasks = ["hopper-gravity-5.0", "hopper-friction-5.0", "hopper-kinematic-thigh-medium"]
    prepared = _script("--prepare", "cql", "lite", *tasks, tmp_path=tmp_path, DEVICE="cpu", **rebuilt_datasets)
    assert prepared.returncode == 0, prepared.stderr
    assert "note: 3 lite runs, CQL among them: the measured lease would finish about two lite CQL runs" in prepared.stderr
    assert f"tasks: [{', '.join(tasks)}]" in (tmp_path / "device-sweep" / "spec.yaml").read_text()
    [travels] = [line for line in prepared.stdout.splitlines() if line.startswith("travels: ")]
    assert f", {tmp_path / 'device-sweep'} " in travels  # the folder to carry, not the one it was built in


@pytest.mark.parametrize("method", ["cql", "sac-target", "darc"])
def test_a_cuda_sweep_replays_the_graph_update_for_exactly_the_methods_whose_config_has_it(method, tmp_path,
                                                                                           rebuilt_datasets):
    from baselines.algorithms import get_algorithm

    prepared = _script("--prepare", method, "40", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cuda",
                       **rebuilt_datasets)
    assert prepared.returncode == 0, prepared.stderr
    spec = (tmp_path / "device-sweep" / "spec.yaml").read_text()
    has_graph = hasattr(get_algorithm(method).default_config(), "cuda_graph")
    assert has_graph == (method != "darc")  # the premise: DARC has no graph update
    assert (f'overrides: {{{method}: {{cuda_graph: "true"}}}}' in spec) == has_graph, spec


def test_an_added_group_needs_a_prepared_folder_and_trains_no_cell_another_group_trains(tmp_path, rebuilt_datasets):
    alone = _script("--prepare", "cql", "40", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cpu", ADD="1")
    assert alone.returncode == 2
    assert "error: ADD=1: no prepared " in alone.stderr and "prepare the first group without ADD" in alone.stderr
    assert not any(tmp_path.glob("device-sweep*"))

    first = _script("--prepare", "cql", "40", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cpu", **rebuilt_datasets)
    assert first.returncode == 0, first.stderr
    prepared = sorted(path.name for path in (tmp_path / "device-sweep").iterdir())
    # Other seeds of the same cell in a second group: the lease could not publish both runs.
    again = _script("--prepare", "cql", "40", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cpu", ADD="1",
                    SEEDS="5,6")
    assert again.returncode == 2
    assert "error: ADD=1: spec.yaml trains these already, and a seed is published once: cql/hopper-gravity-0.5" \
        in again.stderr
    # The prepared folder is as it was.
    assert sorted(path.name for path in (tmp_path / "device-sweep").iterdir()) == prepared
    assert not (tmp_path / "device-sweep.partial").exists()


@pytest.mark.slow
def test_two_groups_share_a_lease_each_its_own_sweep_and_both_come_back(tmp_path):
    """Runs no one spec can hold (here other seeds per run) go as groups of one lease."""
    first = _script("--prepare", "cql", "40", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cpu")
    assert first.returncode == 0, first.stderr
    added = _script("--prepare", "cql", "40", "hopper-friction-0.5", tmp_path=tmp_path, DEVICE="cpu", ADD="1",
                    SEEDS="0,1")
    assert added.returncode == 0, added.stderr
    folder = tmp_path / "device-sweep"
    assert "out: " + str(tmp_path / "sweep-root" / "gpu-reference-2") in (folder / "spec-2.yaml").read_text()
    with tarfile.open(folder / "payload-2.tar.xz") as payload:  # its dataset only
        assert {Path(name).parts[2] for name in payload.getnames() if len(Path(name).parts) > 3} == {"hopper-friction-0p5"}

    ran = _script("900", tmp_path=tmp_path, OUT=str(tmp_path / "out"))
    assert ran.returncode == 0, ran.stderr
    assert "the sweep has ended" in ran.stdout and ran.stdout.count("1/1 runs done, 0 failed") == 2
    with tarfile.open(tmp_path / "out" / "sweep.tar.xz") as archive:
        names = archive.getnames()
    assert "gpu-reference/runs/cql/hopper-gravity-0.5/seeds-0-4/evaluation.json" in names
    assert "gpu-reference-2/runs/cql/hopper-friction-0.5/seeds-0-1/evaluation.json" in names
    assert (tmp_path / "out" / "sweep.log").stat().st_size > 0 and (tmp_path / "out" / "sweep-2.log").stat().st_size > 0


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
    assert not list((tmp_path / "out").glob("partial.*"))  # nothing unfinished to bring back


def _partial_of_another_run(tmp_path: Path) -> Path:
    """An archive of a run cut short that is no run of the lease's spec (RL on source, 300 steps)."""
    train_tiny_source(tmp_path / "other" / "runs" / "sac-source" / TASK / "seed-0", stop_after=100)
    pack_unfinished(tmp_path / "other", tmp_path / "back")
    return tmp_path / "back"


@pytest.mark.parametrize(("files", "message"), [
    (None, "usage: "),
    ([], "holds neither sweep.tar.xz nor partial.*.tar (what a lease call brings back)"),
])
def test_collecting_what_a_call_brought_back_refuses_a_folder_without_it(files, message, tmp_path):
    back = tmp_path / "back"
    if files is not None:
        back.mkdir()
    result = _script("--collect", str(back), str(tmp_path / "runs"), tmp_path=tmp_path)
    assert result.returncode == 2 and message in result.stderr
    assert not (tmp_path / "runs").exists()


def test_collecting_files_each_cut_short_run_by_its_group_and_drops_it_once_finished(tmp_path):
    """A call's partial.*.tar goes to its group's RESUME_FROM folder; when a later call brings the
    run back finished, the kept archive goes (resuming it would train what is done)."""
    folder = tmp_path / "device-sweep"
    folder.mkdir()
    (folder / "spec.yaml").write_text(f"methods: [sac-source]\ntasks: [{TASK}]\nseeds: [1]\ntrack: offline-target\n"
                                      f"steps: 300\nout: {tmp_path / 'sweep-root' / 'gpu-reference'}\n")
    (folder / "spec-2.yaml").write_text(f"methods: [sac-source]\ntasks: [{TASK}]\nseeds: [0]\n"
                                        f"track: offline-target\nsteps: 300\n"
                                        f"out: {tmp_path / 'sweep-root' / 'gpu-reference-2'}\n")
    back = _partial_of_another_run(tmp_path)  # sac-source/<TASK>/seed-0: group 2's run
    (back / "partial.cql.hopper-gravity-0.5.seeds-0-4.tar").write_bytes(b"")  # no group's
    runs = tmp_path / "runs"
    collected = _script("--collect", str(back), str(runs), tmp_path=tmp_path)
    assert collected.returncode == 0, collected.stderr
    kept = runs / "cut-short" / "group-2" / f"partial.sac-source.{TASK}.seed-0.tar"
    assert kept.read_bytes() == (back / kept.name).read_bytes()
    assert not (runs / "cut-short" / "group-1").exists()
    assert ("warning: partial.cql.hopper-gravity-0.5.seeds-0-4.tar is no run of " in collected.stderr
            and (runs / "cut-short" / "partial.cql.hopper-gravity-0.5.seeds-0-4.tar").exists())

    # The next call: the run came back finished (its evaluation written). Its archive is
    # dropped, then the finished runs are published (here refused: 300 steps is no budget).
    finished = tmp_path / "root" / "gpu-reference-2" / "runs" / "sac-source" / TASK / "seed-0"
    finished.mkdir(parents=True)
    (finished / "evaluation.json").write_text("{}")
    later = tmp_path / "later"
    later.mkdir()
    with tarfile.open(later / "sweep.tar.xz", "w:xz") as archive:
        archive.add(tmp_path / "root" / "gpu-reference-2", arcname="gpu-reference-2")
    again = _script("--collect", str(later), str(runs), tmp_path=tmp_path, PUBLISH_TO=str(tmp_path / "published"))
    assert not kept.exists() and f"finished, so no longer kept: {kept}" in again.stdout
    [lease] = runs.glob("lease-*")
    assert (lease / "gpu-reference-2" / "runs" / "sac-source" / TASK / "seed-0" / "evaluation.json").exists()
    assert f"publishing {lease / 'gpu-reference-2'}" in again.stdout
    assert again.returncode != 0 and "error: " in again.stderr and "Traceback" not in again.stderr  # refused, with why
    assert not (tmp_path / "published").exists()


def test_resuming_what_a_lease_did_not_finish_refuses_what_is_not_the_specs(tmp_path):
    (tmp_path / "empty").mkdir()
    nothing = _script("--prepare", "cql", "40", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cpu",
                      RESUME_FROM=str(tmp_path / "empty"))
    assert nothing.returncode == 2 and "holds no partial.*.tar (what a lease call brings back)" in nothing.stderr
    assert "rebuilding it from its recipe" not in nothing.stderr  # refused before any dataset
    other = _script("--prepare", "cql", "40", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cpu",
                    RESUME_FROM=str(_partial_of_another_run(tmp_path)))
    assert other.returncode == 2
    assert ("error: partial.sac-source.invertedpendulum-gravity-3.0.seed-0.tar holds "
            "sac-source/invertedpendulum-gravity-3.0/seed-0, not a run of ") in other.stderr
    assert "rebuilding it from its recipe" not in other.stderr
    assert not any(tmp_path.glob("device-sweep*"))


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="freezes the sweep with SIGSTOP")
def test_a_run_the_lease_cut_short_comes_back_and_the_next_lease_resumes_it(tmp_path):
    first, second = tmp_path / "lease-1", tmp_path / "lease-2"
    first.mkdir(), second.mkdir()
    prepared = _script("--prepare", "cql", "400", "hopper-gravity-0.5", tmp_path=first, DEVICE="cpu")
    assert prepared.returncode == 0, prepared.stderr
    started = _script("1", tmp_path=first, OUT=str(first / "out"))  # starts the sweep, returns at once
    assert "still running" in started.stdout, started.stdout + started.stderr
    run = first / "sweep-root" / "gpu-reference" / "runs" / "cql" / "hopper-gravity-0.5" / "seeds-0-4"
    deadline = time.monotonic() + 600
    while not list((run / "checkpoints").glob("step_*")) and time.monotonic() < deadline:
        time.sleep(1)
    # The lease ends here: the sweep frozen, as the machine's end would leave it mid-run.
    group = int((first / "sweep-root" / "sweep.pid").read_text())
    os.killpg(group, signal.SIGSTOP)
    try:
        ended = _script("0", tmp_path=first, OUT=str(first / "out"))
    finally:
        os.killpg(group, signal.SIGKILL)
    assert ended.returncode == 0, ended.stderr
    [partial] = (first / "out").glob("partial.*.tar")
    assert partial.name == "partial.cql.hopper-gravity-0.5.seeds-0-4.tar"
    assert "packed: cql/hopper-gravity-0.5/seeds-0-4 at step " in ended.stdout

    # The next lease, on a bare machine: the partial travels, and the sweep resumes it.
    again = _script("--prepare", "cql", "400", "hopper-gravity-0.5", tmp_path=second, DEVICE="cpu",
                    RESUME_FROM=str(first / "out"))
    assert again.returncode == 0, again.stderr
    assert "resumes: partial.cql.hopper-gravity-0.5.seeds-0-4.tar" in again.stdout
    finished = _script("900", tmp_path=second, OUT=str(second / "out"))
    assert finished.returncode == 0, finished.stderr
    assert "resuming runs/cql/hopper-gravity-0.5/seeds-0-4 from the archive" in finished.stdout
    assert "1/1 runs done, 0 failed" in finished.stdout
    log = (second / "sweep-root" / "gpu-reference" / "logs").rglob("*.log")
    assert any("=== resuming: " in path.read_text() for path in log)
    result = json.loads((second / "sweep-root" / "gpu-reference" / "runs" / "cql" / "hopper-gravity-0.5"
                         / "seeds-0-4" / "result.json").read_text())
    assert result["compute"]["attempts"] == 2  # the cut-short lease's attempt is counted
    assert not list((second / "out").glob("partial.*"))


@pytest.mark.slow
def test_a_lite_lease_trains_the_reference_grids_settings(tmp_path):
    """DARC at lite: the reference grid's correction from step 10,000 (examples/sweeps/reference-lite.yaml),
    not the published 100,000 that a lite run never reaches."""
    prepared = _script("--prepare", "darc", "lite", "hopper-gravity-0.5", tmp_path=tmp_path, DEVICE="cpu")
    assert prepared.returncode == 0, prepared.stderr
    spec = (tmp_path / "device-sweep" / "spec.yaml").read_text()
    assert 'overrides: {darc: {warmup_steps: "10000"}}' in spec
