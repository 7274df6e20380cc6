"""CQL's batched conservative penalty against the formulation it replaced: same loss, same
gradients, same training steps (to float tolerance), with the same random draws."""

from __future__ import annotations

import pytest
import torch

from baselines import cql
from baselines.method import MethodContext
from baselines.sac import Batch, SACAgent, SACConfig, sac_update


def _dataset(n: int = 500, obs_dim: int = 5, action_dim: int = 2) -> Batch:
    g = torch.Generator().manual_seed(7)
    return Batch(torch.randn(n, obs_dim, generator=g), torch.rand(n, action_dim, generator=g) * 2 - 1,
                 torch.randn(n, generator=g), torch.randn(n, obs_dim, generator=g),
                 (torch.rand(n, generator=g) < 0.1).float())


def _pair(batch_size: int, n_action_samples: int = 10) -> tuple[cql.CQL, cql.CQL]:
    """Two identical CQL learners (same seeds, so same weights and random streams)."""
    config = lambda: cql.Config(sac=SACConfig(hidden_sizes=(32, 32), batch_size=batch_size),  # noqa: E731
                                n_action_samples=n_action_samples)
    context = MethodContext(observation_dim=5, action_dim=2, seeds=(0, 1), target_data=_dataset())
    return cql.CQL(config(), context), cql.CQL(config(), context)


# 40 states are two full blocks of 16 and a remainder of 8.
@pytest.mark.parametrize("batch_size, n_action_samples", [(40, 10), (16, 1), (7, 3)])
def test_the_batched_penalty_equals_the_unbatched_one(batch_size, n_action_samples):
    fast, reference = _pair(batch_size, n_action_samples)
    batch = fast.data.sample(batch_size)
    results = []
    for learner, build in ((fast, fast.conservative_penalty), (reference, reference.conservative_penalty_unbatched)):
        penalty = build(batch)
        q_data = learner.agent.q_values(batch.observations, batch.actions)
        loss, metrics = penalty(learner.agent.q_values, q_data)
        loss.sum().backward()
        results.append((loss.detach(), metrics["cql/gap"], [p.grad.clone() for p in learner.agent.critic]))
    (loss_a, gap_a, grads_a), (loss_b, gap_b, grads_b) = results
    assert loss_a.shape == (2,) and loss_a.abs().min() > 1e-3  # a real, per-seed penalty
    torch.testing.assert_close(loss_a, loss_b, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gap_a, gap_b, rtol=1e-5, atol=1e-5)
    for a, b in zip(grads_a, grads_b):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    # Same draws from the same streams: both left their generators in the same state.
    assert torch.equal(fast.agent.generator.get_state(), reference.agent.generator.get_state())
    assert torch.equal(fast.uniform_generator.get_state(), reference.uniform_generator.get_state())


def test_training_steps_match_the_unbatched_formulation():
    fast, reference = _pair(64)
    for _ in range(5):
        batch = fast.data.sample(64)
        assert torch.equal(batch.observations, reference.data.sample(64).observations)
        sac_update(fast.agent, batch, extra_loss=fast.conservative_penalty(batch))
        sac_update(reference.agent, batch, extra_loss=reference.conservative_penalty_unbatched(batch))
    for a, b in zip(fast.agent.critic + fast.agent.actor, reference.agent.critic + reference.agent.actor):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    assert not torch.equal(fast.agent.critic[0], _pair(64)[0].agent.critic[0])  # it did train


def test_several_samples_per_state_are_the_repeated_state_samples():
    agent, twin = (SACAgent(4, 2, (3,), SACConfig(hidden_sizes=(16,))) for _ in range(2))
    states = torch.randn(1, 9, 4, generator=torch.Generator().manual_seed(1))
    actions, log_probs = agent.sample_actions(states, samples_per_state=5)
    expected_actions, expected_log_probs = twin.sample_actions(states.repeat_interleave(5, dim=1))
    assert actions.shape == (1, 45, 2) and log_probs.shape == (1, 45)
    torch.testing.assert_close(actions, expected_actions)
    torch.testing.assert_close(log_probs, expected_log_probs)
