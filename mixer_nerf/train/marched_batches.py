"""Training batches prepared one step ahead.

Preparing an occupancy-sampler batch (:func:`~mixer_nerf.train.occupancy_batch.prepare_marched_batch`)
reads sample counts back to the host twice (marching, then the early-termination filter), so done
in line it drains the GPU twice a step and leaves it idle while the host launches the next
kernels. :class:`MarchedBatches` instead prepares batch n+1 while step n's backward pass runs, on
a side CUDA stream, so those waits overlap GPU work (docs/training.md).

Batch n+1 is therefore prepared with the weights from before step n's update (the optimizer step
waits for the preparation, which reads them). It only decides where to sample, on the CPU too,
so a run does the same on either device.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import torch

from .occupancy_batch import MarchedBatch
from .sampler import RaySampler


class MarchedBatches:
    """Prepares batches one step ahead with ``prepare(step)``, which draws from ``rays``.

    Steps count the optimizer steps already taken (0 for the first batch). Use per step n:
    :meth:`take` (the batch of step n), forward and backward, then :meth:`prefetch` for step n+1
    before the optimizer step. :meth:`discard` drops a prefetched batch and rewinds the random
    state and batch size of ``rays`` to before it, so that a checkpoint taken between steps
    resumes exactly as the run continues.
    """

    def __init__(self, prepare: Callable[[int], MarchedBatch], rays: RaySampler) -> None:
        self.prepare, self.rays = prepare, rays
        self.device = rays.generator.device
        on_cuda = self.device.type == "cuda"
        self._stream = torch.cuda.Stream(self.device) if on_cuda else None
        self._weights_ready = torch.cuda.Event() if on_cuda else None
        self._next: tuple[int, MarchedBatch, tuple[torch.Tensor, int]] | None = None

    def take(self, step: int) -> MarchedBatch:
        """The batch of ``step`` (prefetched, or prepared now), ready for the current stream."""
        self.mark_weights()
        if self._next is None or self._next[0] != step:
            self.discard()
            self.prefetch(step)
        _, batch, _ = self._next
        self._next = None
        return batch

    def prefetch(self, step: int) -> None:
        """Prepare the batch of ``step`` (on the side stream on CUDA). Returns once its sample
        counts are known; the current stream then waits for it before anything it queues next
        (the optimizer step that changes the weights the pre-pass read, the batch's use)."""
        if not isinstance(step, int):  # a device tensor would sync at take() and never match it
            raise TypeError(f"step must be the host's int, got {type(step).__name__}")
        rewind = (self.rays.generator.get_state(), self.rays.batch_rays)
        with self._on_side_stream():
            batch = self.prepare(step)
        if self._stream is not None:
            torch.cuda.current_stream(self.device).wait_stream(self._stream)
            for tensor in _tensors(batch):
                tensor.record_stream(torch.cuda.current_stream(self.device))
        self._next = (step, batch, rewind)

    def discard(self) -> None:
        """Drop a prefetched batch, restoring the random state and batch size from before it."""
        if self._next is not None:
            _, _, (rng_state, batch_rays) = self._next
            self.rays.generator.set_state(rng_state)
            self.rays.batch_rays = batch_rays
            self._next = None

    def mark_weights(self) -> None:
        """The current stream's weights are this step's: the next prefetch reads them after here."""
        if self._weights_ready is not None:
            self._weights_ready.record()

    def _on_side_stream(self):
        if self._stream is None:
            return contextlib.nullcontext()
        self._stream.wait_event(self._weights_ready)
        return torch.cuda.stream(self._stream)


def _tensors(batch: MarchedBatch) -> list[torch.Tensor]:
    fields = [batch.rays_o, batch.rays_d, batch.target, *batch.samples, batch.empty_points, batch.empty_mask]
    return [t for t in fields if t is not None]
