"""Sweep specs: every mistake is one clear line, found before anything is written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.sweep import SweepSpec, load_spec, parse_spec
from offdyn_bench.sweep.runs import expand, seed_groups

TASK = "invertedpendulum-gravity-3.0"

runner = CliRunner()


def _refused(tmp_path, spec, *, suffix=".json", text=None):
    """Run `offdyn-bench sweep` on a bad spec: exit code 2, one `error:` line, nothing written."""
    path = tmp_path / f"spec{suffix}"
    if text is not None:
        path.write_text(text)
    else:
        path.write_text(json.dumps(spec))
    result = runner.invoke(app, ["sweep", str(path), "--quiet"])
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert not (tmp_path / "out").exists()
    return lines[0]


@pytest.mark.parametrize("changes, message", [
    ({"methods": ["sac-sorce"], "overrides": {}}, "methods: unknown algorithm 'sac-sorce'; closest valid names: 'sac-source'"),
    ({"tasks": ["invertedpendulum-gravity-3.1"]}, "tasks: unknown task"),
    ({"track": "offline"}, "track: unknown track 'offline'"),
    ({"steps": None, "budget": "medium"}, "budget: unknown budget 'medium'"),
    ({"overrides": {"sac-source": {"batch_size": 8}}}, ("overrides.sac-source: unknown setting of sac-source "
                                                        "'batch_size'; closest valid names: 'sac.batch_size'")),
    ({"overrides": {"sac-source": {"sac.batch_size": -3}}}, "overrides.sac-source: "),
])
def test_names_the_registry_and_protocol_refuse_are_one_line_each(tmp_path, tiny_spec, write_spec, changes, message):
    line = _refused(tmp_path, tiny_spec(tmp_path / "out", **changes))
    assert message in line


def test_methods_off_their_track_are_all_listed_before_anything_runs(tmp_path, tiny_spec, write_spec):
    line = _refused(tmp_path, tiny_spec(tmp_path / "out", methods=["sac-source", "darc-online", "matl", "dap"]))
    assert "the protocol refuses 2 method(s) on track 'offline-target'" in line
    assert "darc-online belongs on the 'online-target' track" in line and "matl belongs on" in line
    assert "dap belongs" not in line and "sac-source belongs" not in line


@pytest.mark.parametrize("seeds, expected", [
    (0, "seeds: got 0; expected a count in [1, 1000]"),
    ([1, 1], "seeds: got [1, 1]; expected distinct seeds"),
    ([0, -1], "seeds: got [0, -1]; expected a count >= 1"),
    ("five", 'seeds: got "five"; expected a count >= 1'),
    (True, "seeds: got true; expected a count >= 1"),
    ([], "seeds: got []; expected a count >= 1"),
])
def test_bad_seeds(tmp_path, tiny_spec, write_spec, seeds, expected):
    assert expected in _refused(tmp_path, tiny_spec(tmp_path / "out", seeds=seeds))


@pytest.mark.parametrize("changes, expected", [
    ({"seed": 3}, "unknown key 'seed' (did you mean 'seeds'?); valid keys: methods, tasks, seeds"),
    ({"training": {"eval_every": 10, "checkpoint": 5}}, ("training: unknown key 'checkpoint'; valid keys: "
                                                         "eval_every, eval_episodes, checkpoint_every")),
    ({"budget": "lite"}, "give exactly one of budget (lite|full, the protocol's) and steps"),
    ({"steps": None}, "give exactly one of budget"),
    ({"steps": 0}, "steps: got 0; expected an integer >= 1"),
    ({"methods": []}, "methods: got []; expected a non-empty list of method names"),
    ({"methods": ["dap", "dap"]}, "methods: got [\"dap\", \"dap\"]; expected each method once"),
    ({"tasks": 7}, "tasks: got 7; expected 'core' (the protocol's core suite) or a non-empty list"),
    ({"max_retries": -1}, "max_retries: got -1; expected an integer in [0, 100]"),
    ({"cpus_per_run": 0}, "cpus_per_run: got 0; expected a number > 0"),
    ({"gpus_per_run": 1}, "gpus_per_run is 1 but device is 'cpu'"),
    ({"overrides": {"dap": {"sac.batch_size": 8}}}, "overrides: 'dap' is not one of the sweep's methods (sac-source)"),
    ({"track": None}, "missing key 'track'"),
])
def test_bad_keys_and_values(tmp_path, tiny_spec, write_spec, changes, expected):
    assert expected in _refused(tmp_path, tiny_spec(tmp_path / "out", **changes))


def test_unreadable_files_are_one_line(tmp_path):
    assert "not valid YAML (line 2" in _refused(tmp_path, None, suffix=".yaml", text="methods: [a\nseeds: 2\n")
    assert "not valid JSON (line 1" in _refused(tmp_path, None, text="{methods: 1}")
    assert "expected a mapping of keys" in _refused(tmp_path, None, suffix=".yaml", text="- just\n- a list\n")
    result = runner.invoke(app, ["sweep", str(tmp_path / "missing.yaml")])
    assert result.exit_code == 2 and result.output.startswith("error: cannot read sweep spec")


def test_yaml_and_json_give_the_same_spec(tmp_path, tiny_spec, write_spec):
    yaml_path = tmp_path / "spec.yaml"
    yaml_path.write_text(f"""
