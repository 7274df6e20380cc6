"""The SAC core against a hand-computed SAC step, and the seed batching."""

from __future__ import annotations

import math

import pytest
import torch

from baselines.sac import Batch, SACAgent, SACConfig, sac_update


def _batch(seeds: int = 1, size: int = 5, obs_dim: int = 3, action_dim: int = 2) -> Batch:
    g = torch.Generator().manual_seed(123)
    return Batch(observations=torch.randn(seeds, size, obs_dim, generator=g),
                 actions=torch.rand(seeds, size, action_dim, generator=g) * 2 - 1,
                 rewards=torch.randn(seeds, size, generator=g),
                 next_observations=torch.randn(seeds, size, obs_dim, generator=g),
                 terminations=torch.tensor([[0.0, 1.0, 0.0, 0.0, 1.0]] * seeds)[:, :size])


def _net(params: list[torch.Tensor], member: int, x: torch.Tensor) -> torch.Tensor:
    """A plain two-layer MLP, written out: relu(x W0 + b0) W1 + b1."""
    hidden = torch.relu(x @ params[0][member] + params[1][member][0])
    return hidden @ params[2][member] + params[3][member][0]


def _policy(actor: list[torch.Tensor], obs: torch.Tensor, noise: torch.Tensor):
    out = _net(actor, 0, obs)
    mean, log_std = out[:, :2], out[:, 2:].clamp(-20.0, 2.0)
    pre_tanh = mean + log_std.exp() * noise
    action = torch.tanh(pre_tanh)
    normal = torch.distributions.Normal(mean, log_std.exp())
    log_prob = (normal.log_prob(pre_tanh) - torch.log(1 - action.pow(2))).sum(-1)
    return action, log_prob


def _adam_first_step(param: torch.Tensor, grad: torch.Tensor, lr: float) -> torch.Tensor:
    # Adam's first step with bias correction: m_hat = g, v_hat = g^2.
    return param - lr * grad / (grad.abs() + 1e-8)


def test_one_update_equals_a_hand_computed_sac_step():
    config = SACConfig(hidden_sizes=(8,), batch_size=5, actor_lr=1e-3, critic_lr=2e-3, temperature_lr=5e-3,
                       discount=0.9, target_update_rate=0.1, initial_temperature=0.5)
    agent = SACAgent(observation_dim=3, action_dim=2, seeds=[7], config=config)
    batch = _batch()
    actor0 = [p.detach().clone() for p in agent.actor]
    critic0 = [p.detach().clone() for p in agent.critic]
    target0 = [p.clone() for p in agent.critic_target]
    log_alpha0 = agent.log_temperature.detach().clone()
    noise_stream = torch.Generator()
    noise_stream.set_state(agent.generator.get_state())

    sac_update(agent, batch)

    obs, actions, rewards, next_obs, done = (x[0] for x in batch)
    alpha = math.exp(float(log_alpha0))
    # Critic: y = r + gamma (1 - d) (min_i Q'_i(s', a') - alpha log pi(a'|s')).
    next_action, next_log_prob = _policy(actor0, next_obs, torch.randn((1, 5, 2), generator=noise_stream)[0])
    sa_next = torch.cat([next_obs, next_action], -1)
    next_q = torch.minimum(_net(target0, 0, sa_next), _net(target0, 1, sa_next))[:, 0]
    y = rewards + 0.9 * (1 - done) * (next_q - alpha * next_log_prob)
    critic = [p.clone().requires_grad_() for p in critic0]
    sa = torch.cat([obs, actions], -1)
    critic_loss = sum(0.5 * (_net(critic, c, sa)[:, 0] - y).pow(2).mean() for c in (0, 1))
    critic_grads = torch.autograd.grad(critic_loss, critic)
    critic1 = [_adam_first_step(p, g, 2e-3) for p, g in zip(critic0, critic_grads)]
    for got, want in zip(agent.critic, critic1):
        torch.testing.assert_close(got.detach(), want, rtol=1e-5, atol=1e-6)

    # Actor: mean [alpha log pi(a|s) - min_i Q_i(s, a)] with the updated critic, a ~ pi(s).
    actor = [p.clone().requires_grad_() for p in actor0]
    action, log_prob = _policy(actor, obs, torch.randn((1, 5, 2), generator=noise_stream)[0])
    sa_pi = torch.cat([obs, action], -1)
    q_pi = torch.minimum(_net(critic1, 0, sa_pi), _net(critic1, 1, sa_pi))[:, 0]
    actor_loss = (alpha * log_prob - q_pi).mean()
    actor_grads = torch.autograd.grad(actor_loss, actor)
    for got, p, g in zip(agent.actor, actor0, actor_grads):
        torch.testing.assert_close(got.detach(), _adam_first_step(p, g, 1e-3), rtol=1e-5, atol=1e-6)

    # Temperature: loss -log_alpha (log pi + target entropy), target entropy = -|A| = -2.
    alpha_grad = -(log_prob.detach() - 2.0).mean()
    torch.testing.assert_close(agent.log_temperature.detach(),
                               _adam_first_step(log_alpha0, alpha_grad.reshape(1), 5e-3), rtol=1e-5, atol=1e-6)

    # Targets: Polyak averaging with tau = 0.1.
    for got, old, new in zip(agent.critic_target, target0, critic1):
        torch.testing.assert_close(got, old + 0.1 * (new - old), rtol=1e-5, atol=1e-6)


def test_each_seed_starts_from_its_own_weights_whatever_runs_beside_it():
    alone = SACAgent(4, 1, seeds=[3], config=SACConfig(hidden_sizes=(16, 16)))
    together = SACAgent(4, 1, seeds=[1, 2, 3], config=SACConfig(hidden_sizes=(16, 16)))
    for a, t in zip(alone.actor, together.actor):
        assert torch.equal(a[0], t[2])
    for a, t in zip(alone.critic, together.critic):
        assert torch.equal(a[0:2], t[4:6])
    assert not torch.equal(together.actor[0][0], together.actor[0][1])


def test_seeds_train_independently():
    """A seed's update ignores the other seeds' data: changing seed 1's batch leaves seed 0 alone."""
    config = SACConfig(hidden_sizes=(16,))
    batch = _batch(seeds=2)
    results = []
    for scale in (1.0, 5.0):
        agent = SACAgent(3, 2, seeds=[0, 1], config=config)
        agent.generator.manual_seed(0)
        changed = batch._replace(rewards=torch.stack([batch.rewards[0], scale * batch.rewards[1]]))
        for _ in range(3):  # Adam's first step only sees gradient signs
            sac_update(agent, changed)
        results.append([p.detach().clone() for p in agent.critic])
    for first, second in zip(*results):
        torch.testing.assert_close(first[0:2], second[0:2], rtol=1e-5, atol=1e-6)
        assert not torch.allclose(first[2:4], second[2:4])


@pytest.mark.parametrize("hook", ["reward_correction", "sample_weights"])
def test_hooks_change_the_update(hook):
    batch = _batch()
    outputs = []
    for kwargs in ({}, {hook: torch.tensor([[3.0, 0.1, 2.0, 0.5, 1.0]])}):
        agent = SACAgent(3, 2, seeds=[0], config=SACConfig(hidden_sizes=(8,)))
        for _ in range(3):  # Adam's first step only sees gradient signs
            sac_update(agent, batch, **kwargs)
        outputs.append(agent.critic[0].detach().clone())
    assert not torch.allclose(*outputs)
