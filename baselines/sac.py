"""The one SAC core every baseline composes.

Soft Actor-Critic (Haarnoja et al. 2018) with twin critics and clipped double-Q targets, a
tanh-squashed Gaussian actor, automatic entropy tuning and Polyak-averaged target critics,
written as small updates that take a batch and return metrics (jaxrl style):

* :func:`critic_update` -- the soft Bellman update, with three hooks the methods use:
  ``reward_correction`` (DARC, DAP add the classifier reward), ``sample_weights`` (H2O's
  dynamics-ratio importance weights) and ``extra_loss`` (the H2O and CQL value penalties);
* :func:`actor_update` -- the policy step, which also tunes the temperature;
* :func:`update_targets` -- Polyak averaging;
* :func:`sac_update` -- the three in order.

Everything is batched over training seeds: tensors are ``[seeds, batch, ...]``, networks have a
leading member dimension (see :mod:`baselines.networks`), and losses are summed over seeds so the
seeds stay independent (each seed's parameters only receive gradients from its own loss).
Actions live in ``[-1, 1]``; the training loop maps them to the environment's bounds.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import ClassVar, NamedTuple

import torch

from baselines.limits import FINITE, POSITIVE, Limit, integer, layer_sizes, number, optional
from baselines.networks import Params, detached, init_mlp, mlp


@dataclasses.dataclass
class SACConfig:
    """SAC hyperparameters (Haarnoja et al. 2018, Table 1, with the automatic temperature of the
    follow-up paper); the same values DARC, H2O (Table 3) and DAP use."""

    hidden_sizes: tuple[int, ...] = (256, 256)
    """Hidden layer widths of the actor and of each critic."""
    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    temperature_lr: float = 3e-4
    discount: float = 0.99
    target_update_rate: float = 0.005
    """Polyak rate tau of the target critics."""
    batch_size: int = 256
    initial_temperature: float = 1.0
    target_entropy: float | None = None
    """None: ``target_entropy_per_action_dim`` times the action dimension."""
    target_entropy_per_action_dim: float = -1.0
    """-1: the usual heuristic, minus the action dimension; DARC's original code uses -1/2."""
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    reward_scale: float = 1.0
    """Multiplies the (corrected) reward in the Bellman target; DARC's original code uses 0.1."""
    backup_entropy: bool = True
    """Back the entropy term ``-alpha log pi(a'|s')`` up into the target, as SAC does. The official
    CQL and H2O code default to False (their penalties were tuned on targets without it)."""

    LIMITS: ClassVar[dict[str, Limit]] = {
        "hidden_sizes": layer_sizes(allow_empty=False), "actor_lr": POSITIVE, "critic_lr": POSITIVE,
        "temperature_lr": POSITIVE, "discount": number(0.0, 1.0), "target_update_rate": number(0.0, 1.0, low_open=True),
        "batch_size": integer(1), "initial_temperature": POSITIVE, "target_entropy": optional(FINITE),
        "log_std_min": FINITE, "log_std_max": FINITE, "target_entropy_per_action_dim": FINITE,
        "reward_scale": POSITIVE}

    def cross_checks(self) -> list[str]:
        if self.log_std_min >= self.log_std_max:
            return [f"log_std_min={self.log_std_min}: expected a number below log_std_max={self.log_std_max}"]
        return []


class Batch(NamedTuple):
    """A batch of transitions, ``[seeds, batch, ...]``; actions in [-1, 1]."""

    observations: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_observations: torch.Tensor
    terminations: torch.Tensor  # 1.0 where the episode ended in a terminal state (no bootstrap)


Metrics = dict[str, torch.Tensor]
QFunction = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
ExtraCriticLoss = Callable[[QFunction, torch.Tensor], tuple[torch.Tensor, Metrics]]
"""Given ``q(observations, actions) -> [seeds, 2, batch]`` (live critic parameters) and the live
values of the batch's own pairs, ``Q(s, a_data)`` ``[seeds, 2, batch]`` (computed for the TD loss
already: reuse them rather than evaluate the critics twice), return a per-seed loss ``[seeds]`` to
add to the critic loss, and metrics."""


