"""H2O: dynamics-aware hybrid offline-and-online RL ("When to Trust Your Simulator", Niu et al.
2022, Sections 4.1-4.4 and Appendix B.1).

SAC on a mixed batch, half from the fixed target ("real") dataset and half from a simulated replay
buffer filled by the current policy in the source simulator, with a dynamics-aware critic loss:

* **Fixing the Bellman error (Eq. 8).** The simulated TD errors are weighted by the dynamics ratio
  ``P_real(s'|s,a) / P_sim(s'|s,a)`` from the classifiers, clipped to ``dynamics_ratio_clip``.
* **Adaptive value regularisation (Eq. 6).** ``beta * [log sum_i w_i exp Q(s_i, a_i) - E_real Q]``
  per critic, over the simulated mini-batch, with ``w_i`` the normalised dynamics-gap measure
  ``u(s, a) = KL(P_sim || P_real)``, estimated by averaging ``-log ratio(s, a, s'_j)`` over
  ``kl_samples`` next states ``s'_j ~ N(s'_sim, Sigma)`` (Sigma: covariance of the dataset's states)
  and clipped to ``kl_clip``. High-gap simulated samples are pushed down; real data is pulled up.
* Fixed min-Q weight ``beta`` = 0.01, discriminator input noise 0.1, simulated buffer 10x the
  dataset, half-and-half batches (Appendix B.1).

Loss scale as in the official code (t6-thu/H2O): per critic, ``mse_real + mse_sim`` with each half
its own mean (the simulated half weighted by the dynamics ratio), plus the penalty; the target backs
up no entropy term (``backup_entropy=False``). beta = 0.01 was tuned on that scale; SAC's usual
``0.5 * mean over the mixed batch`` would make it 4x stronger.

Composition with the core: ``sample_weights`` and ``extra_loss`` passed to
:func:`baselines.sac.sac_update`, by :class:`DynamicsAwareCritic` (which the offline-source H2O,
:mod:`baselines.h2o_offline_source`, shares with the sides swapped). With ``min_q_weight=0`` and ``dynamics_ratio_clip=(1, 1)`` it is
SAC on the mixed buffer (a test checks this).

Chosen where the extraction lost the value (Table 3's ranges): ``dynamics_ratio_clip`` = (1e-5,
1.0), so simulated samples are only ever down-weighted; ``kl_clip`` = (1e-6, 10); ``kl_samples`` =
10; ``random_steps`` = 5000 uniform-random simulator steps before updates start, as for SAC.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import torch

from baselines.buffers import DatasetSampler, ReplayBuffer, concat_batches
from baselines.classifiers import ClassifierConfig, DomainClassifiers
from baselines.limits import NON_NEGATIVE, Limit, integer, ordered_pair
from baselines.method import MethodContext, SACActing, require_target_data
from baselines.sac import Batch, Metrics, QFunction, SACAgent, SACConfig, sac_update, seed_generator

TD_LOSS_WEIGHT = 1.0
"""Per critic ``mse_real + mse_sim`` (weight 1 on each half's mean), as in the official code."""


@dataclasses.dataclass
class DynamicsAwareSettings:
    """The settings of H2O's dynamics-aware critic, shared by :class:`Config` and the offline-source
    H2O (:mod:`baselines.h2o_offline_source`)."""

    sac: SACConfig = dataclasses.field(default_factory=lambda: SACConfig(backup_entropy=False))
    """SAC's settings, with the official code's ``backup_entropy=False``."""
    classifier: ClassifierConfig = dataclasses.field(
        default_factory=lambda: ClassifierConfig(input_noise_std=0.1))
    min_q_weight: float = 0.01
    """beta of Eq. 6 (0.01 in all of H2O's simulation experiments)."""
    dynamics_ratio_clip: tuple[float, float] = (1e-5, 1.0)
    kl_clip: tuple[float, float] = (1e-6, 10.0)
    kl_samples: int = 10

    LIMITS: ClassVar[dict[str, Limit]] = {
        "min_q_weight": NON_NEGATIVE, "dynamics_ratio_clip": ordered_pair(0.0, low_open=True),
        "kl_clip": ordered_pair(0.0, low_open=True), "kl_samples": integer(1)}

    def cross_checks(self) -> list[str]:
        # Half of each batch is real data, half simulated: both halves need a transition.
        if self.sac.batch_size < 2:
            return [f"sac.batch_size={self.sac.batch_size}: expected an integer >= 2 (h2o splits it in halves)"]
        return []


@dataclasses.dataclass
class Config(DynamicsAwareSettings):
    buffer_size_factor: int = 10
    """Simulated buffer capacity, in multiples of the dataset size."""
    random_steps: int = 5_000

    LIMITS: ClassVar[dict[str, Limit]] = DynamicsAwareSettings.LIMITS | {
        "buffer_size_factor": integer(1), "random_steps": integer(0)}


class DynamicsAwareCritic:
    """What makes H2O's update dynamics-aware, whichever side is offline: the domain classifiers,
    the dynamics ratio, the dynamics-gap estimate and the weighted, penalised SAC step.

    ``real`` transitions follow the target dynamics (trusted: pulled up by the penalty), ``sim``
    ones the source dynamics (weighted by the ratio, pushed down where the gap is large). In H2O
    ``real`` is the fixed target dataset and ``sim`` the simulator's buffer; in the offline-source
    H2O ``real`` is the online target buffer and ``sim`` the fixed source dataset.
    """

    def __init__(self, settings: DynamicsAwareSettings, context: MethodContext, offline_states: torch.Tensor
                 ) -> None:
        self.settings = settings
        obs_dim, act_dim, device = context.observation_dim, context.action_dim, context.device
        self.classifiers = DomainClassifiers(obs_dim, act_dim, context.seeds, settings.classifier, device=device)
        # Sigma: covariance of the offline dataset's states, as a Cholesky factor for sampling.
        covariance = torch.cov(offline_states.T) + 1e-6 * torch.eye(obs_dim)
        self.state_cholesky = torch.linalg.cholesky(covariance).to(device)
        self.kl_generator = seed_generator(context.stream("h2o-kl"), device)

    def dynamics_ratio(self, sim: Batch) -> torch.Tensor:
        """Clipped ``P_real / P_sim`` on the simulated transitions, ``[S, B]``."""
        low, high = self.settings.dynamics_ratio_clip
        log_ratio = self.classifiers.log_ratio(sim.observations, sim.actions, sim.next_observations).mean(dim=1)
        return log_ratio.exp().clamp(low, high)

    def dynamics_gap(self, sim: Batch) -> torch.Tensor:
        """Clipped ``u(s, a) = KL(P_sim || P_real)`` estimated on Gaussian next states, ``[S, B]``."""
        n = self.settings.kl_samples
        seeds, batch, obs_dim = sim.observations.shape

        def repeat(x: torch.Tensor) -> torch.Tensor:
            return x.repeat_interleave(n, dim=1)

        noise = torch.randn((seeds, batch * n, obs_dim), generator=self.kl_generator,
                            device=sim.observations.device) @ self.state_cholesky.T
        log_ratio = self.classifiers.log_ratio(repeat(sim.observations), repeat(sim.actions),
                                               repeat(sim.next_observations) + noise).mean(dim=1)
        kl = -log_ratio.view(seeds, batch, n).mean(dim=-1)
        return kl.clamp(*self.settings.kl_clip)

    def agent_update(self, agent: SACAgent, real: Batch, sim: Batch) -> Metrics:
        """The dynamics-aware SAC step on one real half-batch and one simulated half-batch."""
        n_real, n_sim = real.rewards.shape[1], sim.rewards.shape[1]
        ratio = self.dynamics_ratio(sim)
        # The core takes one mean over the mixed batch; these weights turn it into the official
        # mean_real + mean_sim (each half its own mean), with TD weight 1.
        weights = torch.cat([torch.full_like(real.rewards, (n_real + n_sim) / n_real),
                             ratio * ((n_real + n_sim) / n_sim)], dim=1)
        gap = self.dynamics_gap(sim)
        log_gap_weights = (gap / gap.sum(dim=1, keepdim=True)).log()  # log w_i, sums to 1 over the batch
        beta = self.settings.min_q_weight

        def value_penalty(q: QFunction, q_mixed: torch.Tensor) -> tuple[torch.Tensor, Metrics]:
            # The mixed batch is real then simulated: its TD-loss values are Q on both halves.
            q_real, q_sim = q_mixed.split([real.rewards.shape[1], sim.rewards.shape[1]], dim=2)  # [S, 2, B] each
            pushed_down = torch.logsumexp(q_sim + log_gap_weights[:, None, :], dim=2)
            penalty = (pushed_down - q_real.mean(dim=2)).sum(dim=1)
            return beta * penalty, {"h2o/penalty": penalty.detach()}

        mixed = concat_batches(real, sim)
        metrics = sac_update(agent, mixed, sample_weights=weights, extra_loss=value_penalty,
                             td_loss_weight=TD_LOSS_WEIGHT)
        return metrics | {"h2o/dynamics_ratio": ratio.mean(), "h2o/kl": gap.mean()}

    def state_dict(self) -> dict[str, torch.Tensor]:
        return self.classifiers.state_dict("classifiers") | {"kl_generator": self.kl_generator.get_state()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.classifiers.load_state_dict(state, "classifiers")
        self.kl_generator.set_state(state["kl_generator"])


class H2O(SACActing):
    interaction = "source"
    target_step_every = None

    def __init__(self, config: Config, context: MethodContext) -> None:
        self.config = config
        data = require_target_data(context, "h2o")
        obs_dim, act_dim = context.observation_dim, context.action_dim
        device = context.device
        self.agent = SACAgent(obs_dim, act_dim, context.seeds, config.sac, device)
        capacity = config.buffer_size_factor * int(data.rewards.shape[0])
        self.buffer = ReplayBuffer(len(context.seeds), capacity, obs_dim, act_dim, context.stream("buffer"), device)
        self.real = DatasetSampler(data, len(context.seeds), context.stream("target"), device)
        self.critic = DynamicsAwareCritic(config, context, data.observations)
        self.classifiers, self.kl_generator = self.critic.classifiers, self.critic.kl_generator

    def record_target(self, *transition) -> None:
        raise RuntimeError("H2O uses the fixed target dataset, not online target transitions")

    def dynamics_ratio(self, sim: Batch) -> torch.Tensor:
        return self.critic.dynamics_ratio(sim)

    def dynamics_gap(self, sim: Batch) -> torch.Tensor:
        return self.critic.dynamics_gap(sim)

    def agent_update(self, real: Batch, sim: Batch) -> Metrics:
        return self.critic.agent_update(self.agent, real, sim)

    def train_step(self, step: int) -> Metrics:
        if step < self.config.random_steps:
            return {}
        half = self.config.sac.batch_size // 2
        real, sim = self.real.sample(half), self.buffer.sample(half)
        metrics = self.classifiers.update(sim, real)
        return metrics | self.agent_update(real, sim)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return (self.agent.state_dict() | self.buffer.state_dict("buffer") | self.real.state_dict("target")
                | self.critic.state_dict())

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.agent.load_state_dict(state)
        self.buffer.load_state_dict(state, "buffer")
        self.real.load_state_dict(state, "target")
        self.critic.load_state_dict(state)


def build(config: Config, context: MethodContext) -> H2O:
    return H2O(config, context)
