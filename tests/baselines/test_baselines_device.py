"""Training on a device: ``--device cpu|cuda|auto``, errors before anything is written, one device
per run folder, (where there is CUDA) determinism per device, and the CUDA-graph update, which must
compute exactly what the eager update computes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from baselines.algorithms import ALGORITHMS, get_algorithm
from baselines.method import MethodContext
from baselines.online_sac import Config as OnlineConfig
from baselines.online_sac import build_source
from baselines.sac import Batch, SACConfig
from baselines.train import resolve_device, train
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError

PENDULUM = "invertedpendulum-kinematic-slider-hard"
TINY = {"sac.hidden_sizes": "[16, 16]", "sac.batch_size": "16", "random_steps": "20"}
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device visible to torch")
no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error where there is no CUDA")


def test_auto_and_cpu_resolve_and_other_names_are_refused():
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(OffdynError, match=r"--device 'tpu': expected cpu, cuda, cuda:N or auto"):
        resolve_device("tpu")
    with pytest.raises(OffdynError, match="expected cpu, cuda, cuda:N or auto"):
        resolve_device("cuda:x")


@no_cuda
def test_cuda_without_a_device_fails_before_anything_is_written(tmp_path):
    with pytest.raises(OffdynError, match="--device cuda: this torch .* sees no CUDA device; use --device cpu or auto"):
        train("sac-source", PENDULUM, steps=40, out=tmp_path / "run", overrides=TINY, progress=False, device="cuda")
    assert not (tmp_path / "run").exists()
    result = CliRunner().invoke(app, ["train", "sac-source", "--task", PENDULUM, "--steps", "40", "--out",
                                      str(tmp_path / "cli"), "--device", "cuda:0", "--no-progress"])
    assert result.exit_code == 2 and "error: --device cuda:0: this torch" in result.output
    assert not (tmp_path / "cli").exists()


def test_the_device_is_recorded_and_a_run_resumes_only_on_its_own(tmp_path):
    out = tmp_path / "run"
    assert train("sac-source", PENDULUM, steps=60, out=out, overrides=TINY, eval_episodes=1, progress=False,
                 stop_after=30, checkpoint_every=30) is None
    config = json.loads((out / "config.json").read_text())
    assert config["device"] == "cpu"
    # A run folder from another device (written as a CUDA run would be) is not resumed on this one.
    config["device"] = "cuda:0"
    (out / "config.json").write_text(json.dumps(config))
    before = sorted(p.name for p in out.rglob("*"))
    with pytest.raises(OffdynError, match="was trained on cuda:0, not cpu; nothing was changed"):
        train("sac-source", PENDULUM, steps=60, out=out, overrides=TINY, eval_episodes=1, progress=False,
              checkpoint_every=30)
    assert sorted(p.name for p in out.rglob("*")) == before


@pytest.mark.parametrize("algo", ["sac-target", "cql"])
def test_cuda_graph_on_a_cpu_is_refused_before_anything_is_written(algo, tmp_path, pendulum_dataset):
    context = MethodContext(observation_dim=4, action_dim=1, seeds=(0,))
    if algo == "sac-target":
        with pytest.raises(OffdynError, match=r"cuda_graph=true needs --device cuda .* this run is on cpu"):
            build_source(OnlineConfig(sac=SACConfig(hidden_sizes=(8,)), cuda_graph=True), context)
    dataset = ["--dataset", str(pendulum_dataset)] if algo == "cql" else []
    result = CliRunner().invoke(app, ["train", algo, "--task", PENDULUM, "--steps", "40", "--out", str(tmp_path / "run"),
                                      "--set", "cuda_graph=true", "--device", "cpu", "--no-progress", *dataset])
    assert result.exit_code != 0 and "cuda_graph=true needs --device cuda" in result.output
    assert not (tmp_path / "run").exists()


def _batch(n_seeds: int, size: int, seed: int):
    from baselines.sac import Batch

    g = torch.Generator().manual_seed(seed)
    return Batch(torch.randn(n_seeds, size, 5, generator=g), torch.rand(n_seeds, size, 2, generator=g) * 2 - 1,
                 torch.randn(n_seeds, size, generator=g), torch.randn(n_seeds, size, 5, generator=g),
                 torch.zeros(n_seeds, size))


@pytest.mark.parametrize("started", [False, True], ids=["fresh-optimizers", "started-optimizers"])
def test_a_rewind_undoes_updates_in_place_so_the_next_update_is_the_eager_one(started):
    """What a graph's warm-up relies on (here on the CPU): after real updates, rewinding puts
    parameters, targets, optimizer states and random streams back into the same storage, so the
    next update equals a twin's that never made them, fresh optimizers or a resumed run's alike."""
    from baselines.sac import SACAgent, _Rewind, sac_update

    config = SACConfig(hidden_sizes=(16, 16), batch_size=8)
    agent, twin = (SACAgent(5, 2, seeds=[0, 1], config=config) for _ in range(2))
    if started:
        for i in range(2):
            sac_update(agent, _batch(2, 8, i)), sac_update(twin, _batch(2, 8, i))
    state = agent.update_state()
    storage = [t.data_ptr() for t in state.tensors]
    rewind = _Rewind(state)
    for i in range(3):
        sac_update(agent, _batch(2, 8, 10 + i))
    assert not torch.equal(agent.actor[0], twin.actor[0])  # the updates did change it
    rewind.restore()
    assert [t.data_ptr() for t in state.tensors] == storage
    for _ in range(2):
        batch = _batch(2, 8, 99)
        mine, theirs = sac_update(agent, batch), sac_update(twin, batch)
        assert all(torch.equal(mine[k], theirs[k]) for k in theirs)
    for name, value in twin.state_dict().items():
        assert torch.equal(agent.state_dict()[name], value), name


@needs_cuda
@pytest.mark.parametrize("algo", ["sac-target", "cql"])
def test_a_graphed_run_computes_exactly_the_eager_run(algo, tmp_path, pendulum_dataset):
    overrides = TINY if algo == "sac-target" else {k: v for k, v in TINY.items() if k.startswith("sac.")}
    dataset = str(pendulum_dataset) if algo == "cql" else None
    common = {"steps": 80, "n_seeds": 2, "dataset": dataset, "eval_episodes": 2, "eval_every": 40,
              "progress": False, "device": "cuda"}
    eager = train(algo, PENDULUM, out=tmp_path / "eager", overrides=overrides, **common)
    graphed = train(algo, PENDULUM, out=tmp_path / "graphed", overrides=overrides | {"cuda_graph": "true"}, **common)
    assert graphed["returns"] == eager["returns"]

    def curve(run: str) -> list[dict]:
        return [{k: v for k, v in json.loads(line).items() if not k.endswith("time_s")}
                for line in (tmp_path / run / "metrics.jsonl").read_text().splitlines()]

    assert curve("graphed") == curve("eager")  # the losses too, at every evaluation


@needs_cuda
def test_a_resumed_graphed_run_captures_again_and_equals_an_uninterrupted_one(tmp_path, pendulum_dataset):
    overrides = {k: v for k, v in TINY.items() if k.startswith("sac.")} | {"cuda_graph": "true"}
    common = {"steps": 80, "overrides": overrides, "dataset": str(pendulum_dataset), "eval_episodes": 2,
              "progress": False, "device": "cuda", "checkpoint_every": 40}
    whole = train("cql", PENDULUM, out=tmp_path / "whole", **common)
    assert train("cql", PENDULUM, out=tmp_path / "cut", stop_after=40, **common) is None
    assert train("cql", PENDULUM, out=tmp_path / "cut", **common)["returns"] == whole["returns"]


@needs_cuda
@pytest.mark.parametrize("algo", ["sac-source", "dap-u", "h2o", "cql"])
def test_cuda_runs_are_deterministic(algo, tmp_path, pendulum_dataset):
    overrides = TINY | ({"warmup_steps": "30"} if algo == "dap-u" else {})
    if algo == "cql":
        overrides = {k: v for k, v in TINY.items() if k.startswith("sac.")}
    dataset = None if algo == "sac-source" else str(pendulum_dataset)
    runs = [train(algo, PENDULUM, steps=80, out=tmp_path / f"run{i}", n_seeds=2, dataset=dataset, overrides=overrides,
                  eval_episodes=2, progress=False, device="cuda") for i in range(2)]
    assert runs[0]["returns"] == runs[1]["returns"] and runs[0]["device"] == "cuda"


@needs_cuda
def test_cuda_resume_equals_an_uninterrupted_run(tmp_path):
    common = dict(steps=80, overrides=TINY, eval_episodes=2, progress=False, device="cuda", checkpoint_every=40)
    whole = train("sac-source", PENDULUM, out=tmp_path / "whole", **common)
    assert train("sac-source", PENDULUM, out=tmp_path / "cut", stop_after=40, **common) is None
    resumed = train("sac-source", PENDULUM, out=tmp_path / "cut", **common)
    assert resumed["returns"] == whole["returns"]
    # One machine, named with its card, across the resume: the same card is the same machine.
    card = torch.cuda.get_device_name(0)
    assert [m["cuda"]["name"] for m in resumed["machines"]] == [card] == [m["cuda"]["name"] for m in whole["machines"]]


@needs_cuda
def test_only_the_newest_graphed_update_of_a_process_replays():
    """Replaying a GraphedUpdate after a second one was built in the process gave NaN losses and
    then illegal memory accesses on an H200: the older one refuses to replay, the newest works."""
    from baselines.buffers import ReplayBuffer
    from baselines.sac import GraphedUpdate, SACAgent, make_capturable, sac_update

    def graphed(n_seeds: int):
        agent = SACAgent(5, 2, seeds=list(range(n_seeds)), config=SACConfig(hidden_sizes=(64, 64), batch_size=64),
                         device="cuda")
        buffer = ReplayBuffer(n_seeds, 500, 5, 2, seed=0, device="cuda")
        g = torch.Generator().manual_seed(0)
        for _ in range(500):
            buffer.add(torch.randn(n_seeds, 5, generator=g), torch.rand(n_seeds, 2, generator=g) * 2 - 1,
                       torch.randn(n_seeds, generator=g), torch.randn(n_seeds, 5, generator=g), torch.zeros(n_seeds))
        make_capturable(agent)
        update = GraphedUpdate(lambda batch: sac_update(agent, batch), buffer.sample(64), [agent.generator])
        return lambda: update(buffer.sample(64))["critic/td_loss"].clone()

    first = graphed(1)
    assert torch.isfinite(first()).all()
    second = graphed(4)
    with pytest.raises(RuntimeError, match=r"only the newest may replay.*one GraphedUpdate per process"):
        first()
    assert torch.isfinite(torch.stack([second() for _ in range(20)])).all()


_MATL_FAMILY = {"matl", "matl-u", "matl-f", "independent", "direct-transfer", "fine-tuning"}
"""TRPO agents without ``host_deploy``: they evaluate on their device (the CPU, on a CPU run)."""


@pytest.mark.parametrize("algo", sorted(set(ALGORITHMS) - _MATL_FAMILY))
def test_host_deploy_acts_as_deploy_does_from_a_copy_of_the_policy(algo):
    """What an accelerator run evaluates with: the deployed action, exactly, from CPU copies of the
    policy's parameters taken when asked (later updates do not reach them)."""
    g = torch.Generator().manual_seed(0)

    def data(n: int = 64) -> Batch:
        return Batch(torch.randn(n, 4, generator=g), torch.rand(n, 2, generator=g) * 2 - 1, torch.randn(n, generator=g),
                     torch.randn(n, 4, generator=g), torch.zeros(n))

    spec = get_algorithm(algo)
    method = spec.build(spec.default_config(), MethodContext(4, 2, (0, 1), target_data=data(), source_data=data()))
    observations = torch.randn(2, 4, generator=g)
    host = method.host_deploy()
    before = host(observations)
    assert before.device.type == "cpu" and torch.equal(before, method.deploy(observations))
    with torch.no_grad():
        for parameter in method.agent.actor:
            parameter.add_(0.5)
    assert not torch.equal(method.deploy(observations), before)  # the policy did change...
    assert torch.equal(host(observations), before)                # ...and the copy did not


