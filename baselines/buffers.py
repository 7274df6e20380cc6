"""Replay buffers batched over seeds, and a sampler over a fixed (shared) dataset.

Both return :class:`baselines.sac.Batch` tensors ``[seeds, batch, ...]`` and draw indices from
their own generator, so sampling never shifts the policy's random stream. Storage, indices and
generator live on one device, so sampling on an accelerator never waits for the host.
"""

from __future__ import annotations

import torch

from baselines.sac import Batch, seed_generator

FIELDS = ("observations", "actions", "rewards", "next_observations", "terminations")


class ReplayBuffer:
    """A ring buffer per seed; all seeds add one transition per step, so they share a size."""

    def __init__(self, n_seeds: int, capacity: int, observation_dim: int, action_dim: int, seed: int,
                 device: torch.device | str = "cpu") -> None:
        self.capacity, self.n_seeds = int(capacity), n_seeds
        self.device = torch.device(device)
        shapes = {"observations": (observation_dim,), "actions": (action_dim,), "rewards": (),
                  "next_observations": (observation_dim,), "terminations": ()}
        self.storage = {k: torch.zeros((n_seeds, self.capacity, *shape), device=self.device)
                        for k, shape in shapes.items()}
        self.size = 0
        self.position = 0
        self.generator = seed_generator(seed, self.device)
        self.seed_index = torch.arange(n_seeds, device=self.device)[:, None]

    def add(self, observations: torch.Tensor, actions: torch.Tensor, rewards: torch.Tensor,
            next_observations: torch.Tensor, terminations: torch.Tensor) -> None:
        """Add one transition per seed (``[seeds, ...]`` each)."""
        for name, value in zip(FIELDS, (observations, actions, rewards, next_observations, terminations)):
            self.storage[name][:, self.position] = value
        self.position = (self.position + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int) -> Batch:
        if self.size == 0:
            raise RuntimeError("cannot sample from an empty replay buffer")
        index = torch.randint(self.size, (self.n_seeds, batch_size), generator=self.generator, device=self.device)
        return Batch(*(self.storage[name][self.seed_index, index] for name in FIELDS))

    def state_dict(self, prefix: str) -> dict[str, torch.Tensor]:
        state = {f"{prefix}.{k}": v[:, :self.size] for k, v in self.storage.items()}
        state[f"{prefix}.counters"] = torch.tensor([self.size, self.position])
        state[f"{prefix}.generator"] = self.generator.get_state()
        return state

    def load_state_dict(self, state: dict[str, torch.Tensor], prefix: str) -> None:
        self.size, self.position = (int(x) for x in state[f"{prefix}.counters"])
        for name, storage in self.storage.items():
            storage[:, :self.size] = state[f"{prefix}.{name}"].to(self.device)
        self.generator.set_state(state[f"{prefix}.generator"])


class DatasetSampler:
    """Uniform minibatches from one fixed dataset, independently for each seed."""

    def __init__(self, data: Batch, n_seeds: int, seed: int, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        self.data, self.n_seeds = Batch(*(field.to(self.device) for field in data)), n_seeds
        self.size = int(data.rewards.shape[0])
        self.generator = seed_generator(seed, self.device)

    def sample(self, batch_size: int) -> Batch:
        return self.sample_with_index(batch_size)[0]

    def sample_with_index(self, batch_size: int) -> tuple[Batch, torch.Tensor]:
        """A minibatch and the dataset rows it came from, ``[seeds, batch]`` (the same draws as
        :meth:`sample`): for a sampler over joined datasets, which rows came from which."""
        index = torch.randint(self.size, (self.n_seeds, batch_size), generator=self.generator, device=self.device)
        return Batch(*(field[index] for field in self.data)), index

    def state_dict(self, prefix: str) -> dict[str, torch.Tensor]:
        return {f"{prefix}.generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, torch.Tensor], prefix: str) -> None:
        self.generator.set_state(state[f"{prefix}.generator"])


def concat_batches(first: Batch, second: Batch) -> Batch:
    """Join two batches along the batch dimension (H2O's half-and-half batches)."""
    return Batch(*(torch.cat([a, b], dim=1) for a, b in zip(first, second)))


def concat_datasets(first: Batch, second: Batch) -> Batch:
    """Join two datasets (``[N, ...]`` fields) row-wise: ``first``'s rows, then ``second``'s (DARA's union)."""
    return Batch(*(torch.cat([a, b], dim=0) for a, b in zip(first, second)))
