"""Sanity relations between the methods: DARC with no correction is SAC, DAP with tied actions is
DARC, H2O with its penalty and weights off is SAC on the mixed buffer."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from baselines import dap, darc, h2o
from baselines.buffers import concat_batches
from baselines.checkpoint import STATE_FILE, latest_checkpoint
from baselines.classifiers import ClassifierConfig
from baselines.method import MethodContext
from baselines.sac import Batch, SACAgent, SACConfig, sac_update
from baselines.train import train

PENDULUM = "invertedpendulum-kinematic-slider-hard"
TINY = {"sac.hidden_sizes": "[32, 32]", "sac.batch_size": "32", "random_steps": "50"}
SAC_SETTINGS = {"sac.reward_scale": "1.0", "sac.target_entropy_per_action_dim": "-1.0"}
"""Published DARC's reward scale and target entropy set back to SAC's."""


def _random_batch(seeds: int, size: int, obs_dim: int, action_dim: int, seed: int) -> Batch:
    g = torch.Generator().manual_seed(seed)
    return Batch(torch.randn(seeds, size, obs_dim, generator=g), torch.rand(seeds, size, action_dim, generator=g) * 2 - 1,
                 torch.randn(seeds, size, generator=g), torch.randn(seeds, size, obs_dim, generator=g),
                 (torch.rand(seeds, size, generator=g) < 0.1).float())


def _dataset(n: int = 200, obs_dim: int = 4, action_dim: int = 1) -> Batch:
    one = _random_batch(1, n, obs_dim, action_dim, seed=99)
    return Batch(*(x[0] for x in one))


def _final_tensors(run_dir) -> dict[str, torch.Tensor]:
    return load_file(str(latest_checkpoint(run_dir) / STATE_FILE))


def test_darc_with_zero_correction_is_exactly_sac(tmp_path, pendulum_dataset):
    common = dict(task=PENDULUM, steps=160, eval_every=80, eval_episodes=2, progress=False)
    sac = train("sac-source", out=tmp_path / "sac", overrides=TINY, **common)
    darc_run = train("darc", out=tmp_path / "darc", dataset=str(pendulum_dataset),
                     overrides=TINY | SAC_SETTINGS | {"reward_correction_scale": "0", "warmup_steps": "0"}, **common)
    sac_state, darc_state = _final_tensors(tmp_path / "sac"), _final_tensors(tmp_path / "darc")
    for name in [k for k in sac_state if k.startswith(("actor.", "critic."))]:
        assert torch.equal(sac_state[name], darc_state[name]), name
    assert sac["returns"] == darc_run["returns"]
    # ...and the correction does act when switched on (the comparison above can fail).
    corrected = train("darc", out=tmp_path / "darc-on", dataset=str(pendulum_dataset),
                      overrides=TINY | SAC_SETTINGS | {"warmup_steps": "0"}, **common)
    on_state = _final_tensors(tmp_path / "darc-on")
    assert corrected is not None and not torch.equal(on_state["critic.0"], sac_state["critic.0"])


def test_dap_with_tied_actions_gets_the_darc_reward():
    context = MethodContext(observation_dim=4, action_dim=2, seeds=(0, 1), target_data=_dataset(action_dim=2))
    dap_method = dap.DAP(dap.Config(warmup_steps=0, regularization_weight=5.0, regularized_actions="sampled"), context)
    # DAP keeps the classifiers of the H2O variant of DARC (256 wide, clipped logits).
    darc_variant = darc.h2o_variant_config()
    darc_variant.warmup_steps = 0
    darc_method = darc.DARC(darc_variant, context)
    source = _random_batch(2, 64, 4, 2, seed=1)
    for _ in range(20):  # train both classifiers identically (same streams, same data)
        target = _random_batch(2, 64, 4, 2, seed=2)
        dap_method.classifiers.update(source, target)
        darc_method.classifiers.update(source, target)
    tied = source._replace(actions=torch.cat([source.actions, source.actions], dim=-1))
    torch.testing.assert_close(dap_method.reward_correction(tied, step=0), darc_method.reward_correction(source, 0))
    assert darc_method.reward_correction(source, 0).abs().mean() > 1e-3
    # Untied actions pay lambda * mean squared difference on top.
    untied = source._replace(actions=torch.cat([source.actions, -source.actions], dim=-1))
    assert (dap_method.reward_correction(untied, 0) < dap_method.reward_correction(tied, 0) - 1e-3).all() or \
        torch.allclose(source.actions, torch.zeros_like(source.actions))


@pytest.mark.slow
def test_dap_with_a_large_lambda_makes_both_actions_coincide():
    """Trained on the same fixed buffer, lambda = 100 pulls a_t onto a_s; lambda = 0 lets them drift."""
    transitions = _random_batch(1, 2000, 4, 2, seed=4)
    states = torch.randn(1, 256, 4, generator=torch.Generator().manual_seed(0))
    gaps = {}
    for weight in (0.0, 100.0):
        small = SACConfig(hidden_sizes=(32, 32), batch_size=64, actor_lr=1e-3, critic_lr=1e-3, temperature_lr=1e-3)
        method = dap.DAP(dap.Config(sac=small, random_steps=0, warmup_steps=0, regularization_weight=weight),
                         MethodContext(4, 1, (0,), target_data=_dataset()))
        for i in range(transitions.rewards.shape[1]):
            method.record(*(x[:, i] for x in transitions))
        for step in range(800):
            method.train_step(step)
        source_action, target_action = method.split(method.agent.mean_actions(states))
        gaps[weight] = float((source_action - target_action).abs().mean())
    assert gaps[100.0] < 0.05 and gaps[100.0] < gaps[0.0] / 3, gaps


def test_h2o_without_penalty_and_weights_is_sac_on_the_mixed_buffer():
    context = MethodContext(observation_dim=4, action_dim=1, seeds=(0, 1), target_data=_dataset())
    small = SACConfig(hidden_sizes=(32,), batch_size=32)
    real, sim = _random_batch(2, 16, 4, 1, seed=5), _random_batch(2, 16, 4, 1, seed=6)

    def run(config: h2o.Config) -> list[torch.Tensor]:
        method = h2o.H2O(config, context)
        for _ in range(3):
            method.agent_update(real, sim)
        return [p.detach() for p in method.agent.actor + method.agent.critic]

    switched_off = run(h2o.Config(sac=small, min_q_weight=0.0, dynamics_ratio_clip=(1.0, 1.0)))
    agent = SACAgent(4, 1, (0, 1), small)
    for _ in range(3):
        # H2O's per-critic mean_real + mean_sim, with equal halves: twice the mixed batch's mean.
        sac_update(agent, concat_batches(real, sim), td_loss_weight=2.0)
    for got, want in zip(switched_off, agent.actor + agent.critic):
        assert torch.equal(got, want)
    default = run(h2o.Config(sac=small))
    assert not all(torch.equal(a, b) for a, b in zip(default, switched_off))


def test_h2o_weights_and_gap_are_in_their_clipping_ranges():
    context = MethodContext(observation_dim=4, action_dim=1, seeds=(0,), target_data=_dataset())
    method = h2o.H2O(h2o.Config(), context)
    sim = _random_batch(1, 64, 4, 1, seed=3)
    ratio, gap = method.dynamics_ratio(sim), method.dynamics_gap(sim)
    assert ratio.shape == gap.shape == (1, 64)
    assert ((ratio >= 1e-5) & (ratio <= 1.0)).all() and ((gap >= 1e-6) & (gap <= 10.0)).all()


def test_classifiers_learn_to_tell_the_domains_apart():
    """A shift in s' given (s, a) is what the (s, a, s') classifier should pick up: dr < 0 on source
    transitions, > 0 on target ones."""
    from baselines.classifiers import DomainClassifiers

    classifiers = DomainClassifiers(2, 1, (0,), ClassifierConfig(input_noise_std=0.05))
    g = torch.Generator().manual_seed(0)

    def transitions(shift: float) -> Batch:
        s, a = torch.randn(1, 128, 2, generator=g), torch.rand(1, 128, 1, generator=g) * 2 - 1
        return Batch(s, a, torch.zeros(1, 128), s + a + shift, torch.zeros(1, 128))

    for _ in range(300):
        classifiers.update(transitions(0.0), transitions(1.0))
    source, target = transitions(0.0), transitions(1.0)
    assert classifiers.log_ratio(*source[:2], source.next_observations).mean() < -1.0
    assert classifiers.log_ratio(*target[:2], target.next_observations).mean() > 1.0


def test_dap_u_resamples_actions_around_themselves_with_the_uncertainty():
    context = MethodContext(observation_dim=4, action_dim=1, seeds=(0,), target_data=_dataset())
    method = dap.DAP(dap.dap_u_config(), context)
    obs = torch.randn(1, 512, 4)
    actions = torch.zeros(1, 512, 2)
    u = method.uncertainty(obs, actions[..., :1])
    assert (u > 0).all()  # randomly initialised members disagree
    robust = method.robust_actions(obs, actions)
    spread = robust[..., 0].std() / (0.1 * u.mean())
    assert 0.7 < float(spread) < 1.3
    method.config.uncertainty_scale = 0.0
    assert torch.equal(method.robust_actions(obs, actions), actions)


@pytest.mark.parametrize("algo", ["dap", "dap-u"])
def test_dap_deploys_the_target_action(algo):
    from baselines.algorithms import get_algorithm

    context = MethodContext(observation_dim=4, action_dim=1, seeds=(0,), target_data=_dataset())
    method = get_algorithm(algo).build(get_algorithm(algo).default_config(), context)
    obs = torch.randn(1, 4)
    joint = method.agent.mean_actions(obs[:, None])[:, 0]
    assert torch.equal(method.deploy(obs), joint[:, 1:])
    env_action, stored = method.explore(obs, step=10**9)
    assert env_action.shape == (1, 1) and stored.shape == (1, 2) and torch.equal(env_action, stored[:, :1])
    assert np.isfinite(stored.numpy()).all()


@pytest.mark.parametrize("algo", ["sac-source", "darc", "h2o"])
def test_sac_family_explores_uniformly_then_with_the_policy_and_records_into_its_buffer(algo):
    from baselines.algorithms import get_algorithm

    context = MethodContext(observation_dim=4, action_dim=2, seeds=(0, 1), target_data=_dataset(action_dim=2))
    method = get_algorithm(algo).build(get_algorithm(algo).default_config(), context)
    obs = torch.randn(2, 4)
    early, stored = method.explore(obs, step=0)
    assert early is stored and early.shape == (2, 2) and bool((early.abs() <= 1).all())
    late, _ = method.explore(obs, step=method.config.random_steps)
    # After the uniform phase the action is a policy sample around the deterministic action.
    assert late.shape == (2, 2) and not torch.equal(late, early)
    assert torch.equal(method.deploy(obs), method.agent.mean_actions(obs[:, None])[:, 0])
    assert method.buffer.size == 0
    method.record(obs, early, torch.ones(2), obs + 1, torch.zeros(2))
    assert method.buffer.size == 1
    stored_transition = method.buffer.sample(1)
    assert torch.equal(stored_transition.observations[:, 0], obs)
    assert torch.equal(stored_transition.next_observations[:, 0], obs + 1)


@pytest.mark.parametrize("algo, name", [("cql", "CQL"), ("dara", "DARA")])
def test_offline_methods_refuse_to_explore_or_record_naming_themselves(algo, name):
    from baselines.algorithms import get_algorithm

    context = MethodContext(observation_dim=4, action_dim=2, seeds=(0,), target_data=_dataset(action_dim=2),
                            source_data=_dataset(action_dim=2))
    method = get_algorithm(algo).build(get_algorithm(algo).default_config(), context)
    obs = torch.randn(1, 4)
    assert torch.equal(method.deploy(obs), method.agent.mean_actions(obs[:, None])[:, 0])
    transition = (obs, torch.zeros(1, 2), torch.ones(1), obs, torch.zeros(1))
    for call in (lambda: method.explore(obs, 0), lambda: method.record(*transition),
                 lambda: method.record_target(*transition)):
        with pytest.raises(RuntimeError, match=f"^{name} is offline: it takes no environment steps$"):
            call()
