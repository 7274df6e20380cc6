"""`leaderboard coverage`: a sweep spec's grid against the published reference runs."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from leaderboard.cli import leaderboard_app
from leaderboard.coverage import coverage_lines, reference_coverage
from leaderboard.reference_runs import REFERENCE_RUNS_DIR
from leaderboard.submission import SubmissionError
from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import format_duration

H2O_GRAVITY = "halfcheetah-h2o-gravity-2.0"
HOPPER_TASKS = ["hopper-gravity-0.5", "hopper-friction-0.5"]


def spec_of(tmp_path: Path, **fields: object):
    data = {"seeds": 5, "track": "offline-target", "budget": "lite", "out": str(tmp_path / "out")} | fields
    return parse_spec(data, source="test spec")


def copy_published(tmp_path: Path, *parts: str) -> Path:
    """The published runs of ``lite/<parts>`` (and the compute file) under a root of their own."""
    root = tmp_path / "published"
    (root / "lite").mkdir(parents=True)
    shutil.copy(REFERENCE_RUNS_DIR / "lite" / "compute.json", root / "lite" / "compute.json")
    for part in parts:
        shutil.copytree(REFERENCE_RUNS_DIR / "lite" / part, root / "lite" / part)
    return root


def test_the_h2o_cell_counts_the_published_seeds_and_prices_the_missing_ones(tmp_path):
    # The published runs of these methods, less any medium-replay ones (none yet, but this test
    # must not change meaning when they come) and all CQL seeds but 0.
    root = copy_published(tmp_path, "h2o", "darc", "cql")
    for folder in (root / "lite").glob("*/*/*"):
        later_cql_seed = folder.parts[-3] == "cql" and folder.name != "medium-v0.seed-0"
        if folder.name.startswith("medium-replay-v0.") or later_cql_seed:
            shutil.rmtree(folder)
    spec = spec_of(tmp_path, methods=["h2o", "darc", "cql"], tasks=[H2O_GRAVITY], datasets=["medium", "medium-replay"],
                   overrides={"darc": {"warmup_steps": 10000}})  # as h2o-table1-lite.yaml
    coverage = reference_coverage(spec, root)
    medium, replay = (H2O_GRAVITY, "medium-v0"), (H2O_GRAVITY, "medium-replay-v0")
    assert coverage.rows == (medium, replay)
    assert coverage.published[("h2o", *medium)] == (0, 1, 2, 3, 4)
    assert coverage.published[("darc", *medium)] == (0, 1, 2, 3, 4)
    published_cql = coverage.published[("cql", *medium)]
    assert published_cql == (0,)
    assert coverage.published[("h2o", *replay)] == ()
    assert (coverage.seeds_wanted, coverage.seeds_published) == (30, 10 + len(published_cql))
    costs = {cost.method: cost for cost in coverage.costs}
    assert (costs["h2o"].seeds_to_go, costs["h2o"].trainings_to_go) == (5, 5)
    assert costs["cql"].seeds_to_go == 10 - len(published_cql)
    # Priced at the median of the method's own published one-seed CPU trainings on the robot
    # (compute.json's training counts; the seed-batched GPU runs are not priced): this task's are
    # HalfCheetah's, and the method's count takes in those on every robot.
    compute = json.loads((REFERENCE_RUNS_DIR / "lite" / "compute.json").read_text())["runs"]
    one_seed = {run_id: entry["training"]["cpu_time_s"] for run_id, entry in compute.items()
                if run_id.startswith("cql/") and run_id.rpartition("/")[2].rpartition(".")[2].startswith("seed-")
                and entry.get("training", {}).get("complete")}
    cheetah_times = sorted(cpu for run_id, cpu in one_seed.items() if run_id.startswith("cql/halfcheetah"))
    assert costs["cql"].trainings_counted == len(one_seed) >= len(cheetah_times) >= 1
    (cheetah,) = costs["cql"].robots
    assert (cheetah.robot, cheetah.trainings_counted) == ("HalfCheetah", len(cheetah_times))
    assert min(cheetah_times) <= cheetah.median_training_cpu_s <= max(cheetah_times)
    assert costs["cql"].cpu_to_go_s == pytest.approx(costs["cql"].trainings_to_go * cheetah.median_training_cpu_s)
    assert coverage.others == ()

    lines = coverage_lines(coverage)
    assert lines[0].startswith(f"test spec at lite, against {root / 'lite'}: {coverage.seeds_published} "
                               "of 30 seed result(s) published")
    assert lines[1].split() == ["task", "dataset", "h2o", "darc", "cql"]
    assert lines[3].split() == [H2O_GRAVITY, "medium-v0", "5/5", "5/5", f"{len(published_cql)}/5"]
    assert lines[4].split() == [H2O_GRAVITY, "medium-replay-v0", "0/5", "0/5", "0/5"]
    to_go = 30 - coverage.seeds_published
    assert lines[5].startswith(f"to go: {to_go} seed result(s), {to_go} training(s), about ")


def test_rl_on_source_counts_one_training_for_the_tasks_that_share_its_policy(tmp_path):
    root = copy_published(tmp_path, "sac-source")
    spec = spec_of(tmp_path, methods=["sac-source"], tasks=HOPPER_TASKS)
    assert reference_coverage(spec, root).costs[0].seeds_to_go == 0
    assert coverage_lines(reference_coverage(spec, root))[-1] == "every run of the spec is published"

    # Seed 2 gone on both tasks: two runs to go, but one training (the nominal Hopper's seed 2).
    for task in HOPPER_TASKS:
        shutil.rmtree(root / "lite" / "sac-source" / task / "seed-2")
    cost = reference_coverage(spec, root).costs[0]
    assert (cost.seeds_to_go, cost.trainings_to_go) == (2, 1)
    # A run lacking only its source-side record is not published either: the task's gap needs both.
    (root / "lite" / "sac-source" / HOPPER_TASKS[0] / "seed-3" / "evaluation-source.json").unlink()
    coverage = reference_coverage(spec, root)
    assert coverage.published[("sac-source", HOPPER_TASKS[0], None)] == (0, 1, 4)
    assert (coverage.costs[0].seeds_to_go, coverage.costs[0].trainings_to_go) == (3, 2)


def test_a_record_of_another_run_is_listed_not_counted(tmp_path):
    root = copy_published(tmp_path, "dap")
    spec = spec_of(tmp_path, methods=["dap"], tasks=["halfcheetah-friction-5.0"])
    assert reference_coverage(spec, root).seeds_published == 5
    # The same runs, scored on 10 episodes: the published 20-episode records are other runs.
    fewer = spec_of(tmp_path, methods=["dap"], tasks=["halfcheetah-friction-5.0"], evaluation_episodes=10)
    coverage = reference_coverage(fewer, root)
    assert coverage.seeds_published == 0 and len(coverage.others) == 5
    path, why = coverage.others[0]
    assert path == root / "lite" / "dap" / "halfcheetah-friction-5.0" / "seed-0" / "evaluation.json"
    assert why == "20 episodes per seed, the spec's 10"
    assert coverage_lines(coverage)[-6] == ("5 published record(s) where the spec's runs belong are other runs "
                                            "(not counted):")
    # A run that would train on another dataset than the published one.
    other_data = spec_of(tmp_path, methods=["dap"], tasks=["halfcheetah-friction-5.0"], dataset="collect:random:5000")
    why = reference_coverage(other_data, root).others[0][1]
    assert why == "trained on offdyn/halfcheetah-friction-5p0/source-policy-v0, the spec's run on collect:random:5000"


def test_a_record_trained_with_other_settings_is_another_run(tmp_path):
    """The reference specs train DARC with its correction from step 10,000 (at lite the published
    100,000 never comes); runs trained with the defaults are other runs. A setting that changes how
    an update runs, not what it computes (cuda_graph), makes none."""
    root = copy_published(tmp_path, "darc")
    medium = (H2O_GRAVITY, "medium-v0")
    records = sorted((root / "lite" / "darc" / H2O_GRAVITY).glob("medium-v0.seed-*/evaluation.json"))
    assert len(records) == 5

    def trained_with(settings: str) -> None:
        """Rewrite the published records' train commands to carry exactly these settings."""
        for path in records:
            record = json.loads(path.read_text())
            command = re.sub(r" --set \S+", "", record["train_command"])
            record["train_command"] = command.replace(" --out", f"{settings} --out")
            path.write_text(json.dumps(record))

    corrected = spec_of(tmp_path, methods=["darc"], tasks=[H2O_GRAVITY], datasets=["medium"],
                        overrides={"darc": {"warmup_steps": 10000}})
    trained_with("")  # the published schedule, as DARC's first 15 H2O runs were
    coverage = reference_coverage(corrected, root)
    assert coverage.published[("darc", *medium)] == () and len(coverage.others) == 5
    assert coverage.others[0][1] == "trained with the defaults, the spec's run with --set warmup_steps=10000"
    assert coverage.skippable == frozenset()  # `sweep --skip-published` trains them again

    # A record whose train command carries the spec's settings is the spec's run, whatever it says
    # of execution-only ones.
    trained_with(" --set warmup_steps=10000 --set cuda_graph=true")
    assert reference_coverage(corrected, root).published[("darc", *medium)] == (0, 1, 2, 3, 4)
    defaults = spec_of(tmp_path, methods=["darc"], tasks=[H2O_GRAVITY], datasets=["medium"])
    why = reference_coverage(defaults, root).others[0][1]
    assert why == "trained with --set warmup_steps=10000, the spec's run with the defaults"


