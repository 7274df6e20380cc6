"""Learning tests on a fast InvertedPendulum pair (slow: tens of minutes per method on a 2-core CPU).

The protocol of the DAP paper at toy scale, over five seeds trained in one process: RL on source is
trained first; its seed-0 policy collects the target dataset; every method then trains with that
dataset and is evaluated in the target. Relations are asserted on the IQM over the seeds (one lucky
seed proves nothing): every method beats the random policy, and the methods listed in
``SHOULD_BEAT_SOURCE`` beat RL on source. ``baselines/results/`` holds the full measurement
(``python -m baselines.results.learning``), including the papers' claims that do not hold here.
"""

from __future__ import annotations

import numpy as np
import pytest

from baselines.results.learning import FAST, METHODS
from baselines.train import EVAL_SEED, train
from offdyn_bench.datasets.collect import episode_returns
from offdyn_bench.datasets.policies import UniformRandomPolicy
from offdyn_bench.protocol.statistics import iqm
from offdyn_bench.tasks import get_task

TASK = "invertedpendulum-rail-offset-hard"
"""RL on source fails in this target on 4 of 5 seeds measured (baselines/results/README.md)."""
STEPS = 12_000
SEEDS = 5
EPISODES = 5
DAP, DAP_U = "dap[regularized_actions=mean]", "dap-u[regularized_actions=mean]"
"""DAP and DAP+U with their current defaults (the learning script also keeps the former ones)."""
TESTED = ["sac-target", DAP, DAP_U, "h2o", "cql",
          pytest.param("darc", marks=pytest.mark.xfail(strict=True, reason=(
              "DARC collapses to return 2.0 on every seed here, below random, with the paper's settings and "
              "with the H2O variant alike (baselines/results/README.md)")))]
SHOULD_BEAT_SOURCE = {"sac-target", DAP, DAP_U}
"""Only relations the committed results support (baselines/results/learning-<TASK>.md)."""


def _iqm_return(result: dict) -> float:
    return iqm(np.array([[np.mean(r)] for r in result["returns"].values()]))


def _random_policy_return() -> float:
    env = get_task(TASK).make("target")
    policy = UniformRandomPolicy(env.action_space.low, env.action_space.high, seed=0)
    return float(np.mean(episode_returns(env, policy, episodes=EPISODES, seed=EVAL_SEED)))


@pytest.fixture(scope="module")
def source_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("learning") / "sac-source"
    result = train("sac-source", TASK, steps=STEPS, out=out, n_seeds=SEEDS, overrides=FAST, eval_episodes=EPISODES,
                   eval_every=STEPS, progress=False)
    return out, result


@pytest.mark.slow
@pytest.mark.parametrize("name", TESTED)
def test_method_beats_random_and_rl_on_source_over_seeds(name, source_run, tmp_path):
    source_dir, source_result = source_run
    algo, overrides = METHODS[name]
    dataset = f"collect:{source_dir}:5000" if algo not in ("sac-target", "darc-online") else None
    result = train(algo, TASK, steps=STEPS, out=tmp_path / algo, n_seeds=SEEDS, dataset=dataset, overrides=overrides,
                   eval_episodes=EPISODES, eval_every=STEPS, progress=False)
    method_iqm, source_iqm, random_return = _iqm_return(result), _iqm_return(source_result), _random_policy_return()
    assert method_iqm > random_return, (name, result["returns"], random_return)
    if name in SHOULD_BEAT_SOURCE:
        assert method_iqm > source_iqm, (name, method_iqm, source_iqm)
