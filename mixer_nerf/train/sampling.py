"""Where a run samples its rays, decided from its config in one place: which sampler a scene
gets, the occupancy sampler's grid and settings, and the image renderer of every sampler."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

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
from .config import (
    DEFAULT_STEPS,
    FORWARD_FACING_PROPOSAL_STEPS,
    PROPOSAL_REGULARISERS,
    TrainConfig,
)
from .fields import RadianceFields


def resolve_sampler(cfg: TrainConfig, bbox: torch.Tensor | None, ndc: bool) -> TrainConfig:
    """``cfg`` with ``sampler="auto"`` decided by the scene and that sampler's learning-rate
    recipe where ``cfg`` leaves it open. The occupancy and proposal samplers render one pass, so
    they train no separate fine network.

    "auto" marches an occupancy grid in bounded scenes (a box, world space); forward-facing NDC
    scenes fill their box, so a grid skips little there, and unbounded scenes have no box: both get
    the proposal sampler (docs/skipping.md), as does a model whose density depends on the view
    direction (the paper's Eq. 7), which a grid cannot store. ``steps`` left open is
    :data:`FORWARD_FACING_PROPOSAL_STEPS` for the proposal sampler in a forward-facing scene,
    :data:`DEFAULT_STEPS` elsewhere."""
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
    # only "auto" gets here: TrainConfig refuses the other samplers when named
    for name in PROPOSAL_REGULARISERS:
        if getattr(cfg, name) > 0 and sampler != "proposal":
            raise ValueError(f"{name} applies to the proposal sampler only, and sampler 'auto' chose "
                             f"{sampler!r} for this scene: pass sampler 'proposal' or {name} 0")
    cfg = cfg.with_recipe(sampler)
    if cfg.lr * cfg.mlca_weight_decay >= 1:  # each step scales the mixing by 1 - lr * W
        raise ValueError(f"mlca_weight_decay {cfg.mlca_weight_decay:g} times lr {cfg.lr:g} must be below 1 "
                         "(each step scales the mixing by 1 - lr * W)")
    steps = cfg.steps or (FORWARD_FACING_PROPOSAL_STEPS if sampler == "proposal" and ndc else DEFAULT_STEPS)
    return dataclasses.replace(cfg, fine_network=cfg.fine_network and sampler == "hierarchical", steps=steps)


def recipe_notes(cfg: TrainConfig) -> list[str]:
    """What a reader of a run's results needs to know about the regularisers a resolved ``cfg``
    trained with and about its val split."""
    notes = []
    if cfg.val_holdout:
        notes.append(f"val views: 1 in {cfg.val_holdout} of the training views, left out of training "
                     f"(--val-holdout {cfg.val_holdout})")
    if cfg.occlusion_weight:
        notes.append(f"occlusion loss {cfg.occlusion_weight:g} on the first {cfg.occlusion_fraction:g} "
                     "of each ray (--occlusion-weight)")
    if cfg.mlca_weight_decay:
        notes.append(f"MLCA's mixing decayed toward the identity, W = {cfg.mlca_weight_decay:g} "
                     "(--mlca-weight-decay; presets C and D)")
    return notes


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
    options = ProposalOptions(cfg.proposal_rounds, cfg.proposal_samples, "linear" if bounded else "disparity",
                              cfg.proposal_weight_padding, cfg.proposal_jitter, cfg.proposal_residual,
                              cfg.proposal_intervals)
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
    step: Callable[[], int] | None = None,
) -> ImageRenderer:
    """The chunked, deterministic renderer of a run's ``fields`` for its sampler (resolved ``cfg``).
    ``grid`` and ``marching`` replace the fields' grid and the config's marching options (e.g. to
    measure what a skip saves). ``step`` reads the run's training step: with it, a CPU render of a
    run still in its grid warm-up marches a grid measured from the field (:class:`RenderGrid`)."""
    device = background.device
    coarse, fine = fields.runners(cfg.precision, device)
    render_grid = RenderGrid(cfg, fields.grid if grid is None else grid, coarse, step if grid is None else None)
    if fields.proposal is not None:
        def render_chunk(rays_o: torch.Tensor, rays_d: torch.Tensor) -> ChunkResult:
            out, samples = render_rays_proposal(coarse, fields.proposal, rays_o, rays_d, near, far,
                                                stratified=False, background=background, backend=cfg.backend)
            shaded = samples.t_starts.numel()
            return ChunkResult(out.color, out.depth, out.opacity, shaded, shaded)
    elif render_grid.grid is None:
        def render_chunk(rays_o: torch.Tensor, rays_d: torch.Tensor) -> ChunkResult:
            return chunk_result(render_rays(
                coarse, rays_o, rays_d, near, far, cfg.num_coarse, cfg.num_fine, fine, stratified=False,
                background=background, backend=cfg.backend))
    else:
        options = cfg.marching() if marching is None else marching

        def render_chunk(rays_o: torch.Tensor, rays_d: torch.Tensor) -> ChunkResult:
            out = render_rays_marched(coarse, rays_o, rays_d, render_grid(), near, far, options, stratified=False,
                                      background=background, backend=cfg.backend)
            return ChunkResult(out.color, out.depth, out.opacity, out.samples.t_starts.shape[0],
                               out.num_marched)
    budget = cfg.render_samples or RENDER_SAMPLES[device.type]
    per_ray = samples_per_ray(cfg, render_grid.grid)
    return ImageRenderer(render_chunk, fields, device, rays_per_chunk(budget, per_ray, cfg.chunk))


def measures_render_grid(cfg: TrainConfig, step: int) -> bool:
    """Whether renders of a resolved ``cfg``'s run at ``step`` march a grid measured from the field:
    on a CPU while training's grid is still all-occupied (warm-up). There each ray would shade
    ~1000 samples (an hour a 400x400 view on 2 cores); a GPU gets past warm-up in seconds."""
    return cfg.sampler == "occupancy" and torch.device(cfg.device).type == "cpu" and step < cfg.grid_warmup


class RenderGrid:
    """The grid a run's renders march (None without one): ``grid`` itself, or, where
    :func:`measures_render_grid` says so at ``step()`` (``step`` None: never), a copy measured from
    ``field.density`` by :meth:`OccupancyGrid.measured`, measured again only when the step changed."""

    def __init__(self, cfg: TrainConfig, grid: OccupancyGrid | None, field: torch.nn.Module,
                 step: Callable[[], int] | None) -> None:
        self.cfg, self.grid, self.field, self.step = cfg, grid, field, step
        self._measured: tuple[int, OccupancyGrid] | None = None

    def __call__(self) -> OccupancyGrid | None:
        step = None if self.step is None or self.grid is None else self.step()
        if step is None or not measures_render_grid(self.cfg, step):
            return self.grid
        if self._measured is None or self._measured[0] != step:
            self._measured = (step, self.grid.measured(self.field.density, self.cfg.grid_threshold))
        return self._measured[1]


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
