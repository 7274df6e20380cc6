"""Trust Region Policy Optimization (Schulman et al. 2015) with GAE (Schulman et al. 2016), batched
over training seeds: the policy learner of MATL and its reference points (:mod:`baselines.matl`).

One update, as in the TRPO paper (Appendix C) and rllab, which MATL used:

1. advantages by generalized advantage estimation (:func:`gae`) from the rollout's rewards and the
   value function, centred and scaled per seed;
2. the policy gradient ``g`` of the importance-sampled surrogate ``mean exp(log pi - log pi_old) A``;
3. the natural gradient direction ``x = F^-1 g`` by conjugate gradient (:func:`conjugate_gradient`),
   with Fisher-vector products from the Hessian of the mean KL (plus damping), never forming ``F``;
4. the largest step ``sqrt(2 delta / x^T F x) x`` along it, shrunk by backtracking until the
   surrogate improves and the mean KL stays within ``max_kl`` (no step when none does);
5. the value function regressed on the GAE returns.

The policy is a diagonal Gaussian: a tanh MLP for the mean and a state-independent log standard
deviation (rllab's ``GaussianMLPPolicy``). Its samples are unbounded; the environment gets them
clipped to [-1, 1] and the rollout stores the raw sample, so log-probabilities stay exact.

Seeds stay independent: every network has a leading member dimension, losses are summed over seeds,
so the KL's Hessian is block-diagonal and every conjugate-gradient quantity (dot products, step
sizes, the line search's acceptance) is computed per seed.

Chosen where MATL's paper is silent (its supplementary settings are not available): the defaults
of rllab's TRPO and of common TRPO implementations -- max KL 0.01, 10 conjugate-gradient iterations
with damping 0.1, backtracking ratio 0.8 over at most 15 steps, discount 0.99, GAE lambda 0.97,
two hidden layers of 64 tanh units for policy and value function, initial standard deviation 1,
value function fitted by 80 full-batch Adam steps at 1e-3.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import ClassVar

import torch

from baselines.limits import FINITE, POSITIVE, Limit, integer, layer_sizes, number
from baselines.networks import Params, init_mlp
from baselines.sac import Metrics, seed_generator


@dataclasses.dataclass
class TRPOConfig:
    hidden_sizes: tuple[int, ...] = (64, 64)
    """Hidden tanh layers of the policy mean and of the value function."""
    max_kl: float = 0.01
    """The trust region: mean KL(pi_old || pi_new) per update."""
    discount: float = 0.99
    gae_lambda: float = 0.97
    cg_iterations: int = 10
    cg_damping: float = 0.1
    """Added to the Fisher-vector product (F + damping I) for a well-conditioned solve."""
    backtrack_ratio: float = 0.8
    max_backtracks: int = 15
    initial_log_std: float = 0.0
    value_lr: float = 1e-3
    value_iterations: int = 80
    """Full-batch Adam steps on the value function per update."""

    LIMITS: ClassVar[dict[str, Limit]] = {
        "hidden_sizes": layer_sizes(allow_empty=True), "max_kl": POSITIVE, "discount": number(0.0, 1.0),
        "gae_lambda": number(0.0, 1.0), "cg_iterations": integer(1), "cg_damping": number(0.0),
        "backtrack_ratio": number(0.0, 1.0, low_open=True), "max_backtracks": integer(0),
        "initial_log_std": FINITE, "value_lr": POSITIVE, "value_iterations": integer(0)}


def tanh_mlp(params: Sequence[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """Forward ``x: [members, batch, in]`` through tanh hidden layers and a linear output."""
    n_layers = len(params) // 2
    for i in range(n_layers):
        x = torch.baddbmm(params[2 * i + 1], x, params[2 * i])
        if i < n_layers - 1:
            x = torch.tanh(x)
    return x


# --- the three numerical pieces, each testable on its own -------------------------------------


def gae(rewards: torch.Tensor, values: torch.Tensor, next_values: torch.Tensor, terminations: torch.Tensor,
        episode_ends: torch.Tensor, discount: float, gae_lambda: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalized advantage estimates and value targets, ``[S, T]`` each.

    ``next_values`` are ``V(s_{t+1})`` of each transition's own next state, so an episode cut by a
    time limit or by the end of the rollout bootstraps correctly; ``terminations`` zero the
    bootstrap; ``episode_ends`` (terminated, truncated, or the rollout's last step) stop the
    backward recursion ``A_t = delta_t + gamma lambda A_{t+1}``.
    """
    deltas = rewards + discount * (1.0 - terminations) * next_values - values
    advantages = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[:, 0])
    for t in range(rewards.shape[1] - 1, -1, -1):
        running = deltas[:, t] + discount * gae_lambda * (1.0 - episode_ends[:, t]) * running
        advantages[:, t] = running
    return advantages, advantages + values


