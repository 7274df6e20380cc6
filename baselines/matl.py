"""MATL: Mutual Alignment Transfer Learning (Wulfmeier, Posner and Abbeel, CoRL 2017), on the
protocol's online-target track, with the paper's reference points.

Two TRPO agents (:mod:`baselines.trpo`) train side by side: a *simulator* agent ``pi_theta`` in the
source and a *robot* agent ``pi_phi`` in the target. A discriminator ``D`` sees subsampled state
sequences ``zeta_t = (s_t, s_{t+k}, ..., s_{t+nk})`` and is trained (Eq. 2) to maximise
``E_sim[log D] + E_robot[log(1 - D)]``: ``D(zeta)`` is its probability that ``zeta`` came from the
simulator. Each agent is rewarded for looking like the other system (Eqs. 3-5, the confusion form)::

    simulator: r_S + lambda * rho_S,  rho_S = -log D(zeta)   (high where the simulator looks like the robot)
    robot:     r_R + lambda * rho_R,  rho_R = +log D(zeta)   (high where the robot looks like the simulator)

Algorithm 1, per outer iteration: a rollout of each agent, a discriminator update, TRPO updates of
both with the auxiliary rewards, then M simulator-only rollouts and updates without them. Here the
protocol fixes the ratio: the training loop steps the source every step and the target once per
``target_step_every`` = 10 steps (counted and enforced by :mod:`offdyn_bench.protocol.training`).
With the same rollout length T on both sides, one outer iteration is T robot steps and 10 T
simulator steps, so M = 9. The simulator's M plain rollouts come first in each iteration and its
aligned rollout last, so that rollout ends on the same training step as the robot's and both feed
the joint update (the paper's order with the inner loop rotated by one: the same updates, except
that the simulator makes its first M plain updates before the first joint one).

Variants (one registry entry each, ``offdyn-bench train <name>``):

=================  ==============================================================================
``matl``           both auxiliary rewards
``matl-u``         the robot's auxiliary reward only (unilateral alignment)
``matl-f``         MATL with both policies starting from a fully trained simulator policy
                   (``init_run``: a finished ``direct-transfer`` or MATL run of the same source)
``independent``    the robot agent alone, target reward only (no simulator)
``direct-transfer``the simulator agent alone, deployed in the target (no target steps)
``fine-tuning``    the robot agent alone, starting from a fully trained simulator policy
=================  ==============================================================================

Robot reward modes (``target_reward``; the simulator always gets the full reward), the paper's
Sections 4.2-4.4. The mode is a config field, so it is recorded in ``config.json`` and
``result.json``; evaluation always scores the environment's full reward (the task itself):

* ``full``: the environment's reward;
* ``sparse``: 1 on steps that end near the task's goal, else 0; defined where a task has a goal
  state (:data:`SPARSE_GOALS`; InvertedPendulum: pole within 0.05 rad of upright and cart within
  0.05 m of the rail's centre);
* ``uninformative``: only a cost of :data:`FALL_COST` on the step where the robot falls (its
  episode terminates), else 0; defined for the robots whose episodes end with a fall
  (:data:`ROBOTS_THAT_FALL`; InvertedPendulum: the pole falls). HalfCheetah never falls, so it has
  no uninformative mode;
* ``none``: zero: the robot learns from the auxiliary reward alone.

State sequences, as in the paper: single states (n = 0) for the simple tasks (InvertedPendulum),
state pairs ``(s_t, s_{t+4})`` (n = 1, k = 4) for locomotion (every other robot). Where ``t + jk``
runs past the end of the episode (or of the rollout), the episode's last state stands in.

Chosen where the paper is silent (its supplementary settings are not available): lambda = 0.1 (the
value of most of its experiments); rollout length T = 1000 steps per seed; a discriminator with two
hidden layers of 64 ReLU units, trained by 10 full-batch Adam steps (lr 1e-3) per outer iteration on
the two aligned rollouts; the auxiliary reward of step t uses ``zeta_t``, which starts at ``s_t`` (the
paper's ``rho(s_t)``). With ``alignment_weight=0`` MATL is exactly ``independent`` plus
``direct-transfer`` side by side (a test checks this).

Two properties of the paper's rewards matter in tasks whose episodes end on a fall: ``rho_R = log D
<= 0`` on every step, so it is also a per-step cost that the robot avoids by falling early (on
InvertedPendulum with the uninformative reward the robot agent learns exactly that; see README), and
``rho_S >= 0`` is a survival bonus. The extra ``robot_reward_form="nonnegative"`` rewards the robot
with ``-log(1 - D) >= 0`` instead: the same preference for simulator-like states (both increase with
D), without the incentive to end the episode (GAIL's reward form). ``paper`` is the default.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F

from baselines.limits import POSITIVE, Limit, integer, layer_sizes, number, one_of, optional
from baselines.method import MethodContext
from baselines.networks import Params, init_mlp, mlp
from baselines.sac import Metrics, seed_generator
from baselines.trpo import TRPOAgent, TRPOConfig, gae, on_device, tanh_mlp
from offdyn_bench.errors import OffdynError

VARIANTS: tuple[str, ...] = ("matl", "matl-u", "matl-f", "independent", "direct-transfer", "fine-tuning")
ALIGNED_VARIANTS = ("matl", "matl-u", "matl-f")
"""Variants with a discriminator and the robot's auxiliary reward."""
PRETRAINED_VARIANTS = ("matl-f", "fine-tuning")
"""Variants that start from a fully trained simulator policy (``init_run``)."""
SIMULATOR_RUNS = ("direct-transfer", "matl", "matl-u", "matl-f")
"""Algorithms whose runs hold a trained simulator agent (what ``init_run`` may name)."""

