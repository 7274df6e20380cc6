"""From a finished protocol sweep to the leaderboard: the printed `leaderboard submit` command and
`--submit` both give a valid submission. The runs' evaluations are written by hand here (training
the core suite at the lite budget is hours), in the format `offdyn-bench evaluate` writes."""

from __future__ import annotations

import json
import shlex

from typer.testing import CliRunner

from offdyn_bench.cli import app
from offdyn_bench.protocol import CORE_SUITE, EPISODE_SEEDS, PROTOCOL_VERSION, official_dataset
from offdyn_bench.sweep import parse_spec
from offdyn_bench.sweep.driver import run_sweep, summary_lines
from offdyn_bench.sweep.runs import expand
from offdyn_bench.tasks import get_task

runner = CliRunner()
VERSIONS = {"offdyn_bench": "0.1.0", "mujoco": "3.17.0", "gymnasium": "1.4.0", "minari": "0.5.4",
            "torch": "2.13.0+cpu", "numpy": "2.4.6", "python": "3.11.7"}


def _evaluation(run, index: int) -> dict:
    pair = get_task(run.task)
    return {
        "format": "offdyn-bench/evaluation", "format_version": 1, "protocol_version": PROTOCOL_VERSION,
        "task": run.task, "task_version": pair.version, "target_env_id": pair.env_id("target"), "side": "target",
        "env_id": pair.env_id("target"), "track": "offline-target", "budget": "lite", "method": run.method,
        "agent": {"kind": "run", "path": str(run.folder), "checkpoint": "step_000100000",
                  "policy_sha256": {str(seed): f"{seed:02d}" * 32 for seed in run.seeds}},
        "steps": 100_000, "dataset": {"dataset_id": official_dataset(run.task, "offline-target"), "sha256": "ab" * 32},
        "train_command": shlex.join(["offdyn-bench", *run.train_args]),
        "episode_seeds": list(EPISODE_SEEDS),
        "seeds": [{"seed": seed, "returns": [float(100 * index + seed + e) for e in range(len(EPISODE_SEEDS))]}
                  for seed in run.seeds],
        "protocol_conformant": True, "notes": [], "versions": VERSIONS,
        "command": shlex.join(["offdyn-bench", *run.evaluate_args]),
    }


def test_a_finished_protocol_sweep_prints_a_submit_command_that_works(tmp_path, monkeypatch):
    spec = parse_spec({"methods": ["dap"], "tasks": "core", "seeds": 5, "track": "offline-target", "budget": "lite",
                       "out": str(tmp_path / "out")})
    for index, run in enumerate(expand(spec)):
        run.folder.mkdir(parents=True)
        (run.folder / "evaluation.json").write_text(json.dumps(_evaluation(run, index)))

    def no_subprocess(*args, **kwargs):
        raise AssertionError("a finished sweep starts no process")

    monkeypatch.setattr("offdyn_bench.sweep.execute.subprocess.Popen", no_subprocess)
    report = run_sweep(spec, echo=None, submit=True, description="DAP, the suite's implementation")
    assert report.launched == 0 and report.submissions == {"dap": []}
    written = tmp_path / "out" / "submission" / "dap.json"
    assert report.submitted == {"dap": written}
    document = json.loads(written.read_text())
    assert set(document["tasks"]) == set(CORE_SUITE) and document["budget"] == "lite"
    assert [s["seed"] for s in document["tasks"]["hopper-gravity-0.5"]["seeds"]] == [0, 1, 2, 3, 4]

    command = next(line for line in summary_lines(report) if "offdyn-bench leaderboard submit" in line)
    args = shlex.split(command.split("submit with: ", 1)[1])[1:]
    assert args[:3] == ["leaderboard", "submit", str(tmp_path / "out" / "submission" / "dap")]
    written.unlink()
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "13 tasks x 5 seeds" in result.output and json.loads(written.read_text())["tasks"] == document["tasks"]
