"""H2O with an offline source: the offline-source-online-target track's H2O (ODRL, Lyu et al. 2024,
"Offline-Online" setting), built from H2O's pieces (:class:`baselines.h2o.DynamicsAwareCritic`).

H2O (Niu et al. 2022) mixes a fixed target dataset with online simulator data. Here the roles of
the two sides' *data* swap, while the roles of the two *dynamics* stay: the offline data is the
task's fixed **source** dataset, and the online data comes from the **target** environment, one
target step per ``target_step_every`` = 10 gradient updates (the track's budget, counted by the
trainer). No source simulator is stepped. Each update takes half a batch from each side:

* ``real`` = the online target replay buffer (target dynamics): trusted, pulled up by the value
  penalty, TD weight 1;
* ``sim`` = the source dataset (source dynamics): its TD errors weighted by the clipped dynamics
  ratio ``P_target / P_source``, and pushed down by ``beta * log sum_i w_i exp Q(s_i, a_i)`` with
  ``w_i`` the normalised dynamics gap ``KL(P_source || P_target)``;
* the classifiers learn source (dataset) against target (buffer) transitions, one step per update.

Everything of H2O is kept as :mod:`baselines.h2o` has it (beta = 0.01, the clips, input noise 0.1,
``backup_entropy=False``, per-half TD means). Chosen where nothing published says:

* ``Sigma`` of the gap estimate is the covariance of the source dataset's states: as in H2O, the
  covariance of the fixed dataset (it is fixed from the start; the target buffer starts empty);
* the first ``random_steps`` = 5,000 updates' worth of steps (500 target steps) act uniformly at
  random in the target and make no update, as H2O's and SAC's warm-up: both halves of a batch need
  data, and the classifiers need target transitions to tell anything apart;
* the target buffer holds ``target_buffer_size`` = 100,000 transitions, the full budget's target
  steps, so nothing the track allows is ever dropped.

With ``min_q_weight=0`` and ``dynamics_ratio_clip=(1, 1)`` it is SAC on half-and-half batches of
source data and online target data (a test checks this, bit for bit).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import ClassVar

import torch

from baselines.buffers import DatasetSampler, ReplayBuffer
from baselines.h2o import DynamicsAwareCritic, DynamicsAwareSettings
from baselines.limits import Limit, integer
from baselines.method import (
    MethodContext,
    deploy_actions,
    explore_actions,
    host_deploy_actions,
    require_source_data,
)
from baselines.sac import Metrics, SACAgent


@dataclasses.dataclass
class Config(DynamicsAwareSettings):
    target_step_every: int = 10
    """One target-environment step per this many updates (the track allows one per ten)."""
    target_buffer_size: int = 100_000
    random_steps: int = 5_000
    """Steps of uniform-random target actions (one target step per ``target_step_every``) before
    updates start."""

    target_data: ClassVar[str] = "online"
    """Read by the trainer (and sweeps) as for ``darc-online``: target transitions come from the
    environment, not a dataset. Not a setting."""

    LIMITS: ClassVar[dict[str, Limit]] = DynamicsAwareSettings.LIMITS | {
        "target_step_every": integer(1), "target_buffer_size": integer(1), "random_steps": integer(0)}


class H2OOfflineSource:
    interaction = "none"

    def __init__(self, config: Config, context: MethodContext) -> None:
        self.config = config
        source = require_source_data(context, "h2o-offline-source")
        obs_dim, act_dim, device = context.observation_dim, context.action_dim, context.device
        self.target_step_every: int | None = config.target_step_every
        self.agent = SACAgent(obs_dim, act_dim, context.seeds, config.sac, device)
        self.target = ReplayBuffer(len(context.seeds), config.target_buffer_size, obs_dim, act_dim,
                                   context.stream("target"), device)
        self.source = DatasetSampler(source, len(context.seeds), context.stream("source"), device)
        self.critic = DynamicsAwareCritic(config, context, source.observations)

    def explore(self, observations: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The target-environment action (the only environment this method steps)."""
        actions = explore_actions(self.agent, observations, step, self.config.random_steps)
        return actions, actions

    def deploy(self, observations: torch.Tensor) -> torch.Tensor:
        return deploy_actions(self.agent, observations)

    def host_deploy(self) -> Callable[[torch.Tensor], torch.Tensor]:
        return host_deploy_actions(self.agent)

    def record(self, *transition) -> None:
        raise RuntimeError("h2o-offline-source steps no source simulator: its source data is a fixed dataset")

    def record_target(self, observations, stored_actions, rewards, next_observations, terminations) -> None:
        self.target.add(observations, stored_actions, rewards, next_observations, terminations)

    def train_step(self, step: int) -> Metrics:
        if step < self.config.random_steps or self.target.size == 0:
            return {}
        half = self.config.sac.batch_size // 2
        real, sim = self.target.sample(half), self.source.sample(half)
        metrics = self.critic.classifiers.update(sim, real)
        return metrics | self.critic.agent_update(self.agent, real, sim)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return (self.agent.state_dict() | self.target.state_dict("target") | self.source.state_dict("source")
                | self.critic.state_dict())

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.agent.load_state_dict(state)
        self.target.load_state_dict(state, "target")
        self.source.load_state_dict(state, "source")
        self.critic.load_state_dict(state)


def build(config: Config, context: MethodContext) -> H2OOfflineSource:
    return H2OOfflineSource(config, context)
