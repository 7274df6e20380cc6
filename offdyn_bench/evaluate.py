"""Score anything that acts under the protocol: this suite's training runs or a user's policy.

``evaluate(agent, task)`` runs the final policy of every training seed for
:data:`~offdyn_bench.protocol.EVAL_EPISODES` target episodes with the protocol's fixed episode
seeds and deterministic actions, and returns (and writes) raw per-episode returns with the
versions, the task's version and the protocol version: the ``evaluation.json`` that
``offdyn-bench leaderboard submit`` and the oracle references read. Each episode's length and
whether the time limit ended it (``truncated``, against a fall or a reached goal) are recorded
beside its return; scores use the returns alone.

An agent is either

* a run folder written by ``offdyn-bench train`` (one agent per training seed, read from the final
  checkpoint), or
* ``package.module:factory``: ``factory`` is called once per training seed with the keyword
  arguments it accepts among ``task`` (the task name) and ``seed`` (the training seed) and returns
  an :class:`Agent` (or a plain function from an observation to an action).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import inspect
import itertools
import json
import os
import pathlib
import shlex
from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from offdyn_bench.envs import flat_observations
from offdyn_bench.errors import OffdynError
from offdyn_bench.json_values import is_integer, is_number
from offdyn_bench.protocol.definition import (
    BUDGETS,
    EPISODE_SEEDS,
    EVAL_EPISODES,
    PROTOCOL_VERSION,
    REFERENCE_METHODS,
    TRACKS,
    ProtocolError,
    check_method_on_track,
    get_budget,
    get_track,
    official_datasets,
    official_source_dataset,
    track_of_method,
)

EVALUATION_FILE = "evaluation.json"
SOURCE_SIDE_NOTE = "evaluated in the source, not the target (the source-target gap)"
"""The note of a source-side record: its only departure from the protocol when evaluated as it prescribes."""
FORMAT = "offdyn-bench/evaluation"


@runtime_checkable
class Agent(Protocol):
    """Anything that can act in a task's target: one observation in, one action (env units) out.

    ``reset()``, when an agent has it, is called before every episode."""

    def act(self, observation: np.ndarray) -> np.ndarray: ...


class EvaluationError(OffdynError):
    """An agent or run that cannot be evaluated as asked."""


@dataclasses.dataclass
class _FunctionAgent:
    function: Callable[[np.ndarray], np.ndarray]

    def act(self, observation: np.ndarray) -> np.ndarray:
        return self.function(observation)


@dataclasses.dataclass
class LoadedAgents:
    """The agents of one evaluation, one per training seed, and what is known about them."""

    agents: list[tuple[int, Agent]]
    description: dict[str, Any]
    method: str | None = None
    task: str | None = None
    steps: int | None = None
    dataset: dict[str, Any] | None = None
    train_command: str | None = None
    source_dataset: dict[str, Any] | None = None
    """Provenance of the source dataset of an offline-source run (None for every other run)."""
    training_machines: list[Any] | None = None
    """The machines a run's training ran on (its ``result.json``); None for a user's agent and for
    runs trained before results recorded them."""
    training_provenance: dict[str, Any] | None = None
    """When a run trained and from which code (its ``result.json``: ``source_revisions``,
    ``started_at``, ``finished_at``); None for a user's agent and for runs trained before results
    recorded them."""


def _sha256_arrays(arrays: Sequence[np.ndarray]) -> str:
    digest = hashlib.sha256()
    for array in arrays:
        digest.update(str(array.shape).encode())
        digest.update(np.ascontiguousarray(array, dtype=np.float32).tobytes())
    return digest.hexdigest()


def _settings_of(algo: str, config: Any) -> dict[str, str]:
    """The run's settings that differ from its method's defaults (its ``--set`` overrides), so that
    the record's train command trains the same run; none for a config this version cannot read."""
    from baselines.algorithms import ALGORITHMS, overrides_of

    if algo not in ALGORITHMS or not isinstance(config, dict):
        return {}
    return overrides_of(algo, config)


def train_command_settings(command: str) -> dict[str, str] | None:
    """The ``--set key=value`` settings of a record's train command, in order (None where the
    command cannot be split). Records written before train commands carried them hold none."""
    try:
        words = shlex.split(command)
    except ValueError:
        return None
    return {key: value for flag, word in itertools.pairwise(words) if flag == "--set"
            for key, _, value in [word.partition("=")]}


