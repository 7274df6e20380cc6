"""Batched MLPs: every network carries a leading *member* dimension.

A member is one independent network: one training seed of an actor, one of the twin critics of
one seed, one classifier of an ensemble. Stacking members lets several seeds (and both critics)
train in one process with one batched matrix product per layer (``torch.baddbmm``) instead of a
Python loop over small networks, which is where the vectorised-seeds speed-up comes from.

Parameters are plain lists of tensors ``[W0, b0, W1, b1, ...]`` with ``W: [members, in, out]`` and
``b: [members, 1, out]``; :func:`mlp` is a pure function of them, so a caller can evaluate a
network with detached parameters (the actor's view of the critic) without toggling grad flags.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

Params = list[torch.Tensor]


def init_mlp(generators: Sequence[torch.Generator], sizes: Sequence[int]) -> Params:
    """Parameters of one MLP per generator (a member each), layer sizes ``sizes`` (input first).

    Same initialisation as ``torch.nn.Linear`` (uniform in +-1/sqrt(fan_in) for weights and
    biases); member ``i`` is drawn from ``generators[i]`` only.
    """
    params: Params = []
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
        bound = 1.0 / math.sqrt(fan_in)
        weight = torch.stack([torch.rand(fan_in, fan_out, generator=g) for g in generators])
        bias = torch.stack([torch.rand(1, fan_out, generator=g) for g in generators])
        params += [((weight * 2 - 1) * bound).requires_grad_(), ((bias * 2 - 1) * bound).requires_grad_()]
    return params


def mlp(params: Sequence[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """Forward ``x: [members, batch, in]`` through ReLU hidden layers and a linear output."""
    n_layers = len(params) // 2
    for i in range(n_layers):
        x = torch.baddbmm(params[2 * i + 1], x, params[2 * i])
        if i < n_layers - 1:
            x = torch.relu(x)
    return x


def detached(params: Sequence[torch.Tensor]) -> Params:
    return [p.detach() for p in params]