TARGET_REWARDS: Mapping[str, str] = MappingProxyType({
    "full": "the environment's reward",
    "sparse": "1 on steps that end near the task's goal, else 0",
    "uninformative": "only a cost for falling (the step whose episode terminates), else 0",
    "none": "no environment reward: the auxiliary reward alone",
})
FALL_COST = 1.0
"""The robot's reward on the step it falls, in the ``uninformative`` mode, is ``-FALL_COST``."""
ROBOTS_THAT_FALL = ("Hopper", "Walker2d", "Ant", "InvertedPendulum", "WheelLegged")
"""Robots whose episodes terminate when they fall (HalfCheetah's never terminate)."""


@dataclasses.dataclass(frozen=True)
class SparseGoal:
    description: str
    reached: Callable[[torch.Tensor], torch.Tensor]
    """Observations ``[..., d]`` -> 1.0 where the goal is reached, else 0.0."""


SPARSE_GOALS: Mapping[str, SparseGoal] = MappingProxyType({
    # Observation: cart position, pole angle, cart velocity, pole angular velocity.
    "InvertedPendulum": SparseGoal("pole within 0.05 rad of upright and cart within 0.05 m of the centre",
                                   lambda obs: ((obs[..., 1].abs() < 0.05) & (obs[..., 0].abs() < 0.05)).float()),
})
SINGLE_STATE_ROBOTS = ("InvertedPendulum",)
"""The simple tasks, where the paper's discriminator sees single states; state pairs elsewhere."""


@dataclasses.dataclass
class DiscriminatorConfig:
    hidden_sizes: tuple[int, ...] = (64, 64)
    lr: float = 1e-3
    steps: int = 10
    """Full-batch Adam steps per outer iteration."""

    LIMITS: ClassVar[dict[str, Limit]] = {"hidden_sizes": layer_sizes(allow_empty=True), "lr": POSITIVE,
                                          "steps": integer(1)}


def _path_or_empty() -> Limit:
    return Limit(lambda v: isinstance(v, str), 'a run folder path, or "" for none')