methods: sac-source
tasks: [{TASK}]
seeds: [3, 1, 2]
track: offline-target
steps: 300
out: {tmp_path / 'out'}
overrides:
  sac-source: {{sac.hidden_sizes: [32, 32], random_steps: 40}}
""")
    spec = load_spec(yaml_path)
    same = load_spec(write_spec(tmp_path / "spec.json", {
        "methods": ["sac-source"], "tasks": [TASK], "seeds": [1, 2, 3], "track": "offline-target", "steps": 300,
        "out": str(tmp_path / "out"), "overrides": {"sac-source": {"sac.hidden_sizes": "[32, 32]",
                                                                    "random_steps": "40"}}}))
    assert isinstance(spec, SweepSpec)
    assert spec.to_dict() | {"source": ""} == same.to_dict() | {"source": ""}
    assert spec.seeds == (1, 2, 3) and spec.max_retries == 2 and spec.evaluation_episodes == 20


def test_expansion_names_folders_and_commands_deterministically(tmp_path, tiny_spec, write_spec):
    spec = parse_spec(tiny_spec(tmp_path / "out", seeds=[0, 1, 2, 5], seeds_per_run=2))
    runs = expand(spec)
    assert [run.run_id for run in runs] == [f"sac-source/{TASK}/seeds-0-1", f"sac-source/{TASK}/seed-2",
                                           f"sac-source/{TASK}/seed-5"]
    assert runs[0].folder == tmp_path / "out" / "runs" / "sac-source" / TASK / "seeds-0-1"
    args = list(runs[0].train_args)
    assert args[:2] == ["train", "sac-source"] and args[args.index("--n-seeds") + 1] == "2"
    assert "sac.hidden_sizes=[32, 32]" in args and args[-2:] == ["--out", str(runs[0].folder)]
    assert [run.run_id for run in expand(spec)] == [run.run_id for run in runs]
    assert seed_groups([4, 0, 1, 2, 3], 3) == [(0, 1, 2), (3, 4)]


def test_runs_start_seed_group_by_seed_group_so_a_stopped_sweep_has_comparable_cells(tmp_path, tiny_spec):
    spec = parse_spec(tiny_spec(tmp_path / "out", methods=["sac-source", "sac-target"],
                                tasks=[TASK, "invertedpendulum-action-delay-1"], seeds=[2, 0, 1]))
    runs = expand(spec)
    assert [run.seeds for run in runs] == [(0,)] * 4 + [(1,)] * 4 + [(2,)] * 4
    # Within a seed, method then task: the shared source training comes before the run that scores it.
    assert [run.run_id for run in runs[:4]] == [f"sac-source/{TASK}/seed-0",
                                                "sac-source/invertedpendulum-action-delay-1/seed-0",
                                                f"sac-target/{TASK}/seed-0",
                                                "sac-target/invertedpendulum-action-delay-1/seed-0"]
    assert runs[1].shared_training == runs[0].folder and runs[0].shared_training is None


def test_core_expands_to_the_protocol_core_suite(tmp_path, tiny_spec, write_spec):
    from offdyn_bench.protocol import CORE_SUITE

    spec = parse_spec(tiny_spec(tmp_path / "out", methods=["dap"], tasks="core", seeds=5, steps=None,
                                budget="lite", overrides={}))
    runs = expand(spec)
    assert len(runs) == 5 * len(CORE_SUITE) and {run.task for run in runs} == set(CORE_SUITE)
    assert all("--budget" in run.train_args and "lite" in run.train_args for run in runs)
    # The official datasets the runs need are known before any run starts.
    assert all(run.official_dataset and run.official_dataset.endswith("/source-policy-v0") for run in runs)
    assert not (tmp_path / "out").exists()


def test_a_method_without_a_dataset_for_its_task_is_refused_at_expansion(tmp_path, tiny_spec, write_spec):
    line = _refused(tmp_path, tiny_spec(tmp_path / "out", methods=["sac-source", "dap"], overrides={}))
    assert f"no official offline-target dataset for dap on {TASK}" in line and "set dataset" in line


def test_dry_run_lists_runs_and_writes_nothing(tmp_path, tiny_spec, write_spec):
    path = write_spec(tmp_path / "spec.json", tiny_spec(tmp_path / "out"))
    result = runner.invoke(app, ["sweep", str(path), "--dry-run"])
    assert result.exit_code == 0, result.output
    assert f"sac-source/{TASK}/seed-1 (to run)" in result.output and "offdyn-bench train sac-source" in result.output
    assert not (tmp_path / "out").exists()


def test_paths_in_the_spec_are_made_absolute_for_workers_in_other_folders(tmp_path, monkeypatch, tiny_spec):
    monkeypatch.chdir(tmp_path)
    spec = parse_spec(tiny_spec("out", dataset="collect:runs/behaviour:500"))
    assert spec.out == tmp_path / "out" and spec.dataset == f"collect:{tmp_path / 'runs' / 'behaviour'}:500"
    assert parse_spec(tiny_spec("out", dataset="data/target.npz")).dataset == str(tmp_path / "data" / "target.npz")
    for unchanged in ("collect:random:500", "offdyn/hopper-gravity-0p5/source-policy-v0"):
        assert parse_spec(tiny_spec("out", dataset=unchanged)).dataset == unchanged


def test_an_out_that_is_a_file_is_one_line(tmp_path, tiny_spec):
    (tmp_path / "out").write_text("a file")
    path = tmp_path / "spec.json"
    path.write_text(json.dumps(tiny_spec(tmp_path / "out")))
    result = runner.invoke(app, ["sweep", str(path), "--quiet"])
    assert result.exit_code == 2 and result.output.strip().count("\n") == 0
    assert "exists and is not a folder" in result.output and (tmp_path / "out").read_text() == "a file"


def test_a_second_sweep_on_the_same_out_stops_at_once(tmp_path, tiny_spec):
    import fcntl
    import os

    from offdyn_bench.errors import OffdynError
    from offdyn_bench.sweep.driver import LOCK_FILE, STATE_FILE, run_sweep

    out = tmp_path / "out"
    out.mkdir()
    fd = os.open(out / LOCK_FILE, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(OffdynError, match="another sweep is running on .*sweep.lock is locked"):
            run_sweep(parse_spec(tiny_spec(out)), echo=None)
    finally:
        os.close(fd)
    assert not (out / STATE_FILE).exists() and not (out / "runs").exists()


def test_an_online_method_over_the_tracks_target_steps_is_refused_at_expansion(tmp_path, tiny_spec):
    line = _refused(tmp_path, tiny_spec(tmp_path / "out", methods=["darc-online"], track="online-target",
                                        overrides={"darc-online": {"target_step_every": 5}}))
    assert "darc-online would take 60 target steps per seed; the online-target track allows 30" in line
    line = _refused(tmp_path, tiny_spec(tmp_path / "out", methods=["darc"], overrides={"darc": {"target_data": "online"}}))
    assert "darc steps the target environment; the offline-target track allows no target interaction" in line


def test_offline_source_runs_install_both_official_datasets_first(tmp_path, tiny_spec, write_spec):
    """A sweep on the offline-source tracks installs each task's source dataset as well as its target
    one before any run starts, and records it as the run's setting, as train does."""
    from offdyn_bench.sweep.runs import official_datasets

    for track, method, target in (("offline-source-offline-target", "dara", "/source-policy-v0"),
                                  ("offline-source-online-target", "h2o-offline-source", None)):
        spec = parse_spec(tiny_spec(tmp_path / track, methods=[method], tasks=["hopper-gravity-0.5"], seeds=2,
                                    steps=None, budget="lite", overrides={}, track=track))
        runs = expand(spec)
        assert [run.official_source_dataset for run in runs] == ["offdyn/hopper-gravity-0p5/source-v0"] * 2
        assert all(run.settings["source_dataset"] == run.official_source_dataset for run in runs)
        expected = (["offdyn/hopper-gravity-0p5" + target] if target else []) + ["offdyn/hopper-gravity-0p5/source-v0"]
        assert official_datasets(runs) == expected