def test_a_hand_edited_record_is_refused(tmp_path):
    root = copy_published(tmp_path, "dap")
    edited = root / "lite" / "dap" / "halfcheetah-friction-5.0" / "seed-1" / "evaluation.json"
    record = json.loads(edited.read_text())
    record["method"] = "dap-u"
    edited.write_text(json.dumps(record))
    spec = spec_of(tmp_path, methods=["dap"], tasks=["halfcheetah-friction-5.0"])
    with pytest.raises(SubmissionError, match=r"seed-1/evaluation.json: holds 'dap-u' on 'halfcheetah-friction-5.0', "
                                              r"but its folder names 'dap'"):
        reference_coverage(spec, root)
    edited.write_text("{not json")
    with pytest.raises(SubmissionError, match=r"seed-1/evaluation.json: .*not valid JSON"):
        reference_coverage(spec, root)


def test_a_method_without_a_counted_training_is_not_priced(tmp_path):
    root = copy_published(tmp_path)  # the compute file alone: nothing published
    (root / "lite" / "compute.json").write_text(json.dumps({"runs": {}}))
    spec = spec_of(tmp_path, methods=["dap"], tasks=["halfcheetah-friction-5.0"], seeds=[0, 1])
    coverage = reference_coverage(spec, root)
    assert coverage.costs[0].cpu_to_go_s is None
    lines = coverage_lines(coverage)
    assert lines[-1] == "run only those: offdyn-bench sweep 'test spec' --skip-published"
    assert lines[-3] == ("to go: 2 seed result(s), 2 training(s), CPU not estimated (each training at the median CPU "
                         "of its method's published trainings at this budget on its robot, or on any robot where none "
                         "is on its own; from compute.json):")
    assert lines[-2] == ("  dap: 2 seed result(s), 2 training(s) not estimated: no published training of it "
                         "(1 seed(s) per run) counted its compute")
    (root / "lite" / "compute.json").write_text("[1, 2]")
    with pytest.raises(SubmissionError, match=r"compute.json: unreadable .*; move it away to record compute anew"):
        reference_coverage(spec, root)


