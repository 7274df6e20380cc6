"""CQL (Kumar et al. 2020): offline SAC on the target dataset only, with the conservative penalty.

The CQL(H) penalty per critic, with the importance-sampled log-sum-exp of the original:

    alpha * [ log sum_j exp(Q(s, a_j) - log mu(a_j)) - Q(s, a_data) ],

over ``n_action_samples`` actions each from the uniform distribution, the policy at s and the
policy at s' (``mu`` their densities). ``alpha`` (min-Q weight) is fixed at 2.0 with no Lagrange
tuning, as the H2O paper's CQL baseline for MuJoCo (Appendix B.1). No environment is stepped:
one training step is one gradient update.

Loss scale as in the official code (young-geng/CQL, and H2O's CQL): the penalty is added to
``mse(Q1) + mse(Q2)`` (TD weight 1, not SAC's 0.5), and the target backs up no entropy term
(``backup_entropy=False``), so alpha = 2.0 means what it meant where it was tuned.

Composition with the core: an ``extra_loss``. Chosen: ``n_action_samples`` = 10 (CQL's default).

Cost: per update the critics see ``3 n`` sampled actions per state (7,680 rows at batch 256), the
part of CQL that is inherent. What is not is avoided: the policy runs once per state (not once per
repeated state), the data term reuses the TD loss's critic values, and the sampled actions go
through the critics as one batched tensor (in cache-sized blocks on a CPU).
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import torch

from baselines.buffers import DatasetSampler
from baselines.limits import NON_NEGATIVE, Limit, integer
from baselines.method import MethodContext, OfflineActing, require_target_data
from baselines.sac import (Batch, ExtraCriticLoss, GraphedUpdate, Metrics, QFunction, SACAgent, SACConfig,
                           sac_update, seed_generator)
from offdyn_bench.errors import OffdynError


TD_LOSS_WEIGHT = 1.0
"""The official code's ``mse(Q1) + mse(Q2)``: the scale the published alpha was tuned against."""

CPU_STATES_PER_CRITIC_PASS = 16
"""States whose 3 n sampled actions go through the critics together on a CPU (16 x 30 = 480 rows;
blocks of 8 to 32 states were fastest in benchmarks/bench_cql.py on a 2-core EPYC, 1 MiB L2)."""


@dataclasses.dataclass
class Config:
    sac: SACConfig = dataclasses.field(default_factory=lambda: SACConfig(backup_entropy=False))
    """SAC's settings, with the official code's ``backup_entropy=False``."""
    min_q_weight: float = 2.0
    n_action_samples: int = 10
    cuda_graph: bool = False
    """On ``--device cuda``, replay the update from a CUDA graph (:class:`baselines.sac.GraphedUpdate`,
    its warm-up rewound): the same numbers as the eager update, with one launch per update instead
    of hundreds, which is what CQL on a GPU is bound by. Refused on a CPU."""

    LIMITS: ClassVar[dict[str, Limit]] = {"min_q_weight": NON_NEGATIVE, "n_action_samples": integer(1)}