@dataclasses.dataclass
class Config:
    trpo: TRPOConfig = dataclasses.field(default_factory=TRPOConfig)
    discriminator: DiscriminatorConfig = dataclasses.field(default_factory=DiscriminatorConfig)
    variant: str = "matl"
    """Fixed by the algorithm's name (``matl``, ``matl-u``, ...)."""
    alignment_weight: float = 0.1
    """lambda, the weight of the auxiliary rewards (0.1 in most of the paper's experiments)."""
    rollout_steps: int = 1000
    """T: steps per seed of each rollout (one TRPO batch), the same for both agents."""
    target_step_every: int = 10
    """One target step per this many source steps (the online-target track's ratio); M = this - 1."""
    robot_reward_form: str = "paper"
    """``paper``: rho_R = log D (Eq. 5); ``nonnegative``: -log(1 - D), an extra: see the module docstring."""
    target_reward: str = "full"
    """The robot's reward: full, sparse, uninformative or none (see the module docstring)."""
    sequence_stride: int = 4
    """k: steps between the states of a discriminator sequence."""
    sequence_extra_states: int | None = None
    """n: states after s_t in a sequence; None: 0 for the simple tasks, 1 for locomotion (the paper's)."""
    init_run: str = ""
    """matl-f and fine-tuning: the run folder of a finished direct-transfer or MATL run of the same
    source whose simulator policy (and value function) both agents start from."""

    LIMITS: ClassVar[dict[str, Limit]] = {
        "variant": one_of(*VARIANTS), "alignment_weight": number(0.0), "rollout_steps": integer(1),
        "robot_reward_form": one_of("paper", "nonnegative"),
        "target_step_every": integer(1), "target_reward": one_of(*TARGET_REWARDS), "sequence_stride": integer(1),
        "sequence_extra_states": optional(integer(0)), "init_run": _path_or_empty()}

    @property
    def target_data(self) -> str:
        """What the trainer reads to count target steps: "online" unless the variant takes none."""
        return "none" if self.variant == "direct-transfer" else "online"

    def budget_warnings(self, algo: str, steps: int) -> list[str]:
        """What a budget of ``steps`` training steps is too short for (the trainer prints these)."""
        if self.variant == "direct-transfer":
            if steps < self.rollout_steps:
                return [f"--steps {steps} is below rollout_steps={self.rollout_steps}: this {algo} run makes no "
                        f"update and deploys its initial policy; the minimum useful budget is {self.rollout_steps} "
                        "steps (or lower it with --set rollout_steps=N)"]
            return []
        iteration = self.rollout_steps * self.target_step_every
        if steps < iteration:
            return [f"--steps {steps} is below one outer iteration (rollout_steps x target_step_every = "
                    f"{iteration} steps): this {algo} run's robot agent makes no update and deploys its initial "
                    f"policy; the minimum useful budget is {iteration} steps (or lower it with --set rollout_steps=N)"]
        return []

    def cross_checks(self) -> list[str]:
        if self.variant in PRETRAINED_VARIANTS and not self.init_run:
            return [f'init_run="": {self.variant} starts from a fully trained simulator policy; expected the run '
                    "folder of a finished direct-transfer run of this task, e.g. --set init_run=runs/direct-transfer"]
        if self.variant not in PRETRAINED_VARIANTS and self.init_run:
            return [f"init_run={json.dumps(self.init_run)}: {self.variant} starts from scratch; expected \"\" "
                    "(matl-f and fine-tuning take an init_run)"]
        return []


# --- rollouts and state sequences ---------------------------------------------------------------


