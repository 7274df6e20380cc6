"""What a trained run's critics believe, next to what its data earned: a check for runaway values.

A critic trained on a fixed dataset can climb far above any return the task pays, because the
Bellman backup at a dataset state asks the critic about the *policy's* action there, which the
data may never have taken. CQL pushes those values down at the data's own states; H2O pushes
down only its simulated samples and pulls up the real ones (Niu et al. 2022, Eq. 6), so nothing
holds the policy's actions at the real states. This module measures where a run's values stand,
for one checkpoint of a run folder and each of its training seeds (twin critics' minimum, as the
backup uses it):

* ``q_data``: Q on the target dataset's own transitions, beside ``data_return_to_go``, the
  discounted return those very actions earned (Monte Carlo over the data's episodes);
* ``q_policy_at_data_states``: Q of the policy's deterministic action at the dataset's states,
  ``q_random_at_data_states``: of uniformly random actions there (one per state);
* where the checkpoint holds a simulated replay buffer (H2O's, DARC's): ``q_buffer`` on its
  transitions, beside ``buffer_return_to_go`` (what the policies that filled it earned in the
  simulator; episodes are told apart by their termination flags and by a next state that is not
  the following row's state, a reset), and ``q_policy_at_buffer_states``.

A policy action valued far above the data's actions, and both far above the data's return, is the
signature of backups through actions nothing penalises; every action valued alike, and far above
what was earned, is values drifting with the states. A critic that backs up the entropy term
(``backs_up_entropy``) holds entropy bonuses too, and DARC's reward carries its correction, so
their values differ from a return of rewards alone by design.

Runs whose critic does not take (observation, action), such as DAP's critic of (a_s, a_t), are
refused with a message saying so.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from baselines.checkpoint import latest_checkpoint, load_checkpoint
from baselines.networks import mlp
from baselines.run_folder import CONFIG_FILE, read_config
from offdyn_bench.envs import flat_observations
from offdyn_bench.errors import OffdynError
from offdyn_bench.tasks import get_task

RANDOM_ACTIONS_SEED = 0


@dataclasses.dataclass(frozen=True)
class CriticValues:
    """One training seed's critic at one checkpoint; every value a mean over rows."""

    seed: int
    step: int
    discount: float
    backs_up_entropy: bool
    data_rows: int
    data_return_to_go: float
    """Discounted return-to-go of the data's own actions; a lower bound on rows of episodes that
    ended by truncation or at the end of the file (their tail after that is unknown, counted 0)."""
    data_rows_terminated: float
    """Fraction of the rows in episodes that ended by termination, where the return-to-go is exact."""
    q_data: float
    q_policy_at_data_states: float
    q_random_at_data_states: float
    buffer_rows: int | None
    buffer_return_to_go: float | None
    buffer_rows_terminated: float | None
    q_buffer: float | None
    q_policy_at_buffer_states: float | None


def discounted_return_to_go(rewards: np.ndarray, terminations: np.ndarray, truncations: np.ndarray,
                            discount: float) -> tuple[np.ndarray, np.ndarray]:
    """Per row, the discounted sum of the rewards from that row to its episode's end, and whether
    that episode ended by termination (so the sum is exact). Rows are episodes laid end to end; an
    episode ends at a termination or truncation flag, or at the last row."""
    rewards = np.asarray(rewards, dtype=np.float64)
    terminations, truncations = np.asarray(terminations, dtype=bool), np.asarray(truncations, dtype=bool)
    if not (rewards.shape == terminations.shape == truncations.shape) or rewards.ndim != 1:
        raise OffdynError(f"rewards, terminations and truncations must be 1-dimensional and of one length, got "
                          f"shapes {rewards.shape}, {terminations.shape} and {truncations.shape}")
    ends = terminations | truncations
    if not 0.0 <= discount <= 1.0:
        raise OffdynError(f"discount={discount}: expected a number in [0, 1]")
    returns = np.empty_like(rewards)
    exact = np.empty(rewards.shape, dtype=bool)
    following, following_exact = 0.0, False
    for i in range(len(rewards) - 1, -1, -1):
        if ends[i] or i == len(rewards) - 1:
            following, following_exact = 0.0, bool(terminations[i])
        following = rewards[i] + discount * following
        returns[i], exact[i] = following, following_exact
    return returns, exact


def _buffer_in_order(tensors: dict[str, torch.Tensor], member: int) -> dict[str, np.ndarray]:
    """One seed's replay buffer rows oldest first (a full ring buffer starts at its write position),
    with the episode ends that its stored flags and its resets imply."""
    size, position = (int(x) for x in tensors["buffer.counters"])
    rows = {name: tensors[f"buffer.{name}"][member].double().numpy()
            for name in ("observations", "actions", "rewards", "next_observations", "terminations")}
    if 0 < position < size:  # wrapped: the oldest row is the next to be overwritten
        rows = {name: np.roll(array, -position, axis=0) for name, array in rows.items()}
    resets = np.zeros(size, dtype=bool)
    resets[:-1] = np.any(rows["next_observations"][:-1] != rows["observations"][1:], axis=1)
    rows["truncations"] = resets & (rows["terminations"] == 0)
    return rows


def _params(tensors: dict[str, torch.Tensor], name: str) -> list[torch.Tensor]:
    keys = sorted((k for k in tensors if k.startswith(f"{name}.") and k.split(".")[1].isdigit()),
                  key=lambda k: int(k.split(".")[1]))
    return [tensors[k].float() for k in keys]


