"""The critic-value check: the data's return-to-go by hand, and a run's values as its own agent
computes them, seed by seed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from baselines.checkpoint import latest_checkpoint, load_checkpoint
from baselines.critic_values import _buffer_in_order, discounted_return_to_go, read_critic_values
from baselines.data import TransitionDataset
from baselines.sac import SACAgent, SACConfig
from baselines.train import train
from offdyn_bench.envs import flat_observations
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import get_task
from scripts.critic_values import main as critic_values_main

PENDULUM = "invertedpendulum-kinematic-slider-hard"
TINY = {"sac.hidden_sizes": "[32, 32]", "sac.batch_size": "32", "random_steps": "50"}


def test_return_to_go_restarts_at_each_episode_and_says_which_are_exact():
    rewards = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 4.0, 4.0])
    terminations = np.array([0, 0, 1, 0, 0, 0, 0], dtype=bool)
    truncations = np.array([0, 0, 0, 0, 1, 0, 0], dtype=bool)
    returns, exact = discounted_return_to_go(rewards, terminations, truncations, 0.5)
    # Terminated episode: exact. Truncated one and the unfinished tail: lower bounds.
    np.testing.assert_allclose(returns, [1.75, 1.5, 1.0, 3.0, 2.0, 6.0, 4.0])
    assert exact.tolist() == [True, True, True, False, False, False, False]


def test_return_to_go_refuses_mismatched_rows_and_a_bad_discount():
    with pytest.raises(OffdynError, match="one length"):
        discounted_return_to_go(np.ones(3), np.zeros(2, bool), np.zeros(3, bool), 0.9)
    with pytest.raises(OffdynError, match=r"discount=1.5: expected a number in \[0, 1\]"):
        discounted_return_to_go(np.ones(3), np.zeros(3, bool), np.zeros(3, bool), 1.5)


def test_a_wrapped_replay_buffer_is_read_oldest_first_and_split_at_its_resets():
    # Five chronological steps: an episode of two that terminates, then one of three that is cut
    # by a reset (next state 9 is not the following state 5) and an unfinished one; the ring buffer
    # of capacity 5 has wrapped twice, so row 0 holds the fourth step.
    observations = np.array([[0.0], [1.0], [4.0], [5.0], [6.0]])
    next_observations = np.array([[1.0], [2.0], [9.0], [6.0], [7.0]])
    order = [3, 4, 0, 1, 2]  # storage row -> chronological step
    stored = {"observations": observations[order], "next_observations": next_observations[order],
              "actions": np.zeros((5, 1)), "rewards": np.array([1.0, 2.0, 3.0, 4.0, 5.0])[order],
              "terminations": np.array([0.0, 1.0, 0.0, 0.0, 0.0])[order]}
    tensors = {f"buffer.{name}": torch.as_tensor(array)[None] for name, array in stored.items()}
    tensors["buffer.counters"] = torch.tensor([5, 2])
    rows = _buffer_in_order(tensors, 0)
    np.testing.assert_array_equal(rows["observations"][:, 0], [0.0, 1.0, 4.0, 5.0, 6.0])
    assert rows["truncations"].tolist() == [False, False, True, False, False]
    returns, exact = discounted_return_to_go(rows["rewards"], rows["terminations"], rows["truncations"], 1.0)
    np.testing.assert_allclose(returns, [3.0, 2.0, 3.0, 9.0, 5.0])
    assert exact.tolist() == [True, True, False, False, False]


@pytest.fixture(scope="module")
def h2o_run(tmp_path_factory, pendulum_dataset):
    out = tmp_path_factory.mktemp("h2o") / "run"
    train("h2o", task=PENDULUM, steps=160, out=out, seed=3, n_seeds=2, dataset=str(pendulum_dataset),
          overrides=TINY, eval_every=80, eval_episodes=1, progress=False)
    return out


def test_values_are_what_the_runs_own_agent_computes_for_each_seed(h2o_run, pendulum_dataset):
    values = read_critic_values(h2o_run)
    assert [v.seed for v in values] == [3, 4] and {v.step for v in values} == {160}
    tensors, _ = load_checkpoint(latest_checkpoint(h2o_run))
    env = flat_observations(get_task(PENDULUM).make("target"))
    agent = SACAgent(env.observation_space.shape[0], env.action_space.shape[0], [3, 4], SACConfig(hidden_sizes=(32, 32)))
    agent.load_state_dict(tensors)
    data = TransitionDataset.from_npz(pendulum_dataset)
    batch = data.to_batch(env.action_space)
    states = batch.observations.expand(2, -1, -1)
    with torch.no_grad():
        q_data = agent.q_values(states, batch.actions.expand(2, -1, -1)).min(dim=1).values.mean(dim=1)
        q_policy = agent.q_values(states, agent.mean_actions(states)).min(dim=1).values.mean(dim=1)
        buffer = [tensors[f"buffer.{k}"] for k in ("observations", "actions")]
        q_buffer = agent.q_values(*buffer).min(dim=1).values.mean(dim=1)
    for member, entry in enumerate(values):
        assert entry.q_data == pytest.approx(float(q_data[member]), rel=1e-5)
        assert entry.q_policy_at_data_states == pytest.approx(float(q_policy[member]), rel=1e-5)
        assert entry.q_buffer == pytest.approx(float(q_buffer[member]), rel=1e-5)
        assert entry.buffer_rows == 160 and entry.data_rows == len(data)
        # The pendulum pays 1 a step alive: its buffer's episodes earn between 1 and 1/(1-0.99).
        assert 1.0 <= entry.buffer_return_to_go <= 100.0 and 0.0 < entry.buffer_rows_terminated <= 1.0
        assert entry.discount == 0.99 and entry.backs_up_entropy is False  # H2O's official setting
    assert values[0].q_data != values[1].q_data  # each seed reads its own critics
    returns, _ = discounted_return_to_go(data.rewards, data.terminations, data.truncations, 0.99)
    assert values[0].data_return_to_go == pytest.approx(returns.mean())


def test_the_script_writes_each_checkpoint_once(h2o_run, tmp_path, capsys):
    log = tmp_path / "values.jsonl"
    for _ in range(2):
        assert critic_values_main([str(h2o_run), "--every-checkpoint", "--jsonl", str(log)]) == 0
    lines = log.read_text().splitlines()
    assert len(lines) == 2 * 2  # two kept checkpoints x two seeds, the second reading adds nothing
    assert "Q pi(s)" in capsys.readouterr().out


def test_a_run_without_target_data_and_a_folder_that_is_no_run_are_refused(tmp_path, capsys):
    sac = tmp_path / "sac"
    train("sac-source", task=PENDULUM, steps=80, out=sac, overrides={"sac.hidden_sizes": "[8]", "sac.batch_size": "8",
                                                                     "random_steps": "20"},
          eval_every=80, eval_episodes=1, progress=False)
    with pytest.raises(OffdynError, match="trained without a target dataset"):
        read_critic_values(sac)
    assert critic_values_main([str(tmp_path / "nothing")]) == 2
    assert "is not a training run folder" in capsys.readouterr().err
    edited = tmp_path / "edited"
    edited.mkdir()
    (edited / "config.json").write_text('{"task": "hopper-gravity-0.5", "seeds": "0", "config": {}}')
    with pytest.raises(OffdynError, match="does not name a task and a list of integer seeds"):
        read_critic_values(edited)
