"""Learning tests on the fast InvertedPendulum pair (slow: minutes per method on a 2-core CPU).

The protocol of the DAP paper at toy scale: RL on source is trained first; it collects the target
dataset; every method then trains with that dataset and is evaluated in the target. Each method must
beat the random policy; the off-dynamics methods must also beat RL on source, which the shift makes
possible (the source policy drives the cart into the short target rail).
"""

from __future__ import annotations

import numpy as np
import pytest

from baselines.train import EVAL_SEED, train
from offdyn_bench.datasets.collect import episode_returns
from offdyn_bench.datasets.policies import UniformRandomPolicy
from offdyn_bench.tasks import get_task

TASK = "invertedpendulum-kinematic-slider-hard"
STEPS = 12_000
EPISODES = 5
FAST = {"sac.hidden_sizes": "[64, 64]", "sac.batch_size": "128", "sac.actor_lr": "0.001",
        "sac.critic_lr": "0.001", "sac.temperature_lr": "0.001", "random_steps": "1000"}
OFF_DYNAMICS = {"warmup_steps": "3000", "classifier.input_noise_std": "0.1"}
METHODS = {
    "dap": FAST | OFF_DYNAMICS,
    "darc": FAST | OFF_DYNAMICS,
    "dap-u": FAST | OFF_DYNAMICS,
    "h2o": FAST,
    "cql": {k: v for k, v in FAST.items() if k != "random_steps"},
    "darc-online": FAST | OFF_DYNAMICS,
    "sac-target": FAST,
}
SHOULD_BEAT_SOURCE = {"sac-target", "darc", "darc-online", "dap", "dap-u", "h2o"}


def _random_policy_return() -> float:
    env = get_task(TASK).make("target")
    policy = UniformRandomPolicy(env.action_space.low, env.action_space.high, seed=0)
    return float(np.mean(episode_returns(env, policy, episodes=EPISODES, seed=EVAL_SEED)))


@pytest.fixture(scope="module")
def source_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("learning") / "sac-source"
    result = train("sac-source", TASK, steps=STEPS, out=out, overrides=FAST, eval_episodes=EPISODES, progress=False)
    return out, result


@pytest.mark.slow
@pytest.mark.parametrize("algo", list(METHODS))
def test_method_beats_random_and_rl_on_source(algo, source_run, tmp_path):
    source_dir, source_result = source_run
    dataset = f"collect:{source_dir}:5000" if algo not in ("sac-target", "darc-online") else None
    result = train(algo, TASK, steps=STEPS, out=tmp_path / algo, dataset=dataset, overrides=METHODS[algo],
                   eval_episodes=EPISODES, progress=False)
    random_return = _random_policy_return()
    assert result["mean_return"] > random_return, (algo, result["mean_return"], random_return)
    if algo in SHOULD_BEAT_SOURCE:
        assert result["mean_return"] > source_result["mean_return"], \
            (algo, result["mean_return"], source_result["mean_return"])