def seed_generator(seed: int, device: torch.device | str = "cpu") -> torch.Generator:
    """A random stream on ``device``. CPU and CUDA generators give different numbers for one
    seed, so a run is deterministic per device, not across devices."""
    return torch.Generator(device=device).manual_seed(int(seed))


class SACAgent:
    """Parameters, optimizers and random stream of SAC for ``len(seeds)`` independent seeds.

    Each seed's networks are initialised from that seed alone, so seed 3 starts from the same
    weights whether it trains alone or next to others, and on every device (initial weights are
    drawn on the CPU and then moved; later random streams live on ``device``).
    """

    def __init__(self, observation_dim: int, action_dim: int, seeds: Sequence[int],
                 config: SACConfig | None = None, device: torch.device | str = "cpu") -> None:
        self.config = config = config or SACConfig()
        self.device = torch.device(device)
        self.observation_dim, self.action_dim = observation_dim, action_dim
        self.n_seeds = len(seeds)
        hidden = list(config.hidden_sizes)
        inits = [seed_generator(s) for s in seeds]
        self.actor = _stack([init_mlp([g], [observation_dim, *hidden, 2 * action_dim]) for g in inits], self.device)
        # Critic members are ordered (seed, critic): member 2*s + c.
        self.critic = _stack([init_mlp([g, g], [observation_dim + action_dim, *hidden, 1]) for g in inits],
                             self.device)
        self.critic_target = [p.detach().clone() for p in self.critic]
        self.log_temperature = torch.full((self.n_seeds,), math.log(config.initial_temperature),
                                          device=self.device, requires_grad=True)
        self.target_entropy = (config.target_entropy_per_action_dim * float(action_dim)
                               if config.target_entropy is None else config.target_entropy)
        # On CUDA the optimizers keep their step counters on the device (capturable), so an eager
        # update and one replayed from a CUDA graph (cuda_graph=true) compute the same numbers.
        capturable = self.device.type == "cuda"
        self.actor_optimizer = torch.optim.Adam(self.actor, lr=config.actor_lr, foreach=True, capturable=capturable)
        self.critic_optimizer = torch.optim.Adam(self.critic, lr=config.critic_lr, foreach=True,
                                                 capturable=capturable)
        self.temperature_optimizer = torch.optim.Adam([self.log_temperature], lr=config.temperature_lr,
                                                      foreach=True, capturable=capturable)
        # Policy noise; other components (buffers, classifiers) own their streams, so adding a
        # component never shifts this one.
        self.generator = seed_generator(seeds[0] * 7919 + 1, self.device)

    def update_state(self, *generators: torch.Generator) -> UpdateState:
        """What :func:`sac_update` writes: every parameter, the target critics, the three optimizers
        and the policy noise, plus a method's own ``generators`` drawn inside its update."""
        return UpdateState([*self.actor, *self.critic, *self.critic_target, self.log_temperature],
                           [self.actor_optimizer, self.critic_optimizer, self.temperature_optimizer],
                           [self.generator, *generators])

    @property
    def temperature(self) -> torch.Tensor:
        return self.log_temperature.detach().exp()

    # --- the policy ------------------------------------------------------------------------

    def _mean_log_std(self, observations: torch.Tensor, params: Params) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = mlp(params, observations).chunk(2, dim=-1)
        return mean, log_std.clamp(self.config.log_std_min, self.config.log_std_max)

    def sample_actions(self, observations: torch.Tensor, params: Params | None = None, samples_per_state: int = 1
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterised tanh-Gaussian sample and its log-probability, ``[S, B, A]``, ``[S, B]``.

        With ``samples_per_state`` = n: n samples per state, rows state-major (``[S, B * n, ...]``):
        the same draws as sampling at ``observations.repeat_interleave(n, 1)`` (equal up to float
        rounding), with the policy network evaluated once per state instead of n times."""
        mean, log_std = self._mean_log_std(observations, self.actor if params is None else params)
        if samples_per_state > 1:
            mean = mean.repeat_interleave(samples_per_state, dim=1)
            log_std = log_std.repeat_interleave(samples_per_state, dim=1)
        noise = torch.randn(mean.shape, generator=self.generator, device=mean.device)
        pre_tanh = mean + log_std.exp() * noise
        gaussian_log_prob = (-0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
        # log(1 - tanh(u)^2), written stably.
        squash = 2.0 * (math.log(2.0) - pre_tanh - torch.nn.functional.softplus(-2.0 * pre_tanh))
        return torch.tanh(pre_tanh), gaussian_log_prob - squash.sum(-1)

    def mean_actions(self, observations: torch.Tensor, params: Params | None = None) -> torch.Tensor:
        """The deterministic action used in evaluation: tanh of the Gaussian mean (of ``params``,
        default the actor, e.g. :meth:`actor_copy`'s)."""
        with torch.no_grad():
            return torch.tanh(self._mean_log_std(observations, self.actor if params is None else params)[0])

    def actor_copy(self, device: torch.device | str = "cpu") -> Params:
        """A detached copy of the actor's parameters on ``device``: the policy as it is now."""
        return [p.detach().to(device, copy=True) for p in self.actor]

    # --- the critics -----------------------------------------------------------------------

    def q_values(self, observations: torch.Tensor, actions: torch.Tensor,
                 params: Params | None = None) -> torch.Tensor:
        """Both critics' values, ``[S, 2, B]``."""
        inputs = torch.cat([observations, actions], dim=-1)
        seeds, batch, width = inputs.shape
        inputs = inputs.unsqueeze(1).expand(seeds, 2, batch, width).reshape(seeds * 2, batch, width)
        return mlp(self.critic if params is None else params, inputs).view(seeds, 2, batch)

    # --- checkpoints -----------------------------------------------------------------------

    def state_dict(self) -> dict[str, torch.Tensor]:
        from baselines.checkpoint import optimizer_tensors

        state = {f"actor.{i}": p.detach() for i, p in enumerate(self.actor)}
        state |= {f"critic.{i}": p.detach() for i, p in enumerate(self.critic)}
        state |= {f"critic_target.{i}": p for i, p in enumerate(self.critic_target)}
        state["log_temperature"] = self.log_temperature.detach()
        state["generator"] = self.generator.get_state()
        state |= optimizer_tensors(self.actor_optimizer, "actor_optimizer")
        state |= optimizer_tensors(self.critic_optimizer, "critic_optimizer")
        state |= optimizer_tensors(self.temperature_optimizer, "temperature_optimizer")
        return state

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        from baselines.checkpoint import load_optimizer_tensors

        with torch.no_grad():
            for name, params in (("actor", self.actor), ("critic", self.critic),
                                 ("critic_target", self.critic_target)):
                for i, p in enumerate(params):
                    p.copy_(state[f"{name}.{i}"])
            self.log_temperature.copy_(state["log_temperature"])
        self.generator.set_state(state["generator"])
        load_optimizer_tensors(self.actor_optimizer, state, "actor_optimizer")
        load_optimizer_tensors(self.critic_optimizer, state, "critic_optimizer")
        load_optimizer_tensors(self.temperature_optimizer, state, "temperature_optimizer")


def _stack(per_seed: list[Params], device: torch.device) -> Params:
    """Concatenate per-seed parameter lists along the member dimension, on ``device``."""
    return [torch.cat([p[i].detach() for p in per_seed]).to(device).requires_grad_()
            for i in range(len(per_seed[0]))]


# --- the updates -----------------------------------------------------------------------------


def soft_bellman_target(agent: SACAgent, batch: Batch, reward_correction: torch.Tensor | None = None
                        ) -> torch.Tensor:
    """c (r + dr) + gamma (1 - done) [min_i Q'_i(s', a') - alpha log pi(a'|s')],  a' ~ pi(s'),
    with c = ``reward_scale``; the entropy term only with ``backup_entropy``. ``[S, B]``."""
    config = agent.config
    with torch.no_grad():
        next_actions, next_log_probs = agent.sample_actions(batch.next_observations)
        next_q = agent.q_values(batch.next_observations, next_actions, agent.critic_target).min(dim=1).values
        soft_value = next_q - agent.temperature[:, None] * next_log_probs if config.backup_entropy else next_q
        rewards = batch.rewards if reward_correction is None else batch.rewards + reward_correction
        if config.reward_scale != 1.0:
            rewards = config.reward_scale * rewards
        return rewards + config.discount * (1.0 - batch.terminations) * soft_value


def td_loss(agent: SACAgent, batch: Batch, q: torch.Tensor, *, reward_correction: torch.Tensor | None = None,
            sample_weights: torch.Tensor | None = None, td_loss_weight: float = 0.5) -> torch.Tensor:
    """``td_loss_weight * sum_critics mean_batch w (Q(s, a) - y)^2`` per seed, ``[S]``, with ``q`` the
    live critic values ``[S, 2, B]``, ``y`` from :func:`soft_bellman_target` and ``w`` =
    ``sample_weights`` (``[S, B]``, default 1).

    ``td_loss_weight`` = 0.5 is SAC's usual scale. It matters only next to a value penalty: the
    official CQL and H2O code add their penalties to ``mse(Q1) + mse(Q2)``, weight 1."""
    target = soft_bellman_target(agent, batch, reward_correction)
    squared_error = (q - target[:, None, :]).pow(2)
    if sample_weights is not None:
        squared_error = squared_error * sample_weights[:, None, :]
    return td_loss_weight * squared_error.mean(dim=2).sum(dim=1)


def critic_update(agent: SACAgent, batch: Batch, *, reward_correction: torch.Tensor | None = None,
                  sample_weights: torch.Tensor | None = None, extra_loss: ExtraCriticLoss | None = None,
                  td_loss_weight: float = 0.5) -> Metrics:
    """One gradient step on both critics: :func:`td_loss` plus ``extra_loss``."""
    q = agent.q_values(batch.observations, batch.actions)
    loss_per_seed = td_loss(agent, batch, q, reward_correction=reward_correction, sample_weights=sample_weights,
                            td_loss_weight=td_loss_weight)
    metrics: Metrics = {"critic/td_loss": loss_per_seed.detach(), "critic/q": q.detach().mean(dim=(1, 2))}
    if extra_loss is not None:
        extra, extra_metrics = extra_loss(agent.q_values, q)
        loss_per_seed = loss_per_seed + extra
        metrics |= extra_metrics
    agent.critic_optimizer.zero_grad(set_to_none=True)
    loss_per_seed.sum().backward()
    agent.critic_optimizer.step()
    return metrics


ExtraActorLoss = Callable[[Params, torch.Tensor], torch.Tensor]
"""Given the live actor parameters and the observations ``[S, B, obs]``, a per-seed loss ``[S]`` to
add to the policy loss (DAP's regulariser on the policy means)."""


def actor_update(agent: SACAgent, observations: torch.Tensor, extra_loss: ExtraActorLoss | None = None) -> Metrics:
    """One policy step, ``mean_batch [alpha log pi(a|s) - min_i Q_i(s, a)]`` (+ ``extra_loss``), then
    one temperature step towards the target entropy, using the same sampled actions."""
    actions, log_probs = agent.sample_actions(observations)
    q = agent.q_values(observations, actions, detached(agent.critic)).min(dim=1).values
    actor_loss = (agent.temperature[:, None] * log_probs - q).mean(dim=1)
    if extra_loss is not None:
        actor_loss = actor_loss + extra_loss(agent.actor, observations)
    agent.actor_optimizer.zero_grad(set_to_none=True)
    actor_loss.sum().backward()
    agent.actor_optimizer.step()

    entropy_gap = (log_probs.detach() + agent.target_entropy).mean(dim=1)
    temperature_loss = -(agent.log_temperature * entropy_gap)
    agent.temperature_optimizer.zero_grad(set_to_none=True)
    temperature_loss.sum().backward()
    agent.temperature_optimizer.step()
    return {"actor/loss": actor_loss.detach(), "actor/entropy": -log_probs.detach().mean(dim=1),
            "actor/temperature": agent.temperature}


def update_targets(agent: SACAgent) -> None:
    with torch.no_grad():
        torch._foreach_lerp_(agent.critic_target, detached(agent.critic), agent.config.target_update_rate)


def sac_update(agent: SACAgent, batch: Batch, *, reward_correction: torch.Tensor | None = None,
               sample_weights: torch.Tensor | None = None, extra_loss: ExtraCriticLoss | None = None,
               actor_observations: torch.Tensor | None = None, td_loss_weight: float = 0.5,
               extra_actor_loss: ExtraActorLoss | None = None) -> Metrics:
    """Critic step, actor and temperature step, target update. ``actor_observations`` defaults to
    the batch's observations."""
    metrics = critic_update(agent, batch, reward_correction=reward_correction,
                            sample_weights=sample_weights, extra_loss=extra_loss, td_loss_weight=td_loss_weight)
    metrics |= actor_update(agent, batch.observations if actor_observations is None else actor_observations,
                            extra_actor_loss)
    update_targets(agent)
    return metrics


@dataclasses.dataclass(frozen=True)
class UpdateState:
    """Everything an update writes besides its outputs: the tensors it changes in place
    (parameters, target networks), the optimizers it steps (Adam, ``capturable``) and the random
    streams it draws from. :class:`GraphedUpdate` rewinds these after its warm-up."""

    tensors: Sequence[torch.Tensor]
    optimizers: Sequence[torch.optim.Optimizer]
    generators: Sequence[torch.Generator]


class _Rewind:
    """A copy of an :class:`UpdateState` taken now, put back in place later (same storage, so a
    CUDA graph captured in between still points at the live tensors)."""

    def __init__(self, state: UpdateState) -> None:
        self.state = state
        self.tensors = [t.detach().clone() for t in state.tensors]
        self.optimizers = []
        for optimizer in state.optimizers:
            if not isinstance(optimizer, torch.optim.Adam):
                raise TypeError(f"GraphedUpdate rewinds Adam only, not {type(optimizer).__name__}: Adam's "
                                "state starts at zero, which is what rewinding an unstarted optimizer restores")
            saved = {}
            for group in optimizer.param_groups:
                for p in group["params"]:
                    state_of_p = optimizer.state.get(p)
                    saved[p] = {k: v.clone() for k, v in state_of_p.items()} if state_of_p else None
            self.optimizers.append((optimizer, saved))
        self.generators = [g.get_state() for g in state.generators]

    def restore(self) -> None:
        with torch.no_grad():
            for live, saved in zip(self.state.tensors, self.tensors, strict=True):
                live.copy_(saved)
            for optimizer, saved in self.optimizers:
                for p, before in saved.items():
                    for key, value in optimizer.state[p].items():
                        if before is None:
                            value.zero_()  # Adam's fresh state: step 0, both moments 0
                        else:
                            value.copy_(before[key])
        for generator, saved_state in zip(self.state.generators, self.generators, strict=True):
            generator.set_state(saved_state)


class GraphedUpdate:
    """``update(batch)`` captured once in a CUDA graph and replayed: one launch per update instead
    of a few hundred small kernels, which is what a seed-batched update on a GPU is bound by.

    The batch is copied into static input tensors before each replay (sampling stays outside the
    graph, so a growing buffer needs no re-capture); the returned metrics are static output tensors,
    read without a host sync until the caller needs them. Random streams used inside the update
    (the agent's policy noise, a method's own generators) are passed as ``generators`` and
    registered with the graph, so every replay draws fresh numbers. The optimizers must be
    ``capturable`` (see :func:`make_capturable`).

    Capture needs warm-up updates, which are real ones. Given ``rewind`` (an :class:`UpdateState`
    holding ``generators``), the warm-up leaves no trace: tensors, optimizer states and random
    streams are put back in place after the capture, so the replays continue exactly where the
    eager update would have (checked bit for bit on an H200: whole graphed ``sac-target`` and
    ``cql`` runs against eager ones, in ``tests/baselines/test_baselines_device.py`` and
    ``benchmarks/bench_cuda_graph.py``).
    Without it, a graphed run is deterministic but not equal to an eager one.

    Only the newest GraphedUpdate of a process may replay (an older one raises): on an H200, an
    older graph replayed after a newer one was built computed NaN losses, then faulted.
    """

    _built: ClassVar[int] = 0
    """How many GraphedUpdates this process has built: only the newest may replay."""

    def __init__(self, update: Callable[[Batch], Metrics], example: Batch,
                 generators: Sequence[torch.Generator], warmup_updates: int = 3,
                 rewind: UpdateState | None = None) -> None:
        if example.observations.device.type != "cuda":
            raise ValueError("GraphedUpdate needs CUDA tensors (a CUDA graph captures GPU work)")
        if rewind is not None and {id(g) for g in generators} != {id(g) for g in rewind.generators}:
            raise ValueError("rewind must hold exactly the generators the graph registers")
        if rewind is not None and not all(group.get("capturable") for optimizer in rewind.optimizers
                                          for group in optimizer.param_groups):
            raise ValueError("the optimizers of a graphed update must be capturable (SACAgent on CUDA, or "
                             "make_capturable)")
        snapshot = _Rewind(rewind) if rewind is not None else None
        GraphedUpdate._built += 1
        self.number = GraphedUpdate._built
        self.static_batch = Batch(*(x.clone() for x in example))
        side_stream = torch.cuda.Stream()
        side_stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side_stream):  # warm-up off the capture stream, as CUDA graphs require
            for _ in range(warmup_updates):
                update(self.static_batch)
        torch.cuda.current_stream().wait_stream(side_stream)
        self.graph = torch.cuda.CUDAGraph()
        register = getattr(self.graph, "register_generator_state", None)
        if register is None:
            raise RuntimeError(f"torch {torch.__version__} cannot register generators with a CUDA graph "
                               "(needs torch >= 2.5 built with CUDA)")
        for generator in generators:
            register(generator)
        with torch.cuda.graph(self.graph):
            self.metrics = update(self.static_batch)
        if snapshot is not None:
            snapshot.restore()

    def __call__(self, batch: Batch) -> Metrics:
        if self.number != GraphedUpdate._built:
            # Seen on an H200 (torch 2.11): once a second GraphedUpdate was built in the process,
            # the first one's replays gave NaN losses, then illegal memory accesses.
            raise RuntimeError(f"this GraphedUpdate is number {self.number} of {GraphedUpdate._built} built in "
                               "this process, and only the newest may replay: replaying an older one after "
                               "another was built corrupts its updates. Build one GraphedUpdate per process "
                               "(one training run per process; a benchmark measures one graph at a time)")
        for static, fresh in zip(self.static_batch, batch):
            static.copy_(fresh, non_blocking=True)
        self.graph.replay()
        return self.metrics


def make_capturable(agent: SACAgent) -> None:
    """Switch the agent's Adam optimizers to ``capturable=True`` (step counters on the device), as
    CUDA-graph capture requires; call before the first update."""
    for optimizer in (agent.actor_optimizer, agent.critic_optimizer, agent.temperature_optimizer):
        for group in optimizer.param_groups:
            group["capturable"] = True
