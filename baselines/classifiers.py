"""Domain classifiers q(target | s, a) and q(target | s, a, s'), as in DARC.

Shared by DARC, DAP, DAP+U (an ensemble of them) and H2O (its "discriminators"). Following DARC
and H2O Appendix B.1:

* each network outputs two logits (source, target), soft-clipped by ``2 tanh`` to [-2, 2] as in
  H2O's code (``soft_clip_logits``; DARC's original code uses the raw logits);
* the (s, a, s') logits are built *on* the (s, a) logits -- ``sas = 2 tanh(f(s, a, s')) +
  sa`` -- so the (s, a, s') classifier's gradient also trains the (s, a) network (the residual
  form of the original);
* Gaussian noise is added to every input while training, which keeps the classifiers from
  separating the domains on tiny state differences;
* both are trained with cross-entropy on equal numbers of source and target transitions;
* ensemble members (DAP+U) are independent: each draws its own input noise, and a caller can
  hand each member its own bootstrap minibatch (``member_batches``), so members differ in more than
  their initialisation.

By Bayes' rule, ``log p_target(s'|s,a) - log p_source(s'|s,a) = [log q(t|s,a,s') - log
q(s|s,a,s')] - [log q(t|s,a) - log q(s|s,a)]``: :meth:`DomainClassifiers.log_ratio`. With the residual
form this equals the difference of the two soft-clipped (s, a, s') residual logits.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import ClassVar

import torch
import torch.nn.functional as F

from baselines.limits import NON_NEGATIVE, POSITIVE, Limit, integer, layer_sizes
from baselines.networks import Params, init_mlp, mlp
from baselines.sac import Batch, Metrics, seed_generator

SOURCE, TARGET = 0, 1


@dataclasses.dataclass
class ClassifierConfig:
    hidden_sizes: tuple[int, ...] = (256,)
    """One hidden layer of 256 (H2O Table 3). DARC's original code: 32 (see
    :func:`baselines.darc.published_config`)."""
    lr: float = 3e-4
    input_noise_std: float = 1.0
    """DARC's default Gaussian input noise; H2O uses 0.1."""
    ensemble_size: int = 1
    """Independently initialised classifier pairs per seed (DAP+U's deep ensemble)."""
    soft_clip_logits: bool = True
    """True: logits ``2 tanh(f)`` in [-2, 2] (H2O's code, which bounds the reward correction to
    +-8); False: raw logits, as in DARC's original code."""

    LIMITS: ClassVar[dict[str, Limit]] = {"hidden_sizes": layer_sizes(allow_empty=True), "lr": POSITIVE,
                                          "input_noise_std": NON_NEGATIVE, "ensemble_size": integer(1)}


