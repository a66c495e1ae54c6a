"""Renderer that skips what a scene does not need: occupancy-grid marching, early ray
termination and packed (ragged) samples.

    rays -> ray_marching (box clip + empty-space skip) -> [no-grad density pass ->
    filter_by_transmittance (early termination, optional alpha threshold)] -> field on the
    surviving samples -> composite_packed

:func:`march_samples` is the no-grad first half (up to the filter), :func:`shade_samples` the
differentiable second; :func:`render_rays_marched` runs both. A ray that misses the box or crosses only empty cells has no samples: it costs nothing but its
background. Every skip is a switch: ``early_stop_eps=0`` and ``alpha_threshold=0`` keep every
marched sample; an :class:`~mixer_nerf.occupancy_grid.OccupancyGrid` that is fully occupied (as
during warm-up) marches densely through the box.
"""

from __future__ import annotations

import inspect
from typing import NamedTuple

import torch
from torch import nn

from ..occupancy_grid import OccupancyGrid
from ..ops import composite_packed
from ..ops.ray_marching import PackedSamples, filter_by_transmittance, ray_marching


class MarchedSamples(NamedTuple):
    """Where a batch of rays needs its field evaluated: the first stage of marched rendering."""

    samples: PackedSamples  # the samples that survive every skip (N,)
    num_marched: int  # samples marching emitted: what the early-termination pre-pass evaluated


class MarchedResult(NamedTuple):
    color: torch.Tensor  # (R, 3)
    depth: torch.Tensor  # (R,) unnormalised expected depth
    opacity: torch.Tensor  # (R,)
    samples: PackedSamples  # the samples the field was evaluated at (N,)
    weights: torch.Tensor  # (N,)
    num_marched: int  # samples marching emitted: what the early-termination pre-pass evaluated


def _field_inputs(field: nn.Module, rays_o, rays_d, samples: PackedSamples):
    """What a field call on packed samples needs: the points ``(N, 3)``, their unit view
    directions ``(N, 3)``, their rays' ``|d|`` ``(N,)`` (densities are per unit t) and the samples'
    packed layout as far as ``field.forward`` takes it (``ray_indices`` with ``num_rays``, and the
    CSR ``offsets`` of its fused SE path)."""
    parameters = inspect.signature(field.forward).parameters
    layout = {}
    if "ray_indices" in parameters:
        layout.update(ray_indices=samples.ray_indices, num_rays=rays_o.shape[0])
    if "offsets" in parameters:
        layout["offsets"] = samples.offsets
    norm = torch.linalg.vector_norm(rays_d, dim=-1)
    viewdirs = rays_d / norm.clamp_min(torch.finfo(rays_d.dtype).tiny)[:, None]
    mid = 0.5 * (samples.t_starts + samples.t_ends)
    rays = samples.ray_indices
    return rays_o[rays] + rays_d[rays] * mid[:, None], viewdirs[rays], norm[rays], layout


@torch.no_grad()
def march_samples(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    grid: OccupancyGrid,
    near: float | torch.Tensor = 0.0,
    far: float | torch.Tensor = float("inf"),
    step_size: float | None = None,
    stratified: bool = True,
    early_stop_eps: float = 1e-4,
    alpha_threshold: float = 0.0,
    cone_angle: float = 0.0,
    backend: str = "auto",
    generator: torch.Generator | None = None,
    density_field: nn.Module | None = None,
) -> MarchedSamples:
    """The samples of :func:`render_rays_marched` (no grad): marching through ``grid``, then, when
    ``density_field`` is given and ``early_stop_eps`` or ``alpha_threshold`` is positive, a
    forward-only density pass over them and :func:`~mixer_nerf.ops.filter_by_transmittance`.

    Splitting this stage from :func:`shade_samples` lets a trainer prepare the next batch while
    the current one's backward pass runs. Arguments as for :func:`render_rays_marched`;
    ``density_field`` None skips the pre-pass (every marched sample is kept).
    """
    step = grid.step_size if step_size is None else step_size
    samples = ray_marching(rays_o, rays_d, near, far, grid, step, stratified=stratified,
                           generator=generator, cone_angle=cone_angle, backend=backend)
    num_marched = samples.t_starts.shape[0]
    filtering = early_stop_eps > 0 or alpha_threshold > 0
    if density_field is None or not filtering or not num_marched:
        return MarchedSamples(samples, num_marched)
    x, viewdirs, norm, layout = _field_inputs(density_field, rays_o, rays_d, samples)
    if hasattr(density_field, "density"):
        sigma = density_field.density(x, **layout)
    else:
        sigma = density_field(x, viewdirs, **layout)[0]
    keep = filter_by_transmittance(sigma.float() * norm, samples, early_stop_eps, alpha_threshold)
    return MarchedSamples(samples.select(keep), num_marched)


