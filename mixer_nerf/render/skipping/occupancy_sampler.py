"""The occupancy sampler: an occupancy grid refreshed from the field's own density, marching
through it with early termination, and the sample budget that sizes the ray batches."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .marching import MarchedSamples, MarchingOptions, march_samples
from .occupancy_grid import CellShare, OccupancyGrid
from .sample_budget import SampleBudget


@dataclass(frozen=True)
class GridRefresh:
    """When and how :meth:`OccupancyGrid.update` refreshes the grid during training.

    Attributes:
        every: refresh every N steps.
        warmup: steps during which every cell counts as occupied.
        threshold: opacity of one marching step above which a cell is occupied.
        decay: per refresh, of the cells' moving maximum.
    """

    every: int = 16
    warmup: int = 256
    threshold: float = 0.01
    decay: float = 0.95


class OccupancySampler:
    """Where the field of a bounded scene needs evaluating: ``grid`` (its box and occupied cells),
    ``marching`` (step and skips), ``refresh`` (the grid's training schedule), ``budget``
    (None: the ray batch stays as drawn) and ``share`` (this process's part of refreshes shared by
    several training processes; None: one process)."""

    def __init__(
        self,
        grid: OccupancyGrid,
        marching: MarchingOptions = MarchingOptions(),
        refresh: GridRefresh = GridRefresh(),
        budget: SampleBudget | None = None,
        share: CellShare | None = None,
    ) -> None:
        self.grid, self.marching, self.refresh, self.budget = grid, marching, refresh, budget
        self.share = share

    def update(self, step: int, density_field: nn.Module, generator: torch.Generator | None = None) -> bool:
        """Refresh the grid from ``density_field.density`` if ``step`` is a refresh step."""
        r = self.refresh
        return self.grid.update(step, lambda x: density_field.density(x), every=r.every, decay=r.decay,
                                threshold=r.threshold, warmup_steps=r.warmup, generator=generator,
                                share=self.share)

    def is_refresh_step(self, step: int) -> bool:
        """Whether ``step`` refreshes the grid after its warm-up."""
        return step >= self.refresh.warmup and step % self.refresh.every == 0

    def sample(
        self,
        rays_o: torch.Tensor,
        rays_d: torch.Tensor,
        near: float | torch.Tensor,
        far: float | torch.Tensor,
        *,
        stratified: bool,
        density_field: nn.Module | None,
        generator: torch.Generator | None = None,
        backend: str = "auto",
    ) -> MarchedSamples:
        """:func:`~mixer_nerf.render.skipping.march_samples` with this sampler's grid and options."""
        return march_samples(rays_o, rays_d, self.grid, near, far, self.marching, stratified=stratified,
                             density_field=density_field, generator=generator, backend=backend)

    def next_batch_rays(self, num_rays: int, marched: MarchedSamples) -> int | None:
        """The ray batch that keeps the next step near the budget (None without a budget)."""
        if self.budget is None:
            return None
        return self.budget.next_rays(num_rays, marched.samples.t_starts.shape[0])