class DomainClassifiers:
    """``ensemble_size`` classifier pairs for each of ``len(seeds)`` seeds (members ``[S*K]``)."""

    def __init__(self, observation_dim: int, action_dim: int, seeds: Sequence[int],
                 config: ClassifierConfig, stream: int = 1, device: torch.device | str = "cpu") -> None:
        self.config = config
        self.device = torch.device(device)
        self.n_seeds, self.ensemble_size = len(seeds), config.ensemble_size
        # Distinct streams per seed and ensemble member; ``stream`` separates classifier sets.
        inits = [seed_generator(1_000_003 * stream + 7_919 * s + k)
                 for s in seeds for k in range(config.ensemble_size)]
        hidden = list(config.hidden_sizes)
        self.sa_params: Params = _on(init_mlp(inits, [observation_dim + action_dim, *hidden, 2]), self.device)
        self.sas_params: Params = _on(init_mlp(inits, [2 * observation_dim + action_dim, *hidden, 2]), self.device)
        self.optimizer = torch.optim.Adam(self.sa_params + self.sas_params, lr=config.lr, foreach=True)
        self.generator = seed_generator(10_007 * stream + seeds[0], self.device)

    def _per_member(self, x: torch.Tensor) -> torch.Tensor:
        """``[S, B, d]`` -> ``[S*K, B, d]``: every ensemble member of a seed sees that seed's batch."""
        seeds, batch, width = x.shape
        k = self.ensemble_size
        return x.unsqueeze(1).expand(seeds, k, batch, width).reshape(seeds * k, batch, width)

    def _members(self, x: torch.Tensor, member_batches: bool) -> torch.Tensor:
        """``[S, B, d]`` -> ``[S*K, B, d]`` (every member sees its seed's batch) or, with
        ``member_batches``, ``[S, K*B, d]`` -> ``[S*K, B, d]`` (member k gets the k-th block)."""
        if not member_batches:
            return self._per_member(x)
        seeds, rows, width = x.shape
        return x.reshape(seeds * self.ensemble_size, rows // self.ensemble_size, width)

    def _head(self, outputs: torch.Tensor) -> torch.Tensor:
        return 2.0 * torch.tanh(outputs) if self.config.soft_clip_logits else outputs

    def logits(self, observations: torch.Tensor, actions: torch.Tensor, next_observations: torch.Tensor,
               noise_std: float = 0.0, member_batches: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(s, a) and (s, a, s') logits, ``[S*K, B, 2]`` each; ``noise_std`` > 0 while training
        (each member draws its own noise)."""
        sa = self._members(torch.cat([observations, actions], dim=-1), member_batches)
        sas = self._members(torch.cat([observations, actions, next_observations], dim=-1), member_batches)
        if noise_std > 0:
            sa = sa + noise_std * torch.randn(sa.shape, generator=self.generator, device=sa.device)
            sas = sas + noise_std * torch.randn(sas.shape, generator=self.generator, device=sas.device)
        sa_logits = self._head(mlp(self.sa_params, sa))
        sas_logits = self._head(mlp(self.sas_params, sas)) + sa_logits
        return sa_logits, sas_logits

    def update(self, source: Batch, target: Batch, member_batches: bool = False) -> Metrics:
        """One cross-entropy step on source (label 0) and target (label 1) transitions.

        ``member_batches``: the batches are ``[S, K*B, ...]``, one bootstrap minibatch of B per
        ensemble member (DAP+U), instead of one ``[S, B, ...]`` minibatch all members share."""
        if member_batches:
            # Interleave per member: member k's rows are its source block then its target block.
            def per_member(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
                k = self.ensemble_size
                a = a.reshape(a.shape[0], k, -1, *a.shape[2:])
                b = b.reshape(b.shape[0], k, -1, *b.shape[2:])
                return torch.cat([a, b], dim=2).flatten(1, 2)
        else:
            def per_member(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
                return torch.cat([a, b], dim=1)
        observations = per_member(source.observations, target.observations)
        actions = per_member(source.actions, target.actions)
        next_observations = per_member(source.next_observations, target.next_observations)
        labels = per_member(torch.full(source.rewards.shape, SOURCE, device=source.rewards.device),
                            torch.full(target.rewards.shape, TARGET, device=target.rewards.device))
        labels = self._members(labels.unsqueeze(-1), member_batches).squeeze(-1)
        sa_logits, sas_logits = self.logits(observations, actions, next_observations, self.config.input_noise_std,
                                            member_batches)
        sa_loss = F.cross_entropy(sa_logits.flatten(0, 1), labels.flatten(), reduction="none").view(labels.shape)
        sas_loss = F.cross_entropy(sas_logits.flatten(0, 1), labels.flatten(), reduction="none").view(labels.shape)
        loss = (sa_loss.mean(dim=1) + sas_loss.mean(dim=1)).sum()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        with torch.no_grad():
            accuracy = (sas_logits.argmax(-1) == labels).float().mean()
        return {"classifier/sa_loss": sa_loss.detach().mean(), "classifier/sas_loss": sas_loss.detach().mean(),
                "classifier/sas_accuracy": accuracy}

    def log_ratio(self, observations: torch.Tensor, actions: torch.Tensor,
                  next_observations: torch.Tensor) -> torch.Tensor:
        """``log p_target(s'|s,a) - log p_source(s'|s,a)`` per member, ``[S, K, B]`` (no gradient)."""
        with torch.no_grad():
            sa_logits, sas_logits = self.logits(observations, actions, next_observations)
            sa_log_probs, sas_log_probs = sa_logits.log_softmax(-1), sas_logits.log_softmax(-1)
            ratio = (sas_log_probs[..., TARGET] - sas_log_probs[..., SOURCE]
                     - sa_log_probs[..., TARGET] + sa_log_probs[..., SOURCE])
        return ratio.view(self.n_seeds, self.ensemble_size, -1)

    def target_log_prob_sa(self, observations: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """``log q(target | s, a)`` per member, ``[S, K, B]`` (no gradient): DAP+U's uncertainty input."""
        with torch.no_grad():
            sa = torch.cat([observations, actions], dim=-1)
            log_probs = self._head(mlp(self.sa_params, self._per_member(sa))).log_softmax(-1)
        return log_probs[..., TARGET].view(self.n_seeds, self.ensemble_size, -1)

    def target_log_prob_sas(self, observations: torch.Tensor, actions: torch.Tensor,
                            next_observations: torch.Tensor) -> torch.Tensor:
        """``log q(target | s, a, s')`` per member, ``[S, K, B]`` (no gradient)."""
        with torch.no_grad():
            _, sas_logits = self.logits(observations, actions, next_observations)
        return sas_logits.log_softmax(-1)[..., TARGET].view(self.n_seeds, self.ensemble_size, -1)

    def state_dict(self, prefix: str) -> dict[str, torch.Tensor]:
        from baselines.checkpoint import optimizer_tensors

        state = {f"{prefix}.sa.{i}": p.detach() for i, p in enumerate(self.sa_params)}
        state |= {f"{prefix}.sas.{i}": p.detach() for i, p in enumerate(self.sas_params)}
        state[f"{prefix}.generator"] = self.generator.get_state()
        return state | optimizer_tensors(self.optimizer, f"{prefix}.optimizer")

    def load_state_dict(self, state: dict[str, torch.Tensor], prefix: str) -> None:
        from baselines.checkpoint import load_optimizer_tensors

        with torch.no_grad():
            for name, params in (("sa", self.sa_params), ("sas", self.sas_params)):
                for i, p in enumerate(params):
                    p.copy_(state[f"{prefix}.{name}.{i}"])
        self.generator.set_state(state[f"{prefix}.generator"])
        load_optimizer_tensors(self.optimizer, state, f"{prefix}.optimizer")


def _on(params: Params, device: torch.device) -> Params:
    """Initial weights are drawn on the CPU (the same on every device), then moved."""
    return params if device.type == "cpu" else [p.detach().to(device).requires_grad_() for p in params]