def _min_q(critic: list[torch.Tensor], member: int, observations: torch.Tensor, actions: torch.Tensor) -> float:
    twins = [p[2 * member:2 * member + 2] for p in critic]
    inputs = torch.cat([observations, actions], dim=-1).expand(2, -1, -1)
    return float(mlp(twins, inputs).squeeze(-1).min(dim=0).values.mean())


def _policy_actions(actor: list[torch.Tensor], member: int, observations: torch.Tensor) -> torch.Tensor:
    mean, _ = mlp([p[member:member + 1] for p in actor], observations[None]).chunk(2, dim=-1)
    return torch.tanh(mean[0])


def read_critic_values(run_dir: str | Path, checkpoint: str | Path | None = None) -> list[CriticValues]:
    """The critic values of ``run_dir``'s newest complete checkpoint (or ``checkpoint``, a folder
    under it), one entry per training seed. The target dataset is loaded as the run loaded it."""
    from baselines.data import load_dataset
    from baselines.train import DATASET_SEED

    run_dir = Path(run_dir)
    if not (run_dir / CONFIG_FILE).exists():
        raise OffdynError(f"{str(run_dir)!r} is not a training run folder (no {CONFIG_FILE})")
    config = read_config(run_dir)
    if not isinstance(config.get("task"), str) or not (
            isinstance(config.get("seeds"), list) and all(isinstance(seed, int) for seed in config["seeds"])):
        raise OffdynError(f"{str(run_dir)!r}: config.json does not name a task and a list of integer seeds; "
                          "expected the config.json that offdyn-bench train writes")
    if not config.get("dataset"):
        raise OffdynError(f"{str(run_dir)!r} trained without a target dataset ({config.get('algo')}); "
                          "there is no data to hold its values against")
    path = latest_checkpoint(run_dir) if checkpoint is None else Path(checkpoint)
    if path is None:
        raise OffdynError(f"{str(run_dir)!r} has no complete checkpoint")
    tensors, trainer = load_checkpoint(path)
    pair = get_task(str(config["task"]))
    env = flat_observations(pair.make("target"))
    observation_dim = int(np.prod(env.observation_space.shape))
    action_dim = int(np.prod(env.action_space.shape))
    action_space = env.action_space
    env.close()
    actor, critic = _params(tensors, "actor"), _params(tensors, "critic")
    if not actor or not critic:
        raise OffdynError(f"{path}: holds no SAC actor and critic (actor.*, critic.*)")
    if critic[0].shape[1] != observation_dim + action_dim or actor[-1].shape[-1] != 2 * action_dim:
        raise OffdynError(f"{path}: the critic takes {critic[0].shape[1]} inputs and the actor gives "
                          f"{actor[-1].shape[-1]} outputs; expected {observation_dim + action_dim} (observation and "
                          f"action) and {2 * action_dim} (a Gaussian over one action), as SAC, CQL, H2O and DARC "
                          f"have ({config.get('algo')}'s critic values are not read here)")
    sac_config = config["config"].get("sac", {})
    discount = float(sac_config.get("discount", 0.99))
    dataset, _ = load_dataset(str(config["dataset"]), pair, DATASET_SEED)
    returns, exact = discounted_return_to_go(dataset.rewards, dataset.terminations, dataset.truncations, discount)
    data = dataset.to_batch(action_space)
    random_actions = torch.rand(data.actions.shape, generator=torch.Generator().manual_seed(RANDOM_ACTIONS_SEED)) * 2 - 1
    has_buffer = "buffer.observations" in tensors and int(tensors["buffer.counters"][0]) > 0
    out = []
    with torch.no_grad():
        for member, seed in enumerate(config["seeds"]):
            buffer_values: tuple[int | None, float | None, float | None, float | None, float | None] = (
                None, None, None, None, None)
            if has_buffer:
                rows = _buffer_in_order(tensors, member)
                buffer_returns, buffer_exact = discounted_return_to_go(
                    rows["rewards"], rows["terminations"], rows["truncations"], discount)
                states = torch.as_tensor(rows["observations"], dtype=torch.float32)
                buffer_values = (len(buffer_returns), float(buffer_returns.mean()), float(buffer_exact.mean()),
                                 _min_q(critic, member, states, torch.as_tensor(rows["actions"], dtype=torch.float32)),
                                 _min_q(critic, member, states, _policy_actions(actor, member, states)))
            out.append(CriticValues(
                seed=int(seed), step=int(trainer.get("step", -1)), discount=discount,
                backs_up_entropy=bool(sac_config.get("backup_entropy", True)), data_rows=len(returns),
                data_return_to_go=float(returns.mean()), data_rows_terminated=float(exact.mean()),
                q_data=_min_q(critic, member, data.observations, data.actions),
                q_policy_at_data_states=_min_q(critic, member, data.observations,
                                               _policy_actions(actor, member, data.observations)),
                q_random_at_data_states=_min_q(critic, member, data.observations, random_actions),
                buffer_rows=buffer_values[0], buffer_return_to_go=buffer_values[1],
                buffer_rows_terminated=buffer_values[2], q_buffer=buffer_values[3],
                q_policy_at_buffer_states=buffer_values[4]))
    return out
