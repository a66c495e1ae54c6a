"""An occupancy-sampler batch in buffers of fixed capacity, so that its step can be replayed as a
CUDA graph (fixed shapes at fixed addresses).

The sampler's batches change size every step (rays drawn to a sample budget, samples kept by the
grid and early termination). :class:`StaticMarchedBatch` holds ``rays`` + 1 rays and ``samples``
samples: the batch's rays first, then empty rays, and last one padding ray that owns every sample
slot past the batch's samples, each a zero-length interval. Every sample then belongs to a ray (the
packed ops need no special case), the padding composites to nothing, and the loss of
:meth:`StaticMarchedBatch.mse` (weighted by ray) sends exactly zero gradient to what is not the
batch.
"""

from __future__ import annotations

import math

import torch

from ..ops.ray_marching import PackedSamples
from .occupancy_batch import MarchedBatch

# Room over the batch that outgrew the last buffers. Samples: the budget holds a batch's samples
# near its target, and every spare sample slot costs the MLP a row at each step, where a recapture
# costs one eager step once. Rays: cheap to pad, and a run's rays per batch drift up as its
# density sharpens.
SAMPLE_GROWTH, RAY_GROWTH = 1.05, 1.25
RAY_ALIGN, SAMPLE_ALIGN = 128, 1024


class StaticMarchedBatch:
    """Buffers for batches of up to ``rays`` rays and ``samples`` samples on ``device``."""

    def __init__(self, rays: int, samples: int, device: torch.device | str) -> None:
        self.rays, self.samples = rays, samples
        f32 = dict(device=device, dtype=torch.float32)
        self.rays_o = torch.zeros(rays + 1, 3, **f32)  # the last row: the padding ray
        self.rays_d = torch.zeros(rays + 1, 3, **f32)
        self.target = torch.zeros(rays + 1, 3, **f32)
        self.ray_weight = torch.zeros(rays + 1, **f32)  # 1 for the batch's rays
        self.num_rays = torch.ones((), **f32)  # the batch's rays, what the loss averages over
        self.t_starts = torch.zeros(samples, **f32)
        self.t_ends = torch.zeros(samples, **f32)
        self.ray_indices = torch.full((samples,), rays, device=device, dtype=torch.int64)
        self.offsets = torch.zeros(rays + 2, device=device, dtype=torch.int64)

    @classmethod
    def for_batch(cls, batch: MarchedBatch) -> StaticMarchedBatch:
        """Buffers with room for ``batch`` and some growth (:data:`RAY_GROWTH`, :data:`SAMPLE_GROWTH`)."""
        rays, samples = batch.rays_o.shape[0], batch.samples.t_starts.shape[0]
        return cls(_round_up(rays * RAY_GROWTH, RAY_ALIGN), _round_up(samples * SAMPLE_GROWTH, SAMPLE_ALIGN),
                   batch.rays_o.device)

    def fits(self, batch: MarchedBatch) -> bool:
        return batch.rays_o.shape[0] <= self.rays and batch.samples.t_starts.shape[0] <= self.samples

    @property
    def packed(self) -> PackedSamples:
        return PackedSamples(self.t_starts, self.t_ends, self.ray_indices, self.offsets)

    def load(self, batch: MarchedBatch) -> None:
        """Copy ``batch`` in (it must :meth:`fit`); the slots it leaves become padding."""
        if not self.fits(batch):
            raise ValueError(f"a batch of {batch.rays_o.shape[0]} rays and {batch.samples.t_starts.shape[0]} "
                             f"samples does not fit buffers of {self.rays} rays and {self.samples} samples")
        R, N, s = batch.rays_o.shape[0], batch.samples.t_starts.shape[0], batch.samples
        self.rays_o[:R].copy_(batch.rays_o)
        self.rays_o[R:].zero_()
        self.rays_d[:R].copy_(batch.rays_d)
        self.rays_d[R:, :2].zero_()
        self.rays_d[R:, 2].fill_(1.0)  # a unit direction: padding positions and view directions stay finite
        self.target[:R].copy_(batch.target)
        self.target[R:].zero_()
        self.ray_weight[:R].fill_(1.0)
        self.ray_weight[R:].zero_()
        self.num_rays.fill_(R)
        self.t_starts[:N].copy_(s.t_starts)
        self.t_starts[N:].zero_()
        self.t_ends[:N].copy_(s.t_ends)
        self.t_ends[N:].zero_()
        self.ray_indices[:N].copy_(s.ray_indices)
        self.ray_indices[N:].fill_(self.rays)
        self.offsets[: R + 1].copy_(s.offsets)
        self.offsets[R + 1 : -1].fill_(N)
        self.offsets[-1].fill_(self.samples)

    def mse(self, color: torch.Tensor) -> torch.Tensor:
        """The mean squared error of the batch's rays in ``color`` (rays + 1, 3) against their
        targets, the padding weighted out."""
        return ((color - self.target).square() * self.ray_weight[:, None]).sum() / (3 * self.num_rays)


def _round_up(value: float, multiple: int) -> int:
    return max(multiple, math.ceil(value / multiple) * multiple)
