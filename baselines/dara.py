"""DARA: dynamics-aware reward augmentation in offline RL (Liu et al., ICLR 2022), the
offline-source-offline-target track's method (ODRL, Lyu et al. 2024, "Offline-Offline" setting).

Two fixed datasets and no interaction: a large one from the source dynamics, a small one from the
target. DARA moves DARC's reward correction offline:

1. DARC's domain classifiers (:mod:`baselines.classifiers`) learn source-dataset against
   target-dataset transitions; their log-ratio estimates ``log p_target(s'|s,a) - log
   p_source(s'|s,a)``;
2. every source reward is augmented, ``r - eta * dr`` with ``dr = log p_source(s'|s,a) / p_target(s'|s,a)``
   (minus the log-ratio): source transitions the target dynamics would not produce lose reward;
   target rewards stay as they are;
3. an offline RL learner trains on the union of the augmented source data and the target data.

The learner is the suite's CQL (:mod:`baselines.cql`: the SAC core with CQL's ``extra_loss``, alpha
2.0, TD weight 1, no entropy backup), composed with the correction through ``reward_correction``
of :func:`baselines.sac.sac_update`. With ``reward_penalty_weight=0`` DARA is CQL on the union of
both datasets, bit for bit with the same random streams (a test checks this against ``cql``).

Chosen where this suite has no copy of the paper (and configurable):

* **Two phases.** The first ``classifier_steps`` = 10,000 steps train only the classifiers (one
  step on a fresh source and target minibatch each); then they are frozen and the remaining steps
  are CQL updates, so the augmented reward is one fixed function of the transition, as DARA's
  augmented dataset is. Every step counts against the budget; a classifier step costs a small
  fraction of a CQL update.
* ``reward_penalty_weight`` (eta) = 0.1: the correction is a shaping term next to the task reward,
  not a replacement; with the soft-clipped logits (``2 tanh``) ``|dr| <= 8``, so a source reward
  moves by at most 0.8 per step.
* Classifiers as H2O's (one hidden layer of 256, ``2 tanh`` clipped logits, input noise 0.1): both
  sides are datasets, as H2O's real side is; DARC's input noise of 1.0 was set for states
  produced online.
* Batches sampled uniformly from the union (target rows first, then source rows), as DARA trains
  on the joined dataset; the target share of a batch is the target share of the data.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import torch

from baselines import cql
from baselines.buffers import DatasetSampler, concat_datasets
from baselines.classifiers import ClassifierConfig, DomainClassifiers
from baselines.limits import FINITE, Limit, integer
from baselines.method import (
    MethodContext,
    OfflineActing,
    require_source_data,
    require_target_data,
)
from baselines.sac import Batch, Metrics, SACConfig, sac_update


@dataclasses.dataclass
class Config:
    sac: SACConfig = dataclasses.field(default_factory=lambda: SACConfig(backup_entropy=False))
    """SAC's settings, with CQL's ``backup_entropy=False``."""
    min_q_weight: float = 2.0
    """CQL's alpha (:class:`baselines.cql.Config`)."""
    n_action_samples: int = 10
    classifier: ClassifierConfig = dataclasses.field(default_factory=lambda: ClassifierConfig(input_noise_std=0.1))
    reward_penalty_weight: float = 0.1
    """eta: source rewards become ``r - eta * dr``."""
    classifier_steps: int = 10_000
    """Steps that train only the classifiers, before they are frozen and the CQL updates start."""

    LIMITS: ClassVar[dict[str, Limit]] = cql.Config.LIMITS | {
        "reward_penalty_weight": FINITE, "classifier_steps": integer(0)}

    def learner_config(self) -> cql.Config:
        return cql.Config(sac=self.sac, min_q_weight=self.min_q_weight, n_action_samples=self.n_action_samples)

    def budget_warnings(self, algo: str, steps: int) -> list[str]:
        if steps <= self.classifier_steps:
            return [(f"--steps {steps} is not above classifier_steps={self.classifier_steps}: this {algo} run only "
                     "trains its classifiers and deploys its untrained initial policy; the minimum useful budget is "
                     f"more than {self.classifier_steps} steps (or lower it with --set classifier_steps=N)")]
        return []


class DARA(OfflineActing):
    name = "DARA"
    interaction = "none"
    target_step_every = None

    def __init__(self, config: Config, context: MethodContext) -> None:
        self.config = config
        target = require_target_data(context, "dara")
        source = require_source_data(context, "dara")
        self.n_target = int(target.rewards.shape[0])
        # The learner samples the union through CQL's own sampler (stream "target"), so that with
        # no correction it draws exactly what cql draws on the joined dataset.
        self.learner = cql.CQL(config.learner_config(),
                               dataclasses.replace(context, target_data=concat_datasets(target, source)))
        self.agent = self.learner.agent
        self.classifiers = DomainClassifiers(context.observation_dim, context.action_dim, context.seeds,
                                             config.classifier, device=context.device)
        seeds = len(context.seeds)
        self.classifier_source = DatasetSampler(source, seeds, context.stream("dara-source"), context.device)
        self.classifier_target = DatasetSampler(target, seeds, context.stream("dara-target"), context.device)

    def reward_correction(self, batch: Batch, from_source: torch.Tensor) -> torch.Tensor:
        """``-eta * dr`` on the source rows of ``batch`` (``from_source``, ``[S, B]`` bool), 0 on the
        target rows, ``[S, B]``."""
        log_ratio = self.classifiers.log_ratio(batch.observations, batch.actions, batch.next_observations).mean(dim=1)
        return self.config.reward_penalty_weight * log_ratio * from_source

    def train_step(self, step: int) -> Metrics:
        batch_size = self.config.sac.batch_size
        if step < self.config.classifier_steps:
            return self.classifiers.update(self.classifier_source.sample(batch_size),
                                           self.classifier_target.sample(batch_size))
        batch, rows = self.learner.data.sample_with_index(batch_size)
        from_source = rows >= self.n_target
        correction = self.reward_correction(batch, from_source)
        metrics = sac_update(self.agent, batch, reward_correction=correction,
                             extra_loss=self.learner.conservative_penalty(batch), td_loss_weight=cql.TD_LOSS_WEIGHT)
        source_rows = from_source.sum().clamp(min=1)
        return metrics | {"dara/reward_correction": correction.sum() / source_rows,
                          "dara/source_fraction": from_source.float().mean()}

    def state_dict(self) -> dict[str, torch.Tensor]:
        return (self.learner.state_dict() | self.classifiers.state_dict("classifiers")
                | self.classifier_source.state_dict("classifier_source")
                | self.classifier_target.state_dict("classifier_target"))

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.learner.load_state_dict(state)
        self.classifiers.load_state_dict(state, "classifiers")
        self.classifier_source.load_state_dict(state, "classifier_source")
        self.classifier_target.load_state_dict(state, "classifier_target")


def build(config: Config, context: MethodContext) -> DARA:
    return DARA(config, context)
