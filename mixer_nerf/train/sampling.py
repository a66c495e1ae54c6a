"""Where a run samples its rays, decided from its config in one place: which sampler a scene
gets, the occupancy sampler's grid and settings, and the image renderer of every sampler."""

from __future__ import annotations

import dataclasses
import math

import torch

from ..model import ModelConfig
from ..model.proposal_network import ProposalNetwork
from ..render import ImageRenderer, chunk_result, render_rays
from ..render.image_renderer import RENDER_SAMPLES, ChunkResult, rays_per_chunk
from ..render.skipping import (
    CellShare,
    GridRefresh,
    MarchingOptions,
    OccupancyGrid,
    OccupancySampler,
    ProposalOptions,
    ProposalSampler,
    SampleBudget,
    render_rays_marched,
    render_rays_proposal,
)
from .config import TrainConfig
from .fields import RadianceFields


def resolve_sampler(cfg: TrainConfig, bbox: torch.Tensor | None, ndc: bool) -> TrainConfig:
    """``cfg`` with ``sampler="auto"`` decided by the scene and that sampler's learning-rate
    recipe where ``cfg`` leaves it open. The occupancy and proposal samplers render one pass, so
    they train no separate fine network.

    "auto" marches an occupancy grid in bounded scenes (a box, world space); forward-facing NDC
    scenes fill their box, so a grid skips little there, and unbounded scenes have no box: both get
    the proposal sampler (docs/skipping.md), as does a model whose density depends on the view
    direction (the paper's Eq. 7), which a grid cannot store."""
    view_dependent = bool(cfg.model_overrides.get("mlca_concat_direction", False))
    if cfg.sampler != "auto":
        sampler = cfg.sampler
    else:
        sampler = "occupancy" if bbox is not None and not ndc and not view_dependent else "proposal"
    if sampler == "occupancy" and bbox is None:
        raise ValueError("sampler 'occupancy' needs a scene box (bbox); this scene has none")
    if sampler == "occupancy" and view_dependent:
        raise ValueError("sampler 'occupancy' needs a density without a view direction; "
                         "mlca_concat_direction (Eq. 7) makes it view-dependent: use 'proposal' or 'hierarchical'")
    cfg = cfg.with_recipe(sampler)
    return dataclasses.replace(cfg, fine_network=cfg.fine_network and sampler == "hierarchical")


def make_grid(cfg: TrainConfig, bbox: torch.Tensor | None) -> OccupancyGrid | None:
    """The occupancy grid of a resolved ``cfg`` (None for hierarchical sampling)."""
    if cfg.sampler != "occupancy":
        return None
    return OccupancyGrid(bbox, cfg.grid_resolution, cfg.step_size)


def make_proposal(cfg: TrainConfig, model_cfg: ModelConfig, bounded: bool) -> ProposalSampler | None:
    """The proposal sampler of a resolved ``cfg`` (None for the other samplers): its networks see
    positions as the main field does; an unbounded scene (no box) is sampled in disparity and
    contracted."""
    if cfg.sampler != "proposal":
        return None
    networks = [ProposalNetwork(model_cfg.scene_center, model_cfg.scene_scale, width=cfg.proposal_width,
                                contract_space=not bounded, backend=cfg.backend)
                for _ in cfg.proposal_rounds]
    options = ProposalOptions(cfg.proposal_rounds, cfg.proposal_samples,
                              "linear" if bounded else "disparity")
    return ProposalSampler(networks, options)


def make_fields(cfg: TrainConfig, model_cfg: ModelConfig, bbox: torch.Tensor | None) -> RadianceFields:
    """The fields of a resolved ``cfg``, with its sampler's grid or proposal networks."""
    return RadianceFields(model_cfg, cfg.fine_network, make_grid(cfg, bbox),
                          make_proposal(cfg, model_cfg, bounded=bbox is not None))


def occupancy_sampler(
    cfg: TrainConfig, grid: OccupancyGrid, share: CellShare | None = None
) -> OccupancySampler:
    """The occupancy sampler of a resolved ``cfg`` over ``grid`` (``share``: this process's part of
    its refreshes when several train it)."""
    budget = None if cfg.target_samples is None else SampleBudget(cfg.target_samples)
    refresh = GridRefresh(every=cfg.grid_every, warmup=cfg.grid_warmup, threshold=cfg.grid_threshold)
    return OccupancySampler(grid, cfg.marching(), refresh, budget, share)


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
    if fields.proposal is not None:
        def render_chunk(rays_o: torch.Tensor, rays_d: torch.Tensor) -> ChunkResult:
            out, samples = render_rays_proposal(coarse, fields.proposal, rays_o, rays_d, near, far,
                                                stratified=False, background=background, backend=cfg.backend)
            shaded = samples.t_starts.numel()
            return ChunkResult(out.color, out.depth, out.opacity, shaded, shaded)
    elif grid is None:
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
    budget = cfg.render_samples or RENDER_SAMPLES[device.type]
    return ImageRenderer(render_chunk, fields, device, rays_per_chunk(budget, samples_per_ray(cfg, grid), cfg.chunk))


def samples_per_ray(cfg: TrainConfig, grid: OccupancyGrid | None) -> int:
    """The most samples one field evaluation of a resolved ``cfg``'s sampler can take per ray:
    a marched ray crosses the box diagonal in steps (camera rays, |d| >= 1), a proposal round
    or the final pass, the fine pass of coarse + fine."""
    if cfg.sampler == "occupancy" and grid is not None:
        step = cfg.step_size or grid.step_size
        return math.ceil(float((grid.aabb[1] - grid.aabb[0]).norm()) / step) + 1
    if cfg.sampler == "proposal":
        return max(*cfg.proposal_rounds, cfg.proposal_samples)
    return cfg.num_coarse + cfg.num_fine
