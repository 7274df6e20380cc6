"""The command line's front door: sub-commands load on first use, ``--version``, and help that
lists every sub-command without importing the heavy libraries behind them."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from importlib import metadata

import pytest
from typer.testing import CliRunner

from offdyn_bench.cli import SUB_COMMANDS, app, load_sub_command, version_lines

runner = CliRunner()
HEAVY = ("torch", "scipy", "matplotlib", "mujoco.sysid", "minari", "baselines.train", "offdyn_bench.diagnose.loop")


def _modules_after(code: str) -> set[str]:
    """The heavy modules loaded by ``code`` in a fresh interpreter."""
    script = textwrap.dedent(f"""
        import json, sys
        {code}
        print(json.dumps(sorted(m for m in {list(HEAVY)!r} if m in sys.modules)))
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True)
    return set(json.loads(result.stdout.strip().splitlines()[-1]))


def test_importing_the_cli_imports_no_heavy_library():
    assert _modules_after("import offdyn_bench.cli") == set()


@pytest.mark.parametrize("args", [["--help"], ["tasks", "list", "--help"], ["--version"]])
def test_help_and_version_import_no_heavy_library(args):
    code = f"""
        from offdyn_bench.cli import app
        try:
            app({args!r}, standalone_mode=False)
        except SystemExit:
            pass
    """
    assert _modules_after(code) == set()


def test_import_offdyn_bench_still_registers_every_pair():
    code = """
        import gymnasium, offdyn_bench
        assert "offdyn/Hopper-gravity-0.5-target-v0" in gymnasium.registry
        assert callable(offdyn_bench.make_robot_env) and "make_robot_env" in dir(offdyn_bench)
    """
    assert _modules_after(code) == set()


def test_help_lists_every_sub_command_with_its_own_help_line():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0, result.output
    for name in [*SUB_COMMANDS, "demo"]:
        assert name in result.output
    for name, entry in SUB_COMMANDS.items():
        command = load_sub_command(name)
        own_help = " ".join((command.help or "").split("\n\n")[0].split())
        assert entry.help == own_help, f"{name}: the table says {entry.help!r}, the command {own_help!r}"


def test_a_sub_command_runs_and_a_typo_is_pointed_at():
    result = runner.invoke(app, ["tasks", "list", "--robot", "hopper", "--shift", "gravity"])
    assert result.exit_code == 0 and "hopper-gravity-0.5" in result.output
    typo = runner.invoke(app, ["taks", "list"])
    assert typo.exit_code == 2
    assert "No such command 'taks'" in typo.output and "tasks" in typo.output


def test_version_prints_the_suite_and_its_libraries():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    lines = result.output.strip().splitlines()
    assert lines[0] == "offdyn-bench 0.1.0"
    assert lines[1:] == [f"{name} {metadata.version(name)}" for name in ("mujoco", "gymnasium", "minari", "torch")]
    assert version_lines() == lines


def test_help_does_not_even_load_mujoco():
    """Loading MuJoCo (and its GLFW library) is about a quarter of the CLI's start-up CPU time;
    declaring and registering effects does not need it, so help does not pay for it."""
    code = """
        import sys
        from offdyn_bench.cli import app
        for args in (["--help"], ["tasks", "list", "--help"]):
            try:
                app(args, standalone_mode=False)
            except SystemExit:
                pass
        assert "mujoco" not in sys.modules, "help imported mujoco"
    """
    _modules_after(code)


@pytest.mark.parametrize("args, message", [
    (["--n-seeds", "0"], "--n-seeds 0: expected 1 or more"),
    (["--training-steps", "-1"], "--training-steps -1: expected 0 \\(no training\\) or more"),
    (["--task", "hopper-gravity-9"], "unknown task 'hopper-gravity-9'"),
    (["--out", "{blocked}/demo"], "--out '.*/a-file/demo': cannot create the demo's folder"),
])
def test_demo_refuses_bad_arguments_before_its_first_step(tmp_path, args, message):
    import re

    blocked = tmp_path / "a-file"
    blocked.write_text("")
    args = [a.replace("{blocked}", str(blocked)) for a in args]
    out = ["--out", str(tmp_path / "demo-out")] if "--out" not in args else []
    result = runner.invoke(app, ["demo", *args, *out])
    assert result.exit_code == 2 and re.search("error: " + message, result.output), result.output
    assert "The task grid" not in result.output  # nothing ran
    assert not (tmp_path / "demo-out").exists()


def test_datasets_build_refuses_an_out_folder_it_cannot_create_before_building(tmp_path):
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    result = runner.invoke(app, ["datasets", "build", "offdyn/hopper-gravity-0p5/random-v0", "--no-install",
                                 "--out", str(blocked / "remote")])
    assert result.exit_code == 2, result.output
    assert f"error: --out '{blocked / 'remote'}': cannot create it" in result.output
    assert "transitions in" not in result.output  # refused before the build, not after it
