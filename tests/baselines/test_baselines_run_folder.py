"""Training runs against damage and misuse: damaged checkpoints and files, two processes on one
folder, bad settings and paths, budgets too short to learn. Each fault is injected into a real run
folder; the checks are what the user sees and that nothing is written or lost."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from baselines.checkpoint import CHECKSUMS_FILE, STATE_FILE, TRAINER_FILE, checkpoints, latest_checkpoint
from baselines.run_folder import TrainingCompute, run_folder_lock, write_json_atomic, write_lines_atomic
from baselines.train import train
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError, UnknownNameError

PENDULUM = "invertedpendulum-kinematic-slider-hard"
TINY = {"sac.hidden_sizes": "[16, 16]", "sac.batch_size": "16", "random_steps": "20"}
RUN = dict(steps=120, overrides=TINY, eval_every=30, eval_episodes=1, checkpoint_every=40, progress=False, seed=2)


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _curve(folder: Path) -> list[dict]:
    return [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def whole_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("whole") / "run"
    return train("sac-source", PENDULUM, out=out, **RUN), out


@pytest.fixture
def cut_run(tmp_path):
    """A run "killed" at step 90: checkpoints step 40 and step 80 kept, curve up to step 90."""
    out = tmp_path / "cut"
    assert train("sac-source", PENDULUM, out=out, stop_after=90, **RUN) is None
    assert [p.name for p in checkpoints(out)] == ["step_000000040", "step_000000080"]
    return out


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])


def _flip_tensor_byte(path: Path) -> None:
    """Flip one byte inside the tensor data (after the safetensors header), leaving a valid file."""
    data = bytearray(path.read_bytes())
    header_length = int.from_bytes(data[:8], "little")
    data[8 + header_length + (len(data) - 8 - header_length) // 2] ^= 0x10
    path.write_bytes(bytes(data))


DAMAGE = {
    "truncated state": (lambda cp: _truncate(cp / STATE_FILE), f"{STATE_FILE} does not match its sha256"),
    "empty state": (lambda cp: (cp / STATE_FILE).write_bytes(b""), f"{STATE_FILE} is empty"),
    "deleted state": (lambda cp: (cp / STATE_FILE).unlink(), f"{STATE_FILE} is missing"),
    "truncated trainer": (lambda cp: _truncate(cp / TRAINER_FILE), f"{TRAINER_FILE} does not match its sha256"),
    "flipped tensor byte": (lambda cp: _flip_tensor_byte(cp / STATE_FILE), f"{STATE_FILE} does not match its sha256"),
    "garbage checksums": (lambda cp: (cp / CHECKSUMS_FILE).write_text("{"), f"{CHECKSUMS_FILE} is unreadable"),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_newest_checkpoint_falls_back_to_the_previous_one(whole_run, cut_run, damage, capsys):
    inflict, reason = DAMAGE[damage]
    inflict(checkpoints(cut_run)[-1])
    capsys.readouterr()
    resumed = train("sac-source", PENDULUM, out=cut_run, **RUN)
    err = capsys.readouterr().err
    assert f"checkpoint step_000000080 is damaged ({reason}" in err
    assert "); resuming from step_000000040" in err
    whole, whole_dir = whole_run
    assert resumed["returns"] == whole["returns"]  # the fallback costs time, never correctness
    assert [c["target_return"] for c in _curve(cut_run)] == [c["target_return"] for c in _curve(whole_dir)]


def test_flipped_bytes_without_checksums_would_have_loaded(cut_run):
    """The checksum is what catches a flipped byte: the safetensors file itself still parses."""
    from safetensors.torch import load_file

    newest = checkpoints(cut_run)[-1]
    _flip_tensor_byte(newest / STATE_FILE)
    assert load_file(str(newest / STATE_FILE))  # parses fine, wrong numbers inside
    assert latest_checkpoint(cut_run) == checkpoints(cut_run)[0]


def test_checkpoints_from_before_checksums_still_resume(whole_run, cut_run):
    for checkpoint in checkpoints(cut_run):
        (checkpoint / CHECKSUMS_FILE).unlink()
    assert train("sac-source", PENDULUM, out=cut_run, **RUN)["returns"] == whole_run[0]["returns"]


def _trainer(checkpoint: Path) -> dict:
    return json.loads((checkpoint / TRAINER_FILE).read_text())


def test_a_resumed_run_counts_the_compute_of_every_attempt(whole_run, cut_run):
    first = _trainer(checkpoints(cut_run)[-1])["compute"]
    assert first["attempts"] == 1 and first["complete"] is True and first["wall_time_s"] > 0
    before_resume = _curve(cut_run)
    resumed = train("sac-source", PENDULUM, out=cut_run, **RUN)
    compute = resumed["compute"]
    assert compute["attempts"] == 2 and compute["complete"] is True
    # The second attempt adds its own time to what the step-80 checkpoint carried.
    assert compute["wall_time_s"] > first["wall_time_s"] and compute["cpu_time_s"] > first["cpu_time_s"]
    curve = _curve(cut_run)
    # The lines kept from the first attempt keep its times; the later ones go on from the checkpoint.
    assert curve[:2] == before_resume[:2]
    for key in ("wall_time_s", "cpu_time_s"):
        times = [line[key] for line in curve]
        assert times == sorted(times), f"{key} went back at the resume: {times}"
        assert times[2] > first[key]
    assert whole_run[0]["compute"]["attempts"] == 1 and whole_run[0]["compute"]["complete"] is True


def test_training_progress_reads_how_far_a_run_got_its_pace_and_what_it_took(cut_run):
    from baselines.run_folder import training_progress

    curve = _curve(cut_run)
    cut = training_progress(cut_run)
    assert cut.fraction == 90 / 120 and cut.compute is None  # evaluated up to step 90, unfinished
    # The pace between the last two curve lines, over the whole run's 120 steps.
    assert cut.seconds_per_run == pytest.approx((curve[2]["wall_time_s"] - curve[1]["wall_time_s"]) / 30 * 120)
    # What it took so far, over its attempts: the last curve line's counts.
    assert cut.spent == (curve[2]["wall_time_s"], curve[2]["cpu_time_s"])
    with open(cut_run / "metrics.jsonl", "a") as f:
        f.write('{"step": 120, "target_ret')  # a line cut off by a kill is no progress
    assert training_progress(cut_run) == cut
    resumed = train("sac-source", PENDULUM, out=cut_run, **RUN)
    done = training_progress(cut_run)
    assert done.fraction == 1.0 and done.compute == TrainingCompute.parse(resumed["compute"])
    # Times that do not increase (a curve from before they were carried across resumes) give no pace.
    lines = _curve(cut_run)
    lines[-1]["wall_time_s"] = lines[-2]["wall_time_s"] - 1.0
    write_lines_atomic(cut_run / "metrics.jsonl", [json.dumps(line) for line in lines])
    assert training_progress(cut_run).seconds_per_run is None
    (cut_run / "config.json").write_text("{")
    assert training_progress(cut_run) is None and training_progress(cut_run / "absent") is None


def test_a_checkpoint_from_before_compute_was_recorded_resumes_and_says_the_times_are_partial(whole_run, cut_run):
    for checkpoint in checkpoints(cut_run):
        trainer = _trainer(checkpoint)
        del trainer["compute"]
        (checkpoint / TRAINER_FILE).write_text(json.dumps(trainer))
        (checkpoint / CHECKSUMS_FILE).unlink()  # as checkpoints of that time may lack them too
    resumed = train("sac-source", PENDULUM, out=cut_run, **RUN)
    assert resumed["returns"] == whole_run[0]["returns"]
    assert resumed["compute"]["attempts"] == 2 and resumed["compute"]["complete"] is False


def test_a_run_records_the_machines_its_attempts_ran_on(whole_run, cut_run, monkeypatch):
    """PROTOCOL §8: the same seed trains another policy on another CPU model, so a result says where
    it was trained: one entry per distinct machine, in order, carried across resumes by checkpoints."""
    import baselines.train as training
    from offdyn_bench.versions import machine

    here = machine()
    assert whole_run[0]["machines"] == [here]
    assert here["isa"] == [flag for flag in here["isa"] if flag in ("sse4_2", "avx", "fma", "avx2", "avx512f",
                                                                    "avx512_vnni", "avx512_bf16", "amx_tile")]
    assert _trainer(checkpoints(cut_run)[-1])["machines"] == [here]
    # The same run resumed on "another" machine: both are listed, and the numbers are the run's.
    elsewhere = here | {"cpu": "another CPU model", "torch_cpu_capability": "AVX2"}
    monkeypatch.setattr(training, "machine", lambda device="cpu": elsewhere)
    resumed = train("sac-source", PENDULUM, out=cut_run, **RUN)
    assert resumed["machines"] == [here, elsewhere]
    assert resumed["returns"] == whole_run[0]["returns"]


def test_a_run_records_which_code_trained_it_and_when(whole_run, cut_run, monkeypatch):
    """The package version stays 0.1.0 between releases: a result names the code revisions its
    attempts ran (carried across resumes like the machines) and when it started and finished."""
    import datetime

    import baselines.train as training
    from offdyn_bench.versions import source_revision

    here = source_revision()
    result = whole_run[0]
    assert result["source_revisions"] == [here]
    started, finished = (datetime.datetime.fromisoformat(result[key]) for key in ("started_at", "finished_at"))
    assert started <= finished and finished.utcoffset() == datetime.timedelta(0)
    first = _trainer(checkpoints(cut_run)[-1])
    assert first["source_revisions"] == [here] and isinstance(first["started_at"], str)
    # Resumed under another commit: both are listed; the start stays the first attempt's.
    other = {"commit": "0" * 40, "modified": True}
    monkeypatch.setattr(training, "source_revision", lambda: other)
    resumed = train("sac-source", PENDULUM, out=cut_run, **RUN)
    assert resumed["source_revisions"] == [here, other]
    assert resumed["started_at"] == first["started_at"] <= resumed["finished_at"]
    assert resumed["returns"] == whole_run[0]["returns"]


def test_a_checkpoint_from_before_revisions_were_recorded_says_the_earlier_ones_are_unknown(cut_run):
    from offdyn_bench.versions import source_revision

    for checkpoint in checkpoints(cut_run):
        trainer = _trainer(checkpoint)
        del trainer["source_revisions"], trainer["started_at"], trainer["compute"]["reference_updates"]
        (checkpoint / TRAINER_FILE).write_text(json.dumps(trainer))
        (checkpoint / CHECKSUMS_FILE).unlink()
    resumed = train("sac-source", PENDULUM, out=cut_run, **RUN)
    assert resumed["source_revisions"] == [None, source_revision()] and resumed["started_at"] is None
    # Nor did it count its CPU in reference updates: the whole count is unknown, not a part.
    assert "reference_updates" not in resumed["compute"]


def test_a_training_counts_its_cpu_in_reference_updates_across_a_resume(whole_run, cut_run, monkeypatch):
    import baselines.train as training
    from offdyn_bench.machine_speed import reference_update_seconds

    compute = whole_run[0]["compute"]
    # A real measurement: the CPU per update it implies is the machine's, within its noise.
    update_s = TrainingCompute.parse(compute).reference_update_s
    assert math.isfinite(compute["reference_updates"]) and 0.2 < update_s / reference_update_seconds() < 5.0

    # Resumed on a machine that takes 1 s an update: the resumed attempt adds about its own CPU
    # seconds, and the first attempt's count is kept.
    carried = _trainer(checkpoints(cut_run)[-1])["compute"]
    monkeypatch.setattr(training, "reference_update_seconds", lambda: 1.0)
    resumed = train("sac-source", PENDULUM, out=cut_run, **RUN)["compute"]
    added_cpu = resumed["cpu_time_s"] - carried["cpu_time_s"]
    assert resumed["reference_updates"] - carried["reference_updates"] == pytest.approx(added_cpu, abs=0.2)
    assert resumed["reference_updates"] > carried["reference_updates"] > 0


def test_a_checkpoint_from_before_machines_were_recorded_says_the_earlier_ones_are_unknown(cut_run):
    from offdyn_bench.versions import machine

    for checkpoint in checkpoints(cut_run):
        trainer = _trainer(checkpoint)
        del trainer["machines"]
        (checkpoint / TRAINER_FILE).write_text(json.dumps(trainer))
        (checkpoint / CHECKSUMS_FILE).unlink()
    assert train("sac-source", PENDULUM, out=cut_run, **RUN)["machines"] == [None, machine()]


def test_a_cuda_record_names_the_card_and_the_gpus_the_process_was_given(monkeypatch):
    """A CUDA number depends on the card and CUDA build; a CPU record never asks (that would
    initialise CUDA). The card is faked here: CI has none."""
    import types

    import torch

    from offdyn_bench.versions import machine

    assert "cuda" not in machine() and "cuda" not in machine("cpu")
    card = types.SimpleNamespace(name="NVIDIA H200", major=9, minor=0, total_memory=143771 * 2**20)
    asked = []
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda index: asked.append(index) or card)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3")
    record = machine("cuda:1")["cuda"]
    assert asked == [1]
    assert record["name"] == "NVIDIA H200" and record["capability"] == "9.0" and record["index"] == 1
    assert record["memory_gib"] == pytest.approx(140.4, abs=0.05) and record["visible_devices"] == "3"
    assert machine("cuda")["cuda"]["index"] == 0  # no index: the current device


def test_the_numerics_environment_is_recorded_where_set(monkeypatch):
    from offdyn_bench.versions import machine

    monkeypatch.delenv("MKL_CBWR", raising=False)
    assert "MKL_CBWR" not in machine()["numerics_environment"]
    monkeypatch.setenv("MKL_CBWR", "COMPATIBLE")
    monkeypatch.setenv("SOMETHING_ELSE", "1")
    environment = machine()["numerics_environment"]
    assert environment["MKL_CBWR"] == "COMPATIBLE" and "SOMETHING_ELSE" not in environment


@pytest.mark.parametrize("stored", [{"wall_time_s": float("nan"), "cpu_time_s": 1.0, "attempts": 1, "complete": True},
                                    {"wall_time_s": -1.0, "cpu_time_s": 1.0, "attempts": 1, "complete": True},
                                    {"wall_time_s": 1.0, "cpu_time_s": 1.0, "attempts": 0, "complete": True},
                                    {"wall_time_s": 1.0, "cpu_time_s": "1", "attempts": 1, "complete": True},
                                    "1.0 s"])
def test_compute_a_checkpoint_carries_that_is_not_time_counts_as_missing(stored):
    assert TrainingCompute.parse(stored) is None
    whole = {"wall_time_s": 2, "cpu_time_s": 3.5, "attempts": 2, "complete": False}
    assert TrainingCompute.parse(whole) == TrainingCompute(2.0, 3.5, 2, False)


def test_every_checkpoint_damaged_is_a_clear_error_and_changes_nothing(cut_run, capsys):
    for checkpoint in checkpoints(cut_run):
        (checkpoint / STATE_FILE).write_bytes(b"")
    before = _snapshot(cut_run)
    with pytest.raises(OffdynError, match=r"every checkpoint is damaged \(step_000000080: state.safetensors is "
                                          r"empty; step_000000040: .*\); nothing was changed"):
        train("sac-source", PENDULUM, out=cut_run, **RUN)
    assert _snapshot(cut_run) == before


def test_a_partial_last_metrics_line_is_dropped_on_resume(whole_run, cut_run, capsys):
    with open(cut_run / "metrics.jsonl", "a") as f:
        f.write('{"step": 120, "target_ret')  # the kill came mid-write
    resumed = train("sac-source", PENDULUM, out=cut_run, **RUN)
    err = capsys.readouterr().err
    assert "dropped a partial last line (line 4" in err and "dropped 1 line(s) after step 80" in err
    assert resumed["returns"] == whole_run[0]["returns"]
    assert [c["step"] for c in _curve(cut_run)] == [30, 60, 90, 120]
    assert [c["target_return"] for c in _curve(cut_run)] == [c["target_return"] for c in _curve(whole_run[1])]


def test_a_damaged_line_inside_the_metrics_is_an_error(cut_run):
    lines = (cut_run / "metrics.jsonl").read_text().splitlines()
    (cut_run / "metrics.jsonl").write_text("\n".join([lines[0], "garbage", *lines[1:]]) + "\n")
    before = _snapshot(cut_run)
    with pytest.raises(OffdynError, match="metrics.jsonl' line 2 is damaged"):
        train("sac-source", PENDULUM, out=cut_run, **RUN)
    assert _snapshot(cut_run) == before


@pytest.mark.parametrize("content", ["{not json", "[1, 2]", '{"algo": "sac-source"}', "\xff\xfe"])
def test_a_garbage_config_is_a_clear_error(cut_run, content):
    (cut_run / "config.json").write_text(content, errors="surrogateescape") if content != "\xff\xfe" else \
        (cut_run / "config.json").write_bytes(b"\xff\xfe")
    before = _snapshot(cut_run)
    with pytest.raises(OffdynError, match=r"config.json' is damaged|holds a run with other settings"):
        train("sac-source", PENDULUM, out=cut_run, **RUN)
    assert _snapshot(cut_run) == before


def test_only_the_two_newest_checkpoints_are_kept(tmp_path):
    train("sac-source", PENDULUM, out=tmp_path / "r", **RUN)
    assert [p.name for p in checkpoints(tmp_path / "r")] == ["step_000000080", "step_000000120"]


def test_a_second_process_on_the_same_folder_is_refused(tmp_path):
    out = tmp_path / "run"
    with run_folder_lock(out):
        with pytest.raises(OffdynError, match=f"--out '{out}' is in use by another training process"):
            train("sac-source", PENDULUM, out=out, **RUN)
        assert [p.name for p in out.iterdir()] == [".lock"]
    train("sac-source", PENDULUM, out=out, **RUN)  # the lock was released: the folder is usable


def test_the_lock_holds_across_real_processes(tmp_path):
    out = tmp_path / "run"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from pathlib import Path; from baselines.run_folder import "
         "run_folder_lock\nwith run_folder_lock(Path(sys.argv[1])):\n print('locked', flush=True); time.sleep(60)",
         str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        done = subprocess.run([sys.executable, "-m", "baselines", "train", "sac-source", "--task", PENDULUM,
                               "--steps", "40", "--out", str(out), "--no-progress"],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and done.stderr.strip().startswith("error: --out") \
            and "in use by another training process" in done.stderr and len(done.stderr.strip().splitlines()) == 1
    finally:
        holder.kill()
        holder.wait()
    assert not (out / "config.json").exists()


def test_bad_settings_fail_before_anything_is_written_and_a_fixed_rerun_works(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(OffdynError, match=r"sac-source: invalid setting sac.batch_size=-3: expected an integer >= 1"):
        train("sac-source", PENDULUM, out=out, **(RUN | {"overrides": TINY | {"sac.batch_size": "-3"}}))
    assert not out.exists()
    assert train("sac-source", PENDULUM, out=out, **RUN) is not None


@pytest.mark.parametrize("algo, key, value, message", [
    ("sac-source", "sac.discount", "1.5", "sac.discount=1.5: expected a number in [0, 1]"),
    ("sac-source", "sac.actor_lr", "NaN", "sac.actor_lr=NaN: expected a number > 0"),
    ("sac-source", "sac.hidden_sizes", '["a"]', 'sac.hidden_sizes=["a"]: expected a non-empty list of integers'),
    ("sac-source", "sac.hidden_sizes", "[]", "sac.hidden_sizes=[]: expected a non-empty list"),
    ("sac-source", "sac.log_std_min", "5", "sac.log_std_min=5.0: expected a number below log_std_max=2.0"),
    ("sac-source", "random_steps", "-1", "random_steps=-1: expected an integer >= 0"),
    ("cql", "n_action_samples", "0", "n_action_samples=0: expected an integer >= 1"),
    ("darc", "target_data", "sometimes", "target_data=\"sometimes\": expected one of 'offline', 'online'"),
    ("h2o", "kl_clip", "[1, 0.5]", "kl_clip=[1, 0.5]: expected a pair [low, high]"),
    ("h2o", "sac.batch_size", "1", "sac.batch_size=1: expected an integer >= 2 (h2o splits it in halves)"),
    ("dap", "classifier.ensemble_size", "0", "classifier.ensemble_size=0: expected an integer >= 1"),
])
def test_every_config_value_is_checked(tmp_path, pendulum_dataset, algo, key, value, message):
    dataset = str(pendulum_dataset) if algo in ("cql", "darc", "h2o", "dap") else None
    with pytest.raises(OffdynError) as raised:
        train(algo, PENDULUM, steps=10, out=tmp_path / "run", dataset=dataset, overrides={key: value})
    assert message in str(raised.value)
    assert not (tmp_path / "run").exists()


def test_unknown_settings_suggest_the_nested_name(tmp_path):
    with pytest.raises(UnknownNameError, match="unknown setting of cql 'batch_size'; closest valid names: "
                                               "'sac.batch_size'"):
        train("cql", PENDULUM, steps=10, out=tmp_path / "run", overrides={"batch_size": "3"})
    with pytest.raises(OffdynError, match="invalid sac='3'; expected one setting of the group, e.g. sac.hidden_sizes"):
        train("cql", PENDULUM, steps=10, out=tmp_path / "run", overrides={"sac": "3"})
    with pytest.raises(OffdynError, match="--eval-every=0: expected an integer >= 1"):
        train("sac-source", PENDULUM, steps=10, out=tmp_path / "run", eval_every=0)
    assert not (tmp_path / "run").exists()


def test_an_out_path_under_a_file_or_unwritable_is_refused_before_any_work(tmp_path, monkeypatch):
    (tmp_path / "afile").write_text("mine")
    with pytest.raises(OffdynError, match=f"lies under '{tmp_path / 'afile'}', which is a file, not a folder"):
        train("sac-source", PENDULUM, out=tmp_path / "afile" / "sub", **RUN)
    with pytest.raises(OffdynError, match="exists and is not a folder"):
        train("sac-source", PENDULUM, out=tmp_path / "afile", **RUN)
    assert (tmp_path / "afile").read_text() == "mine"
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode: False if Path(path) == locked else real_access(path, mode))
    with pytest.raises(OffdynError, match=f"'{locked / 'run'}' cannot be created: '{locked}' is not writable"):
        train("sac-source", PENDULUM, out=locked / "run", **RUN)
    assert not (locked / "run").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through any permission bits")
def test_a_read_only_parent_folder_is_refused(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(OffdynError, match="is not writable"):
            train("sac-source", PENDULUM, out=locked / "run", **RUN)
    finally:
        locked.chmod(0o700)


def test_a_budget_too_short_to_learn_is_warned_about_and_recorded(tmp_path, capsys, pendulum_dataset):
    result = train("sac-source", PENDULUM, out=tmp_path / "a", **(RUN | {"steps": 20, "checkpoint_every": 20}))
    err = capsys.readouterr().err
    assert "warning: --steps 20 is not above random_steps=20: this sac-source run makes no gradient update" in err
    assert "minimum useful budget is more than 20 steps" in err
    assert result["warnings"] and "random_steps=20" in result["warnings"][0]
    result = train("darc", PENDULUM, out=tmp_path / "b", dataset=str(pendulum_dataset),
                   **(RUN | {"steps": 40, "overrides": TINY | {"warmup_steps": "50"}}))
    assert "warmup_steps=50: this darc run never applies its reward correction" in result["warnings"][0]
    assert "warning:" in capsys.readouterr().err


def test_cli_errors_are_one_line_with_no_progress_bar(tmp_path):
    runner = CliRunner()
    base = ["train", "sac-source", "--task", PENDULUM, "--steps", "40", "--out", str(tmp_path / "run")]
    for extra in (["--set", "sac.batch_size=-3"], ["--set", "batch_size=3"], ["--eval-every", "-2"]):
        done = runner.invoke(app, base + extra)  # progress bar on (the default)
        assert done.exit_code == 2, done.output
        assert done.output.startswith("error: ") and len(done.output.strip().splitlines()) == 1, done.output
    assert not (tmp_path / "run").exists()
    (tmp_path / "afile").write_text("")
    done = runner.invoke(app, base[:-1] + [str(tmp_path / "afile" / "sub")])
    assert done.exit_code == 2 and "which is a file, not a folder" in done.output


def test_cli_resume_error_comes_before_the_progress_bar(cut_run):
    for checkpoint in checkpoints(cut_run):
        (checkpoint / STATE_FILE).unlink()
    args = ["train", "sac-source", "--task", PENDULUM, "--steps", "120", "--out", str(cut_run), "--seed", "2",
            "--eval-every", "30", "--eval-episodes", "1", "--checkpoint-every", "40"]
    for key, value in TINY.items():
        args += ["--set", f"{key}={value}"]
    done = CliRunner().invoke(app, args)
    assert done.exit_code == 2 and done.output.startswith("error: cannot resume")
    assert len(done.output.strip().splitlines()) == 1, done.output


@pytest.mark.slow
def test_two_concurrent_cli_runs_on_one_folder_give_one_run(tmp_path, pendulum_dataset):
    args = [sys.executable, "-m", "baselines", "train", "sac-source", "--task", PENDULUM, "--steps", "300",
            "--out", str(tmp_path / "run"), "--no-progress", "--eval-episodes", "1", "--set", "random_steps=20"]
    first = subprocess.Popen(args, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (tmp_path / "run" / "config.json").exists() and time.time() < deadline:
        time.sleep(0.05)
    second = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert first.wait(timeout=600) == 0
    assert second.returncode == 2 and "in use by another training process" in second.stderr
    assert [c["step"] for c in _curve(tmp_path / "run")] == list(range(15, 301, 15))


def test_a_failed_atomic_write_keeps_the_old_file_and_leaves_no_partial(tmp_path, monkeypatch):
    path = tmp_path / "state.json"
    write_json_atomic(path, {"old": True})

    def broken_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", broken_replace)
    for write in (lambda: write_json_atomic(path, {"new": True}), lambda: write_lines_atomic(path, ["new"])):
        with pytest.raises(OSError, match="No space left"):
            write()
        assert path.read_text() == '{\n "old": true\n}'
        assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]
