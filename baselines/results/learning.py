"""Reproduce the learning benchmark of issue 9: every method, five seeds, one fast pair, scored
under the protocol.

    python -m baselines.results.learning --task invertedpendulum-action-delay-1 --runs runs/learning

1. ``sac-source`` trains (seeds 0-4, one process); its seed-0 policy collects the target dataset
   (``collect:<run>:5000``, the DAP paper's protocol at toy scale: a sub-optimal source policy);
2. every other method trains with that dataset (or none), seeds 0-4 in one process, with the
   settings of ``tests/baselines/test_baselines_learning.py`` (64x64 networks, 12k steps);
3. ``offdyn-bench evaluate`` scores each run's final policies on the target (20 fixed episodes per
   seed), and ``offdyn-bench protocol score`` normalizes them against the random policy and the
   best possible return (1000), IQM with a stratified-bootstrap 95% interval;
4. per-seed returns, IQMs and the paper claims checked on them go to
   ``baselines/results/learning-<task>.json`` and ``.md``.

Every run folder is resumable and a finished one is skipped, so the command can be run again after
an interruption. ``--jobs`` trains that many methods at once (each in its own process).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent
STEPS = 12_000
SEEDS = 5
DATASET_TRANSITIONS = 5_000
EVAL_EPISODES = 20
BEST_RETURN = 1000.0
"""InvertedPendulum pays 1 per step for 1000 steps: the best possible return."""
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


def train(task: str, runs: Path, name: str, source_run: Path) -> Path:
    algo, overrides = METHODS[name]
    out = run_folder(runs, name)
    if (out / "result.json").exists():
        return out
    command = [sys.executable, "-m", "baselines", "train", algo, "--task", task, "--steps", str(STEPS),
               "--seed", "0", "--n-seeds", str(SEEDS), "--out", str(out), "--eval-every", "3000",
               "--eval-episodes", "5", "--no-progress"]
    command += [x for key, value in overrides.items() for x in ("--set", f"{key}={value}")]
    if algo in NEEDS_DATASET:
        command += ["--dataset", f"collect:{source_run}:{DATASET_TRANSITIONS}"]
    _run(command, out.with_suffix(".log"))
    return out


def evaluate(task: str, out: Path) -> Path:
    evaluation = out / "evaluation.json"
    if not evaluation.exists():
        _run([sys.executable, "-m", "offdyn_bench", "evaluate", "--agent", str(out), "--task", task,
              "--episodes", str(EVAL_EPISODES), "--no-progress"], out.with_suffix(".evaluate.log"))
    return evaluation


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


def summarize(task: str, runs: Path, names: list[str]) -> dict:
    from offdyn_bench.protocol.statistics import iqm, stratified_bootstrap_ci

    j_random = random_return(task)
    methods = {}
    for name in names:
        evaluation = json.loads((run_folder(runs, name) / "evaluation.json").read_text())
        per_seed = {seed: float(np.mean(r)) for seed, r in _returns_by_seed(evaluation).items()}
        normalized = np.array([[100.0 * (r - j_random) / (BEST_RETURN - j_random)] for r in per_seed.values()])
        interval = stratified_bootstrap_ci(normalized, iqm, reps=2000, seed=0)
        methods[name] = {"algorithm": METHODS[name][0], "overrides": METHODS[name][1],
                         "target_return_per_seed": per_seed,
                         "iqm_return": float(iqm(np.array([[r] for r in per_seed.values()]))),
                         "iqm_normalized": interval.point, "ci95_normalized": [interval.low, interval.high]}
    return {"task": task, "steps": STEPS, "seeds": list(range(SEEDS)), "eval_episodes_per_seed": EVAL_EPISODES,
            "dataset": f"collect:<sac-source run>:{DATASET_TRANSITIONS} (seed-0 policy of sac-source)",
            "random_return": j_random, "best_return": BEST_RETURN, "methods": methods,
            "claims": claims(methods), "command": f"python -m baselines.results.learning --task {task}"}


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
    """The papers' claims, checked on IQM returns: DAP at least 2x RL on source, DAP+U above DAP,
    H2O above DARC and CQL; for DAP both with the regulariser's former default (sampled actions) and
    its current one (mean actions)."""
    def value(name: str) -> float | None:
        return methods[name]["iqm_return"] if name in methods else None

    checks = {}
    for dap_name, dap_u_name in (("dap", "dap-u"),
                                 ("dap[regularized_actions=mean]", "dap-u[regularized_actions=mean]")):
        source, dap_, dap_u = value("sac-source"), value(dap_name), value(dap_u_name)
        if source is not None and dap_ is not None:
            checks[f"{dap_name} >= 2x rl-on-source (IQM return)"] = {
                "holds": dap_ >= 2 * source, dap_name: dap_, "sac-source": source}
        if dap_ is not None and dap_u is not None:
            checks[f"{dap_u_name} > {dap_name}"] = {"holds": dap_u > dap_, dap_u_name: dap_u, dap_name: dap_}
    h2o_ = value("h2o")
    for other in ("darc", "cql"):
        if h2o_ is not None and value(other) is not None:
            checks[f"h2o > {other}"] = {"holds": h2o_ > value(other), "h2o": h2o_, other: value(other)}
    return checks


def markdown(summary: dict) -> str:
    names = list(summary["methods"])
    seeds = [str(s) for s in summary["seeds"]]
    lines = [f"# Learning benchmark: `{summary['task']}`", "",
             f"{summary['steps']:,} steps, seeds {', '.join(seeds)} (one process), final policies evaluated on "
             f"{summary['eval_episodes_per_seed']} fixed target episodes per seed. Random policy "
             f"{summary['random_return']:.1f}, best possible {summary['best_return']:.0f}. Reproduce: "
             f"`{summary['command']}`.", "",
             "| method | " + " | ".join(f"seed {s}" for s in seeds) + " | IQM return | IQM normalized [95% CI] |",
             "|---" * (len(seeds) + 3) + "|"]
    for name in names:
        m = summary["methods"][name]
        cells = [f"{m['target_return_per_seed'][s]:.1f}" for s in seeds]
        low, high = m["ci95_normalized"]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {m['iqm_return']:.1f} | "
                     f"{m['iqm_normalized']:.1f} [{low:.1f}, {high:.1f}] |")
    lines += ["", "Claims of the papers at this scale:", ""]
    lines += [f"- {claim}: {'holds' if c['holds'] else 'does not hold'} "
              f"({', '.join(f'{k} {v:.1f}' for k, v in c.items() if k != 'holds')})"
              for claim, c in summary["claims"].items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", required=True)
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
    runs = args.runs / args.task
    source_run = args.source_run or run_folder(runs, "sac-source")
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        # The dataset comes from sac-source: unless --source-run names a finished one, sac-source trains
        # first, next to the methods that need no dataset.
        no_dataset = [pool.submit(train, args.task, runs, n, source_run) for n in names
                      if METHODS[n][0] not in NEEDS_DATASET and (n != "sac-source" or args.source_run)]
        if "sac-source" in names and not args.source_run:
            train(args.task, runs, "sac-source", source_run)
        with_dataset = [pool.submit(train, args.task, runs, n, source_run) for n in names
                        if METHODS[n][0] in NEEDS_DATASET]
        for future in no_dataset + with_dataset:
            future.result()
        list(pool.map(lambda n: evaluate(args.task, run_folder(runs, n)), names))
    summary = summarize(args.task, runs, names)
    stem = RESULTS / f"learning-{args.task}"
    if args.merge and stem.with_suffix(".json").exists():
        summary = merged(json.loads(stem.with_suffix(".json").read_text()), summary)
    stem.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
    stem.with_suffix(".md").write_text(markdown(summary))
    print(markdown(summary))


if __name__ == "__main__":
    main()
