"""Rendering that skips what a scene does not need: empty space (an occupancy grid), occluded
samples (early ray termination) and rays that miss the scene (box clipping), on packed samples.

- :class:`OccupancyGrid`: which cells of the scene box can hold anything.
- :class:`MarchingOptions`, :func:`march_samples`, :func:`shade_samples`,
  :func:`render_rays_marched`: marching through the grid and shading what survives;
  :func:`march_samples_fixed`: the same marching in buffers of fixed sizes, with no host sync.
- :class:`SampleBudget`: ray batches sized to a number of samples per step.
- :class:`OccupancySampler`: the grid, its refresh schedule, marching and the budget together, as
  the trainer uses them.
- :class:`ProposalSampler`, :func:`render_rays_proposal`, :func:`proposal_loss`,
  :func:`proposal_update_due`: proposal networks for scenes a grid cannot prune (forward-facing, unbounded).
- :func:`distortion_loss`: mip-NeRF 360's regulariser of the proposal sampler's main field.
- :func:`occlusion_loss`: FreeNeRF's, against density in front of the cameras.
"""

from .distortion import distortion_loss
from .occlusion import occlusion_loss
from .marching import (
    FixedMarchedSamples,
    MarchedResult,
    MarchedSamples,
    MarchingOptions,
    march_samples,
    march_samples_fixed,
    render_rays_marched,
    shade_samples,
)
from .occupancy_grid import CellShare, OccupancyGrid
from .occupancy_sampler import GridRefresh, OccupancySampler
from .proposal import (
    JITTERS,
    INTERVALS,
    RESIDUALS,
    ProposalOptions,
    ProposalSampler,
    proposal_loss,
    proposal_update_due,
    render_rays_proposal,
)
from .sample_budget import SampleBudget

__all__ = [
    "JITTERS",
    "INTERVALS",
    "RESIDUALS",
    "CellShare",
    "FixedMarchedSamples",
    "GridRefresh",
    "MarchedResult",
    "MarchedSamples",
    "MarchingOptions",
    "OccupancyGrid",
    "OccupancySampler",
    "ProposalOptions",
    "ProposalSampler",
    "SampleBudget",
    "distortion_loss",
    "occlusion_loss",
    "march_samples",
    "march_samples_fixed",
    "proposal_loss",
    "proposal_update_due",
    "render_rays_marched",
    "render_rays_proposal",
    "shade_samples",
]