def _check_run_files(run_dir: pathlib.Path, config: Any, result: Any) -> None:
    """A hand-edited or damaged config.json or result.json is a clear error here, not a KeyError
    or TypeError halfway through loading the checkpoint."""
    if not isinstance(config, dict):
        raise EvaluationError(f"{str(run_dir)!r}: config.json holds a JSON {type(config).__name__}; expected "
                              "the object `offdyn-bench train` writes, with the run's algo, task, steps and seeds")
    wrong = []
    for key in ("algo", "task"):
        if not isinstance(config.get(key), str) or not config[key]:
            wrong.append(f"{key!r} {_shown(config, key)} (expected a name)")
    steps = config.get("steps")
    if not is_integer(steps) or steps < 1:
        wrong.append(f"'steps' {_shown(config, 'steps')} (expected a positive whole number)")
    seeds = config.get("seeds")
    if (not isinstance(seeds, list) or not seeds
            or not all(is_integer(seed) for seed in seeds)):
        wrong.append(f"'seeds' {_shown(config, 'seeds')} (expected a non-empty list of whole numbers)")
    if wrong:
        raise EvaluationError(f"{str(run_dir)!r}: config.json is damaged: " + "; ".join(wrong)
                              + ". `offdyn-bench train` writes it; train again into a new --out folder")
    if not isinstance(result, dict):
        raise EvaluationError(f"{str(run_dir)!r}: result.json holds a JSON {type(result).__name__}; expected "
                              "the object `offdyn-bench train` writes when a run finishes")


def _check_members(run_dir: pathlib.Path, seeds: list[int], members: int) -> None:
    # One trained policy per seed: a seeds list edited after training would pair seeds with the
    # wrong policies, or index past the checkpoint's last one.
    if len(seeds) != members:
        raise EvaluationError(f"{str(run_dir)!r}: config.json lists {len(seeds)} training seed(s) {seeds}, but its "
                              f"checkpoint holds {members} policy(ies); expected one per seed, as "
                              "`offdyn-bench train` writes them")


def _shown(config: dict[str, Any], key: str) -> str:
    return f"is {config[key]!r}" if key in config else "is missing"


