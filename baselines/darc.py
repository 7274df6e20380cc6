"""DARC: off-dynamics RL with a reward correction from domain classifiers (Eysenbach et al. 2021;
DAP paper Section 3.2, H2O paper Section 6.2 and Appendix B.1).

SAC trains in the source simulator on the corrected reward

    r + dr(s, a, s'),  dr = log q(t|s,a,s') - log q(s|s,a,s') - log q(t|s,a) + log q(s|s,a),

an estimate of ``log p_target(s'|s,a) - log p_source(s'|s,a)``: transitions the target would not
produce are penalised. The classifiers (:mod:`baselines.classifiers`) learn to tell source
transitions from target ones, one step per policy update. Two sources of target data:

* ``target_data="offline"`` (the offline-target track): the target side is the fixed target
  dataset; no target interaction.
* ``target_data="online"`` (the paper's setting): one target step with the current policy per
  ``target_step_every`` = 10 source steps fills a target replay buffer.

Two sets of settings, both explicit fields of :class:`Config`:

* :func:`published_config` (the default of ``darc`` and ``darc-online``): Eysenbach et al.'s
  paper and code (google-research ``darc``): classifiers with one hidden layer of 32 and raw
  logits, input noise std 1.0, reward correction from step ``delta_r_warmup`` = 100,000, SAC with
  reward scale 0.1 and target entropy ``-|A|/2``. At the lite budget (100k steps) the correction
  never starts: that is the published schedule, and ``--set warmup_steps=N`` changes it.
* :func:`h2o_variant_config` (``--set`` the fields it lists, or the Python API): the DARC baseline of
  the H2O paper's code: classifiers of 256 with ``2 tanh`` clipped logits, warm-up 10,000, reward
  scale 1.0 and target entropy ``-|A|``. This was the suite's DARC before issue 9.

Not reproduced: the original online runs first collect 10,000 uniform-random real steps; here the
target buffer fills at the track's one step per ten (the online-target budget counts every target
step), with uniform-random actions during ``random_steps`` like the source side.

Composition with the core: DARC only passes ``reward_correction`` to :func:`baselines.sac.sac_update`.
With ``reward_correction_scale=0`` and SAC's settings it is exactly SAC (a test checks this).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar, Literal

import torch

from baselines.buffers import DatasetSampler, ReplayBuffer
from baselines.classifiers import ClassifierConfig, DomainClassifiers
from baselines.limits import FINITE, Limit, integer, one_of
from baselines.method import MethodContext, SACActing, require_target_data
from baselines.sac import Batch, Metrics, SACAgent, SACConfig, sac_update


PUBLISHED_WARMUP_STEPS = 100_000
"""``delta_r_warmup`` of the original code's README runs."""


def _published_sac() -> SACConfig:
    return SACConfig(reward_scale=0.1, target_entropy_per_action_dim=-0.5)


def _published_classifier() -> ClassifierConfig:
    return ClassifierConfig(hidden_sizes=(32,), soft_clip_logits=False)


@dataclasses.dataclass
class Config:
    """Defaults: :func:`published_config`."""

    sac: SACConfig = dataclasses.field(default_factory=_published_sac)
    """Published: reward scale 0.1, target entropy -|A|/2 (H2O variant: 1.0 and -|A|)."""
    classifier: ClassifierConfig = dataclasses.field(default_factory=_published_classifier)
    """Published: one hidden layer of 32, raw logits, noise 1.0 (H2O variant: 256, 2 tanh)."""
    buffer_size: int = 1_000_000
    random_steps: int = 5_000
    """Uniform-random actions for the first steps; updates start after them."""
    warmup_steps: int = PUBLISHED_WARMUP_STEPS
    """The reward correction is zero before this step (classifiers train from the start).
    Published: 100,000; H2O variant: 10,000."""
    reward_correction_scale: float = 1.0
    target_data: Literal["offline", "online"] = "offline"
    target_step_every: int = 10
    """online: one target step per this many source steps (DARC's published ratio)."""

    LIMITS: ClassVar[dict[str, Limit]] = {
        "buffer_size": integer(1), "random_steps": integer(0), "warmup_steps": integer(0),
        "reward_correction_scale": FINITE, "target_data": one_of("offline", "online"), "target_step_every": integer(1)}


def published_config(target_data: Literal["offline", "online"] = "offline") -> Config:
    """DARC as in Eysenbach et al.'s paper and code (see the module docstring)."""
    return Config(target_data=target_data)


def h2o_variant_config(target_data: Literal["offline", "online"] = "offline") -> Config:
    """The DARC of the H2O paper's code: wider clipped classifiers, a short warm-up, SAC's usual
    reward scale and target entropy. Not "DARC as published"."""
    return Config(sac=SACConfig(), classifier=ClassifierConfig(), warmup_steps=10_000, target_data=target_data)


class DARC(SACActing):
    interaction = "source"

    def __init__(self, config: Config, context: MethodContext) -> None:
        self.config = config
        obs_dim, act_dim = context.observation_dim, context.action_dim
        device = context.device
        self.agent = SACAgent(obs_dim, act_dim, context.seeds, config.sac, device)
        self.buffer = ReplayBuffer(len(context.seeds), config.buffer_size, obs_dim, act_dim,
                                   context.stream("buffer"), device)
        self.classifiers = DomainClassifiers(obs_dim, act_dim, context.seeds, config.classifier, device=device)
        if config.target_data == "online":
            self.target_step_every: int | None = config.target_step_every
            self.target: ReplayBuffer | DatasetSampler = ReplayBuffer(
                len(context.seeds), config.buffer_size, obs_dim, act_dim, context.stream("target"), device)
        elif config.target_data == "offline":
            self.target_step_every = None
            self.target = DatasetSampler(require_target_data(context, "darc (offline)"), len(context.seeds),
                                         context.stream("target"), device)
        else:
            raise ValueError(f"darc: target_data must be 'offline' or 'online', got {config.target_data!r}")

    def record_target(self, observations, stored_actions, rewards, next_observations, terminations) -> None:
        assert isinstance(self.target, ReplayBuffer)
        self.target.add(observations, stored_actions, rewards, next_observations, terminations)

    def reward_correction(self, batch: Batch, step: int) -> torch.Tensor:
        """``scale * dr`` on a source batch (zero during warm-up), ``[S, B]``."""
        if step < self.config.warmup_steps:
            return torch.zeros_like(batch.rewards)
        ratio = self.classifiers.log_ratio(batch.observations, batch.actions, batch.next_observations)
        return self.config.reward_correction_scale * ratio.mean(dim=1)

    def train_step(self, step: int) -> Metrics:
        if step < self.config.random_steps or self.target.size == 0:
            return {}
        batch_size = self.config.sac.batch_size
        source = self.buffer.sample(batch_size)
        metrics = self.classifiers.update(source, self.target.sample(batch_size))
        correction = self.reward_correction(source, step)
        metrics["darc/reward_correction"] = correction.mean()
        return metrics | sac_update(self.agent, source, reward_correction=correction)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return (self.agent.state_dict() | self.buffer.state_dict("buffer")
                | self.classifiers.state_dict("classifiers") | self.target.state_dict("target"))

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.agent.load_state_dict(state)
        self.buffer.load_state_dict(state, "buffer")
        self.classifiers.load_state_dict(state, "classifiers")
        self.target.load_state_dict(state, "target")


def build(config: Config, context: MethodContext) -> DARC:
    return DARC(config, context)
