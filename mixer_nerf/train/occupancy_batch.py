"""One training batch of the occupancy sampler: everything of a step that needs no gradient."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from ..ops.ray_marching import PackedSamples
from ..render.skipping import OccupancySampler
from .sampler import RaySampler


class MarchedBatch(NamedTuple):
    rays_o: torch.Tensor  # (R, 3)
    rays_d: torch.Tensor  # (R, 3)
    target: torch.Tensor  # (R, 3)
    samples: PackedSamples  # the samples to train on (N,)
    num_marched: int  # samples marching emitted (what the pre-pass evaluated)
    empty_points: torch.Tensor | None  # (P, 3) random box points for the empty-space loss (refresh steps)
    empty_mask: torch.Tensor | None  # (P,) bool: the point lies in a cell the grid marks empty


def prepare_marched_batch(
    step: int,
    rays: RaySampler,
    occupancy: OccupancySampler,
    density_field: nn.Module,
    near: float | torch.Tensor,
    far: float | torch.Tensor,
    empty_space_points: int,
    backend: str,
) -> MarchedBatch:
    """The batch of ``step``: refresh the grid (on its schedule), draw rays, march them and drop
    what early termination drops, size the next batch to the sample budget, and on refresh steps
    draw ``empty_space_points`` (0: none) points for the empty-space loss."""
    generator = rays.generator
    occupancy.update(step, density_field, generator)
    rays_o, rays_d, target = rays.sample()
    marched = occupancy.sample(rays_o, rays_d, near, far, stratified=True, density_field=density_field,
                               generator=generator, backend=backend)
    batch_rays = occupancy.next_batch_rays(rays_o.shape[0], marched)
    if batch_rays is not None:
        rays.batch_rays = batch_rays
    points = mask = None
    if empty_space_points and occupancy.is_refresh_step(step):
        # With the grid's refreshes: a pass of its own every step made steps ~20% longer (Lego).
        points, mask = occupancy.grid.random_points(empty_space_points, generator)
    return MarchedBatch(rays_o, rays_d, target, marched.samples, marched.num_marched, points, mask)