class Rollout:
    """One on-policy batch per seed: ``length`` consecutive transitions, episodes as they came."""

    FIELDS = ("observations", "actions", "rewards", "next_observations", "terminations")

    def __init__(self, n_seeds: int, length: int, observation_dim: int, action_dim: int, device: str = "cpu") -> None:
        self.length = length
        shapes = {"observations": (observation_dim,), "actions": (action_dim,), "rewards": (),
                  "next_observations": (observation_dim,), "terminations": ()}
        self.storage = {k: torch.zeros((n_seeds, length, *shape), device=device) for k, shape in shapes.items()}
        self.size = 0

    def add(self, observations: torch.Tensor, actions: torch.Tensor, rewards: torch.Tensor,
            next_observations: torch.Tensor, terminations: torch.Tensor) -> None:
        if self.size >= self.length:
            raise RuntimeError("rollout is full; update and clear it before adding more")
        for name, value in zip(self.FIELDS, (observations, actions, rewards, next_observations, terminations)):
            self.storage[name][:, self.size] = value
        self.size += 1

    @property
    def full(self) -> bool:
        return self.size == self.length

    @property
    def observations(self) -> torch.Tensor:
        return self.storage["observations"]

    @property
    def actions(self) -> torch.Tensor:
        return self.storage["actions"]

    @property
    def rewards(self) -> torch.Tensor:
        return self.storage["rewards"]

    @property
    def next_observations(self) -> torch.Tensor:
        return self.storage["next_observations"]

    @property
    def terminations(self) -> torch.Tensor:
        return self.storage["terminations"]

    def episode_ends(self) -> torch.Tensor:
        """1.0 where a transition is the last of its episode in this rollout, ``[S, T]``: terminated,
        cut (the next transition does not start from this one's next state: a time limit, or the
        trainer's checkpoint boundary), or the rollout's last step."""
        ends = self.terminations.clone()
        continues = (self.next_observations[:, :-1] == self.observations[:, 1:]).all(dim=-1)
        ends[:, :-1] = torch.maximum(ends[:, :-1], (~continues).float())
        ends[:, -1] = 1.0
        return ends

    def clear(self) -> None:
        self.size = 0

    def state_dict(self, prefix: str) -> dict[str, torch.Tensor]:
        state = {f"{prefix}.{k}": v[:, :self.size] for k, v in self.storage.items()}
        return state | {f"{prefix}.size": torch.tensor(self.size)}

    def load_state_dict(self, state: dict[str, torch.Tensor], prefix: str) -> None:
        self.size = int(state[f"{prefix}.size"])
        for name, storage in self.storage.items():
            storage.zero_()
            storage[:, :self.size] = state[f"{prefix}.{name}"]


def state_sequences(observations: torch.Tensor, next_observations: torch.Tensor, episode_ends: torch.Tensor,
                    offsets: Sequence[int]) -> torch.Tensor:
    """``zeta_t = (s_{t+o} for o in offsets)`` concatenated, ``[S, T, d * len(offsets)]``.

    A state past the end of ``s_t``'s episode in the rollout is replaced by that episode's last state
    (the next state of its last transition)."""
    n_seeds, length = episode_ends.shape
    steps = torch.arange(length, device=episode_ends.device).expand(n_seeds, length)
    end_marks = torch.where(episode_ends > 0, steps, torch.full_like(steps, length))
    # Index of the last transition of each step's episode: the nearest end mark at or after it.
    episode_end = torch.flip(torch.cummin(torch.flip(end_marks, [1]), dim=1).values, [1])
    seeds = torch.arange(n_seeds, device=episode_ends.device)[:, None]
    parts = []
    for offset in offsets:
        index = steps + offset
        inside = index <= episode_end
        state_inside = observations[seeds, torch.minimum(index, episode_end)]
        last_state = next_observations[seeds, episode_end]
        parts.append(torch.where(inside[..., None], state_inside, last_state))
    return torch.cat(parts, dim=-1)


# --- the discriminator --------------------------------------------------------------------------


class Discriminator:
    """``D(zeta)`` = P(simulator | zeta), one network per seed (members ``[S]``)."""

    def __init__(self, input_dim: int, seeds: Sequence[int], config: DiscriminatorConfig, device: str = "cpu") -> None:
        self.config = config
        self.params: Params = on_device(init_mlp([seed_generator(1_000_003 * 3 + 7_919 * s + 29) for s in seeds],
                                                 [input_dim, *config.hidden_sizes, 1]), torch.device(device))
        self.optimizer = torch.optim.Adam(self.params, lr=config.lr, foreach=True)

    def logits(self, sequences: torch.Tensor) -> torch.Tensor:
        return mlp(self.params, sequences)[..., 0]

    def update(self, simulator: torch.Tensor, robot: torch.Tensor) -> Metrics:
        """``config.steps`` full-batch steps on Eq. 2: simulator sequences label 1, robot label 0."""
        loss = torch.zeros(simulator.shape[0], device=simulator.device)
        for _ in range(self.config.steps):
            # -(log D(sim) + log(1 - D(robot))), the mean over each side, per seed.
            loss = -(F.logsigmoid(self.logits(simulator)).mean(dim=1) + F.logsigmoid(-self.logits(robot)).mean(dim=1))
            self.optimizer.zero_grad(set_to_none=True)
            loss.sum().backward()
            self.optimizer.step()
        with torch.no_grad():
            accuracy = 0.5 * ((self.logits(simulator) > 0).float().mean(dim=1)
                              + (self.logits(robot) < 0).float().mean(dim=1))
        return {"discriminator/loss": loss.detach(), "discriminator/accuracy": accuracy}

    def log_simulator_probability(self, sequences: torch.Tensor) -> torch.Tensor:
        """``log D(zeta)``, ``[S, B]`` (no gradient); always finite."""
        with torch.no_grad():
            return F.logsigmoid(self.logits(sequences))

    def state_dict(self, prefix: str) -> dict[str, torch.Tensor]:
        from baselines.checkpoint import optimizer_tensors

        state = {f"{prefix}.{i}": p.detach() for i, p in enumerate(self.params)}
        return state | optimizer_tensors(self.optimizer, f"{prefix}.optimizer")

    def load_state_dict(self, state: dict[str, torch.Tensor], prefix: str) -> None:
        from baselines.checkpoint import load_optimizer_tensors

        with torch.no_grad():
            for i, p in enumerate(self.params):
                p.copy_(state[f"{prefix}.{i}"])
        load_optimizer_tensors(self.optimizer, state, f"{prefix}.optimizer")


