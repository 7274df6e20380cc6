"""Rollouts: episodes for a dataset (in the target, or in the source for ``source`` data), and
returns for reference scores.

Episode ``i`` of a dataset resets with seed ``recipe.seed + i``; uniform-random actions and the
behaviour policy's action noise each draw from their own generator seeded from the recipe.
Nothing else is random, so the same recipe gives the same transitions on the same platform and
MuJoCo version.

Per episode, ``infos`` follows Minari's layout (row 0 from ``reset``, row ``t + 1`` from step
``t``) and holds the full physics state of every observation (``state``), so step ``t`` goes from
``state[t]`` to ``state[t + 1]`` under ``actions[t]``, plus every scalar the env reports per step
(reward terms, positions) and, on targets with action-channel effects, the command the physics
really received (``applied_action``). Keys a reset does not report are NaN in row 0.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator

import gymnasium
import numpy as np
from minari.data_collector.episode_buffer import EpisodeBuffer

from offdyn_bench.datasets.policies import Policy, UniformRandomPolicy, derived_seed
from offdyn_bench.errors import OffdynError

# prev_state is state[t] of the row before: stored once, checked equal while collecting.
_REDUNDANT_INFO = ("prev_state",)


def _as_float_array(value: object) -> np.ndarray | None:
    """A numeric info value as a float64 array, or None for anything non-numeric."""
    if isinstance(value, (bool, np.bool_)):
        return np.asarray(float(value))
    if isinstance(value, (int, float, np.integer, np.floating)):
        return np.asarray(float(value))
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
        return value.astype(np.float64)
    return None


@dataclasses.dataclass
class _InfoColumns:
    """Infos of one episode, collected as columns with a fixed key set."""

    rows: dict[str, list[np.ndarray]] = dataclasses.field(default_factory=dict)
    length: int = 0

    def add(self, info: dict) -> None:
        for key, value in info.items():
            if key in _REDUNDANT_INFO:
                continue
            array = _as_float_array(value)
            if array is None:
                continue
            if key not in self.rows:
                # A key first seen on a step: earlier rows (the reset) are NaN.
                self.rows[key] = [np.full(array.shape, np.nan)] * self.length
            self.rows[key].append(array)
        self.length += 1
        for key, column in self.rows.items():
            if len(column) < self.length:
                raise OffdynError(f"info key {key!r} is missing from a step; infos must report the same keys "
                                  "on every step to be stored")

    def to_arrays(self) -> dict[str, np.ndarray | list[float]]:
        # Scalars go to Minari as lists of floats: its Arrow storage writes an (n,) array's
        # shape as "" and then cannot read it back (minari 0.5.4).
        return {key: np.stack(column) if column[0].ndim else [float(x) for x in column]
                for key, column in sorted(self.rows.items())}


def run_episode(env: gymnasium.Env, policy: Policy, *, seed: int, max_steps: int | None = None,
                action_noise: Callable[[np.ndarray], np.ndarray] | None = None,
                episode_id: int | None = None, step_in_space_dtype: bool = True) -> EpisodeBuffer:
    """One episode from ``reset(seed=seed)`` until it ends or ``max_steps`` transitions are in.

    Actions are stored in the action space's dtype. ``step_in_space_dtype=False`` steps the env
    with the float64 action instead (a replay of a trainer that stepped so); the caller checks
    that storing it in the space's dtype loses nothing."""
    space = env.action_space
    assert isinstance(space, gymnasium.spaces.Box)
    obs, info = env.reset(seed=seed)
    start_episode = getattr(policy, "start_episode", None)
    if start_episode is not None:  # a behaviour with memory (the human operator) starts afresh, seeded
        start_episode(seed)
    observations = [obs]
    actions, rewards, terminations, truncations = [], [], [], []
    infos = _InfoColumns()
    infos.add(info)
    previous_state = info.get("state")
    while True:
        action = np.asarray(policy(obs), dtype=np.float64)
        if action_noise is not None:
            action = action_noise(action)
        # Store exactly what the env received: clipped to the box, in the space's dtype.
        clipped = np.clip(action, space.low, space.high)
        action = clipped.astype(space.dtype)
        obs, reward, terminated, truncated, info = env.step(action if step_in_space_dtype else clipped)
        if previous_state is not None and not np.array_equal(info.get("prev_state"), previous_state):
            raise OffdynError("the env's prev_state differs from the state it reported after the last step; "
                              "a dataset could not restart the simulator exactly")
        previous_state = info.get("state")
        steps = len(actions) + 1
        budget_reached = max_steps is not None and steps >= max_steps
        observations.append(obs)
        actions.append(action)
        rewards.append(float(reward))
        terminations.append(bool(terminated))
        truncations.append(bool(truncated or (budget_reached and not terminated)))
        infos.add(info)
        if terminated or truncated or budget_reached:
            break
    return EpisodeBuffer(
        id=episode_id, seed=seed,
        observations=stack_observations(observations), actions=np.stack(actions),
        rewards=np.asarray(rewards, dtype=np.float64),
        terminations=np.asarray(terminations), truncations=np.asarray(truncations),
        infos=infos.to_arrays(),
    )


