"""``sac-source`` ("RL on source") and ``sac-target`` ("RL on target"): plain SAC in one environment.

``sac-source`` trains in the source simulator and is evaluated in the target: the lower reference
point, and the behaviour policy that collects target datasets (DAP Section 5.1). ``sac-target``
trains in the target itself: the oracle, and the reference for normalized scores.

Chosen where the papers are silent: ``random_steps`` uniform-random actions before learning starts
(5000, the usual SAC warm-up); one gradient update per environment step.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import torch

from baselines.buffers import ReplayBuffer
from baselines.limits import Limit, integer
from baselines.method import Interaction, MethodContext, SACActing
from baselines.sac import GraphedUpdate, Metrics, SACAgent, SACConfig, sac_update
from offdyn_bench.errors import OffdynError


@dataclasses.dataclass
class Config:
    sac: SACConfig = dataclasses.field(default_factory=SACConfig)
    buffer_size: int = 1_000_000
    random_steps: int = 5_000
    """Uniform-random actions for the first steps; updates start after them."""
    cuda_graph: bool = False
    """On ``--device cuda``, replay the update from a CUDA graph (:class:`baselines.sac.GraphedUpdate`,
    its warm-up rewound): the same numbers as the eager update, with one launch per update instead
    of hundreds. Refused on a CPU."""

    LIMITS: ClassVar[dict[str, Limit]] = {"buffer_size": integer(1), "random_steps": integer(0)}


class OnlineSAC(SACActing):
    target_step_every = None

    def __init__(self, config: Config, context: MethodContext, interaction: Interaction) -> None:
        self.config, self.interaction = config, interaction
        self.agent = SACAgent(context.observation_dim, context.action_dim, context.seeds, config.sac, context.device)
        if config.cuda_graph and self.agent.device.type != "cuda":
            raise OffdynError(f"cuda_graph=true needs --device cuda (a CUDA graph replays GPU work); this run is "
                              f"on {self.agent.device}. Leave cuda_graph unset on a CPU")
        self.buffer = ReplayBuffer(len(context.seeds), config.buffer_size, context.observation_dim,
                                   context.action_dim, context.stream("buffer"), context.device)
        self.graphed: GraphedUpdate | None = None

    def record_target(self, *transition) -> None:
        raise RuntimeError("plain SAC takes no online target transitions")

    def train_step(self, step: int) -> Metrics:
        if step < self.config.random_steps:
            return {}
        batch = self.buffer.sample(self.config.sac.batch_size)
        if not self.config.cuda_graph:
            return sac_update(self.agent, batch)
        if self.graphed is None:  # captured at the first update of each process (a resumed run captures again)
            self.graphed = GraphedUpdate(lambda b: sac_update(self.agent, b), batch, [self.agent.generator],
                                         rewind=self.agent.update_state())
        return self.graphed(batch)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return self.agent.state_dict() | self.buffer.state_dict("buffer")

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.agent.load_state_dict(state)
        self.buffer.load_state_dict(state, "buffer")


def build_source(config: Config, context: MethodContext) -> OnlineSAC:
    return OnlineSAC(config, context, "source")


def build_target(config: Config, context: MethodContext) -> OnlineSAC:
    return OnlineSAC(config, context, "target")