def _dap_training_cpu(compute: dict, robot_prefix: str = "") -> list[float]:
    """The CPU seconds of the published one-seed DAP trainings (on tasks starting ``robot_prefix``)."""
    return [entry["training"]["cpu_time_s"] for run_id, entry in compute["runs"].items()
            if run_id.startswith(f"dap/{robot_prefix}") and entry.get("training", {}).get("complete")]


def test_a_missing_training_is_priced_on_its_own_robot(tmp_path):
    """An Ant DAP training costs about 1.4 times a Hopper one (its 105-number
    observations, its costlier steps), so each robot's missing trainings are priced at the
    method's median there; a robot the method has not trained on yet falls back to its median
    over every robot, and the table says which."""
    root = copy_published(tmp_path, "dap")
    tasks = ["ant-friction-5.0", "hopper-gravity-0.5", "hopper-friction-0.5"]
    for task in tasks:
        shutil.rmtree(root / "lite" / "dap" / task / "seed-1")
    spec = spec_of(tmp_path, methods=["dap"], tasks=tasks)
    compute_file = root / "lite" / "compute.json"
    compute = json.loads(compute_file.read_text())
    ant, hopper = _dap_training_cpu(compute, "ant-"), _dap_training_cpu(compute, "hopper-")
    assert len(ant) >= 5 and len(hopper) >= 5 and np.median(ant) > 1.3 * np.median(hopper)  # the premise
    (cost,) = reference_coverage(spec, root).costs
    assert [(robot.robot, robot.trainings_to_go, robot.trainings_counted) for robot in cost.robots] == [
        ("Ant", 1, len(ant)), ("Hopper", 2, len(hopper))]
    assert cost.cpu_to_go_s == pytest.approx(float(np.median(ant) + 2 * np.median(hopper)))
    assert cost.median_training_cpu_s == pytest.approx(float(np.median(_dap_training_cpu(compute))))
    lines = coverage_lines(reference_coverage(spec, root))
    at = next(i for i, line in enumerate(lines) if line.startswith("  dap: "))
    assert lines[at].startswith("  dap: 3 seed result(s), 3 training(s) = ")
    assert lines[at + 1] == f"    Ant: 1 x {format_duration(float(np.median(ant)))} (median of {len(ant)} on Ant)"
    assert lines[at + 2] == f"    Hopper: 2 x {format_duration(float(np.median(hopper)))} (median of {len(hopper)} on Hopper)"

    # No Ant training counted: the Ant one is priced at DAP's median over the other robots.
    compute["runs"] = {run_id: entry for run_id, entry in compute["runs"].items() if not run_id.startswith("dap/ant-")}
    compute_file.write_text(json.dumps(compute))
    everywhere = _dap_training_cpu(compute)
    (cost,) = reference_coverage(spec, root).costs
    assert [(robot.robot, robot.median_training_cpu_s is None) for robot in cost.robots] == [
        ("Ant", True), ("Hopper", False)]
    assert cost.cpu_to_go_s == pytest.approx(float(np.median(everywhere) + 2 * np.median(hopper)))
    lines = coverage_lines(reference_coverage(spec, root))
    assert lines[next(i for i, line in enumerate(lines) if line.startswith("  dap: ")) + 1] == (
        f"    Ant: 1 x {format_duration(float(np.median(everywhere)))} (median of {len(everywhere)} on any robot, "
        "none on Ant)")


