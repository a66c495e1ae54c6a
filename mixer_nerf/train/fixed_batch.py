"""Occupancy-sampler batches with no host synchronisation, for steps replayed as CUDA graphs.

The eager path's batches change size every step (rays drawn to a sample budget, samples kept by
the grid and early termination) and read those sizes back to the host. :class:`FixedBatches`
instead draws a fixed number of rays and marches them into buffers of fixed sizes
(:func:`~mixer_nerf.render.skipping.march_samples_fixed`): only the first ``num_rays`` rays take
part (the others get ``far = near``: no samples), and ``num_rays`` is a device tensor that each
batch adapts for the next from its own sample counts, one step late and without the host. Rays
that lose samples to a full buffer, and the rays past ``num_rays``, are weighted out of the loss.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import nn

from ..ops.ray_marching import PackedSamples, padding_rays
from ..render.skipping import OccupancySampler, SampleBudget, march_samples_fixed
from ..render.skipping.marching import with_padding_rays
from .occupancy_batch import MarchedBatch
from .sampler import RaySampler

# Room over what a batch at the switch held. Rays: cheap (marching an unused ray costs nothing, the
# view branch one row per ray), and a run's rays per batch grow as its density sharpens. Marched
# rows: each costs the density pre-pass a row, the ratio of marched to kept samples drifts. Kept
# rows: each costs the MLP a row with gradient, the batch size holds them near the budget.
RAY_ROOM, MARCHED_ROOM, KEPT_ROOM = 2.5, 1.3, 1.06
ALIGN = 256


class FixedCapacity(NamedTuple):
    rays: int  # rays drawn per batch (the most a batch can use)
    marched: int  # rows of marched samples (what the density pre-pass evaluates)
    kept: int  # rows of kept samples (what the field evaluates with gradient)

    @classmethod
    def for_batch(cls, batch: MarchedBatch, budget: SampleBudget | None) -> FixedCapacity:
        """Room for batches like ``batch`` (an eager one) held near ``budget``'s target of kept
        samples (None: of ``batch``'s rays)."""
        rays, kept = batch.rays_o.shape[0], max(batch.samples.t_starts.shape[0], 1)
        target = kept if budget is None else budget.target
        return cls(_round_up(rays * RAY_ROOM), _round_up(target * MARCHED_ROOM * batch.num_marched / kept),
                   _round_up(target * KEPT_ROOM))


class FixedBatch(NamedTuple):
    rays_o: torch.Tensor  # (R + P, 3): the drawn rays, then the P padding rays of the spare rows
    rays_d: torch.Tensor  # (R + P, 3)
    target: torch.Tensor  # (R + P, 3)
    samples: PackedSamples  # (kept rows,) over the R + P rays
    ray_weight: torch.Tensor  # (R + P,) 1 for the rays the loss counts: in the batch, no sample lost
    empty_points: torch.Tensor | None  # (P, 3) random box points for the empty-space loss (refresh steps)
    empty_mask: torch.Tensor | None  # (P,) bool: the point lies in a cell the grid marks empty

    def mse(self, color: torch.Tensor) -> torch.Tensor:
        """The mean squared error of the counted rays of ``color`` (R + P, 3) against their targets."""
        error = (color - self.target).square() * self.ray_weight[:, None]
        return error.sum() / (3 * self.ray_weight.sum().clamp_min(1))


class FixedBatches:
    """Draws :class:`FixedBatch` es of ``capacity`` from ``rays`` through ``occupancy``, starting
    with ``num_rays`` rays: later batches as the eager path sizes them, near the sample budget's
    target (``occupancy.budget``), or ``rays.batch_rays`` rays without a budget.

    ``seen``: (3,) int64 device counters of the rays used, the samples kept and the samples
    marched, summed over the batches drawn (read them when a sync costs nothing).
    """

    def __init__(self, rays: RaySampler, occupancy: OccupancySampler, capacity: FixedCapacity, num_rays: int,
                 near: float | torch.Tensor, far: float | torch.Tensor, empty_space_points: int,
                 backend: str) -> None:
        self.rays, self.occupancy, self.capacity = rays, occupancy, capacity
        self.empty_space_points, self.backend = empty_space_points, backend
        device = rays.generator.device
        self.num_rays = torch.tensor(min(num_rays, capacity.rays), device=device)
        # The rays the last batch asked for next: for the target, and within the marched buffer.
        self.wanted = torch.zeros(2, device=device)
        self.seen = torch.zeros(3, dtype=torch.int64, device=device)
        self.near, self.far = (torch.as_tensor(v, dtype=torch.float32, device=device) for v in (near, far))

    @torch.no_grad()
    def draw(self, density_field: nn.Module, empty_space: bool) -> FixedBatch:
        """The next batch (no host sync), its samples kept by ``density_field``'s pre-pass; with
        ``empty_space``, points for the empty-space loss too."""
        cap, generator = self.capacity, self.rays.generator
        rays_o, rays_d, target = self.rays.sample(cap.rays)
        used = torch.arange(cap.rays, device=rays_o.device) < self.num_rays
        near = self.near.expand(cap.rays)
        far = torch.where(used, self.far, self.near)  # an empty interval: the unused rays get no sample
        marched = march_samples_fixed(rays_o, rays_d, self.occupancy.grid, near, far, self.occupancy.marching,
                                      cap.marched, cap.kept, stratified=True, density_field=density_field,
                                      generator=generator, backend=self.backend)
        counted = (used & marched.intact()).float()
        self._adapt(marched.samples.total, marched.marched.total)
        self.seen += torch.cat([used.sum(0, keepdim=True), marched.samples.total.clamp_max(cap.kept),
                                marched.marched.total.clamp_max(cap.marched)])
        points = mask = None
        if empty_space and self.empty_space_points:
            points, mask = self.occupancy.grid.random_points(self.empty_space_points, generator)
        pad = padding_rays(cap.kept)
        return FixedBatch(*with_padding_rays(rays_o, rays_d, pad), torch.cat([target, target.new_zeros(pad, 3)]),
                          marched.samples.with_padding_rays(), torch.cat([counted, counted.new_zeros(pad)]),
                          points, mask)

    def _adapt(self, kept: torch.Tensor, marched: torch.Tensor) -> None:
        """The next batch's rays from this one's counts: the budget's target of kept samples (or
        the configured rays), marched samples within their buffer (with a margin for the next
        batch's spread)."""
        n, budget = self.num_rays.float(), self.occupancy.budget
        kept = kept.float().clamp_min(1)
        per_target = torch.full_like(kept, self.rays.batch_rays) if budget is None else n * budget.target / kept
        per_buffer = n * (0.95 * self.capacity.marched) / marched.float().clamp_min(1)
        rays = torch.minimum(per_target, per_buffer).floor().clamp(1, self.capacity.rays)
        self.num_rays.copy_(rays.squeeze(0).long())
        self.wanted.copy_(torch.cat([per_target, per_buffer]))

    def grow(self) -> bool:
        """Grow the capacity where the last batch wanted more than it had: rays (up to the
        budget's ``max_rays``), or marched rows when they limited the batch. One host sync; True
        when the capacity changed (a captured step must then be captured again)."""
        budget = self.occupancy.budget
        max_rays = self.rays.batch_rays if budget is None else budget.max_rays
        for_target, for_buffer = self.wanted.tolist()
        rays, marched, kept = self.capacity
        if for_target > 0.95 * rays and rays < max_rays:
            rays = min(_round_up(1.5 * for_target), max(max_rays, rays))
        if for_buffer < min(for_target, rays):
            marched = _round_up(marched * 1.05 * min(for_target, rays) / max(for_buffer, 1))
        grown = FixedCapacity(rays, marched, kept)
        changed, self.capacity = grown != self.capacity, grown
        return changed


def _round_up(value: float) -> int:
    return max(ALIGN, math.ceil(value / ALIGN) * ALIGN)