def test_a_track_that_is_not_text_names_all_four_tracks(tmp_path, tiny_spec, write_spec):
    line = _refused(tmp_path, tiny_spec(tmp_path / "out", track=3))
    for track in ("offline-target", "online-target", "offline-source-offline-target", "offline-source-online-target"):
        assert track in line


_SHIPPED_SPECS = sorted(p.name for p in (Path(__file__).resolve().parents[2] / "examples" / "sweeps").iterdir()
                        if p.suffix in (".yaml", ".json"))


def test_the_shipped_specs_are_found():
    assert {"oracle-lite.yaml", "reference-lite.yaml", "hopper-candidates-lite.yaml", "tiny.json"} <= set(_SHIPPED_SPECS)


@pytest.mark.parametrize("name", _SHIPPED_SPECS)
def test_every_shipped_spec_expands(name, tmp_path):
    path = Path(__file__).resolve().parents[2] / "examples" / "sweeps" / name
    runs = expand(load_spec(path, out=tmp_path / "out"))
    assert runs and all(run.folder.is_relative_to(tmp_path / "out") for run in runs)
    assert not (tmp_path / "out").exists()  # expanding writes nothing


H2O_TASK = "halfcheetah-h2o-gravity-2.0"


def test_datasets_runs_each_data_method_once_per_quality_and_names_the_dataset_in_its_folder(tmp_path, tiny_spec):
    """The H2O paper's Table 1 grid: every data-hungry method on each quality, the reference point
    (which takes no target data) once per task."""
    spec = parse_spec(tiny_spec(tmp_path / "out", methods=["h2o", "sac-source"], tasks=[H2O_TASK], seeds=2,
                                steps=None, budget="lite", overrides={},
                                datasets=["medium", "medium-replay", "medium-expert"]))
    runs = expand(spec)
    h2o = [run for run in runs if run.method == "h2o"]
    assert [run.run_id for run in h2o] == [f"h2o/{H2O_TASK}/{quality}-v0.seed-{seed}" for seed in (0, 1)
                                           for quality in ("medium", "medium-replay", "medium-expert")]
    for run in h2o:
        quality_id = f"offdyn/halfcheetah-h2o-gravity-2p0/{run.dataset_tag}"
        assert run.folder.name == f"{run.dataset_tag}.seed-{run.seeds[0]}"
        assert run.train_args[run.train_args.index("--dataset") + 1] == quality_id
        assert run.settings["dataset"] == quality_id and run.official_dataset == quality_id
    # Three runs on one task and seed, three folders: nothing is shared or overwritten.
    assert len({run.folder for run in h2o}) == len(h2o)
    assert [run.run_id for run in runs if run.method == "sac-source"] == [f"sac-source/{H2O_TASK}/seed-0",
                                                                          f"sac-source/{H2O_TASK}/seed-1"]