def shade_samples(
    field: nn.Module,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    samples: PackedSamples,
    background: torch.Tensor | None = None,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Evaluate ``field`` at packed ``samples`` of rays ``(R, 3)`` and composite them:
    ``(color (R, 3), depth (R,), opacity (R,), weights (N,))``, differentiable through the field.
    The field gets the samples' layout as in :func:`render_rays_marched`."""
    x, viewdirs, norm, layout = _field_inputs(field, rays_o, rays_d, samples)
    sigma, rgb = field(x, viewdirs, **layout)
    sigma = sigma.to(rays_o.dtype) * norm
    bg = None if background is None else background.to(rays_o.dtype)
    return composite_packed(
        sigma, rgb.to(rays_o.dtype), samples.t_starts, samples.t_ends, samples.offsets, bg,
        backend=backend, check_values=False)


def render_rays_marched(
    field: nn.Module,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    grid: OccupancyGrid,
    near: float | torch.Tensor = 0.0,
    far: float | torch.Tensor = float("inf"),
    step_size: float | None = None,
    stratified: bool = True,
    background: torch.Tensor | None = None,
    early_stop_eps: float = 1e-4,
    alpha_threshold: float = 0.0,
    cone_angle: float = 0.0,
    backend: str = "auto",
    generator: torch.Generator | None = None,
    density_field: nn.Module | None = None,
) -> MarchedResult:
    """Render rays through ``field`` evaluating it only where ``grid`` says there is something:
    :func:`march_samples`, then :func:`shade_samples`.

    Args:
        field: ``field(x (N, 3), d (N, 3) unit) -> (sigma (N,), rgb (N, 3))``; a field whose forward
            takes ``ray_indices`` (e.g. :class:`~mixer_nerf.model.MixerNeRF`, for its per-ray SE
            squeeze) gets them with ``num_rays``, and one that takes ``offsets`` the samples' CSR
            offsets ``(R+1,)``. ``field.density(x)`` is used for the no-grad
            pre-pass when it exists (skips the colour branch).
        rays_o, rays_d: ``(R, 3)``; depths are in units of ``|rays_d|``.
        grid: the occupancy grid (its box clips the rays).
        near, far: floats or ``(R,)`` tensors, further clipped to the box.
        step_size: marching step in t (default: the grid's).
        stratified: jitter each ray's first sample (training).
        background: ``(3,)`` or ``(R, 3)``; None renders on black.
        early_stop_eps: drop samples once transmittance is below this (0: keep them all).
        alpha_threshold: drop samples whose alpha is below this (0: keep them all).
        cone_angle: > 0 grows the step with distance (unbounded scenes).
        density_field: what the no-grad pre-pass evaluates (default ``field``), e.g. the same
            MLP under bf16 autocast: the pre-pass only decides which samples to keep.

    Returns:
        :class:`MarchedResult`; color, depth and opacity are differentiable through the field.
    """
    marched = march_samples(
        rays_o, rays_d, grid, near, far, step_size, stratified, early_stop_eps, alpha_threshold,
        cone_angle, backend, generator, field if density_field is None else density_field)
    color, depth, opacity, weights = shade_samples(
        field, rays_o, rays_d, marched.samples, background, backend)
    return MarchedResult(color, depth, opacity, marched.samples, weights, marched.num_marched)
