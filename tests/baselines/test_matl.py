"""MATL and its TRPO learner: the numerical pieces, the discriminator, the variants, the training
loop's target-step accounting, exact resume, and a learning test (slow)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from typer.testing import CliRunner

from baselines.checkpoint import STATE_FILE, latest_checkpoint
from baselines.matl import (BUILDERS, FALL_COST, Config, Discriminator, DiscriminatorConfig, Rollout,
                            robot_auxiliary_reward, simulator_auxiliary_reward, state_sequences, target_reward)
from baselines.method import MethodContext
from baselines.train import train
from baselines.trpo import TRPOAgent, TRPOConfig, conjugate_gradient, gae, gaussian_kl
from offdyn_bench.cli import app
from offdyn_bench.errors import OffdynError
from offdyn_bench.protocol.definition import ProtocolError

PENDULUM = "invertedpendulum-gravity-3.0"
SMALL = {"trpo.hidden_sizes": "[16, 16]", "discriminator.hidden_sizes": "[16]", "rollout_steps": "20",
         "trpo.value_iterations": "5"}


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Small batched networks: one thread is fastest, and on a shared 2-core machine two threads can
    be 50x slower (as ``train`` itself does, with its default ``threads=1``)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _run(algo: str, out, steps: int = 600, **overrides: str):
    return train(algo, PENDULUM, steps=steps, out=out, overrides=SMALL | overrides, eval_every=steps // 2,
                 eval_episodes=2, progress=False, seed=5, n_seeds=2)


def _state(run) -> dict[str, torch.Tensor]:
    return load_file(str(latest_checkpoint(run) / STATE_FILE))


# --- TRPO's numerical pieces --------------------------------------------------------------------


def test_gae_matches_a_hand_computation_with_a_terminal_and_a_time_limit_cut():
    rewards = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    values = torch.tensor([[0.5, 1.0, 1.5, 2.0]])
    next_values = torch.tensor([[1.0, 9.0, 2.0, 7.0]])  # 9.0: the cut episode's own last state
    terminations = torch.tensor([[0.0, 0.0, 0.0, 1.0]])
    ends = torch.tensor([[0.0, 1.0, 0.0, 1.0]])  # step 1 truncated (bootstraps), step 3 terminal
    gamma, lam = 0.9, 0.8
    d0, d1 = 1 + gamma * 1.0 - 0.5, 2 + gamma * 9.0 - 1.0
    d2, d3 = 3 + gamma * 2.0 - 1.5, 4 - 2.0
    expected = torch.tensor([[d0 + gamma * lam * d1, d1, d2 + gamma * lam * d3, d3]])
    advantages, returns = gae(rewards, values, next_values, terminations, ends, gamma, lam)
    assert torch.allclose(advantages, expected)
    assert torch.allclose(returns, expected + values)


def test_conjugate_gradient_solves_one_spd_system_per_seed():
    generator = torch.Generator().manual_seed(0)
    matrices = []
    for _ in range(3):
        a = torch.randn(6, 6, generator=generator, dtype=torch.float64)
        matrices.append(a @ a.T + 0.5 * torch.eye(6, dtype=torch.float64))
    stacked = torch.stack(matrices)
    b = torch.randn(3, 6, generator=generator, dtype=torch.float64)
    x = conjugate_gradient(lambda v: torch.einsum("sij,sj->si", stacked, v), b, iterations=12)
    assert torch.allclose(x, torch.linalg.solve(stacked, b), atol=1e-8)
    # Fewer iterations than the dimension give an approximation, not the solution: the test can fail.
    rough = conjugate_gradient(lambda v: torch.einsum("sij,sj->si", stacked, v), b, iterations=2)
    assert not torch.allclose(rough, torch.linalg.solve(stacked, b), atol=1e-3)


def _policy_batch(agent: TRPOAgent, n: int = 256):
    generator = torch.Generator().manual_seed(1)
    observations = torch.randn(agent.n_seeds, n, 3, generator=generator)
    with torch.no_grad():
        mean, log_std = agent.distribution(observations)
        actions = mean + log_std.exp() * torch.randn(mean.shape, generator=generator)
    advantages = torch.randn(agent.n_seeds, n, generator=generator) + actions[..., 0]  # favour larger a_0
    return observations, actions, advantages


@pytest.mark.parametrize("max_kl", [0.01, 0.001])
def test_a_trpo_step_improves_the_surrogate_within_the_kl_constraint(max_kl):
    agent = TRPOAgent(3, 2, seeds=(0, 1), config=TRPOConfig(max_kl=max_kl), stream=1)
    observations, actions, advantages = _policy_batch(agent)
    with torch.no_grad():
        mean_old, log_std_old = (t.clone() for t in agent.distribution(observations))
    metrics = agent.policy_step(observations, actions, advantages)
    with torch.no_grad():
        mean_new, log_std_new = agent.distribution(observations)
    kl = gaussian_kl(mean_old, log_std_old, mean_new, log_std_new).mean(dim=1)
    assert (kl <= max_kl * (1 + 1e-5)).all() and (kl > 0.2 * max_kl).all(), kl
    assert torch.allclose(kl, metrics["trpo/kl"])
    assert (metrics["trpo/surrogate_improvement"] > 0).all() and (metrics["trpo/step_fraction"] > 0).all()
    # The advantages favour a larger first action: the policy mean moved that way.
    assert (mean_new[..., 0].mean(dim=1) > mean_old[..., 0].mean(dim=1)).all()


def test_trpo_seeds_stay_independent():
    pair = TRPOAgent(3, 2, seeds=(0, 1), config=TRPOConfig(), stream=1)
    alone = TRPOAgent(3, 2, seeds=(1,), config=TRPOConfig(), stream=1)
    observations, actions, advantages = _policy_batch(pair)
    assert torch.equal(pair.mean_params[0][1:], alone.mean_params[0])
    pair.policy_step(observations, actions, advantages)
    alone.policy_step(observations[1:], actions[1:], advantages[1:])
    assert all(torch.allclose(a[1:], b, atol=1e-5) for a, b in zip(pair.policy_params, alone.policy_params))


# --- rollouts, sequences, the discriminator -----------------------------------------------------


def _rollout_with_a_cut() -> Rollout:
    """One seed, 1-d states 0, 1, 2 | 10, 11 (a time-limit cut after the third transition)."""
    rollout = Rollout(1, 5, 1, 1)
    for s, s_next in ((0, 1), (1, 2), (2, 3), (10, 11), (11, 12)):
        rollout.add(torch.tensor([[float(s)]]), torch.zeros(1, 1), torch.zeros(1), torch.tensor([[float(s_next)]]),
                    torch.zeros(1))
    return rollout


def test_episode_ends_are_found_at_cuts_terminals_and_the_rollouts_end():
    rollout = _rollout_with_a_cut()
    assert rollout.episode_ends().tolist() == [[0.0, 0.0, 1.0, 0.0, 1.0]]
    rollout.terminations[0, 0] = 1.0
    assert rollout.episode_ends().tolist() == [[1.0, 0.0, 1.0, 0.0, 1.0]]


def test_state_sequences_stay_inside_their_episode():
    rollout = _rollout_with_a_cut()
    pairs = state_sequences(rollout.observations, rollout.next_observations, rollout.episode_ends(), (0, 2))
    # (s_t, s_{t+2}); past the episode's end its last state (3, then 12) stands in.
    assert pairs[0].tolist() == [[0.0, 2.0], [1.0, 3.0], [2.0, 3.0], [10.0, 12.0], [11.0, 12.0]]
    single = state_sequences(rollout.observations, rollout.next_observations, rollout.episode_ends(), (0,))
    assert torch.equal(single, rollout.observations)


def test_the_discriminator_separates_two_state_distributions_and_rewards_each_agent_for_looking_like_the_other():
    generator = torch.Generator().manual_seed(0)
    simulator_states = 2.0 + 0.1 * torch.randn(2, 200, 3, generator=generator)
    robot_states = -2.0 + 0.1 * torch.randn(2, 200, 3, generator=generator)
    discriminator = Discriminator(3, seeds=(0, 1), config=DiscriminatorConfig(steps=200))
    metrics = discriminator.update(simulator_states, robot_states)
    assert (metrics["discriminator/accuracy"] == 1.0).all()
    log_d_sim = discriminator.log_simulator_probability(simulator_states)  # D predicts "simulator"
    log_d_robot = discriminator.log_simulator_probability(robot_states)
    assert (log_d_sim > np.log(0.9)).all() and (log_d_robot < np.log(0.1)).all()
    sim_logits = discriminator.logits(simulator_states).detach()
    robot_logits = discriminator.logits(robot_states).detach()
    # The paper's rewards: rho_S = -log D, rho_R = +log D.
    assert torch.allclose(simulator_auxiliary_reward(sim_logits), -log_d_sim)
    assert torch.allclose(robot_auxiliary_reward(robot_logits), log_d_robot)
    # Each agent is rewarded for looking like the other system: the robot for simulator-like states,
    # the simulator for robot-like ones (in both robot forms).
    for form in ("paper", "nonnegative"):
        assert robot_auxiliary_reward(sim_logits, form).min() > robot_auxiliary_reward(robot_logits, form).max()
    assert simulator_auxiliary_reward(robot_logits).min() > simulator_auxiliary_reward(sim_logits).max()
    assert (robot_auxiliary_reward(robot_logits) <= 0).all() and (simulator_auxiliary_reward(sim_logits) >= 0).all()
    assert (robot_auxiliary_reward(robot_logits, "nonnegative") >= 0).all()


# --- target reward modes ------------------------------------------------------------------------


def test_target_reward_modes_on_the_pendulum():
    rewards = torch.tensor([1.0, 1.0, 0.0])
    next_obs = torch.tensor([[0.01, 0.02, 0, 0], [0.01, 0.1, 0, 0], [0.3, 0.5, 0, 0]])
    fell = torch.tensor([0.0, 0.0, 1.0])
    assert torch.equal(target_reward("full", "InvertedPendulum", rewards, next_obs, fell), rewards)
    assert target_reward("none", "InvertedPendulum", rewards, next_obs, fell).tolist() == [0.0, 0.0, 0.0]
    assert target_reward("uninformative", "InvertedPendulum", rewards, next_obs, fell).tolist() == [0.0, 0.0,
                                                                                                    -FALL_COST]
    assert target_reward("sparse", "InvertedPendulum", rewards, next_obs, fell).tolist() == [1.0, 0.0, 0.0]


@pytest.mark.parametrize("task, mode, message", [
    ("halfcheetah-gravity-0.5", "uninformative", "HalfCheetah never falls"),
    ("hopper-gravity-0.5", "sparse", "Hopper tasks have none; sparse is defined for InvertedPendulum"),
])
def test_a_reward_mode_a_task_does_not_define_is_refused_before_anything_is_written(tmp_path, task, mode, message):
    with pytest.raises(OffdynError, match=message):
        train("matl", task, steps=100, out=tmp_path / "run", overrides={"target_reward": mode}, progress=False)
    assert not (tmp_path / "run").exists()


def test_the_target_reward_mode_is_recorded_and_the_robot_learns_from_it(tmp_path):
    result = _run("independent", tmp_path / "run", steps=400, target_reward="uninformative")
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["config"]["target_reward"] == "uninformative" == result["config"]["target_reward"]
    # The robot's rollout stored the uninformative reward: 0, or -1 where the pole fell.
    stored = _state(tmp_path / "run")
    assert set(stored["robot_rollout.rewards"].unique().tolist()) <= {0.0, -FALL_COST}


# --- the variants in the training loop ----------------------------------------------------------


def test_matl_with_zero_alignment_weight_is_exactly_two_independent_trpo_learners(tmp_path):
    matl = _run("matl", tmp_path / "matl", alignment_weight="0.0", target_reward="uninformative")
    independent = _run("independent", tmp_path / "independent", target_reward="uninformative")
    direct = _run("direct-transfer", tmp_path / "direct", target_reward="uninformative")
    state, robot_alone, simulator_alone = (_state(tmp_path / d) for d in ("matl", "independent", "direct"))
    robot_keys = [k for k in robot_alone if k.startswith("robot")]
    simulator_keys = [k for k in simulator_alone if k.startswith("simulator")]
    assert robot_keys and simulator_keys
    assert all(torch.equal(state[k], robot_alone[k]) for k in robot_keys)
    assert all(torch.equal(state[k], simulator_alone[k]) for k in simulator_keys)
    assert matl["returns"] == independent["returns"]
    # The control: with the auxiliary reward on, the robot learns something else...
    aligned = _run("matl", tmp_path / "aligned", alignment_weight="0.1", target_reward="uninformative")
    assert not torch.equal(_state(tmp_path / "aligned")["robot.mean.0"], robot_alone["robot.mean.0"])
    assert not torch.equal(_state(tmp_path / "aligned")["simulator.mean.0"], simulator_alone["simulator.mean.0"])
    assert aligned["returns"] != independent["returns"]
    # ... and MATL-U's simulator agent, which never gets an auxiliary reward, is direct-transfer's.
    _run("matl-u", tmp_path / "unilateral", alignment_weight="0.1", target_reward="uninformative")
    unilateral = _state(tmp_path / "unilateral")
    assert all(torch.equal(unilateral[k], simulator_alone[k]) for k in simulator_keys)
    assert not torch.equal(unilateral["robot.mean.0"], robot_alone["robot.mean.0"])


def test_the_robot_takes_one_target_step_per_ten_and_direct_transfer_none(tmp_path):
    matl = _run("matl", tmp_path / "matl", steps=400)
    direct = _run("direct-transfer", tmp_path / "direct", steps=400)
    assert matl["track"] == "online-target" and matl["target_steps_per_seed"] == 40
    assert direct["target_steps_per_seed"] == 0
    # Two robot rollouts of 20 steps: the robot agent updated twice, the simulator 20 times.
    state = _state(tmp_path / "matl")
    assert int(state["matl.simulator_rollouts_done"]) == 20 and int(state["robot_rollout.size"]) == 0


def test_matl_is_refused_on_the_offline_track_and_with_a_faster_target_ratio(tmp_path):
    with pytest.raises(ProtocolError, match="matl belongs on the 'online-target' track"):
        train("matl", PENDULUM, steps=100, out=tmp_path / "a", track="offline-target", progress=False)
    with pytest.raises(ProtocolError, match="matl would take 20 target steps per seed; the online-target track "
                                            "allows 10"):
        train("matl", PENDULUM, steps=100, out=tmp_path / "b", overrides={"target_step_every": "5"},
              progress=False)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_killed_matl_run_resumes_to_the_same_result(tmp_path):
    kwargs = dict(steps=500, overrides=SMALL, eval_every=100, eval_episodes=2, checkpoint_every=130,
                  progress=False, seed=3, n_seeds=2)
    whole = train("matl", PENDULUM, out=tmp_path / "whole", **kwargs)
    # Killed at step 300; the checkpoint at 260 holds a part-filled robot rollout (26 target steps,
    # 20 of them used by the joint update at step 200).
    assert train("matl", PENDULUM, out=tmp_path / "cut", stop_after=300, **kwargs) is None
    assert int(_state(tmp_path / "cut")["robot_rollout.size"]) == 6
    resumed = train("matl", PENDULUM, out=tmp_path / "cut", **kwargs)
    assert resumed["returns"] == whole["returns"]
    curves = [[json.loads(x) for x in (tmp_path / d / "metrics.jsonl").read_text().splitlines()]
              for d in ("whole", "cut")]
    assert curves[0] and [{k: c[k] for k in ("target_return", "train")} for c in curves[0]] == \
        [{k: c[k] for k in ("target_return", "train")} for c in curves[1]]
    a, b = _state(tmp_path / "whole"), _state(tmp_path / "cut")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_a_budget_below_one_outer_iteration_is_warned_about():
    from baselines.train import budget_warnings

    assert budget_warnings("matl", Config(), 10_000) == []
    (message,) = budget_warnings("independent", Config(variant="independent"), 9_999)
    assert message.startswith("--steps 9999 is below one outer iteration (rollout_steps x target_step_every = "
                              "10000 steps): this independent run's robot agent makes no update")
    assert budget_warnings("direct-transfer", Config(variant="direct-transfer"), 1_000) == []
    assert "is below rollout_steps=1000" in budget_warnings("direct-transfer", Config(variant="direct-transfer"),
                                                            999)[0]


def test_the_variant_is_fixed_by_the_algorithms_name(tmp_path):
    with pytest.raises(OffdynError, match="variant='independent': matl is fixed by the algorithm's name"):
        train("matl", PENDULUM, steps=100, out=tmp_path / "run", overrides={"variant": "independent"},
              progress=False)
    assert not (tmp_path / "run").exists()


def test_fine_tuning_and_matl_f_start_from_a_finished_simulator_run(tmp_path):
    with pytest.raises(OffdynError, match='init_run="": fine-tuning starts from a fully trained simulator policy'):
        _run("fine-tuning", tmp_path / "no-init")
    _run("direct-transfer", tmp_path / "direct")
    _run("independent", tmp_path / "independent")
    with pytest.raises(OffdynError, match="is a 'independent' run, which has no simulator policy"):
        _run("matl-f", tmp_path / "wrong", init_run=str(tmp_path / "independent"))
    with pytest.raises(OffdynError, match=r"trained seeds \[5, 6\] and this run trains \[0\]"):
        train("fine-tuning", PENDULUM, steps=100, out=tmp_path / "seeds", progress=False,
              overrides=SMALL | {"init_run": str(tmp_path / "direct")})
    with pytest.raises(OffdynError, match="trained in the source of invertedpendulum-gravity-3.0, which differs"):
        train("fine-tuning", "hopper-gravity-0.5", steps=100, out=tmp_path / "task", progress=False, seed=5,
              n_seeds=2, overrides=SMALL | {"init_run": str(tmp_path / "direct")})
    assert not any((tmp_path / d).exists() for d in ("no-init", "wrong", "seeds", "task"))

    simulator = _state(tmp_path / "direct")
    context = MethodContext(observation_dim=4, action_dim=1, seeds=(5, 6), task=PENDULUM)
    for variant in ("fine-tuning", "matl-f"):
        config = Config(variant=variant, init_run=str(tmp_path / "direct"))
        config.trpo.hidden_sizes = (16, 16)
        method = BUILDERS[variant](config, context)
        assert torch.equal(method.robot.mean_params[0].detach(), simulator["simulator.mean.0"])
        assert torch.equal(method.robot.log_std.detach(), simulator["simulator.log_std"])
    result = _run("matl-f", tmp_path / "matl-f", init_run=str(tmp_path / "direct"))
    assert np.isfinite(result["mean_return"]) and result["config"]["init_run"] == str(tmp_path / "direct")


def test_cli_errors_are_one_line(tmp_path):
    runner = CliRunner()
    done = runner.invoke(app, ["train", "matl", "--task", "halfcheetah-gravity-0.5", "--steps", "100", "--out",
                               str(tmp_path / "run"), "--set", "target_reward=uninformative", "--no-progress"])
    assert done.exit_code == 2 and done.output.startswith("error: target_reward='uninformative'")
    assert len(done.output.strip().splitlines()) == 1
    done = runner.invoke(app, ["train", "matl", "--task", PENDULUM, "--steps", "100", "--out", str(tmp_path / "run"),
                               "--set", "target_reward=dense", "--no-progress"])
    assert done.exit_code == 2 and "target_reward=\"dense\": expected one of 'full', 'sparse'" in done.output
    assert not (tmp_path / "run").exists()


# --- learning (slow) ----------------------------------------------------------------------------
#
# invertedpendulum-gravity-3.0 (the pole falls three times faster in the target), the robot's reward
# uninformative (-1 when the pole falls), 50,000 training steps (5,000 robot steps per seed), rollouts
# of 200 steps, seeds 0-2 trained together, the learning curve every 10,000 steps over 3 episodes.
# About 5 minutes on a loaded 2-core CPU.

LEARNING = {"rollout_steps": "200", "target_reward": "uninformative"}


@pytest.fixture(scope="module")
def uninformative_curves(tmp_path_factory):
    curves = {}
    for name, algo, overrides in (("independent", "independent", {}), ("matl", "matl", {})):
        out = tmp_path_factory.mktemp("learning") / name
        train(algo, "invertedpendulum-gravity-3.0", steps=50_000, out=out, overrides=LEARNING | overrides,
              eval_every=10_000, eval_episodes=3, progress=False, seed=0, n_seeds=3)
        lines = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
        curves[name] = np.array([line["target_return"] for line in lines])  # [evaluations, seeds]
    return curves


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="not reproduced (measured: independent's mean curve 55, 84, 102, 85, 419; "
                                       "MATL's robot falls within 2-6 steps throughout): the paper's rho_R = log D "
                                       "<= 0 pays the robot to end its episodes early")
def test_the_robot_agent_learns_faster_with_the_auxiliary_reward_than_independent(uninformative_curves):
    # "Faster": a larger area under the learning curve, over all seeds.
    assert uninformative_curves["matl"].mean() > uninformative_curves["independent"].mean()


@pytest.mark.slow
def test_with_the_papers_robot_reward_and_a_fall_cost_only_the_robot_learns_to_fall(uninformative_curves):
    # What the run shows instead: the per-step cost log D outweighs the one-off fall cost, so the
    # robot agent ends its episodes at once, while independent TRPO learns to balance for longer.
    assert uninformative_curves["matl"].max() < 10
    assert uninformative_curves["independent"][-1].mean() > 50


def test_deployed_policies_read_from_a_checkpoint_act_like_the_trained_method(tmp_path):
    from baselines.matl import deployed_policies
    from offdyn_bench.tasks import get_task

    for algo in ("matl", "direct-transfer"):
        _run(algo, tmp_path / algo, steps=400)
        state = _state(tmp_path / algo)
        config = Config(variant=algo)
        config.trpo.hidden_sizes = (16, 16)
        config.discriminator.hidden_sizes = (16,)
        method = BUILDERS[algo](config, MethodContext(observation_dim=4, action_dim=1, seeds=(5, 6), task=PENDULUM))
        method.load_state_dict(state)
        space = get_task(PENDULUM).make("target").action_space
        policies = deployed_policies(state, space.low, space.high)
        observations = torch.randn(2, 4, generator=torch.Generator().manual_seed(0)) * 0.3
        deployed = method.deploy(observations).numpy().astype(np.float64)
        expected = space.low + (deployed + 1.0) * 0.5 * (space.high - space.low)
        assert len(policies) == 2
        for member in range(2):
            assert np.allclose(policies[member](observations[member].numpy()), expected[member], atol=1e-6)
        assert not np.allclose(policies[0](observations[0].numpy()), policies[1](observations[0].numpy()))
    with pytest.raises(OffdynError, match="holds no MATL agent"):
        deployed_policies({"actor.0": torch.zeros(1)}, space.low, space.high)
