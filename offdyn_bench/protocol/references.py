"""Reference scores with provenance, and the normalized score they define.

One file, ``assets/reference_scores.json``, holds per task:

* ``random``: a uniform-random policy on the protocol's episode seeds (its own seeded generator);
* ``zero-command``: the policy that commands nothing (the centre of the action box) on the same
  episode seeds; no score is normalized by it, but an oracle below it is no oracle (the core suite's
  admission test, PROTOCOL.md §9);
* ``oracle``: per budget, ``sac-target`` (SAC trained in the target with that budget's steps),
  evaluated under the protocol like any method, with the policy hashes and the command.

normalized score = 100 x (J - J_random) / (J_oracle - J_random); raw returns are always kept.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from offdyn_bench.protocol.definition import (
    BUDGETS,
    EPISODE_SEEDS,
    MIN_SEEDS,
    PROTOCOL_VERSION,
    ProtocolError,
    get_budget,
)

if TYPE_CHECKING:
    import gymnasium

    from offdyn_bench.tasks import TaskPair

Policy = Callable[[np.ndarray], np.ndarray]

REFERENCE_FILE = pathlib.Path(__file__).resolve().parents[2] / "assets" / "reference_scores.json"
FORMAT = "offdyn-bench/reference-scores"
RANDOM_RNG_STREAM = 7
"""The random reference's action generator is seeded with (episode seed, this stream)."""

Kind = Literal["random", "oracle", "zero-command"]
_FILE_KEYS: Mapping[str, str] = {"random": "random", "zero-command": "zero_command"}
"""The reference file's key of each per-task (not per-budget) kind."""


@dataclasses.dataclass(frozen=True)
class ReferenceScore:
    task: str
    kind: Kind
    mean_return: float
    returns: tuple[float, ...]
    """Every episode's return (all seeds' episodes, seed-major, for the oracle)."""
    provenance: Mapping[str, Any]
    budget: str | None = None
    """The budget of an oracle; None for the random and zero-command references."""

    def seed_means(self) -> tuple[float, ...] | None:
        """An oracle's mean return per training seed (its episodes are stored seed-major); None for
        the random reference or an entry that does not say its episodes per seed."""
        per_seed = self.provenance.get("episodes_per_seed")
        if self.kind != "oracle" or not isinstance(per_seed, int) or per_seed <= 0 or len(self.returns) % per_seed:
            return None
        return tuple(float(np.mean(self.returns[i:i + per_seed])) for i in range(0, len(self.returns), per_seed))


def _path(path: str | os.PathLike[str] | None) -> pathlib.Path:
    return pathlib.Path(path) if path is not None else REFERENCE_FILE


