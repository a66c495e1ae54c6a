"""Where a run samples its rays, decided from its config in one place: which sampler a scene
gets, the occupancy sampler's grid and settings, and the image renderer of every sampler."""

from __future__ import annotations

import dataclasses

import torch

from ..render import ImageRenderer, chunk_result, render_rays
from ..render.image_renderer import ChunkResult
from ..render.skipping import (
    GridRefresh,
    MarchingOptions,
    OccupancyGrid,
    OccupancySampler,
    SampleBudget,
    render_rays_marched,
)
from .config import TrainConfig
from .fields import RadianceFields


def resolve_sampler(cfg: TrainConfig, bbox: torch.Tensor | None, ndc: bool) -> TrainConfig:
    """``cfg`` with ``sampler="auto"`` decided by the scene and that sampler's learning-rate
    recipe where ``cfg`` leaves it open. The occupancy sampler renders one marched pass, so it
    trains no separate fine network.

    "auto" marches an occupancy grid in bounded scenes (a box, world space) and samples
    hierarchically in forward-facing NDC scenes, where the scene fills the box and a grid skips
    little (docs/training.md)."""
    if cfg.sampler != "auto":
        sampler = cfg.sampler
    else:
        sampler = "occupancy" if bbox is not None and not ndc else "hierarchical"
    if sampler == "occupancy" and bbox is None:
        raise ValueError("sampler 'occupancy' needs a scene box (bbox); this scene has none")
    cfg = cfg.with_recipe(sampler)
    return dataclasses.replace(cfg, fine_network=cfg.fine_network and sampler != "occupancy")


def make_grid(cfg: TrainConfig, bbox: torch.Tensor | None) -> OccupancyGrid | None:
    """The occupancy grid of a resolved ``cfg`` (None for hierarchical sampling)."""
    if cfg.sampler != "occupancy":
        return None
    return OccupancyGrid(bbox, cfg.grid_resolution, cfg.step_size)


def occupancy_sampler(cfg: TrainConfig, grid: OccupancyGrid) -> OccupancySampler:
    """The occupancy sampler of a resolved ``cfg`` over ``grid``."""
    budget = None if cfg.target_samples is None else SampleBudget(cfg.target_samples)
    refresh = GridRefresh(every=cfg.grid_every, warmup=cfg.grid_warmup, threshold=cfg.grid_threshold)
    return OccupancySampler(grid, cfg.marching(), refresh, budget)


def image_renderer(
    cfg: TrainConfig,
    fields: RadianceFields,
    near: float,
    far: float,
    background: torch.Tensor,
    grid: OccupancyGrid | None = None,
    marching: MarchingOptions | None = None,
) -> ImageRenderer:
    """The chunked, deterministic renderer of a run's ``fields`` for its sampler (resolved ``cfg``).
    ``grid`` and ``marching`` replace the fields' grid and the config's marching options (e.g. to
    measure what a skip saves)."""
    device = background.device
    coarse, fine = fields.runners(cfg.precision, device)
    grid = fields.grid if grid is None else grid
    if grid is None:
        def render_chunk(rays_o: torch.Tensor, rays_d: torch.Tensor) -> ChunkResult:
            return chunk_result(render_rays(
                coarse, rays_o, rays_d, near, far, cfg.num_coarse, cfg.num_fine, fine, stratified=False,
                background=background, backend=cfg.backend))
    else:
        options = cfg.marching() if marching is None else marching

        def render_chunk(rays_o: torch.Tensor, rays_d: torch.Tensor) -> ChunkResult:
            out = render_rays_marched(coarse, rays_o, rays_d, grid, near, far, options, stratified=False,
                                      background=background, backend=cfg.backend)
            return ChunkResult(out.color, out.depth, out.opacity, out.samples.t_starts.shape[0],
                               out.num_marched)
    return ImageRenderer(render_chunk, fields, device, cfg.chunk)