def conjugate_gradient(matrix_vector: Callable[[torch.Tensor], torch.Tensor], b: torch.Tensor,
                       iterations: int, tolerance: float = 1e-10) -> torch.Tensor:
    """Solve ``A x = b`` for symmetric positive-definite ``A`` given as a product, one system per
    row: ``b`` is ``[S, P]`` and every dot product is per row. Rows that have converged stop moving."""
    x = torch.zeros_like(b)
    residual = b.clone()
    direction = b.clone()
    residual_norm = (residual * residual).sum(dim=1)
    for _ in range(iterations):
        active = residual_norm > tolerance
        if not bool(active.any()):
            break
        product = matrix_vector(direction)
        curvature = (direction * product).sum(dim=1)
        alpha = torch.where(active, residual_norm / curvature.clamp_min(1e-30), torch.zeros_like(curvature))
        x = x + alpha[:, None] * direction
        residual = residual - alpha[:, None] * product
        new_norm = (residual * residual).sum(dim=1)
        beta = torch.where(active, new_norm / residual_norm.clamp_min(1e-30), torch.zeros_like(new_norm))
        direction = residual + beta[:, None] * direction
        residual_norm = torch.where(active, new_norm, residual_norm)
    return x


def gaussian_kl(mean_old: torch.Tensor, log_std_old: torch.Tensor, mean_new: torch.Tensor,
                log_std_new: torch.Tensor) -> torch.Tensor:
    """KL(old || new) of diagonal Gaussians, summed over the last dimension."""
    variance_old, variance_new = (2 * log_std_old).exp(), (2 * log_std_new).exp()
    return (log_std_new - log_std_old + (variance_old + (mean_old - mean_new).pow(2)) / (2 * variance_new)
            - 0.5).sum(-1)