def read_reference_file(path: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """The reference file as data (an empty one when it does not exist yet)."""
    path = _path(path)
    if not path.exists():
        return {"format": FORMAT, "format_version": 1, "protocol_version": PROTOCOL_VERSION, "tasks": {}}
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ProtocolError(f"reference file {str(path)!r} cannot be read ({error}); restore it from git") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT or not isinstance(data.get("tasks"), dict):
        raise ProtocolError(f"reference file {str(path)!r} is not a {FORMAT} file; restore it from git")
    if data.get("protocol_version") != PROTOCOL_VERSION:
        raise ProtocolError(f"reference file {str(path)!r} is for protocol {data.get('protocol_version')!r}, "
                            f"this suite runs protocol {PROTOCOL_VERSION!r}")
    return data


def reference_scores(path: str | os.PathLike[str] | None = None) -> dict[str, dict[str, ReferenceScore]]:
    """task -> {"random": ..., "zero-command": ..., "oracle/<budget>": ...}; kinds not measured yet
    are absent."""
    out: dict[str, dict[str, ReferenceScore]] = {}
    for task, entry in read_reference_file(path)["tasks"].items():
        scores: dict[str, ReferenceScore] = {}
        for kind, key in _FILE_KEYS.items():
            if entry.get(key):
                r = entry[key]
                scores[kind] = ReferenceScore(task, kind, float(r["mean_return"]), tuple(r["returns"]),
                                              r["provenance"])
        for budget, o in (entry.get("oracle") or {}).items():
            scores[f"oracle/{budget}"] = ReferenceScore(task, "oracle", float(o["mean_return"]),
                                                        tuple(o["returns"]), o["provenance"], budget)
        out[task] = scores
    return out


def reference_pair(task: str, budget: str, path: str | os.PathLike[str] | None = None) -> tuple[float, float]:
    """(J_random, J_oracle) of ``task`` at ``budget``; a clear error when one is missing."""
    get_budget(budget)
    scores = reference_scores(path).get(task, {})
    missing = [kind for kind in ("random", f"oracle/{budget}") if kind not in scores]
    if missing:
        raise ProtocolError(f"task {task!r} has no {' and no '.join(missing)} reference score yet; "
                            f"produce it with `offdyn-bench protocol reference` (see PROTOCOL.md)")
    j_random, j_oracle = scores["random"].mean_return, scores[f"oracle/{budget}"].mean_return
    if not j_oracle > j_random:
        raise ProtocolError(f"task {task!r}: the oracle's return {j_oracle:.1f} does not exceed the random "
                            f"policy's {j_random:.1f} at budget {budget!r}; normalized scores are undefined")
    return j_random, j_oracle


def has_references(task: str, budget: str, path: str | os.PathLike[str] | None = None) -> bool:
    scores = reference_scores(path).get(task, {})
    return "random" in scores and f"oracle/{budget}" in scores


def normalized_score(returns: float | Sequence[float] | np.ndarray, task: str, budget: str,
                     path: str | os.PathLike[str] | None = None) -> np.ndarray:
    """100 x (J - J_random) / (J_oracle - J_random), elementwise."""
    j_random, j_oracle = reference_pair(task, budget, path)
    values = np.asarray(returns, dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise ProtocolError(f"returns for {task!r} contain NaN or infinite values")
    return normalize(values, j_random, j_oracle)


def normalize(returns: np.ndarray, j_random: float, j_oracle: float) -> np.ndarray:
    """The protocol's normalized score: 0 for the random policy, 100 for the oracle."""
    return 100.0 * (returns - j_random) / (j_oracle - j_random)


def _write(data: dict[str, Any], path: pathlib.Path) -> None:
    """Atomic: a crash leaves the old file or the new one, never half of one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    partial.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    os.replace(partial, path)


def _target_returns(task: str, episodes: Sequence[int],
                    policy_for: Callable[[gymnasium.spaces.Box, int], Policy]) -> tuple[TaskPair, list[float]]:
    """(the pair, one return per episode seed) of the policy ``policy_for(space, episode_seed)``
    makes for each episode, in ``task``'s target."""
    import gymnasium

    from offdyn_bench.tasks import get_task

    pair = get_task(task)
    env = pair.make("target")
    space = env.action_space
    assert isinstance(space, gymnasium.spaces.Box)
    returns = []
    try:
        for episode_seed in episodes:
            policy = policy_for(space, int(episode_seed))
            observation, _ = env.reset(seed=int(episode_seed))
            total, done = 0.0, False
            while not done:
                observation, reward, terminated, truncated, _ = env.step(policy(observation).astype(space.dtype))
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
    finally:
        env.close()
    return pair, returns


def _record(pair: TaskPair, kind: Kind, returns: list[float], provenance: dict[str, Any],
            path: str | os.PathLike[str] | None) -> ReferenceScore:
    score = ReferenceScore(pair.name, kind, float(np.mean(returns)), tuple(returns), provenance)
    target = _path(path)
    data = read_reference_file(target)
    data["tasks"].setdefault(pair.name, {})[_FILE_KEYS[kind]] = {
        "mean_return": score.mean_return, "returns": list(returns), "provenance": provenance}
    _write(data, target)
    return score


def record_random_reference(task: str, path: str | os.PathLike[str] | None = None,
                            episodes: Sequence[int] = EPISODE_SEEDS) -> ReferenceScore:
    """Measure the uniform-random policy in ``task``'s target on the protocol's episode seeds and
    record it (replacing an older random entry of that task)."""
    from offdyn_bench.datasets.policies import UniformRandomPolicy, derived_seed
    from offdyn_bench.versions import versions

    pair, returns = _target_returns(task, episodes, lambda space, episode_seed: UniformRandomPolicy(
        space.low, space.high, seed=derived_seed([episode_seed, RANDOM_RNG_STREAM])))
    provenance = {"policy": "uniform random actions", "env_id": pair.env_id("target"),
                  "task_version": pair.version, "episode_seeds": [int(s) for s in episodes],
                  "rng_seed": f"SeedSequence([episode_seed, {RANDOM_RNG_STREAM}])",
                  "command": f"offdyn-bench protocol reference random --task {pair.name}", "versions": versions()}
    return _record(pair, "random", returns, provenance, path)


def zero_command(space: gymnasium.spaces.Box) -> np.ndarray:
    """The command that asks for nothing: the centre of the action box (0 for the locomotion robots)."""
    return (np.asarray(space.low, dtype=np.float64) + np.asarray(space.high, dtype=np.float64)) / 2


def record_zero_command_reference(task: str, path: str | os.PathLike[str] | None = None,
                                  episodes: Sequence[int] = EPISODE_SEEDS) -> ReferenceScore:
    """Measure the zero command (:func:`zero_command`, every step) in ``task``'s target on the
    protocol's episode seeds and record it (replacing an older zero-command entry of that task).
    Deterministic: the episode seeds fix every start and any noise of the target."""
    from offdyn_bench.versions import versions

    def policy_for(space: gymnasium.spaces.Box, episode_seed: int) -> Policy:
        command = zero_command(space)
        return lambda observation: command

    pair, returns = _target_returns(task, episodes, policy_for)
    provenance = {"policy": "zero command: the centre of the action box at every step", "env_id": pair.env_id("target"),
                  "task_version": pair.version, "episode_seeds": [int(s) for s in episodes],
                  "command": f"offdyn-bench protocol reference zero-command --task {pair.name}",
                  "versions": versions()}
    return _record(pair, "zero-command", returns, provenance, path)


def portable_paths(text: str | None) -> str | None:
    """``text`` with paths under the working directory made relative to it: the provenance is
    committed with the reference file, where one machine's absolute layout means nothing."""
    if text is None:
        return None
    return text.replace(str(pathlib.Path.cwd()) + os.sep, "")


def record_oracle_reference(evaluations: Sequence[Mapping[str, Any]],
                            path: str | os.PathLike[str] | None = None) -> ReferenceScore:
    """Record ``sac-target`` evaluations (``evaluation.json`` contents, one per run) of one task
    at one budget as that task's oracle for that budget."""
    if not evaluations:
        raise ProtocolError("no evaluation given; pass the evaluation.json of sac-target runs")
    tasks = {e.get("task") for e in evaluations}
    budgets = {e.get("budget") for e in evaluations}
    methods = {e.get("method") for e in evaluations}
    if len(tasks) != 1 or len(budgets) != 1:
        raise ProtocolError(f"the evaluations mix tasks {sorted(map(str, tasks))} or budgets "
                            f"{sorted(map(str, budgets))}; an oracle is one task at one budget")
    if methods != {"sac-target"}:
        raise ProtocolError(f"an oracle reference is sac-target; the evaluations are of {sorted(map(str, methods))}")
    (task,), (budget,) = tasks, budgets
    if budget not in BUDGETS:
        raise ProtocolError(f"the evaluations are not at a protocol budget (budget {budget!r}); "
                            f"train with --budget {'|'.join(BUDGETS)}")
    for e in evaluations:
        if e.get("protocol_version") != PROTOCOL_VERSION:
            raise ProtocolError(f"evaluation of {e.get('agent', {}).get('path')!r} is for protocol "
                                f"{e.get('protocol_version')!r}, not {PROTOCOL_VERSION!r}")
    seeds = [s for e in evaluations for s in e["seeds"]]
    if len({s["seed"] for s in seeds}) != len(seeds):
        raise ProtocolError("the evaluations contain a training seed twice")
    # The oracle anchors every normalized score of the task: it needs at least the seeds a method does.
    if len(seeds) < MIN_SEEDS:
        raise ProtocolError(f"the evaluations hold {len(seeds)} training seed(s); an oracle needs at least "
                            f"{MIN_SEEDS}, like any method")
    for e in evaluations:
        if e.get("protocol_conformant") is False or e.get("side", "target") != "target":
            raise ProtocolError(f"evaluation of {e.get('agent', {}).get('path')!r} is not a protocol result: "
                                + "; ".join(map(str, e.get("notes") or ["it was not made in the target"])))
    returns = [float(x) for s in sorted(seeds, key=lambda s: s["seed"]) for x in s["returns"]]
    if not all(math.isfinite(x) for x in returns):
        raise ProtocolError("the oracle's returns contain NaN or infinite values")
    provenance = {
        "method": "sac-target", "budget": budget, "seeds": sorted(s["seed"] for s in seeds),
        "episodes_per_seed": len(seeds[0]["returns"]), "episode_seeds": evaluations[0]["episode_seeds"],
        "runs": [{"path": portable_paths(e["agent"].get("path")), "policy_sha256": e["agent"].get("policy_sha256"),
                  "train_command": portable_paths(e.get("train_command")), "steps": e.get("steps")}
                 for e in evaluations],
        "command": portable_paths("offdyn-bench protocol reference oracle " + " ".join(
            str(pathlib.Path(str(e["agent"].get("path"))) / "evaluation.json") for e in evaluations)),
        "versions": evaluations[0].get("versions"),
    }
    score = ReferenceScore(task, "oracle", float(np.mean(returns)), tuple(returns), provenance, budget)
    target = _path(path)
    data = read_reference_file(target)
    data["tasks"].setdefault(task, {}).setdefault("oracle", {})[budget] = {
        "mean_return": score.mean_return, "returns": returns, "provenance": provenance}
    _write(data, target)
    return score
