"""What the training loop needs from a method, and what it hands one.

The loop (:mod:`baselines.train`) owns the environments, evaluation and checkpoints; a method owns
its networks and buffers. All tensors are ``[seeds, ...]`` and actions are in [-1, 1].
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING, ClassVar, Literal, Protocol

import torch

from baselines.networks import Params
from baselines.sac import Batch, Metrics, SACAgent

if TYPE_CHECKING:
    from baselines.buffers import ReplayBuffer

Interaction = Literal["source", "target", "none"]


@dataclasses.dataclass(frozen=True)
class MethodContext:
    observation_dim: int
    action_dim: int
    seeds: tuple[int, ...]
    target_data: Batch | None = None
    """The fixed target dataset (actions scaled to [-1, 1]), shared by all seeds; None if unused."""
    source_data: Batch | None = None
    """The fixed source dataset of the offline-source tracks (actions scaled to [-1, 1]), shared by
    all seeds; None if unused."""
    device: str = "cpu"
    """Where the method keeps its networks, buffers and random streams ("cpu", "cuda", "cuda:1")."""
    task: str | None = None
    """The task pair's name (MATL reads its robot for the target reward modes); None in unit tests."""

    def stream(self, name: str) -> int:
        """A seed for one random stream (buffer sampling, ...): the same name gives the same stream
        in every method, so e.g. DARC with a zero reward correction samples exactly like SAC."""
        return (int(self.seeds[0]) * 1_000_003 + sum(ord(c) * 31 ** i for i, c in enumerate(name))) % 2**62


class Method(Protocol):
    """Anything the training loop can train."""

    interaction: Interaction
    """The environment stepped every training step: "source", "target" or "none" (offline)."""
    target_step_every: int | None
    """Online-target methods: one target-environment step per this many steps (else None)."""

    def explore(self, observations: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(action sent to the environment, action stored in the buffer), both ``[S, A]`` or wider."""
        ...

    def deploy(self, observations: torch.Tensor) -> torch.Tensor:
        """The deterministic action used in the target environment, ``[S, A]``."""
        ...

    # Optional: ``explore_target(observations, step)``, the target-environment action of a method that
    # acts differently there (MATL's robot agent); without it the loop calls ``explore`` for both.
    # Optional: ``host_deploy()``, ``deploy`` as it is now, on CPU copies of the deployed policy's
    # parameters (a callable of CPU observations): a run on an accelerator evaluates with it, so its
    # evaluation episodes make no device round trip per step.

    def record(self, observations: torch.Tensor, stored_actions: torch.Tensor, rewards: torch.Tensor,
               next_observations: torch.Tensor, terminations: torch.Tensor) -> None:
        """Store one transition per seed from the interaction environment."""
        ...

    def record_target(self, observations: torch.Tensor, stored_actions: torch.Tensor, rewards: torch.Tensor,
                      next_observations: torch.Tensor, terminations: torch.Tensor) -> None:
        """Store one online target transition per seed (online-target methods only)."""
        ...

    def train_step(self, step: int) -> Metrics:
        ...

    def state_dict(self) -> dict[str, torch.Tensor]:
        ...

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        ...


def uniform_actions(n_seeds: int, action_dim: int, generator: torch.Generator) -> torch.Tensor:
    return torch.rand((n_seeds, action_dim), generator=generator, device=generator.device) * 2 - 1


def explore_actions(agent: SACAgent, observations: torch.Tensor, step: int, random_steps: int) -> torch.Tensor:
    """SAC's exploration: uniform actions for the first ``random_steps`` steps, then policy samples."""
    if step < random_steps:
        return uniform_actions(agent.n_seeds, agent.action_dim, agent.generator)
    with torch.no_grad():
        return agent.sample_actions(observations[:, None])[0][:, 0]


def deploy_actions(agent: SACAgent, observations: torch.Tensor, actor: Params | None = None) -> torch.Tensor:
    """The deterministic policy action, ``tanh(mean)`` (of ``actor``, default the agent's own)."""
    return agent.mean_actions(observations[:, None], actor)[:, 0]


def host_deploy_actions(agent: SACAgent) -> Callable[[torch.Tensor], torch.Tensor]:
    """:func:`deploy_actions` of the agent as it is now, on a CPU copy of its actor."""
    actor = agent.actor_copy("cpu")
    return lambda observations: deploy_actions(agent, observations, actor)


class SACActing:
    """Acting of a method with one SAC agent that keeps every transition of the environment it
    steps in ``self.buffer`` (SAC, DARC, H2O): SAC exploration, the deterministic policy deployed."""

    agent: SACAgent
    buffer: ReplayBuffer
    config: _RandomStepsConfig

    def explore(self, observations: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        actions = explore_actions(self.agent, observations, step, self.config.random_steps)
        return actions, actions

    def deploy(self, observations: torch.Tensor) -> torch.Tensor:
        return deploy_actions(self.agent, observations)

    def host_deploy(self) -> Callable[[torch.Tensor], torch.Tensor]:
        return host_deploy_actions(self.agent)

    def record(self, observations: torch.Tensor, stored_actions: torch.Tensor, rewards: torch.Tensor,
               next_observations: torch.Tensor, terminations: torch.Tensor) -> None:
        self.buffer.add(observations, stored_actions, rewards, next_observations, terminations)


class OfflineActing:
    """Acting of a method that steps no environment (CQL, DARA): it only deploys its SAC agent, and
    the loop asking it to explore or record is a bug, said with the method's name."""

    name: ClassVar[str]
    agent: SACAgent

    def explore(self, observations: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        raise RuntimeError(f"{self.name} is offline: it takes no environment steps")

    def deploy(self, observations: torch.Tensor) -> torch.Tensor:
        return deploy_actions(self.agent, observations)

    def host_deploy(self) -> Callable[[torch.Tensor], torch.Tensor]:
        return host_deploy_actions(self.agent)

    def record(self, *transition: torch.Tensor) -> None:
        raise RuntimeError(f"{self.name} is offline: it takes no environment steps")

    def record_target(self, *transition: torch.Tensor) -> None:
        self.record(*transition)


class _RandomStepsConfig(Protocol):
    random_steps: int


def require_target_data(context: MethodContext, algo: str) -> Batch:
    if context.target_data is None:
        raise ValueError(f"{algo} needs a target dataset")
    return context.target_data


def require_source_data(context: MethodContext, algo: str) -> Batch:
    if context.source_data is None:
        raise ValueError(f"{algo} needs a source dataset")
    return context.source_data
