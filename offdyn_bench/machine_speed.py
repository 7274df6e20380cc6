"""How fast this machine runs the suite's kind of work right now: a fixed reference workload, timed.

CPU seconds are not a stable unit. The same training on the same CPU model of one cloud VM took
about 1.8 times the CPU on one day as on another (PROTOCOL.md §8): what the CPU shares with other
tenants is invisible from inside the machine. So trainings time this workload too, and
:class:`baselines.run_folder.TrainingCompute` counts their CPU in it as well as in seconds. A
reader can then compare runs from other days and machines, and a price can be set for the machine
at hand.

The workload is the inner step of every method here: one update of a SAC-sized critic (a
two-hidden-layer, 256-unit MLP on a batch of 256 HalfCheetah-sized inputs: forward, backward,
Adam), on one thread. Its inputs and weights come from a private generator, so timing it changes
no random stream of the training that calls it. Its definition never changes under its name:
a new workload gets a new :data:`REFERENCE_WORKLOAD`.
"""

from __future__ import annotations

import statistics
import time

REFERENCE_WORKLOAD = "mlp-256x2-adam-batch256/v1"
"""The name of the workload :func:`reference_update_seconds` times, recorded next to its numbers."""

_INPUTS, _HIDDEN, _BATCH = 23, 256, 256  # HalfCheetah: 17 observations + 6 actions


def reference_update_seconds(blocks: int = 5, updates_per_block: int = 8) -> float:
    """The CPU seconds one update of the reference workload takes on this thread now: the median
    over ``blocks`` timed blocks of ``updates_per_block`` updates, after one untimed warm-up update.

    Thread CPU time, not wall time: a thread that waits for a core is not charged, and nor is the
    work of other threads in the process. Takes about 0.1 s here (2-3 ms an update). Runs on the
    CPU with gradients on, whatever the caller's default device or grad mode."""
    if blocks < 1 or updates_per_block < 1:
        raise ValueError(f"blocks and updates_per_block must be at least 1, got {blocks} and {updates_per_block}")
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        generator = torch.Generator().manual_seed(0)
        sizes = [(_HIDDEN, _INPUTS), (_HIDDEN, _HIDDEN), (1, _HIDDEN)]
        cpu = torch.device("cpu")
        weights = [(torch.randn(shape, generator=generator, device=cpu) / shape[1] ** 0.5).requires_grad_()
                   for shape in sizes]
        biases = [torch.zeros(shape[0], device=cpu, requires_grad=True) for shape in sizes]
        inputs = torch.randn(_BATCH, _INPUTS, generator=generator, device=cpu)
        targets = torch.randn(_BATCH, 1, generator=generator, device=cpu)
        optimizer = torch.optim.Adam(weights + biases, lr=3e-4)

        @torch.enable_grad()
        def update() -> None:
            hidden = inputs
            for layer, (weight, bias) in enumerate(zip(weights, biases)):
                hidden = torch.nn.functional.linear(hidden, weight, bias)
                if layer < len(weights) - 1:
                    hidden = torch.relu(hidden)
            loss = (hidden - targets).square().mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()

        update()
        timings = []
        for _ in range(blocks):
            started = time.thread_time()
            for _ in range(updates_per_block):
                update()
            timings.append((time.thread_time() - started) / updates_per_block)
        return statistics.median(timings)
    finally:
        torch.set_num_threads(threads)
