"""Training batches of the occupancy sampler, each prepared one step ahead.

Preparing a batch is everything of a step that needs no gradient: draw the rays, refresh the
grid (every ``grid_every`` steps), march, run the no-grad density pre-pass and drop what early
termination drops (:func:`~mixer_nerf.render.marching.march_samples`). Marching and the filter each
read a sample count back to the host, so done in line they drain the GPU twice a step and leave it
idle while the host launches the next kernels (about 30% of a step on an H100, see
benchmarks/results/train_step/). :class:`MarchedBatches` instead prepares batch n+1 while step n's
backward pass runs, on a side CUDA stream, so those waits overlap GPU work.

Batch n+1 is therefore prepared with the weights from before step n's update (the optimizer step
waits for the preparation, which reads them). It only decides where to sample, on the CPU too,
so a run does the same on either device.
"""

from __future__ import annotations

import contextlib
from typing import NamedTuple

import torch
from torch import nn

from ..occupancy_grid import OccupancyGrid
from ..ops.ray_marching import PackedSamples
from ..render.marching import march_samples
from .config import TrainConfig
from .sampler import RaySampler


class MarchedBatch(NamedTuple):
    rays_o: torch.Tensor  # (R, 3)
    rays_d: torch.Tensor  # (R, 3)
    target: torch.Tensor  # (R, 3)
    samples: PackedSamples  # the samples to train on (N,)
    num_marched: int  # samples marching emitted (what the pre-pass evaluated)
    empty_points: torch.Tensor | None  # (P, 3) random box points for the empty-space loss (refresh steps)
    empty_mask: torch.Tensor | None  # (P,) bool: the point lies in a cell the grid marks empty


class MarchedBatches:
    """Prepares the occupancy sampler's batches one step ahead.

    Steps count the optimizer steps already taken (0 for the first batch). Use per step n:
    :meth:`take` (the batch of step n), forward and backward, then :meth:`prefetch` for step n+1
    before the optimizer step. :meth:`discard` drops a prefetched batch and rewinds the random
    state and batch size to before it, so that a checkpoint taken between steps resumes exactly as
    the run continues.
    """

    def __init__(
        self,
        cfg: TrainConfig,
        sampler: RaySampler,
        grid: OccupancyGrid,
        density_field: nn.Module,
        near: float | torch.Tensor,
        far: float | torch.Tensor,
    ) -> None:
        self.cfg, self.sampler, self.grid, self.density_field = cfg, sampler, grid, density_field
        self.near, self.far = near, far
        self.device = sampler.generator.device
        on_cuda = self.device.type == "cuda"
        self._stream = torch.cuda.Stream(self.device) if on_cuda else None
        self._weights_ready = torch.cuda.Event() if on_cuda else None
        self._next: tuple[int, MarchedBatch, tuple[torch.Tensor, int]] | None = None

    def take(self, step: int) -> MarchedBatch:
        """The batch of ``step`` (prefetched, or prepared now), ready for the current stream."""
        self._mark_weights()
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
        rewind = (self.sampler.generator.get_state(), self.sampler.batch_rays)
        with self._on_side_stream():
            batch = self._prepare(step)
        if self._stream is not None:
            torch.cuda.current_stream(self.device).wait_stream(self._stream)
            for tensor in _tensors(batch):
                tensor.record_stream(torch.cuda.current_stream(self.device))
        self._next = (step, batch, rewind)

    def discard(self) -> None:
        """Drop a prefetched batch, restoring the random state and batch size from before it."""
        if self._next is not None:
            _, _, (rng_state, batch_rays) = self._next
            self.sampler.generator.set_state(rng_state)
            self.sampler.batch_rays = batch_rays
            self._next = None

    def _mark_weights(self) -> None:
        """The current stream's weights are this step's: the next prefetch reads them after here."""
        if self._weights_ready is not None:
            self._weights_ready.record()

    def _on_side_stream(self):
        if self._stream is None:
            return contextlib.nullcontext()
        self._stream.wait_event(self._weights_ready)
        return torch.cuda.stream(self._stream)

    def _prepare(self, step: int) -> MarchedBatch:
        cfg, grid, generator = self.cfg, self.grid, self.sampler.generator
        grid.update(
            step,
            lambda x: self.density_field.density(x),
            every=cfg.grid_every,
            threshold=cfg.grid_threshold,
            warmup_steps=cfg.grid_warmup,
            generator=generator,
        )
        rays_o, rays_d, target = self.sampler.sample()
        marched = march_samples(
            rays_o, rays_d, grid, self.near, self.far, stratified=True,
            early_stop_eps=cfg.early_stop_eps, alpha_threshold=cfg.alpha_threshold,
            backend=cfg.backend, generator=generator, density_field=self.density_field)
        num_samples = marched.samples.t_starts.shape[0]
        if cfg.target_samples is not None:
            # Keep the MLP's work per step near the target as the grid empties (nerfacc's recipe).
            rays = rays_o.shape[0] * cfg.target_samples / max(num_samples, 1)
            self.sampler.batch_rays = int(min(max(rays, 1), 1 << 18))
        points = mask = None
        if cfg.empty_space_weight > 0 and step >= cfg.grid_warmup and step % cfg.grid_every == 0:
            # With the grid's refreshes: a pass of its own every step made steps ~20% longer (Lego).
            points, mask = grid.random_points(cfg.empty_space_points, generator)
        return MarchedBatch(rays_o, rays_d, target, marched.samples, marched.num_marched, points, mask)


def _tensors(batch: MarchedBatch) -> list[torch.Tensor]:
    fields = [batch.rays_o, batch.rays_d, batch.target, *batch.samples, batch.empty_points, batch.empty_mask]
    return [t for t in fields if t is not None]
