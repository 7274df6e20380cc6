"""DAP (Dual Action Policy) and DAP+U (DAP with uncertainty-based robust action resampling),
from "Dual Action Policy for Robust Sim-to-Real Reinforcement Learning", Sections 4.1-4.2.

One SAC policy outputs two actions, ``(a_s, a_t)`` (a ``2 x action_dim`` tanh-Gaussian):

* ``a_s`` steps the source simulator, as in plain SAC;
* ``a_t`` is the action the target should take to reproduce the same transition: it enters the
  DARC reward adjustment ``dr(s, a_t, s')`` (classifiers trained on source transitions against
  the target dataset);
* a regulariser ``lambda * mean_i (a_s,i - a_t,i)^2`` keeps them close: by default on the policy's
  mean actions, in the policy loss (``regularized_actions="mean"``), or on the sampled actions, in
  the reward the critic sees, ``r(s, a_s) + dr(s, a_t, s') - lambda * mean_i (a_s,i - a_t,i)^2``
  (``"sampled"``, the suite's choice before issue 9);

* In deployment the target action ``a_t`` (its tanh-mean) acts.

As lambda grows the two actions coincide and the reward is DARC's (tests check both).

DAP+U trains ``ensemble_size`` classifier pairs (own initialisations, minibatches and noise). Their
disagreement ``u(s, a) = std_k log q_k(target | s, a)`` measures epistemic uncertainty; during
training each sampled action ``a`` (both ``a_s`` and ``a_t``) is replaced by a robust action
``a ~ N(a, (beta * u)^2)`` (clipped to the action bounds) before it is used and stored. ``dr`` is
the ensemble mean. Deployment uses the policy's own action.

Composition with the core: a wider action space, a ``reward_correction``, an optional actor-loss
term, and an action transform applied at rollout time. DARC's defaults everywhere else (DAP Section
5.1), in the form this suite used before DARC got its published preset (256-wide clipped classifiers).

The paper leaves four choices open; each is a :class:`Config` field whose docstring says what the
paper says, what was chosen, and the evidence (``baselines/results/``):

* ``classifier_source_action``: which half labels the classifiers' source transitions;
* ``regularized_actions``: the regulariser on sampled actions (in the reward) or on the policy's
  mean actions (in the policy loss);
* ``uncertainty_input``: the (s, a) classifier's disagreement (the only one known when an action
  is chosen; s' is not);
* ensemble members are independent (DAP+U): each gets its own bootstrap minibatch and its own
  input noise (:class:`baselines.classifiers.DomainClassifiers`), not just its own initialisation.

Chosen where the paper's extraction lost the value: lambda = 10 (the paper reports stability over a
range and fixes one value). The regulariser is the *mean* squared difference over action dimensions
so lambda does not depend on the robot; the ensemble has 5 members; resampling starts when the
reward correction does (before it, the classifiers are untrained and their disagreement is
meaningless); ``u`` is per-sample.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import ClassVar, Literal

import torch

from baselines.buffers import DatasetSampler, ReplayBuffer
from baselines.classifiers import ClassifierConfig, DomainClassifiers
from baselines.limits import FINITE, NON_NEGATIVE, Limit, integer, one_of
from baselines.method import MethodContext, deploy_actions, host_deploy_actions, require_target_data, uniform_actions
from baselines.networks import Params, mlp
from baselines.sac import Batch, Metrics, SACAgent, SACConfig, sac_update, seed_generator


@dataclasses.dataclass
class Config:
    sac: SACConfig = dataclasses.field(default_factory=SACConfig)
    classifier: ClassifierConfig = dataclasses.field(default_factory=ClassifierConfig)
    buffer_size: int = 1_000_000
    random_steps: int = 5_000
    warmup_steps: int = 10_000
    """DARC's warm-up: the classifier reward and the action resampling start here."""
    reward_correction_scale: float = 1.0
    regularization_weight: float = 10.0
    """lambda: weight of the mean squared difference between a_s and a_t."""
    uncertainty_scale: float = 0.0
    """beta: spread of the robust action per unit of uncertainty; 0 is DAP, 0.1 is DAP+U's default
    (the paper found 0.05 to 0.10 best and 0.2 unstable)."""
    classifier_source_action: Literal["source", "target"] = "source"
    """Which action stands in the classifiers' source transitions ``(s, a, s')``. The paper: the
    classifiers of DARC (Eq. 3) evaluated at ``a_t``; it does not say which action the source side
    is trained with. "source": ``a_s``, the action that stepped the simulator (the transition that
    happened); "target": ``a_t``, the action ``dr`` is evaluated at. Chosen: "source". Evidence
    (``baselines/results/``, rail-offset-hard, 5 seeds, with ``regularized_actions="sampled"``):
    "target" fell below random on every seed (IQM return 3.0, random 3.6; "source" 37.2). Issue 9's
    probe on kinematic-slider-hard had favoured "target"; not re-tested with "mean"."""
    regularized_actions: Literal["sampled", "mean"] = "mean"
    """Where the regulariser ``lambda * mean (a_s - a_t)^2`` acts. The paper (Eq. 4) adds it to the
    objective without saying on which actions. "sampled" (the default before issue 9): on the
    buffer's sampled actions, as a reward term, which also penalises both halves' variance and so
    fights the entropy tuning; "mean": on the policy's tanh-means, as a policy-loss term (variance
    left to the entropy tuning). Chosen: "mean". Evidence (``baselines/results/``,
    rail-offset-hard, 5 seeds): "mean" reached 1000 on every seed (RL on target: 1000, RL on
    source: IQM 48.8), "sampled" 28.6 to 45.7 (IQM 37.2), below RL on source."""
    uncertainty_input: Literal["sa"] = "sa"
    """The classifiers whose ensemble disagreement is u. The paper: "the standard deviation of the
    log probabilities" of the ensemble, without saying which classifier. Only the (s, a) one can
    be evaluated when the action is resampled, before s' exists, so it is the only choice
    (a field, so the run's config records it)."""

    LIMITS: ClassVar[dict[str, Limit]] = {
        "buffer_size": integer(1), "random_steps": integer(0), "warmup_steps": integer(0),
        "reward_correction_scale": FINITE, "regularization_weight": NON_NEGATIVE, "uncertainty_scale": NON_NEGATIVE,
        "classifier_source_action": one_of("source", "target"), "regularized_actions": one_of("sampled", "mean"),
        "uncertainty_input": one_of("sa")}