def stack_observations(observations: list) -> np.ndarray | dict:
    """One array per episode, or for a ``Dict`` observation space (AntMaze's goal-conditioned
    observations) a dict of them, key by key, as Minari stores dict observations."""
    first = observations[0]
    if isinstance(first, dict):
        return {key: stack_observations([observation[key] for observation in observations]) for key in first}
    return np.stack(observations)


def gaussian_action_noise(std: float, seed: int) -> Callable[[np.ndarray], np.ndarray] | None:
    if std == 0:
        return None
    rng = np.random.default_rng(seed)
    return lambda action: action + rng.normal(0.0, std, size=action.shape)


def collect_transitions(env: gymnasium.Env, policy: Policy, *, num_transitions: int, seed: int,
                        action_noise: Callable[[np.ndarray], np.ndarray] | None = None,
                        on_step: Callable[[int], None] | None = None,
                        first_episode: int = 0) -> Iterator[EpisodeBuffer]:
    """Episodes until exactly ``num_transitions`` are in; the last one is cut (and marked
    truncated) when the budget ends inside it. Episode ``i`` (counted from ``first_episode``,
    which lets several behaviours fill one dataset) resets with seed ``seed + i``."""
    total = 0
    episode = first_episode
    while total < num_transitions:
        buffer = run_episode(env, policy, seed=seed + episode, max_steps=num_transitions - total,
                             action_noise=action_noise, episode_id=episode)
        total += len(buffer.rewards)
        episode += 1
        if on_step is not None:
            on_step(len(buffer.rewards))
        yield buffer


LEVEL_INFO = "behaviour_level"
"""The infos column of a dataset collected in levels (``skill-mixture``, ``medium-expert``) that
says which level acted: its index in the recipe's order."""


@dataclasses.dataclass(frozen=True)
class Level:
    """One level of a dataset collected in levels: who acts, and with how much action noise."""

    name: str
    actor: Policy
    description: dict
    """What the level is, for the dataset's metadata (actions, noise, its seeds)."""
    noise_std: float | None = None
    noise_seed: list[int] | None = None


def collect_levels(env: gymnasium.Env, levels: list[Level], *, num_transitions: int, seed: int,
                   on_step: Callable[[int], None] | None = None) -> tuple[list[EpisodeBuffer], list[dict]]:
    """Equal shares of ``num_transitions`` from each level, one after the other (episode seeds run
    on across levels: episode ``i`` resets with ``seed + i``), every transition labelled with its
    level's index in the infos (:data:`LEVEL_INFO`); and per level what it was and how it scored
    (the mean return of its complete episodes)."""
    episodes: list[EpisodeBuffer] = []
    described: list[dict] = []
    share, extra = divmod(num_transitions, len(levels))
    for index, level in enumerate(levels):
        noise = (None if level.noise_std is None
                 else gaussian_action_noise(level.noise_std, derived_seed(level.noise_seed or [])))
        count = share + (1 if index < extra else 0)
        collected = list(collect_transitions(env, level.actor, num_transitions=count, seed=seed,
                                             action_noise=noise, on_step=on_step, first_episode=len(episodes)))
        episodes += [dataclasses.replace(e, infos={**e.infos, LEVEL_INFO: [float(index)] * (len(e.rewards) + 1)})
                     for e in collected]
        # Every episode but the last ended on its own; the last one did only if it terminated.
        complete = [float(np.sum(e.rewards)) for e in collected[:-1]]
        complete += [float(np.sum(collected[-1].rewards))] if collected[-1].terminations[-1] else []
        described.append({"level": level.name, "index": index, **level.description, "transitions": count,
                          "episodes": len(collected),
                          "mean_return_of_complete_episodes": float(np.mean(complete)) if complete else None})
    return episodes, described


def episode_returns(env: gymnasium.Env, policy: Policy, *, episodes: int, seed: int) -> list[float]:
    """Undiscounted return of ``episodes`` full episodes with seeds ``seed, seed + 1, ...``."""
    returns = []
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        total, done = 0.0, False
        while not done:
            action = np.clip(np.asarray(policy(obs)), env.action_space.low, env.action_space.high)  # type: ignore[attr-defined]
            obs, reward, terminated, truncated, _ = env.step(action.astype(env.action_space.dtype))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    return returns


def random_reference_returns(env: gymnasium.Env, *, episodes: int, first_seed: int) -> tuple[list[float], list[int]]:
    """Returns of uniform-random actions on episode seeds ``first_seed ...``, its generator seeded
    from ``[first_seed, 1]`` (the datasets' reference-score protocol); and that generator seed."""
    space = env.action_space
    assert isinstance(space, gymnasium.spaces.Box)
    rng_seed = [first_seed, 1]
    policy = UniformRandomPolicy(space.low, space.high, seed=derived_seed(rng_seed))
    return episode_returns(env, policy, episodes=episodes, seed=first_seed), rng_seed