def simulator_auxiliary_reward(logits: torch.Tensor) -> torch.Tensor:
    """rho_S = -log D(zeta) (Eq. 4) from the discriminator's logits: the simulator agent is rewarded
    where it looks like the robot. Always >= 0."""
    return -F.logsigmoid(logits)


def robot_auxiliary_reward(logits: torch.Tensor, form: str = "paper") -> torch.Tensor:
    """The robot agent's reward for looking like the simulator, from the discriminator's logits:
    ``paper``: rho_R = log D(zeta) (Eq. 5, always <= 0); ``nonnegative``: -log(1 - D(zeta)) (the
    same preference, always >= 0, so it never rewards ending an episode early)."""
    if form == "paper":
        return F.logsigmoid(logits)
    if form == "nonnegative":
        return -F.logsigmoid(-logits)
    raise ValueError(f"robot_reward_form must be 'paper' or 'nonnegative', got {form!r}")


# --- the robot's reward modes -------------------------------------------------------------------


def check_target_reward(mode: str, robot: str | None) -> None:
    """Refuse a mode the task's family does not define (before anything is written)."""
    if mode in ("full", "none"):
        return
    if robot is None:
        raise OffdynError(f"target_reward={mode!r} depends on the task's robot; this run names no task")
    if mode == "sparse" and robot not in SPARSE_GOALS:
        raise OffdynError(f"target_reward='sparse' needs a goal state and {robot} tasks have none; sparse is "
                          f"defined for {', '.join(SPARSE_GOALS)}; expected full, uninformative or none")
    if mode == "uninformative" and robot not in ROBOTS_THAT_FALL:
        raise OffdynError(f"target_reward='uninformative' is a cost for falling and {robot} never falls (its "
                          "episodes do not terminate); expected full, none, or a robot of "
                          + ", ".join(ROBOTS_THAT_FALL))


def target_reward(mode: str, robot: str | None, rewards: torch.Tensor, next_observations: torch.Tensor,
                  terminations: torch.Tensor) -> torch.Tensor:
    """The robot agent's reward for one transition per seed under ``mode``."""
    if mode == "full":
        return rewards
    if mode == "none":
        return torch.zeros_like(rewards)
    check_target_reward(mode, robot)
    assert robot is not None
    if mode == "sparse":
        return SPARSE_GOALS[robot].reached(next_observations)
    return -FALL_COST * terminations


# --- the method -------------------------------------------------------------------------------