def load_run_agents(run_dir: str | os.PathLike[str]) -> LoadedAgents:
    """One deterministic agent per training seed of a finished ``offdyn-bench train`` run."""
    from baselines.checkpoint import latest_checkpoint, load_checkpoint
    from offdyn_bench.datasets.policies import MLPPolicy
    from offdyn_bench.tasks import get_task

    run_dir = pathlib.Path(run_dir)
    try:
        config = json.loads((run_dir / "config.json").read_text())
        result = json.loads((run_dir / "result.json").read_text())
    except FileNotFoundError as error:
        what = "config.json" if "config.json" in str(error) else "result.json"
        hint = ("it is not a training run folder" if what == "config.json"
                else "the run has not finished; run its train command again to finish it")
        raise EvaluationError(f"{str(run_dir)!r} has no {what}: {hint}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise EvaluationError(f"{str(run_dir)!r}: config.json or result.json cannot be read ({error})") from None
    _check_run_files(run_dir, config, result)
    try:
        checkpoint = latest_checkpoint(run_dir)
    except OffdynError as error:
        raise EvaluationError(f"{str(run_dir)!r}: {error}") from None
    if checkpoint is None:
        raise EvaluationError(f"{str(run_dir)!r} has no complete checkpoint to evaluate")
    try:
        tensors, trainer = load_checkpoint(checkpoint)
    except OffdynError as error:
        raise EvaluationError(f"{str(run_dir)!r}: {error}") from None
    if int(trainer.get("step", -1)) != int(config["steps"]):
        raise EvaluationError(f"{str(run_dir)!r}: the newest checkpoint is at step {trainer.get('step')}, "
                              f"not the run's final step {config['steps']}")
    pair = get_task(config["task"])
    space = flat_observations(pair.make("target")).action_space
    action_dim = int(np.prod(space.shape))
    names = sorted((k for k in tensors if k.startswith("actor.") and k.split(".")[1].isdigit()),
                   key=lambda k: int(k.split(".")[1]))
    params = [tensors[k].detach().cpu().numpy() for k in names]
    agents: list[tuple[int, Agent]] = []
    hashes = {}
    if not params and any(k.endswith(".log_std") for k in tensors):
        # A TRPO-based run (the MATL family): its own module knows its deployed policy.
        from baselines.matl import deployed_policies

        try:
            policies = deployed_policies(tensors, space.low, space.high)
        except OffdynError as error:
            raise EvaluationError(f"{str(run_dir)!r}: {error}") from None
        _check_members(run_dir, config["seeds"], len(policies))
        role = "robot" if "robot.log_std" in tensors else "simulator"
        mean_params = sorted(k for k in tensors if k.startswith(f"{role}.mean."))
        for member, seed in enumerate(config["seeds"]):
            agents.append((int(seed), _FunctionAgent(policies[member])))
            hashes[str(seed)] = _sha256_arrays([tensors[k][member].detach().cpu().numpy() for k in mean_params])
        params = None
    elif not params or len(params) % 2:
        raise EvaluationError(f"{str(run_dir)!r}: the checkpoint holds no actor network")
    else:
        _check_members(run_dir, config["seeds"], int(params[0].shape[0]))
    for member, seed in enumerate(config["seeds"] if params is not None else []):
        layers = []
        for i in range(len(params) // 2):
            weight, bias = params[2 * i][member].T, params[2 * i + 1][member].reshape(-1)
            if i == len(params) // 2 - 1:
                # Output = (mean, log-std); the deployed action is the mean's last action_dim
                # entries (all of it for SAC, a_t for DAP's (a_s, a_t)).
                half = weight.shape[0] // 2
                weight, bias = weight[half - action_dim:half], bias[half - action_dim:half]
            layers.append((weight, bias))
        policy = MLPPolicy(layers, "relu", space.low, space.high)
        agents.append((int(seed), _FunctionAgent(policy)))
        hashes[str(seed)] = _sha256_arrays([a for layer in layers for a in layer])
    train_command = (f"offdyn-bench train {config['algo']} --task {config['task']} --steps {config['steps']} "
                     f"--seed {config['seeds'][0]} --n-seeds {len(config['seeds'])}"
                     + (f" --dataset {config['dataset']}" if config.get("dataset") else "")
                     + (f" --source-dataset {config['source_dataset']}" if config.get("source_dataset") else "")
                     + "".join(f" --set {shlex.quote(f'{key}={value}')}"
                               for key, value in _settings_of(config["algo"], config.get("config")).items())
                     + f" --out {run_dir}")
    dataset = result.get("dataset") or config.get("dataset_provenance")
    source_dataset = result.get("source_dataset") or config.get("source_dataset_provenance")
    machines = result.get("machines")
    provenance = {key: result[key] for key in ("source_revisions", "started_at", "finished_at") if key in result}
    return LoadedAgents(agents=agents, method=config["algo"], task=pair.name, steps=int(config["steps"]),
                        dataset=dataset, train_command=train_command, source_dataset=source_dataset,
                        training_machines=machines if isinstance(machines, list) else None,
                        training_provenance=provenance or None,
                        description={"kind": "run", "path": str(run_dir), "checkpoint": checkpoint.name,
                                     "policy_sha256": hashes,
                                     # The command above omits --set overrides: config.json holds
                                     # the full configuration, pinned here by its hash.
                                     "config_sha256": hashlib.sha256((run_dir / "config.json").read_bytes())
                                     .hexdigest()})


def load_factory_agents(spec: str, task: str, seeds: Sequence[int]) -> LoadedAgents:
    """``package.module:factory``, called once per training seed."""
    module_name, sep, attribute = spec.partition(":")
    if not sep or not module_name or not attribute:
        raise EvaluationError(f"--agent {spec!r} is neither a run folder nor 'package.module:factory'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise EvaluationError(f"--agent {spec!r}: cannot import {module_name!r} ({error})") from None
    factory = getattr(module, attribute, None)
    if not callable(factory):
        raise EvaluationError(f"--agent {spec!r}: {module_name} has no callable {attribute!r}")
    try:
        accepted = set(inspect.signature(factory).parameters)
    except (TypeError, ValueError):
        accepted = set()
    agents: list[tuple[int, Agent]] = []
    for seed in seeds:
        kwargs = {k: v for k, v in (("task", task), ("seed", int(seed))) if k in accepted}
        try:
            agent = factory(**kwargs)
        except Exception as error:  # the user's code: its failure is reported, not a traceback of ours
            raise EvaluationError(f"--agent {spec!r}: the factory failed for training seed {seed} with "
                                  f"{type(error).__name__}: {error}") from error
        if not isinstance(agent, Agent):
            if not callable(agent):
                raise EvaluationError(f"--agent {spec!r}: the factory returned {type(agent).__name__}, which has "
                                      "no act(observation) method and is not callable")
            agent = _FunctionAgent(agent)
        agents.append((int(seed), agent))
    source = inspect.getsourcefile(module) if hasattr(module, "__file__") else None
    digest = hashlib.sha256(pathlib.Path(source).read_bytes()).hexdigest() if source else None
    return LoadedAgents(agents=agents, task=task,
                        description={"kind": "factory", "path": spec, "module_sha256": digest})


def _act(agent: Agent, observation: np.ndarray, space: Any, where: str) -> np.ndarray:
    action = np.asarray(agent.act(observation), dtype=np.float64)
    if action.shape != space.shape:
        action = action.reshape(-1) if action.size == int(np.prod(space.shape)) else action
        if action.shape != space.shape:
            raise EvaluationError(f"{where}: the agent returned an action of shape {action.shape}; "
                                  f"expected {space.shape}")
    if not np.all(np.isfinite(action)):
        raise EvaluationError(f"{where}: the agent returned a NaN or infinite action")
    # The trainer clips to the box as well: an out-of-range command means the limit.
    return np.clip(action, space.low, space.high).astype(space.dtype)


@dataclasses.dataclass(frozen=True)
class Episode:
    """One evaluation episode: its undiscounted return, its length in env steps, and whether the
    time limit ended it (truncated) rather than the task (terminated: a fall, a goal)."""

    episode_return: float
    length: int
    truncated: bool


def run_episode(agent: Agent, env: Any, episode_seed: int, where: str) -> Episode:
    """One full episode of ``agent`` in ``env``, reset with ``episode_seed``."""
    if callable(getattr(agent, "reset", None)):
        agent.reset()  # type: ignore[attr-defined]
    observation, _ = env.reset(seed=int(episode_seed))
    total, steps, terminated, truncated = 0.0, 0, False, False
    while not (terminated or truncated):
        observation, reward, terminated, truncated, _ = env.step(_act(agent, observation, env.action_space, where))
        total, steps = total + float(reward), steps + 1
    return Episode(episode_return=total, length=steps, truncated=bool(truncated and not terminated))


def episode_returns(agent: Agent, env: Any, episode_seeds: Sequence[int], where: str) -> list[float]:
    """Undiscounted returns of full target episodes, one per seed."""
    return [run_episode(agent, env, seed, where).episode_return for seed in episode_seeds]


def _check_shared_source(loaded: LoadedAgents, task: str) -> None:
    """A run trained on another task scores on ``task`` only when its policy is exactly what
    training on ``task`` would give: a method whose training reads nothing of the target
    (``sac-source``), and the same source simulator on both tasks."""
    from baselines.algorithms import ALGORITHMS
    from offdyn_bench.tasks import get_task

    algorithm = ALGORITHMS.get(loaded.method or "")
    trained, scored = get_task(loaded.task or ""), get_task(task)
    if algorithm is None or not algorithm.source_only:
        raise EvaluationError(f"the run was trained on {loaded.task!r}, not {task!r}; only a run of a method that "
                              "trains in the source alone ("
                              + ", ".join(name for name, a in ALGORITHMS.items() if a.source_only)
                              + f") may be scored on another task with the same source, and {loaded.method!r} "
                              "is not one")
    if trained.source_key != scored.source_key:
        raise EvaluationError(f"the run was trained on {loaded.task!r}, whose source is not {task!r}'s source "
                              f"({trained.source_key} against {scored.source_key}); "
                              f"train {loaded.method} on {task!r} instead")


def _conformance(loaded: LoadedAgents, task: str, track: str | None, budget: str | None,
                 episodes: int) -> tuple[str | None, str | None, list[str]]:
    """(track, budget, reasons the evaluation is not a protocol result)."""
    notes = []
    known = {m for t in TRACKS.values() for m in t.methods} | set(REFERENCE_METHODS)
    if loaded.method in known:
        home = track_of_method(loaded.method)
        if track is None:
            track = home
        elif home is not None:
            check_method_on_track(loaded.method, track)
    if track is not None:
        get_track(track)
    if loaded.steps is not None:
        at_budget = [name for name, b in BUDGETS.items() if b.source_steps == loaded.steps]
        if budget is None:
            budget = at_budget[0] if at_budget else None
            if budget is None:
                notes.append(f"trained for {loaded.steps} steps, not at a protocol budget "
                             f"({', '.join(f'{n}: {b.source_steps}' for n, b in BUDGETS.items())})")
        elif budget not in at_budget:
            raise ProtocolError(f"the run trained for {loaded.steps} steps; budget {budget!r} is "
                                f"{get_budget(budget).source_steps} steps")
    elif budget is not None:
        get_budget(budget)
    if budget is None and loaded.steps is None:
        notes.append("no budget given (--budget)")
    if track is None and loaded.method not in REFERENCE_METHODS:
        notes.append("no track given (--track)")
    if episodes != EVAL_EPISODES:
        notes.append(f"{episodes} episodes per seed; the protocol evaluates {EVAL_EPISODES}")
    if track is not None:
        source_official = official_source_dataset(task, track)
        for kind, provenance, official in (
                ("dataset", loaded.dataset, official_datasets(task, track)),
                ("source dataset", loaded.source_dataset, () if source_official is None else (source_official,))):
            used = (provenance.get("dataset_id") or provenance.get("spec")) if provenance is not None else None
            if official and provenance is not None and used not in official:
                notes.append(f"trained on {kind} {used!r}; the track's official {kind} is "
                             + " or ".join(repr(name) for name in official))
    return track, budget, notes


def evaluate(agent: str | os.PathLike[str], task: str | None = None, *, track: str | None = None,
             budget: str | None = None, seeds: Sequence[int] | None = None, episodes: int = EVAL_EPISODES,
             out: str | os.PathLike[str] | None = None, method: str | None = None,
             progress: bool = True, side: str = "target") -> dict[str, Any]:
    """Evaluate ``agent`` (a run folder or ``module:factory``) on ``task``'s target; write the
    record to ``out`` (default: :func:`default_evaluation_path` in the run folder; none for a
    factory without ``out``) and return it. ``side="source"`` scores the same policies in the
    source instead, for the source-target gap of a task (such a record is no protocol result)."""
    from tqdm import tqdm

    from offdyn_bench.tasks import get_task
    from offdyn_bench.versions import machine, source_revision, versions

    if not 1 <= episodes <= len(EPISODE_SEEDS) * 50:
        raise EvaluationError(f"episodes={episodes}; expected an integer in [1, {len(EPISODE_SEEDS) * 50}]")
    if side not in ("source", "target"):
        raise EvaluationError(f"side {side!r}; expected 'target' (the protocol) or 'source' (the gap)")
    # Named options are checked before any agent is loaded (a factory may be slow or have effects).
    if track is not None:
        get_track(track)
    if budget is not None:
        get_budget(budget)
    agent_path = pathlib.Path(agent)
    is_run = agent_path.is_dir()
    if is_run:
        if seeds is not None:
            raise EvaluationError("--seeds applies to a module:factory agent; a run folder has its own seeds")
        loaded = load_run_agents(agent_path)
        if task is not None and get_task(task).name != loaded.task:
            _check_shared_source(loaded, get_task(task).name)
            loaded.description["trained_task"] = loaded.task
            loaded.task = get_task(task).name
        task = loaded.task
    else:
        if task is None:
            raise EvaluationError("--task is required for a module:factory agent")
        task = get_task(task).name
        loaded = load_factory_agents(str(agent), task, list(seeds) if seeds is not None else [0])
    if method is not None:
        if loaded.method is not None and method != loaded.method:
            raise EvaluationError(f"--method {method!r} contradicts the run's algorithm {loaded.method!r}")
        loaded.method = method
    assert task is not None
    track, budget, notes = _conformance(loaded, task, track, budget, episodes)
    if side == "source":
        notes.append(SOURCE_SIDE_NOTE)
    trained_task = loaded.description.get("trained_task", task)
    target = pathlib.Path(out) if out is not None else (
        default_evaluation_path(agent_path, str(trained_task), task, side) if is_run else None)
    if target is not None:
        _check_writable(target)

    pair = get_task(task)
    episode_seeds = [int(EPISODE_SEEDS[0]) + e for e in range(episodes)]
    env = flat_observations(pair.make(side))
    per_seed = []
    bar = tqdm(total=len(loaded.agents) * episodes, unit="episode", disable=not progress,
               desc=f"evaluate {pair.name} ({side})")
    try:
        for seed, agent_obj in loaded.agents:
            episodes_run = []
            for episode_seed in episode_seeds:
                where = f"seed {seed}, episode seed {episode_seed}"
                episodes_run.append(run_episode(agent_obj, env, episode_seed, where))
                bar.update(1)
            per_seed.append({"seed": seed, "returns": [e.episode_return for e in episodes_run],
                             "lengths": [e.length for e in episodes_run],
                             "truncated": [e.truncated for e in episodes_run]})
    finally:
        bar.close()
        env.close()
    record = {
        "format": FORMAT, "format_version": 1, "protocol_version": PROTOCOL_VERSION,
        "task": pair.name, "task_version": pair.version, "target_env_id": pair.env_id("target"),
        "side": side, "env_id": pair.env_id(side),
        "track": track, "budget": budget, "method": loaded.method, "agent": loaded.description,
        "steps": loaded.steps, "dataset": loaded.dataset, "train_command": loaded.train_command,
        "episode_seeds": episode_seeds, "seeds": per_seed,
        "protocol_conformant": not notes, "notes": notes,
        "versions": versions(),
        # Where the numbers were computed: another CPU model can train, and act, differently (PROTOCOL §8).
        "machine": machine(), "training_machines": loaded.training_machines,
        # The code that evaluated and the code (and dates) that trained: the version stays 0.1.0.
        "source_revision": source_revision(), "training_provenance": loaded.training_provenance,
        "command": "offdyn-bench evaluate " + shlex.join(_command_args(agent, task, track, budget, episodes, side)),
    }
    if loaded.source_dataset is not None:  # offline-source runs only: other records keep their keys
        record["source_dataset"] = loaded.source_dataset
    if target is not None:
        _write_atomic(target, record)
    return record


def _command_args(agent: Any, task: str, track: str | None, budget: str | None, episodes: int,
                  side: str) -> list[str]:
    args = ["--agent", str(agent), "--task", task] + (["--side", side] if side != "target" else [])
    args += ["--track", track] if track else []
    args += ["--budget", budget] if budget else []
    args += ["--episodes", str(episodes)] if episodes != EVAL_EPISODES else []
    return args


def default_evaluation_path(run_dir: pathlib.Path, trained_task: str, task: str, side: str) -> pathlib.Path:
    """Where ``evaluate`` writes without ``--out``: ``evaluation.json`` is the run's protocol record
    (its own task, in the target); another task of the same source or the source side gets a file
    of its own, so that it never replaces that record."""
    stem = "evaluation" + ("" if task == trained_task else f"-{task}") + ("-source" if side == "source" else "")
    return run_dir / f"{stem}.json"


def _check_writable(path: pathlib.Path) -> None:
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise EvaluationError(f"cannot write {str(path)!r}: {str(parent)!r} is a file")
    probe_dir = next((p for p in [parent, *parent.parents] if p.exists()), None)
    if probe_dir is None or not os.access(probe_dir, os.W_OK):
        raise EvaluationError(f"cannot write {str(path)!r}: {str(probe_dir)!r} is not writable")


def _write_atomic(path: pathlib.Path, record: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        partial.write_text(json.dumps(record, indent=1) + "\n")
        os.replace(partial, path)
    except OSError as error:
        partial.unlink(missing_ok=True)
        raise EvaluationError(f"cannot write {str(path)!r}: {error}") from None


def read_evaluation(path: str | os.PathLike[str]) -> dict[str, Any]:
    """An ``evaluation.json``, checked for its format."""
    path = pathlib.Path(path)
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise EvaluationError(f"cannot read evaluation {str(path)!r}: {error}") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise EvaluationError(f"{str(path)!r} is not an {FORMAT} file")
    check_evaluation_record(record, repr(str(path)))
    return record


def check_evaluation_record(record: Any, where: str = "an evaluation") -> None:
    """The fields every reader of an evaluation relies on, with the types ``evaluate`` writes: a
    clear error naming ``where`` and the first field that is wrong, instead of a crash later on."""
    def wrong(field: str, expected: str) -> EvaluationError:
        return EvaluationError(f"{where}: {field} is not {expected}; re-run offdyn-bench evaluate to write it")

    if not isinstance(record, dict):
        raise EvaluationError(f"{where}: not a JSON object")
    if not isinstance(record.get("task"), str):
        raise wrong("'task'", "a task name")
    for field in ("method", "budget"):
        if record.get(field) is not None and not isinstance(record[field], str):
            raise wrong(repr(field), "a string or null")
    seeds = record.get("seeds")
    if not isinstance(seeds, list) or not seeds:
        raise wrong("'seeds'", "a non-empty list of {'seed': int, 'returns': [number, ...]}")
    for i, entry in enumerate(seeds):
        if not isinstance(entry, dict) or type(entry.get("seed")) is not int or entry["seed"] < 0:
            raise wrong(f"seeds[{i}].seed", "a non-negative integer")
        returns = entry.get("returns")
        if not isinstance(returns, list) or not returns or not all(
                is_number(x) for x in returns):
            raise wrong(f"seeds[{i}].returns", "a non-empty list of numbers")