def test_the_command_and_its_refusals(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text(f"methods: [dap, dap-u]\ntasks: [halfcheetah-friction-5.0]\nseeds: 5\ntrack: offline-target\n"
                    f"budget: lite\nout: {tmp_path / 'out'}\n")
    result = CliRunner().invoke(leaderboard_app, ["coverage", str(spec)])
    assert result.exit_code == 0, result.output
    assert "10 of 10 seed result(s) published" in result.output
    assert result.output.splitlines()[-1] == "every run of the spec is published"
    assert not (tmp_path / "out").exists()  # reads; runs nothing, creates nothing

    steps = tmp_path / "steps.yaml"
    steps.write_text(spec.read_text().replace("budget: lite", "steps: 300"))
    result = CliRunner().invoke(leaderboard_app, ["coverage", str(steps)])
    assert result.exit_code == 2
    assert "sets steps, not a protocol budget" in result.output
    result = CliRunner().invoke(leaderboard_app, ["coverage", str(spec), "--reference-runs", str(tmp_path / "none")])
    assert result.exit_code == 2
    assert f"{tmp_path / 'none'}: not a folder; expected published reference runs" in result.output


def test_seeds_count_whichever_seeds_their_run_trained_beside(tmp_path):
    """A spec that trains 5 seeds per run (a GPU sweep's folders, seeds-0-4) finds per-seed records."""
    root = copy_published(tmp_path, "dap")
    grouped = spec_of(tmp_path, methods=["dap"], tasks=["halfcheetah-friction-5.0"], seeds_per_run=5)
    coverage = reference_coverage(grouped, root)
    assert coverage.published[("dap", "halfcheetah-friction-5.0", None)] == (0, 1, 2, 3, 4)
    shutil.rmtree(root / "lite" / "dap" / "halfcheetah-friction-5.0" / "seed-3")
    cost = reference_coverage(grouped, root).costs[0]
    # One seed missing: the sweep retrains its group, one training of 5 seeds; the published
    # trainings are one seed each, so they price none of it.
    assert (cost.seeds_to_go, cost.trainings_to_go, cost.median_training_cpu_s) == (1, 1, None)
    assert cost.unpriced_because == "no published training of it (5 seed(s) per run) counted its compute"
    on_gpu = spec_of(tmp_path, methods=["dap"], tasks=["halfcheetah-friction-5.0"], device="cuda")
    cost = reference_coverage(on_gpu, root).costs[0]
    assert (cost.seeds_to_go, cost.trainings_to_go, cost.cpu_to_go_s) == (1, 1, None)
    assert cost.unpriced_because == "the spec trains on cuda, and the published compute is CPU time"
    on_cpu = reference_coverage(spec_of(tmp_path, methods=["dap"], tasks=["halfcheetah-friction-5.0"]), root)
    assert on_cpu.costs[0].trainings_counted >= 5 and on_cpu.costs[0].cpu_to_go_s is not None  # every published DAP run


def test_a_training_on_a_gpu_prices_no_cpu_run(tmp_path):
    """A GPU run's CPU time is its host thread's, waiting on the device: a CPU sweep of the same
    seeds per run is not priced from it."""
    root = copy_published(tmp_path, "cql")
    budget_dir = root / "lite"
    # A pair outside the core suite: the reference grid publishes no CQL run of it, however far it gets.
    grouped = spec_of(tmp_path, methods=["cql"], tasks=["hopper-gravity-5.0"], seeds_per_run=5)
    gpu_runs = [folder for folder in (budget_dir / "cql").glob("*/seeds-*")
                if any(machine.get("cuda") for machine in
                       json.loads((folder / "evaluation.json").read_text())["training_machines"])]
    assert gpu_runs  # the lease's published 5-seed CQL runs
    cost = reference_coverage(grouped, root).costs[0]
    assert (cost.trainings_to_go, cost.trainings_counted, cost.cpu_to_go_s) == (1, 0, None)
    assert cost.unpriced_because == "no published training of it (5 seed(s) per run) counted its compute"

    # The same run, had it trained on a CPU (its records say so), prices it at its training's CPU.
    for folder in gpu_runs:
        record_file = folder / "evaluation.json"
        record = json.loads(record_file.read_text())
        for machine in record["training_machines"]:
            machine.pop("cuda")
        record_file.write_text(json.dumps(record))
    compute = json.loads((budget_dir / "compute.json").read_text())["runs"]
    times = sorted(compute[folder.relative_to(budget_dir).as_posix()]["training"]["cpu_time_s"] for folder in gpu_runs)
    cost = reference_coverage(grouped, root).costs[0]
    assert cost.trainings_counted == len(gpu_runs)
    assert cost.median_training_cpu_s == pytest.approx(float(np.median(times)))


def test_skippable_runs_are_the_published_ones_less_a_training_a_missing_run_still_scores(tmp_path):
    root = copy_published(tmp_path, "dap", "sac-source")
    spec = spec_of(tmp_path, methods=["dap", "sac-source"], tasks=HOPPER_TASKS)
    every = {f"{method}/{task}/seed-{seed}" for method in ("dap", "sac-source") for task in HOPPER_TASKS
             for seed in range(5)}
    assert reference_coverage(spec, root).skippable == every  # the premise: all of them are published

    # DAP's seed 1 on hopper-friction-0.5 gone: that run is to do again, every other DAP run is not.
    shutil.rmtree(root / "lite" / "dap" / "hopper-friction-0.5" / "seed-1")
    # RL on source's seed 3: both Hopper tasks score one policy, trained in the first task's run.
    # The second task's record gone: its run needs that policy, so the published first run is
    # trained again rather than skipped (published records carry no checkpoint to score).
    shutil.rmtree(root / "lite" / "sac-source" / "hopper-friction-0.5" / "seed-3")
    skippable = reference_coverage(spec, root).skippable
    assert every - skippable == {"dap/hopper-friction-0.5/seed-1", "sac-source/hopper-friction-0.5/seed-3",
                                 "sac-source/hopper-gravity-0.5/seed-3"}

    # The other way round: the training run's record gone, the scoring run's published. The
    # scoring run is skipped; the training one runs.
    root = copy_published(tmp_path / "again", "sac-source")
    shutil.rmtree(root / "lite" / "sac-source" / "hopper-gravity-0.5" / "seed-3")
    skippable = reference_coverage(spec_of(tmp_path, methods=["sac-source"], tasks=HOPPER_TASKS), root).skippable
    assert "sac-source/hopper-friction-0.5/seed-3" in skippable
    assert "sac-source/hopper-gravity-0.5/seed-3" not in skippable


def test_where_priced_trainings_timed_their_machine_the_coverage_compares_this_one(tmp_path):
    """CPU seconds from another day or machine are not this machine's (PROTOCOL §8): trainings
    that timed the reference workload say how fast their machines were, and the coverage sets
    this machine's speed now beside them."""
    root = copy_published(tmp_path, "dap")
    shutil.rmtree(root / "lite" / "dap" / "hopper-gravity-0.5" / "seed-1")
    spec = spec_of(tmp_path, methods=["dap"], tasks=["hopper-gravity-0.5"])
    compute_file = root / "lite" / "compute.json"
    compute = json.loads(compute_file.read_text())
    measured_here = []

    def here() -> float:
        measured_here.append(True)
        return 0.004

    # None of them timed it: no comparison, and no measurement here either.
    for entry in compute["runs"].values():
        entry.get("training", {}).pop("reference_updates", None)
    compute_file.write_text(json.dumps(compute))
    coverage = reference_coverage(spec, root, measure_update_s=here)
    assert coverage.speed is None and not measured_here
    assert not any(line.startswith("machine speed") for line in coverage_lines(coverage))

    # Three DAP trainings timed it (2, 3 and 2.5 ms an update on their machines), and one RL on
    # source training, which prices no DAP run.
    dap = sorted(run_id for run_id, entry in compute["runs"].items()
                 if run_id.startswith("dap/") and entry.get("training", {}).get("complete"))
    for run_id, update_s in zip(dap, (0.002, 0.003, 0.0025)):
        training = compute["runs"][run_id]["training"]
        training["reference_updates"] = training["cpu_time_s"] / update_s
    other = next(run_id for run_id in compute["runs"] if run_id.startswith("sac-source/"))
    compute["runs"][other].setdefault("training", {})["reference_updates"] = 1.0
    compute_file.write_text(json.dumps(compute))
    coverage = reference_coverage(spec, root, measure_update_s=here)
    speed = coverage.speed
    assert (speed.trainings_measured, speed.trainings_counted) == (3, len(_dap_training_cpu(compute)))
    assert speed.published_update_s == pytest.approx(0.0025) and speed.here_update_s == 0.004
    assert speed.ratio == pytest.approx(1.6)
    (line,) = [line for line in coverage_lines(coverage) if line.startswith("machine speed")]
    assert line == (f"machine speed: 3 of the {speed.trainings_counted} priced trainings timed the reference workload "
                    "(mlp-256x2-adam-batch256/v1) on their machine, a median 2.50 ms an update; this machine takes "
                    "4.00 ms now, so a training here would take about 1.60 times the CPU of one of theirs (PROTOCOL §8)")
    # The prices themselves stay the published CPU seconds.
    assert coverage.costs[0].cpu_to_go_s == pytest.approx(float(np.median(_dap_training_cpu(compute, "hopper-"))))