def gaussian_log_prob(mean: torch.Tensor, log_std: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    z = (actions - mean) / log_std.exp()
    return (-0.5 * z.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)


# --- the learner --------------------------------------------------------------------------------


def on_device(params: Params, device: torch.device) -> Params:
    """Leaf parameters on ``device`` (a no-op copy-free move on the CPU)."""
    return [p.detach().to(device).requires_grad_() for p in params]


def _flat(tensors: Sequence[torch.Tensor], n_seeds: int) -> torch.Tensor:
    """Per-seed flat vector ``[S, P]`` of member-stacked tensors."""
    return torch.cat([t.reshape(n_seeds, -1) for t in tensors], dim=1)


def _unflat(vector: torch.Tensor, like: Sequence[torch.Tensor]) -> list[torch.Tensor]:
    sizes = [t[0].numel() for t in like]
    return [chunk.reshape(t.shape) for chunk, t in zip(vector.split(sizes, dim=1), like)]


class TRPOAgent:
    """A Gaussian policy and a value function per seed, with TRPO's update.

    ``stream`` separates agents that train side by side (MATL's simulator and robot agents): each
    draws its initial weights and its exploration noise from its own generators, so one agent's
    randomness never depends on whether the other exists.
    """

    def __init__(self, observation_dim: int, action_dim: int, seeds: Sequence[int], config: TRPOConfig,
                 stream: int, device: str = "cpu") -> None:
        self.config, self.device = config, torch.device(device)
        self.n_seeds, self.action_dim = len(seeds), action_dim
        hidden = list(config.hidden_sizes)
        inits = [seed_generator(1_000_003 * stream + 7_919 * s + 17) for s in seeds]
        # Initial weights are drawn on the CPU, so a seed starts from the same weights on every device.
        self.mean_params: Params = on_device(init_mlp(inits, [observation_dim, *hidden, action_dim]), self.device)
        self.log_std = torch.full((self.n_seeds, 1, action_dim), float(config.initial_log_std), device=self.device,
                                  requires_grad=True)
        self.value_params: Params = on_device(init_mlp(inits, [observation_dim, *hidden, 1]), self.device)
        self.value_optimizer = torch.optim.Adam(self.value_params, lr=config.value_lr, foreach=True)
        self.generator = torch.Generator(device=self.device).manual_seed(104_729 * stream + seeds[0])

    @property
    def policy_params(self) -> Params:
        return [*self.mean_params, self.log_std]

    def distribution(self, observations: torch.Tensor, params: Sequence[torch.Tensor] | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log std, ``[S, B, A]`` each, of ``observations: [S, B, d]``."""
        params = self.policy_params if params is None else params
        mean = tanh_mlp(params[:-1], observations)
        return mean, params[-1].expand_as(mean)

    def sample(self, observations: torch.Tensor) -> torch.Tensor:
        """One unbounded Gaussian action per seed, ``observations: [S, d]`` -> ``[S, A]``."""
        with torch.no_grad():
            mean, log_std = self.distribution(observations[:, None])
            noise = torch.randn(mean.shape, generator=self.generator)
            return (mean + log_std.exp() * noise)[:, 0]

    def mean_action(self, observations: torch.Tensor) -> torch.Tensor:
        """The deterministic action, clipped to [-1, 1], ``[S, A]``."""
        with torch.no_grad():
            return self.distribution(observations[:, None])[0][:, 0].clamp(-1.0, 1.0)

    def values(self, observations: torch.Tensor) -> torch.Tensor:
        """``V(s)``, ``[S, B]`` (no gradient)."""
        with torch.no_grad():
            return tanh_mlp(self.value_params, observations)[..., 0]

    def update(self, observations: torch.Tensor, actions: torch.Tensor, advantages: torch.Tensor,
               value_targets: torch.Tensor) -> Metrics:
        """One TRPO policy step and the value regression on a rollout, tensors ``[S, T, ...]``."""
        metrics = self.policy_step(observations, actions, advantages)
        return metrics | self.value_step(observations, value_targets)

    def policy_step(self, observations: torch.Tensor, actions: torch.Tensor, advantages: torch.Tensor) -> Metrics:
        config, n = self.config, self.n_seeds
        # rllab centres and scales advantages per batch: the step size then means the same across tasks.
        advantages = (advantages - advantages.mean(dim=1, keepdim=True)) / (advantages.std(dim=1, keepdim=True) + 1e-8)
        params = self.policy_params
        old = [p.detach().clone() for p in params]
        with torch.no_grad():
            mean_old, log_std_old = self.distribution(observations, old)
            log_prob_old = gaussian_log_prob(mean_old, log_std_old, actions)

        def surrogate(candidate: Sequence[torch.Tensor]) -> torch.Tensor:
            mean, log_std = self.distribution(observations, candidate)
            ratio = (gaussian_log_prob(mean, log_std, actions) - log_prob_old).exp()
            return (ratio * advantages).mean(dim=1)

        def mean_kl(candidate: Sequence[torch.Tensor]) -> torch.Tensor:
            mean, log_std = self.distribution(observations, candidate)
            return gaussian_kl(mean_old, log_std_old, mean, log_std).mean(dim=1)

        loss_before = surrogate(params)
        gradient = _flat(torch.autograd.grad(loss_before.sum(), params), n)
        kl_gradient = _flat(torch.autograd.grad(mean_kl(params).sum(), params, create_graph=True), n)

        def fisher_vector(vector: torch.Tensor) -> torch.Tensor:
            product = torch.autograd.grad((kl_gradient * vector).sum(), params, retain_graph=True)
            return _flat(product, n) + config.cg_damping * vector

        direction = conjugate_gradient(fisher_vector, gradient, config.cg_iterations)
        curvature = (direction * fisher_vector(direction)).sum(dim=1)
        step_size = torch.sqrt(2 * config.max_kl / curvature.clamp_min(1e-12))
        full_step = step_size[:, None] * direction
        loss_before = loss_before.detach()

        # Backtracking, per seed: the first shrink factor whose step improves the surrogate within
        # the trust region; a seed with none keeps its policy.
        old_flat = _flat(old, n)
        chosen = torch.zeros(n, device=self.device)
        found = torch.zeros(n, dtype=torch.bool, device=self.device)
        with torch.no_grad():
            for k in range(config.max_backtracks + 1):
                fraction = config.backtrack_ratio ** k
                candidate = _unflat(old_flat + fraction * full_step, old)
                accept = ~found & (surrogate(candidate) > loss_before) & (mean_kl(candidate) <= config.max_kl)
                chosen = torch.where(accept, torch.full_like(chosen, fraction), chosen)
                found |= accept
                if bool(found.all()):
                    break
            final = _unflat(old_flat + chosen[:, None] * full_step, old)
            for p, value in zip(params, final):
                p.copy_(value)
            kl = mean_kl(params)
            improvement = surrogate(params) - loss_before
        return {"trpo/kl": kl, "trpo/surrogate_improvement": improvement, "trpo/step_fraction": chosen,
                "trpo/log_std": self.log_std.detach().mean(dim=(1, 2))}

    def value_step(self, observations: torch.Tensor, value_targets: torch.Tensor) -> Metrics:
        loss = torch.zeros(self.n_seeds, device=self.device)
        for _ in range(self.config.value_iterations):
            loss = (tanh_mlp(self.value_params, observations)[..., 0] - value_targets).pow(2).mean(dim=1)
            self.value_optimizer.zero_grad(set_to_none=True)
            loss.sum().backward()
            self.value_optimizer.step()
        return {"trpo/value_loss": loss.detach()}

    def copy_from(self, mean_params: Sequence[torch.Tensor], log_std: torch.Tensor,
                  value_params: Sequence[torch.Tensor]) -> None:
        """Start from another agent's (trained) policy and value function, e.g. for fine-tuning."""
        with torch.no_grad():
            for p, value in zip([*self.mean_params, self.log_std, *self.value_params],
                                [*mean_params, log_std, *value_params]):
                p.copy_(value)

    # --- checkpoints -----------------------------------------------------------------------

    def state_dict(self, prefix: str) -> dict[str, torch.Tensor]:
        from baselines.checkpoint import optimizer_tensors

        state = {f"{prefix}.mean.{i}": p.detach() for i, p in enumerate(self.mean_params)}
        state[f"{prefix}.log_std"] = self.log_std.detach()
        state |= {f"{prefix}.value.{i}": p.detach() for i, p in enumerate(self.value_params)}
        state[f"{prefix}.generator"] = self.generator.get_state()
        return state | optimizer_tensors(self.value_optimizer, f"{prefix}.value_optimizer")

    def load_state_dict(self, state: dict[str, torch.Tensor], prefix: str) -> None:
        from baselines.checkpoint import load_optimizer_tensors

        self.copy_from([state[f"{prefix}.mean.{i}"] for i in range(len(self.mean_params))], state[f"{prefix}.log_std"],
                       [state[f"{prefix}.value.{i}"] for i in range(len(self.value_params))])
        self.generator.set_state(state[f"{prefix}.generator"])
        load_optimizer_tensors(self.value_optimizer, state, f"{prefix}.value_optimizer")