class CQL(OfflineActing):
    name = "CQL"
    interaction = "none"
    target_step_every = None

    def __init__(self, config: Config, context: MethodContext) -> None:
        self.config = config
        self.agent = SACAgent(context.observation_dim, context.action_dim, context.seeds, config.sac, context.device)
        self.data = DatasetSampler(require_target_data(context, "cql"), len(context.seeds), context.stream("target"),
                                   context.device)
        self.uniform_generator = seed_generator(context.stream("cql-uniform"), context.device)
        if config.cuda_graph and self.agent.device.type != "cuda":
            raise OffdynError(f"cuda_graph=true needs --device cuda (a CUDA graph replays GPU work); this run is "
                              f"on {self.agent.device}. Leave cuda_graph unset on a CPU")
        self.graphed: GraphedUpdate | None = None

    def conservative_penalty(self, batch: Batch) -> ExtraCriticLoss:
        """The CQL(H) penalty on ``batch``: the ``3 n`` sampled actions per state (uniform, policy at
        s, policy at s') as one batched critic evaluation, the data term from the TD loss's values."""
        n, agent = self.config.n_action_samples, self.agent
        seeds, size, _ = batch.observations.shape
        action_dim = agent.action_dim
        with torch.no_grad():
            uniform = torch.rand((seeds, size * n, action_dim), generator=self.uniform_generator,
                                 device=agent.device) * 2 - 1
            policy_actions, policy_log_probs = agent.sample_actions(batch.observations, samples_per_state=n)
            next_actions, next_log_probs = agent.sample_actions(batch.next_observations, samples_per_state=n)
            # Sampled actions of one state sit side by side: [S, B, 3n, A], and the log-densities
            # log mu(a_j) subtracted inside the log-sum-exp in the same order, [S, 1, B, 3n].
            actions = torch.cat([uniform.view(seeds, size, n, action_dim),
                                 policy_actions.view(seeds, size, n, action_dim),
                                 next_actions.view(seeds, size, n, action_dim)], dim=2)
            log_densities = torch.cat([torch.full((seeds, size, n), -action_dim * math.log(2.0),
                                                  device=batch.observations.device),
                                       policy_log_probs.view(seeds, size, n),
                                       next_log_probs.view(seeds, size, n)], dim=2)[:, None]
            observations = batch.observations[:, :, None].expand(seeds, size, 3 * n, batch.observations.shape[-1])

        # On a CPU the critics run on blocks of states whose activations stay in cache (one pass
        # over all 7,680 rows measured slower than the three calls it replaced); on an accelerator,
        # where each call costs a launch, one pass.
        block = size if batch.observations.device.type != "cpu" else CPU_STATES_PER_CRITIC_PASS

        def penalty(q: QFunction, q_data: torch.Tensor) -> tuple[torch.Tensor, Metrics]:
            sampled = torch.cat([q(obs.reshape(seeds, -1, obs.shape[-1]), act.reshape(seeds, -1, action_dim))
                                 for obs, act in zip(observations.split(block, dim=1), actions.split(block, dim=1))],
                                dim=2)
            candidates = sampled.view(seeds, 2, size, 3 * n) - log_densities
            gap = torch.logsumexp(candidates, dim=-1).mean(dim=2) - q_data.mean(dim=2)
            return self.config.min_q_weight * gap.sum(dim=1), {"cql/gap": gap.detach().mean(dim=1)}

        return penalty

    def conservative_penalty_unbatched(self, batch: Batch) -> ExtraCriticLoss:
        """The same penalty as first written: three critic passes and one for the data actions, the
        policy evaluated on every repeated state. The plain statement of the maths, which
        :meth:`conservative_penalty` must equal (a test checks it) and ``benchmarks/bench_cql.py``
        times; draws the same random numbers in the same order."""
        n, agent = self.config.n_action_samples, self.agent
        seeds, size, _ = batch.observations.shape
        action_dim = agent.action_dim
        obs = batch.observations.repeat_interleave(n, dim=1)
        next_obs = batch.next_observations.repeat_interleave(n, dim=1)
        with torch.no_grad():
            uniform = torch.rand((seeds, size * n, action_dim), generator=self.uniform_generator,
                                 device=agent.device) * 2 - 1
            policy_actions, policy_log_probs = agent.sample_actions(obs)
            next_actions, next_log_probs = agent.sample_actions(next_obs)
        uniform_log_density = -action_dim * math.log(2.0)

        def penalty(q: QFunction, q_data: torch.Tensor) -> tuple[torch.Tensor, Metrics]:
            def per_state(values: torch.Tensor) -> torch.Tensor:  # [S, 2, B*n] -> [S, 2, B, n]
                return values.view(seeds, 2, size, n)

            candidates = torch.cat([
                per_state(q(obs, uniform)) - uniform_log_density,
                per_state(q(obs, policy_actions) - policy_log_probs[:, None]),
                per_state(q(obs, next_actions) - next_log_probs[:, None]),
            ], dim=-1)
            gap = torch.logsumexp(candidates, dim=-1).mean(dim=2) - q(batch.observations, batch.actions).mean(dim=2)
            return self.config.min_q_weight * gap.sum(dim=1), {"cql/gap": gap.detach().mean(dim=1)}

        return penalty

    def update(self, batch: Batch) -> Metrics:
        return sac_update(self.agent, batch, extra_loss=self.conservative_penalty(batch),
                          td_loss_weight=TD_LOSS_WEIGHT)

    def train_step(self, step: int) -> Metrics:
        batch = self.data.sample(self.config.sac.batch_size)
        if not self.config.cuda_graph:
            return self.update(batch)
        if self.graphed is None:  # captured at the first step of each process (a resumed run captures again)
            self.graphed = GraphedUpdate(self.update, batch, [self.agent.generator, self.uniform_generator],
                                         rewind=self.agent.update_state(self.uniform_generator))
        return self.graphed(batch)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return (self.agent.state_dict() | self.data.state_dict("target")
                | {"uniform_generator": self.uniform_generator.get_state()})

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.agent.load_state_dict(state)
        self.data.load_state_dict(state, "target")
        self.uniform_generator.set_state(state["uniform_generator"])


def build(config: Config, context: MethodContext) -> CQL:
    return CQL(config, context)
