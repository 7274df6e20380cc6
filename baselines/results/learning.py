"""Reproduce the learning benchmark of issue 9: every method, five seeds, one fast pair, scored
under the protocol.

    python -m baselines.results.learning --task invertedpendulum-action-delay-1 --runs runs/learning
    python -m baselines.results.learning --task wheellegged-standstill --steps 8000 --methods sac-source,...

1. ``sac-source`` trains (seeds 0-4, one process); unless the task's official target dataset is
   one no source policy could have collected (the wheel-legged robot's human-operator data), its
   seed-0 policy collects the target dataset (``collect:<run>:5000``, the DAP paper's protocol at
   toy scale: a sub-optimal source policy); ``--dataset`` overrides the choice (``dataset_mode``);
2. every other method trains with that dataset (or none), seeds 0-4 in one process, with the
   settings of ``tests/baselines/test_baselines_learning.py`` (64x64 networks, 12k steps by
   default, ``--steps``; DARC's and DAP's classifier warm-up ``warmup_steps(steps)``);
3. ``offdyn-bench evaluate`` scores each run's final policies on the target (20 fixed episodes per
   seed), normalized (as ``offdyn-bench protocol score`` does) between a random reference (0) and a
   best reference (100), IQM with a stratified-bootstrap 95% interval; the references are
   ``references(task, ...)``: for InvertedPendulum the random policy measured here and the best
   possible return (1000); for a task trained on its official dataset, that dataset's random
   reference in the manifest and, where the robot has one, its clean controller evaluated here
   under the same 20 episodes (``CLEAN_CONTROLLERS``; no ``sac-target`` oracle exists for them);
4. per-seed returns, IQMs, the wall time of every train and evaluate process and the paper claims
   checked on them go to ``baselines/results/learning-<task>.json`` and ``.md``.

Every run folder is resumable and a finished one is skipped, so the command can be run again after
an interruption. ``--jobs`` trains that many methods at once (each in its own process).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent
STEPS = 12_000
"""The default budget (``--steps``)."""
SEEDS = 5
DATASET_TRANSITIONS = 5_000
EVAL_EPISODES = 20
BEST_RETURN = 1000.0
"""InvertedPendulum pays 1 per step for 1000 steps: the best possible return."""
BEST_POSSIBLE = {"InvertedPendulum": BEST_RETURN}
"""Robot -> the best possible return, where the reward makes it known."""
CLEAN_CONTROLLERS = {"WheelLegged": "offdyn_bench.wheel_legged.operator:balancing_agent"}
"""Robot -> a ``module:factory`` agent whose return under the protocol's episodes is the best reference
(the clean LQR of the wheel-legged robot: the README's wheel-legged section normalizes the same way)."""
WARMUP_STEPS = 3000
"""DARC's and DAP's classifier warm-up at the default budget; a quarter of the budget below it."""
FAST = {"sac.hidden_sizes": "[64,64]", "sac.batch_size": "128", "sac.actor_lr": "0.001",
        "sac.critic_lr": "0.001", "sac.temperature_lr": "0.001", "random_steps": "1000"}
OFF_DYNAMICS = {"warmup_steps": "3000", "classifier.input_noise_std": "0.1"}
METHODS: dict[str, tuple[str, dict[str, str]]] = {
    # name in the results: (algorithm, --set overrides)
    "sac-source": ("sac-source", FAST),
    "sac-target": ("sac-target", FAST),
    "cql": ("cql", {k: v for k, v in FAST.items() if k != "random_steps"}),
    "h2o": ("h2o", FAST),
    "darc": ("darc", FAST | OFF_DYNAMICS),
    # The online track: target steps during training (one per ten source steps), no dataset.
    "darc-online": ("darc-online", FAST | OFF_DYNAMICS),
    # DAP's open choices (issue 9, point 4). "sampled" was the default before issue 9; "mean" is now.
    "dap": ("dap", FAST | OFF_DYNAMICS | {"regularized_actions": "sampled"}),
    "dap-u": ("dap-u", FAST | OFF_DYNAMICS | {"regularized_actions": "sampled"}),
    "dap[classifier_source_action=target]": ("dap", FAST | OFF_DYNAMICS | {"classifier_source_action": "target",
                                                                           "regularized_actions": "sampled"}),
    "dap[regularized_actions=mean]": ("dap", FAST | OFF_DYNAMICS | {"regularized_actions": "mean"}),
    "dap-u[regularized_actions=mean]": ("dap-u", FAST | OFF_DYNAMICS | {"regularized_actions": "mean"}),
    # DARC's published settings against the H2O paper's variant (baselines.darc.h2o_variant_config):
    "darc[h2o_variant]": ("darc", FAST | OFF_DYNAMICS | {
        "classifier.hidden_sizes": "[256]", "classifier.soft_clip_logits": "true",
        "sac.reward_scale": "1.0", "sac.target_entropy_per_action_dim": "-1.0"}),
}
NEEDS_DATASET = {"cql", "h2o", "darc", "dap", "dap-u"}


def run_folder(runs: Path, name: str) -> Path:
    return runs / name.replace("[", "-").replace("]", "").replace("=", "-")


def warmup_steps(steps: int) -> int:
    """DARC's and DAP's classifier warm-up: 3,000 at the default 12,000 steps, a quarter of a smaller
    budget (the classifiers need data first; their defaults, 100,000 and 10,000, would leave plain SAC)."""
    return min(WARMUP_STEPS, steps // 4)


def method_overrides(name: str, steps: int = STEPS) -> dict[str, str]:
    """``METHODS[name]``'s --set overrides at ``steps`` (only the warm-up depends on the budget)."""
    overrides = dict(METHODS[name][1])
    if "warmup_steps" in overrides:
        overrides["warmup_steps"] = str(warmup_steps(steps))
    return overrides


def dataset_mode(task: str) -> str:
    """``"official"`` when the task's official target dataset (offline-target track) is one no source
    policy could have collected (a human operator's, as on H2O's real robot); ``"collect"`` (RL on
    source's seed-0 policy collects it, the published InvertedPendulum setting) otherwise."""
    return "official" if _official_dataset_quality(task) not in (None, "source-policy") else "collect"


def official_dataset_id(task: str) -> str:
    from offdyn_bench.protocol.definition import official_dataset

    dataset = official_dataset(task, "offline-target")
    if dataset is None:
        raise SystemExit(f"error: {task} has no official target dataset on the offline-target track")
    return dataset


def _official_dataset_quality(task: str) -> str | None:
    from offdyn_bench.protocol.definition import official_dataset

    dataset = official_dataset(task, "offline-target")
    return None if dataset is None else dataset.split("/")[-1].rsplit("-v", 1)[0]


def dataset_spec(mode: str, source_run: Path) -> str | None:
    """The --dataset of the methods that need one (None: train's default, the official dataset)."""
    return f"collect:{source_run}:{DATASET_TRANSITIONS}" if mode == "collect" else None


def train(task: str, runs: Path, name: str, source_run: Path, steps: int = STEPS, mode: str = "collect") -> Path:
    algo, overrides = METHODS[name][0], method_overrides(name, steps)
    out = run_folder(runs, name)
    if (out / "result.json").exists():
        return out
    command = [sys.executable, "-m", "baselines", "train", algo, "--task", task, "--steps", str(steps),
               "--seed", "0", "--n-seeds", str(SEEDS), "--out", str(out), "--eval-every", str(max(steps // 4, 1)),
               "--eval-episodes", "5", "--no-progress"]
    command += [x for key, value in overrides.items() for x in ("--set", f"{key}={value}")]
    if algo in NEEDS_DATASET and dataset_spec(mode, source_run) is not None:
        command += ["--dataset", dataset_spec(mode, source_run)]
    _timed(command, out.with_suffix(".log"), out, "train")
    return out


def evaluate(task: str, out: Path) -> Path:
    evaluation = out / "evaluation.json"
    if not evaluation.exists():
        _timed([sys.executable, "-m", "offdyn_bench", "evaluate", "--agent", str(out), "--task", task,
                "--episodes", str(EVAL_EPISODES), "--no-progress"], out.with_suffix(".evaluate.log"), out,
               "evaluate")
    return evaluation


def evaluate_clean_controller(task: str, runs: Path) -> Path:
    """The robot's clean controller under the protocol's episodes (one deterministic policy: seed 0)."""
    from offdyn_bench.tasks import get_task

    out = runs / "clean-controller"
    evaluation = out / "evaluation.json"
    if not evaluation.exists():
        _timed([sys.executable, "-m", "offdyn_bench", "evaluate", "--agent", CLEAN_CONTROLLERS[get_task(task).robot],
                "--task", task, "--seeds", "0", "--method", "clean-controller", "--track", "offline-target",
                "--episodes", str(EVAL_EPISODES), "--out", str(evaluation), "--no-progress"],
               out.with_suffix(".evaluate.log"), out, "evaluate")
    return evaluation


def episode_lengths(out: Path) -> Path:
    """How long the final policies of a run stay up, from its ``evaluation.json``: per seed the
    length of every episode and whether it ran to the time limit rather than ending in a fall."""
    path = out / "episode_lengths.json"
    if path.exists():
        return path
    evaluation = json.loads((out / "evaluation.json").read_text())
    if any("lengths" not in entry for entry in evaluation["seeds"]):
        raise SystemExit(f"error: {out}/evaluation.json records no episode lengths (made before evaluate recorded "
                         "them); delete it and run again to re-evaluate")
    record = {str(entry["seed"]): {"lengths": entry["lengths"], "to_time_limit": entry["truncated"]}
              for entry in evaluation["seeds"]}
    path.write_text(json.dumps(record) + "\n")
    return path


def _timed(command: list[str], log: Path, out: Path, stage: str) -> None:
    """``_run``, and its wall time in seconds into ``out/wall_time.json`` (kept when a later call resumes)."""
    start = time.monotonic()
    _run(command, log)
    seconds = time.monotonic() - start
    times = _wall_time(out)
    times[f"{stage}_s"] = round(seconds, 1)
    out.mkdir(parents=True, exist_ok=True)
    (out / "wall_time.json").write_text(json.dumps(times) + "\n")


def _run(command: list[str], log: Path) -> None:
    print("$ " + " ".join(command), flush=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as f:
        subprocess.run(command, check=True, stdout=f, stderr=subprocess.STDOUT, cwd=RESULTS.parent.parent)


def random_return(task: str) -> float:
    from baselines.train import EVAL_SEED
    from offdyn_bench.datasets.collect import episode_returns
    from offdyn_bench.datasets.policies import UniformRandomPolicy
    from offdyn_bench.tasks import get_task

    env = get_task(task).make("target")
    policy = UniformRandomPolicy(env.action_space.low, env.action_space.high, seed=0)
    return float(np.mean(episode_returns(env, policy, episodes=EVAL_EPISODES, seed=EVAL_SEED)))


def references(task: str, runs: Path, mode: str) -> dict:
    """The normalization's references: ``random_return`` (0), ``best_return`` (100) and, for the
    tasks trained on their official dataset, where each comes from (``*_reference`` keys)."""
    from offdyn_bench.tasks import get_task

    robot = get_task(task).robot
    if mode == "collect" and robot in BEST_POSSIBLE:  # the published InvertedPendulum results
        return {"random_return": random_return(task), "best_return": BEST_POSSIBLE[robot]}
    if mode == "collect":
        refs = {"random_return": random_return(task),
                "random_reference": {"source": f"uniform random actions, {EVAL_EPISODES} episodes measured here"}}
    else:
        from offdyn_bench.datasets.manifest import read_manifest

        dataset = official_dataset_id(task)
        random_entry = read_manifest().get(dataset).reference_scores["random"]
        refs = {"random_return": float(random_entry["value"]),
                "random_reference": {"source": f"the manifest's random reference of {dataset}",
                                     "episodes": len(random_entry["returns"]),
                                     "episode_seeds": random_entry.get("episode_seeds")}}
    if robot in BEST_POSSIBLE:
        refs["best_return"] = BEST_POSSIBLE[robot]
        refs["best_reference"] = {"label": "best possible", "source": "best possible return"}
    else:
        if robot not in CLEAN_CONTROLLERS:
            raise SystemExit(f"error: no best reference for {robot}; add a clean controller to CLEAN_CONTROLLERS")
        path = evaluate_clean_controller(task, runs)
        returns = [r for rs in _returns_by_seed(json.loads(path.read_text())).values() for r in rs]
        refs["best_return"] = float(np.mean(returns))
        refs["best_reference"] = {"label": "clean controller", "agent": CLEAN_CONTROLLERS[robot],
                                  "source": f"{CLEAN_CONTROLLERS[robot]} under the same {len(returns)} target "
                                            "episodes (offdyn-bench evaluate, one deterministic policy)",
                                  "returns": returns, "wall_time_s": _wall_time(path.parent).get("evaluate_s")}
    return refs


def published_format(refs: dict) -> bool:
    """Whether results with these references keep the published InvertedPendulum format (random
    and best possible return only; no wall times, episode lengths or reference provenance)."""
    return "best_reference" not in refs


def _wall_time(out: Path) -> dict:
    record = out / "wall_time.json"
    return json.loads(record.read_text()) if record.exists() else {}


def normalized(returns, j_random: float, j_best: float) -> np.ndarray:
    """100 x (J - J_random) / (J_best - J_random), elementwise."""
    return 100.0 * (np.asarray(returns, dtype=float) - j_random) / (j_best - j_random)


def summarize(task: str, runs: Path, names: list[str], steps: int = STEPS, mode: str = "collect",
              refs: dict | None = None, command: str | None = None) -> dict:
    from offdyn_bench.protocol.statistics import iqm, stratified_bootstrap_ci

    refs = refs if refs is not None else references(task, runs, mode)
    j_random, j_best = refs["random_return"], refs["best_return"]
    methods = {}
    for name in names:
        evaluation = json.loads((run_folder(runs, name) / "evaluation.json").read_text())
        per_seed = {seed: float(np.mean(r)) for seed, r in _returns_by_seed(evaluation).items()}
        scores = normalized([[r] for r in per_seed.values()], j_random, j_best)
        interval = stratified_bootstrap_ci(scores, iqm, reps=2000, seed=0)
        methods[name] = {"algorithm": METHODS[name][0], "overrides": method_overrides(name, steps),
                         "target_return_per_seed": per_seed,
                         "iqm_return": float(iqm(np.array([[r] for r in per_seed.values()]))),
                         "iqm_normalized": interval.point, "ci95_normalized": [interval.low, interval.high]}
        if not published_format(refs):  # wall times and episode lengths too
            methods[name]["wall_time_s"] = _wall_time(run_folder(runs, name))
            lengths_file = run_folder(runs, name) / "episode_lengths.json"
            if lengths_file.exists():
                lengths = json.loads(lengths_file.read_text())
                methods[name]["mean_episode_length_per_seed"] = {
                    seed: float(np.mean(entry["lengths"])) for seed, entry in lengths.items()}
                methods[name]["episodes_to_time_limit"] = (
                    f"{sum(sum(e['to_time_limit']) for e in lengths.values())} of "
                    f"{sum(len(e['to_time_limit']) for e in lengths.values())}")
    summary = {"task": task, "steps": steps, "seeds": list(range(SEEDS)), "eval_episodes_per_seed": EVAL_EPISODES,
               "dataset": (f"collect:<sac-source run>:{DATASET_TRANSITIONS} (seed-0 policy of sac-source)"
                           if mode == "collect" else official_dataset_id(task)),
               "random_return": j_random, "best_return": j_best}
    if mode != "collect":
        summary["dataset_id"] = official_dataset_id(task)
    if not published_format(refs):
        summary["warmup_steps"] = warmup_steps(steps)
        summary |= {k: v for k, v in refs.items() if k not in ("random_return", "best_return")}
    return summary | {"methods": methods, "claims": claims(methods),
                      "command": command or f"python -m baselines.results.learning --task {task}"}


def merged(published: dict, new: dict) -> dict:
    """``published`` with ``new``'s methods added or replaced; refused unless both measured the same
    task, steps, seeds and episodes (a table must compare like with like)."""
    for key in ("task", "steps", "seeds", "eval_episodes_per_seed"):
        if published.get(key) != new[key]:
            raise SystemExit(f"error: cannot merge: the published results have {key}={published.get(key)!r}, "
                             f"these runs {new[key]!r}")
    methods = {name: entry for name, entry in published["methods"].items() if name not in new["methods"]}
    methods.update(new["methods"])
    return {**new, "methods": methods, "claims": claims(methods)}


def _returns_by_seed(evaluation: dict) -> dict[str, list[float]]:
    """Per training seed, the per-episode target returns of an ``offdyn-bench evaluate`` record."""
    return {str(entry["seed"]): [float(x) for x in entry["returns"]] for entry in evaluation["seeds"]}


def claims(methods: dict) -> dict[str, dict]:
    """The papers' claims (:data:`offdyn_bench.protocol.claims.PAPER_CLAIMS`), checked on IQM returns;
    the DAP ones both with the regulariser's former default (sampled actions) and its current one
    (mean actions)."""
    from offdyn_bench.protocol.claims import PAPER_CLAIMS

    def value(name: str) -> float | None:
        return methods[name]["iqm_return"] if name in methods else None

    def named(claim, suffix: str) -> tuple[str, str]:
        return tuple(name + suffix if name.startswith("dap") else name for name in (claim.better, claim.worse))

    dap_claims = [c for c in PAPER_CLAIMS if c.better.startswith("dap")]
    other_claims = [c for c in PAPER_CLAIMS if c not in dap_claims]
    checks = {}
    for claim, suffix in [(c, s) for s in ("", "[regularized_actions=mean]") for c in dap_claims] + \
            [(c, "") for c in other_claims]:
        better, worse = named(claim, suffix)
        if value(better) is None or value(worse) is None:
            continue
        label = (f"{better} >= {claim.factor:g}x rl-on-source (IQM return)" if claim.factor != 1.0
                 else f"{better} > {worse}")
        checks[label] = {"holds": claim.verdict(value(better), value(worse)), better: value(better),
                         worse: value(worse)}
    return checks


def markdown(summary: dict) -> str:
    names = list(summary["methods"])
    seeds = [str(s) for s in summary["seeds"]]
    if published_format(summary):
        header = (f"{summary['steps']:,} steps, seeds {', '.join(seeds)} (one process), final policies evaluated on "
                  f"{summary['eval_episodes_per_seed']} fixed target episodes per seed. Random policy "
                  f"{summary['random_return']:.1f}, best possible {summary['best_return']:.0f}. Reproduce: "
                  f"`{summary['command']}`.")
    else:
        best = summary.get("best_reference", {})
        dataset = f"`{summary['dataset_id']}` (official)" if "dataset_id" in summary else summary["dataset"]
        header = (f"{summary['steps']:,} steps, seeds {', '.join(seeds)} (one process), target dataset "
                  f"{dataset}, DARC/DAP classifier warm-up {summary['warmup_steps']:,} "
                  f"steps; final policies evaluated on {summary['eval_episodes_per_seed']} fixed target episodes per "
                  f"seed. Normalized: 0 = random policy {summary['random_return']:.1f} "
                  f"({summary.get('random_reference', {}).get('source', 'measured')}), 100 = "
                  f"{best.get('label', 'best')} {summary['best_return']:.1f}"
                  + (f" (`{best['agent']}`, the same {summary['eval_episodes_per_seed']} episodes)"
                     if "agent" in best else "") + f". Reproduce: `{summary['command']}`.")
    timed = any("wall_time_s" in m for m in summary["methods"].values())
    lines = [f"# Learning benchmark: `{summary['task']}`", "", header, "",
             "| method | " + " | ".join(f"seed {s}" for s in seeds) + " | IQM return | IQM normalized [95% CI] |"
             + (" episodes to the time limit | train / evaluate wall time |" if timed else ""),
             "|---" * (len(seeds) + 3 + 2 * timed) + "|"]
    for name in names:
        m = summary["methods"][name]
        cells = [f"{m['target_return_per_seed'][s]:.1f}" for s in seeds]
        low, high = m["ci95_normalized"]
        row = (f"| {name} | " + " | ".join(cells) + f" | {m['iqm_return']:.1f} | "
               f"{m['iqm_normalized']:.1f} [{low:.1f}, {high:.1f}] |")
        if timed:
            t = m.get("wall_time_s", {})
            row += (f" {m.get('episodes_to_time_limit', 'n/a')} |"
                    f" {_seconds(t.get('train_s'))} / {_seconds(t.get('evaluate_s'))} |")
        lines.append(row)
    lines += ["", "Claims of the papers at this scale:", ""]
    lines += [f"- {claim}: {'holds' if c['holds'] else 'does not hold'} "
              f"({', '.join(f'{k} {v:.1f}' for k, v in c.items() if k != 'holds')})"
              for claim, c in summary["claims"].items()]
    return "\n".join(lines) + "\n"


def _seconds(value: float | None) -> str:
    return "n/a" if value is None else f"{value / 60:.1f} min"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", required=True)
    parser.add_argument("--steps", type=int, default=STEPS, help="environment steps per run (gradient updates "
                        "for cql); DARC's and DAP's warm-up is min(3000, steps // 4)")
    parser.add_argument("--dataset", choices=["official", "collect"], help="the target dataset: the task's official "
                        "one, or collected by sac-source's seed-0 policy (default: official when no source policy "
                        "could have collected it, the human-operator data; collect otherwise)")
    parser.add_argument("--runs", type=Path, default=Path("runs/learning"))
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated names of METHODS")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--merge", action="store_true", help="keep the other methods of the published results "
                        "file (same task, steps and seeds) and add or replace only --methods")
    parser.add_argument("--source-run", type=Path, help="a finished sac-source run of the same robot whose seed-0 "
                        "policy collects the dataset (source training does not depend on the target, so any "
                        "pair of the robot gives the same policy); default: the sac-source run trained here")
    args = parser.parse_args(argv)
    names = args.methods.split(",")
    unknown = [n for n in names if n not in METHODS]
    if unknown:
        parser.error(f"unknown method(s) {unknown}; expected names from {list(METHODS)}")
    if args.steps < 4:
        parser.error("--steps must be at least 4")
    mode = args.dataset or dataset_mode(args.task)
    runs = args.runs / args.task
    source_run = args.source_run or run_folder(runs, "sac-source")
    steps = args.steps
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        # With a collected dataset, it comes from sac-source: unless --source-run names a finished one,
        # sac-source trains first, next to the methods that need no dataset.
        first = "sac-source" in names and not args.source_run and mode == "collect"
        no_dataset = [pool.submit(train, args.task, runs, n, source_run, steps, mode) for n in names
                      if METHODS[n][0] not in NEEDS_DATASET and not (first and n == "sac-source")]
        if first:
            train(args.task, runs, "sac-source", source_run, steps, mode)
        with_dataset = [pool.submit(train, args.task, runs, n, source_run, steps, mode) for n in names
                        if METHODS[n][0] in NEEDS_DATASET]
        for future in no_dataset + with_dataset:
            future.result()
        list(pool.map(lambda n: evaluate(args.task, run_folder(runs, n)), names))
    options = "".join(f" {flag} {value}" for flag, value, default in (
        ("--steps", steps, STEPS), ("--dataset", mode, dataset_mode(args.task)),
        # With --merge the file holds more methods than --methods names.
        ("--methods", f"'{args.methods}'", f"'{','.join(METHODS)}'" if not args.merge else f"'{args.methods}'"))
        if value != default)
    command = f"python -m baselines.results.learning --task {args.task}{options}"
    refs = references(args.task, runs, mode)
    if not published_format(refs):  # how long the policies stay up, too
        for n in names:
            episode_lengths(run_folder(runs, n))
    summary = summarize(args.task, runs, names, steps, mode, refs, command)
    stem = RESULTS / f"learning-{args.task}"
    if args.merge and stem.with_suffix(".json").exists():
        summary = merged(json.loads(stem.with_suffix(".json").read_text()), summary)
    stem.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
    stem.with_suffix(".md").write_text(markdown(summary))
    print(markdown(summary))


if __name__ == "__main__":
    main()