class MATL:
    """MATL or one of its reference points, for the training loop (:mod:`baselines.method`)."""

    def __init__(self, config: Config, context: MethodContext) -> None:
        self.config = config
        self.variant = config.variant
        obs_dim, act_dim, seeds = context.observation_dim, context.action_dim, context.seeds
        n_seeds = len(seeds)
        device = getattr(context, "device", "cpu")
        self.robot_name = _robot_of(context.task)
        check_target_reward(config.target_reward, self.robot_name)
        uses_simulator = self.variant in SIMULATOR_RUNS
        uses_robot = self.variant != "direct-transfer"
        self.aligned = self.variant in ALIGNED_VARIANTS
        self.interaction = "source" if uses_simulator else "none"
        self.target_step_every: int | None = config.target_step_every if uses_robot else None
        # Streams 1 and 2 in every variant: independent's robot is MATL's robot without the
        # auxiliary reward, direct-transfer's simulator agent is MATL's simulator agent.
        self.simulator = TRPOAgent(obs_dim, act_dim, seeds, config.trpo, 1, device) if uses_simulator else None
        self.robot = TRPOAgent(obs_dim, act_dim, seeds, config.trpo, 2, device) if uses_robot else None
        self.simulator_rollout = Rollout(n_seeds, config.rollout_steps, obs_dim, act_dim, device) \
            if uses_simulator else None
        self.robot_rollout = Rollout(n_seeds, config.rollout_steps, obs_dim, act_dim, device) if uses_robot else None
        extra = config.sequence_extra_states
        if extra is None:
            extra = 0 if self.robot_name in SINGLE_STATE_ROBOTS or self.robot_name is None else 1
        self.sequence_offsets = tuple(j * config.sequence_stride for j in range(extra + 1))
        self.discriminator = Discriminator(obs_dim * len(self.sequence_offsets), seeds, config.discriminator,
                                           device) if self.aligned else None
        self.simulator_rollouts_done = 0
        self.last_metrics: Metrics = {}
        if self.variant in PRETRAINED_VARIANTS:
            pretrained = load_simulator_policy(config.init_run, context, config.trpo)
            for agent in (self.simulator, self.robot):
                if agent is not None:
                    agent.copy_from(*pretrained)

    # --- acting --------------------------------------------------------------------------

    def explore(self, observations: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The simulator agent's action in the source: (clipped for the env, raw for the rollout)."""
        assert self.simulator is not None
        raw = self.simulator.sample(observations)
        return raw.clamp(-1.0, 1.0), raw

    def explore_target(self, observations: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The robot agent's action in the target."""
        assert self.robot is not None
        raw = self.robot.sample(observations)
        return raw.clamp(-1.0, 1.0), raw

    def deploy(self, observations: torch.Tensor) -> torch.Tensor:
        agent = self.robot if self.robot is not None else self.simulator
        assert agent is not None
        return agent.mean_action(observations)

    def record(self, observations, stored_actions, rewards, next_observations, terminations) -> None:
        assert self.simulator_rollout is not None
        self.simulator_rollout.add(observations, stored_actions, rewards, next_observations, terminations)

    def record_target(self, observations, stored_actions, rewards, next_observations, terminations) -> None:
        assert self.robot_rollout is not None
        rewards = target_reward(self.config.target_reward, self.robot_name, rewards, next_observations, terminations)
        self.robot_rollout.add(observations, stored_actions, rewards, next_observations, terminations)

    # --- learning ------------------------------------------------------------------------

    def _simulator_rollout_is_aligned(self) -> bool:
        """The last simulator rollout of each outer iteration is the one aligned with the robot's."""
        return self.simulator_rollouts_done % self.config.target_step_every == self.config.target_step_every - 1

    def train_step(self, step: int) -> Metrics:
        sim, robot = self.simulator_rollout, self.robot_rollout
        metrics: Metrics = {}
        if self.aligned:
            assert sim is not None and robot is not None
            if sim.full and self._simulator_rollout_is_aligned():
                if not robot.full:
                    raise RuntimeError("matl: the simulator's aligned rollout ended before the robot's")
                metrics = self._joint_update(sim, robot)
            elif sim.full:
                metrics = self._update(self.simulator, sim, sim.rewards, "simulator")
            elif robot.full:
                raise RuntimeError("matl: the robot's rollout ended before the simulator's aligned one")
        elif sim is not None and sim.full:
            metrics = self._update(self.simulator, sim, sim.rewards, "simulator")
        elif robot is not None and robot.full:
            metrics = self._update(self.robot, robot, robot.rewards, "robot")
        if metrics:
            self.last_metrics = metrics
        return dict(self.last_metrics)

    def _update(self, agent: TRPOAgent | None, rollout: Rollout, rewards: torch.Tensor, role: str) -> Metrics:
        assert agent is not None
        config = self.config.trpo
        advantages, returns = gae(rewards, agent.values(rollout.observations), agent.values(rollout.next_observations),
                                  rollout.terminations, rollout.episode_ends(), config.discount, config.gae_lambda)
        metrics = agent.update(rollout.observations, rollout.actions, advantages, returns)
        out = {f"{role}/{k}": v for k, v in metrics.items()} | {f"{role}/rollout_reward": rewards.mean(dim=1)}
        rollout.clear()
        if role == "simulator":
            self.simulator_rollouts_done += 1
        return out

    def sequences(self, rollout: Rollout) -> torch.Tensor:
        return state_sequences(rollout.observations, rollout.next_observations, rollout.episode_ends(),
                               self.sequence_offsets)

    def _joint_update(self, sim: Rollout, robot: Rollout) -> Metrics:
        """Algorithm 1's inner step: the discriminator, then both agents with their auxiliary rewards."""
        assert self.discriminator is not None
        weight = self.config.alignment_weight
        sim_sequences, robot_sequences = self.sequences(sim), self.sequences(robot)
        metrics = self.discriminator.update(sim_sequences, robot_sequences)
        with torch.no_grad():
            rho_s = simulator_auxiliary_reward(self.discriminator.logits(sim_sequences))
            rho_r = robot_auxiliary_reward(self.discriminator.logits(robot_sequences), self.config.robot_reward_form)
        sim_rewards = sim.rewards + weight * rho_s if self.variant != "matl-u" else sim.rewards
        robot_rewards = robot.rewards + weight * rho_r
        metrics |= {"matl/simulator_auxiliary_reward": rho_s.mean(dim=1),
                    "matl/robot_auxiliary_reward": rho_r.mean(dim=1)}
        metrics |= self._update(self.simulator, sim, sim_rewards, "simulator")
        return metrics | self._update(self.robot, robot, robot_rewards, "robot")

    # --- checkpoints ---------------------------------------------------------------------

    def state_dict(self) -> dict[str, torch.Tensor]:
        state: dict[str, torch.Tensor] = {"matl.simulator_rollouts_done": torch.tensor(self.simulator_rollouts_done)}
        for name, agent, rollout in (("simulator", self.simulator, self.simulator_rollout),
                                     ("robot", self.robot, self.robot_rollout)):
            if agent is not None and rollout is not None:
                state |= agent.state_dict(name) | rollout.state_dict(f"{name}_rollout")
        if self.discriminator is not None:
            state |= self.discriminator.state_dict("discriminator")
        # The latest update's metrics, so a resumed run logs the same learning curve.
        return state | {f"metrics.{k}": v.detach() for k, v in self.last_metrics.items()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.simulator_rollouts_done = int(state["matl.simulator_rollouts_done"])
        for name, agent, rollout in (("simulator", self.simulator, self.simulator_rollout),
                                     ("robot", self.robot, self.robot_rollout)):
            if agent is not None and rollout is not None:
                agent.load_state_dict(state, name)
                rollout.load_state_dict(state, f"{name}_rollout")
        if self.discriminator is not None:
            self.discriminator.load_state_dict(state, "discriminator")
        self.last_metrics = {k[len("metrics."):]: v.clone() for k, v in state.items() if k.startswith("metrics.")}


def _robot_of(task: str | None) -> str | None:
    if task is None:
        return None
    from offdyn_bench.tasks import get_task

    return get_task(task).robot


def load_simulator_policy(run: str, context: MethodContext, trpo: TRPOConfig
                          ) -> tuple[list[torch.Tensor], torch.Tensor, list[torch.Tensor]]:
    """The trained simulator policy (mean network, log std) and value function of run folder
    ``run``, checked to fit this run: a finished run of a method with a simulator agent, the same
    source system, the same seeds and the same network sizes."""
    from baselines.checkpoint import latest_checkpoint, load_checkpoint
    from baselines.run_folder import RESULT_FILE, read_config
    from offdyn_bench.tasks import get_task

    folder = Path(run)
    where = f"init_run={json.dumps(run)}"
    if not (folder / "config.json").is_file():
        raise OffdynError(f"{where} is not a training run folder (no config.json); expected the folder of a "
                          "finished direct-transfer run")
    stored = read_config(folder)
    if stored.get("algo") not in SIMULATOR_RUNS:
        raise OffdynError(f"{where} is a {stored.get('algo')!r} run, which has no simulator policy; expected a run "
                          "of " + ", ".join(SIMULATOR_RUNS))
    if not (folder / RESULT_FILE).is_file():
        raise OffdynError(f"{where} has not finished (no {RESULT_FILE}); a fully trained simulator policy is "
                          "expected: finish that run first")
    if context.task is not None:
        here, there = get_task(context.task), get_task(str(stored.get("task")))
        if (here.robot, here.source_effects, here.task) != (there.robot, there.source_effects, there.task):
            raise OffdynError(f"{where} trained in the source of {there.name}, which differs from this task's "
                              f"({here.name}); expected a run on a task with the same source system")
    if stored.get("seeds") != list(context.seeds):
        raise OffdynError(f"{where} trained seeds {stored.get('seeds')} and this run trains {list(context.seeds)}; "
                          "expected the same --seed and --n-seeds")
    checkpoint = latest_checkpoint(folder)
    if checkpoint is None:
        raise OffdynError(f"{where} has no usable checkpoint")
    tensors, _ = load_checkpoint(checkpoint)
    shapes = TRPOAgent(context.observation_dim, context.action_dim, context.seeds, trpo, stream=1)
    expected = shapes.state_dict("simulator")
    wrong = [k for k in expected if k.startswith(("simulator.mean.", "simulator.log_std", "simulator.value."))
             and (k not in tensors or tensors[k].shape != expected[k].shape)]
    if wrong:
        raise OffdynError(f"{where} has a simulator policy of other sizes ({wrong[0]}); expected one trained with "
                          f"trpo.hidden_sizes={list(trpo.hidden_sizes)}")
    mean = [tensors[f"simulator.mean.{i}"] for i in range(len(shapes.mean_params))]
    value = [tensors[f"simulator.value.{i}"] for i in range(len(shapes.value_params))]
    return mean, tensors["simulator.log_std"], value


def _builder(variant: str) -> Callable[[Config, MethodContext], MATL]:
    def build(config: Config, context: MethodContext) -> MATL:
        if config.variant != variant:
            raise OffdynError(f"variant={config.variant!r}: {variant} is fixed by the algorithm's name; run "
                              f"`offdyn-bench train {config.variant}` instead of --set variant={config.variant}")
        return MATL(config, context)

    build.__name__ = f"build_{variant.replace('-', '_')}"
    return build


def default_config(variant: str) -> Callable[[], Config]:
    def make() -> Config:
        return Config(variant=variant)

    return make


BUILDERS: Mapping[str, Callable[[Config, MethodContext], MATL]] = MappingProxyType(
    {variant: _builder(variant) for variant in VARIANTS})


def deployed_policies(tensors: Mapping[str, torch.Tensor], action_low: np.ndarray, action_high: np.ndarray
                      ) -> list[Callable[[np.ndarray], np.ndarray]]:
    """The deployed policy of every training seed of a MATL-family checkpoint, as functions of one
    observation returning an action in environment units: the robot agent's clipped Gaussian mean
    (the simulator agent's for ``direct-transfer``), exactly :meth:`MATL.deploy`.

    For scoring tools that read checkpoints (``offdyn-bench evaluate`` reads SAC-style ``actor.*``
    networks, which a TRPO agent does not have)."""
    role = "robot" if "robot.log_std" in tensors else "simulator"
    if f"{role}.log_std" not in tensors:
        raise OffdynError("the checkpoint holds no MATL agent (no robot.* or simulator.* tensors)")
    count = sum(1 for k in tensors if k.startswith(f"{role}.mean."))
    params = [tensors[f"{role}.mean.{i}"].detach().cpu() for i in range(count)]
    low, high = np.asarray(action_low, dtype=np.float64), np.asarray(action_high, dtype=np.float64)

    def policy(member: int) -> Callable[[np.ndarray], np.ndarray]:
        own = [p[member:member + 1] for p in params]

        def act(observation: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                x = torch.as_tensor(np.asarray(observation), dtype=torch.float32).view(1, 1, -1)
                action = tanh_mlp(own, x)[0, 0].clamp(-1.0, 1.0).numpy().astype(np.float64)
            return low + (action + 1.0) * 0.5 * (high - low)

        return act

    return [policy(member) for member in range(params[0].shape[0])]