@pytest.mark.parametrize("changes, expected", [
    ({"datasets": []}, "datasets: got []; expected a non-empty list of dataset qualities"),
    ({"datasets": ["medium", "medium"]}, "datasets: got [\"medium\", \"medium\"]; expected each quality once"),
    ({"datasets": [3]}, "datasets: got [3]; expected a non-empty list of dataset qualities"),
    ({"datasets": ["medium"], "dataset": "collect:random:500"}, "give at most one of dataset"),
])
def test_bad_datasets_are_one_line(tmp_path, tiny_spec, changes, expected):
    assert expected in _refused(tmp_path, tiny_spec(tmp_path / "out", methods=["h2o"], overrides={}, **changes))


def test_datasets_a_task_lacks_are_all_named_at_expansion(tmp_path, tiny_spec):
    line = _refused(tmp_path, tiny_spec(tmp_path / "out", methods=["h2o"], tasks=[H2O_TASK, "hopper-gravity-0.5"],
                                        overrides={}, datasets=["medium", "expert"]))
    assert "datasets: unknown quality 'expert'; expected qualities from random, source-policy" in line
    line = _refused(tmp_path, tiny_spec(tmp_path / "out", methods=["h2o"], tasks=[H2O_TASK, "hopper-gravity-0.5"],
                                        overrides={}, datasets=["medium", "random"]))
    assert "hopper-gravity-0.5 has no medium dataset (its qualities: random, source-policy, source)" in line
    assert H2O_TASK not in line  # it has both