def dap_u_config() -> Config:
    return Config(classifier=ClassifierConfig(ensemble_size=5), uncertainty_scale=0.1)


class DAP:
    interaction = "source"
    target_step_every = None

    def __init__(self, config: Config, context: MethodContext) -> None:
        self.config = config
        obs_dim, self.action_dim = context.observation_dim, context.action_dim
        device = context.device
        # The policy's action is (a_s, a_t); the critic sees both.
        self.agent = SACAgent(obs_dim, 2 * self.action_dim, context.seeds, config.sac, device)
        self.buffer = ReplayBuffer(len(context.seeds), config.buffer_size, obs_dim, 2 * self.action_dim,
                                   context.stream("buffer"), device)
        self.classifiers = DomainClassifiers(obs_dim, self.action_dim, context.seeds, config.classifier,
                                             device=device)
        self.target = DatasetSampler(require_target_data(context, "dap"), len(context.seeds),
                                     context.stream("target"), device)
        self.robust_generator = seed_generator(context.stream("robust-actions"), device)

    def split(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(a_s, a_t)`` from a joint action."""
        return actions[..., :self.action_dim], actions[..., self.action_dim:]

    def uncertainty(self, observations: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """``u(s, a)``: std over the ensemble of ``log q(target | s, a)``, ``[S, B]``."""
        return self.classifiers.target_log_prob_sa(observations, actions).std(dim=1)

    def robust_actions(self, observations: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """DAP+U: resample both halves around themselves with std ``beta * u``. ``[S, B, 2A]``."""
        robust = []
        for half in self.split(actions):
            spread = self.config.uncertainty_scale * self.uncertainty(observations, half)
            noise = torch.randn(half.shape, generator=self.robust_generator, device=half.device)
            robust.append((half + spread[..., None] * noise).clamp(-1.0, 1.0))
        return torch.cat(robust, dim=-1)

    def explore(self, observations: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        if step < self.config.random_steps:
            actions = uniform_actions(self.agent.n_seeds, 2 * self.action_dim, self.agent.generator)
        else:
            with torch.no_grad():
                actions = self.agent.sample_actions(observations[:, None])[0]
                if self.config.uncertainty_scale > 0 and self.config.classifier.ensemble_size > 1 \
                        and step >= self.config.warmup_steps:
                    actions = self.robust_actions(observations[:, None], actions)
                actions = actions[:, 0]
        return self.split(actions)[0], actions

    def deploy(self, observations: torch.Tensor) -> torch.Tensor:
        return self.split(deploy_actions(self.agent, observations))[1]

    def host_deploy(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The target half of the joint action, from a CPU copy of the actor."""
        joint = host_deploy_actions(self.agent)
        return lambda observations: self.split(joint(observations))[1]

    def record(self, observations, stored_actions, rewards, next_observations, terminations) -> None:
        self.buffer.add(observations, stored_actions, rewards, next_observations, terminations)

    def record_target(self, *transition) -> None:
        raise RuntimeError("DAP uses the fixed target dataset, not online target transitions")

    def reward_correction(self, batch: Batch, step: int) -> torch.Tensor:
        """``scale * dr(s, a_t, s') - lambda * mean (a_s - a_t)^2``, ``[S, B]`` (the second term only
        with ``regularized_actions="sampled"``)."""
        source_actions, target_actions = self.split(batch.actions)
        if self.config.regularized_actions == "sampled":
            penalty = self.config.regularization_weight * (source_actions - target_actions).pow(2).mean(dim=-1)
        else:
            penalty = torch.zeros_like(batch.rewards)
        if step < self.config.warmup_steps:
            return -penalty
        ratio = self.classifiers.log_ratio(batch.observations, target_actions, batch.next_observations)
        return self.config.reward_correction_scale * ratio.mean(dim=1) - penalty

    def mean_action_penalty(self, actor: Params, observations: torch.Tensor) -> torch.Tensor:
        """``lambda * mean_batch mean_i (tanh mu_s,i - tanh mu_t,i)^2`` per seed, ``[S]``, with
        gradient into the actor (``regularized_actions="mean"``)."""
        mean = torch.tanh(mlp(actor, observations)[..., :2 * self.action_dim])
        source_mean, target_mean = self.split(mean)
        return self.config.regularization_weight * (source_mean - target_mean).pow(2).mean(dim=(1, 2))

    def classifier_batches(self, batch: Batch) -> tuple[Batch, Batch, bool]:
        """The classifiers' (source, target) batches and whether each ensemble member has its own.

        Source transitions carry ``a_s`` or ``a_t`` (``classifier_source_action``). With an
        ensemble, member 0 trains on the policy batch and members 1..K-1 on fresh draws from the
        buffer and the dataset (bootstrap minibatches), so members differ in data, not only in
        initialisation."""
        batch_size, k = self.config.sac.batch_size, self.classifiers.ensemble_size
        if k > 1:
            batch = Batch(*(torch.cat([a, b], dim=1) for a, b in zip(batch, self.buffer.sample((k - 1) * batch_size))))
        source_half, target_half = self.split(batch.actions)
        chosen = source_half if self.config.classifier_source_action == "source" else target_half
        return batch._replace(actions=chosen), self.target.sample(k * batch_size), k > 1

    def train_step(self, step: int) -> Metrics:
        if step < self.config.random_steps:
            return {}
        batch = self.buffer.sample(self.config.sac.batch_size)
        source, target, member_batches = self.classifier_batches(batch)
        metrics = self.classifiers.update(source, target, member_batches=member_batches)
        correction = self.reward_correction(batch, step)
        metrics["dap/reward_correction"] = correction.mean()
        actor_penalty = self.mean_action_penalty if self.config.regularized_actions == "mean" else None
        return metrics | sac_update(self.agent, batch, reward_correction=correction, extra_actor_loss=actor_penalty)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return (self.agent.state_dict() | self.buffer.state_dict("buffer")
                | self.classifiers.state_dict("classifiers") | self.target.state_dict("target")
                | {"robust_generator": self.robust_generator.get_state()})

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.agent.load_state_dict(state)
        self.buffer.load_state_dict(state, "buffer")
        self.classifiers.load_state_dict(state, "classifiers")
        self.target.load_state_dict(state, "target")
        self.robust_generator.set_state(state["robust_generator"])


def build(config: Config, context: MethodContext) -> DAP:
    return DAP(config, context)