def test_eval_on_device_on_a_cpu_run_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(OffdynError, match="--eval-on-device keeps an accelerator run's evaluations on the accelerator"):
        train("sac-source", PENDULUM, steps=40, out=tmp_path / "run", overrides=TINY, progress=False,
              eval_on_device=True)
    result = CliRunner().invoke(app, ["train", "sac-source", "--task", PENDULUM, "--steps", "40", "--out",
                                      str(tmp_path / "cli"), "--eval-on-device", "--no-progress"])
    assert result.exit_code == 2 and "error: --eval-on-device keeps" in result.output
    assert not (tmp_path / "run").exists() and not (tmp_path / "cli").exists()


def test_each_evaluation_logs_its_own_wall_time(tmp_path):
    train("sac-source", PENDULUM, steps=60, out=tmp_path / "run", overrides=TINY, eval_every=20, eval_episodes=2,
          progress=False)
    lines = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [line["step"] for line in lines] == [20, 40, 60]
    for previous, line in zip([{"wall_time_s": 0.0}, *lines], lines):
        # one evaluation's time, inside the (cumulative) wall time spent since the previous line
        assert 0 < line["evaluation_wall_time_s"] <= line["wall_time_s"] - previous["wall_time_s"] + 1e-3


@needs_cuda
def test_a_cuda_run_evaluates_from_a_host_copy_and_trains_as_with_device_evaluation(tmp_path, pendulum_dataset):
    overrides = {k: v for k, v in TINY.items() if k.startswith("sac.")}
    common = {"steps": 80, "n_seeds": 2, "dataset": str(pendulum_dataset), "eval_episodes": 2, "eval_every": 40,
              "progress": False, "device": "cuda", "overrides": overrides}
    host = train("cql", PENDULUM, out=tmp_path / "host", **common)
    device = train("cql", PENDULUM, out=tmp_path / "device", eval_on_device=True, **common)
    assert json.loads((tmp_path / "device" / "config.json").read_text())["eval_on_device"] is True
    assert "eval_on_device" not in json.loads((tmp_path / "host" / "config.json").read_text())

    def losses(run: str) -> list[dict]:
        return [json.loads(line)["train"] for line in (tmp_path / run / "metrics.jsonl").read_text().splitlines()]

    assert losses("host") == losses("device")  # where the evaluation acts changes no update
    assert all(np.isfinite(r).all() for run in (host, device) for r in run["returns"].values())
