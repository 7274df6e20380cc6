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
from baselines.sac import Metrics, SACAgent, SACConfig, sac_update
from offdyn_bench.errors import OffdynError


CUDA_GRAPH_WITHDRAWN = (
    "cuda_graph=true is withdrawn: on an H200 (torch 2.11) the CUDA-graph update corrupted updates once other "
    "CUDA work had run in the process (NaN losses; illegal memory accesses with a second graph), cause not "
    "established. Leave cuda_graph unset: the eager update (the default) runs on CUDA seed-batched")


@dataclasses.dataclass
class Config:
    sac: SACConfig = dataclasses.field(default_factory=SACConfig)
    buffer_size: int = 1_000_000
    random_steps: int = 5_000
    """Uniform-random actions for the first steps; updates start after them."""
    cuda_graph: bool = False
    """Withdrawn: ``true`` is refused. Replaying the update from a CUDA graph
    (:class:`baselines.sac.GraphedUpdate`) was measured on an H200 (torch 2.11) and corrupted
    updates once other CUDA work had run in the process: NaN losses, and illegal memory accesses
    where a second graph was built. The cause is not established; ``benchmarks/bench_gpu.py`` still
    measures the graph, to check a fix. Training runs use the eager update."""

    LIMITS: ClassVar[dict[str, Limit]] = {"buffer_size": integer(1), "random_steps": integer(0)}


class OnlineSAC(SACActing):
    target_step_every = None

    def __init__(self, config: Config, context: MethodContext, interaction: Interaction) -> None:
        if config.cuda_graph:
            raise OffdynError(CUDA_GRAPH_WITHDRAWN)
        self.config, self.interaction = config, interaction
        self.agent = SACAgent(context.observation_dim, context.action_dim, context.seeds, config.sac, context.device)
        self.buffer = ReplayBuffer(len(context.seeds), config.buffer_size, context.observation_dim,
                                   context.action_dim, context.stream("buffer"), context.device)

    def record_target(self, *transition) -> None:
        raise RuntimeError("plain SAC takes no online target transitions")

    def train_step(self, step: int) -> Metrics:
        if step < self.config.random_steps:
            return {}
        return sac_update(self.agent, self.buffer.sample(self.config.sac.batch_size))

    def state_dict(self) -> dict[str, torch.Tensor]:
        return self.agent.state_dict() | self.buffer.state_dict("buffer")

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.agent.load_state_dict(state)
        self.buffer.load_state_dict(state, "buffer")


def build_source(config: Config, context: MethodContext) -> OnlineSAC:
    return OnlineSAC(config, context, "source")


def build_target(config: Config, context: MethodContext) -> OnlineSAC:
    return OnlineSAC(config, context, "target")
