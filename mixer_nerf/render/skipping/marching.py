"""Rendering that skips what a scene does not need: occupancy-grid marching, early ray termination
and packed (ragged) samples.

    rays -> ray_marching (box clip + empty-space skip) -> [no-grad density pass ->
    filter_by_transmittance (early termination, optional alpha threshold)] -> field on the
    surviving samples -> composite_packed

:func:`march_samples` is the no-grad first half (up to the filter), :func:`shade_samples` the
differentiable second; :func:`render_rays_marched` runs both. A ray that misses the box or crosses
only empty cells has no samples: it costs nothing but its background. Every skip is a switch in
:class:`MarchingOptions`: ``early_stop_eps=0`` and ``alpha_threshold=0`` keep every marched sample;
a fully occupied grid (as during warm-up) marches densely through the box.

Fields: ``field(x (N, 3), d (N, 3) unit) -> (sigma (N,), rgb (N, 3))``. A field that also takes the
samples' packed layout declares it in ``packed_layout``, a tuple of ``"ray_indices"`` (then it
gets ``ray_indices`` (N,) and ``num_rays``), ``"offsets"`` (the CSR offsets (R+1,)) and
``"ray_directions"`` (then it gets ``d=None`` and the rays' unit directions ``ray_directions``
(R, 3) instead), as :class:`~mixer_nerf.model.MixerNeRF` does for its per-ray squeeze-and-excitation
and its view branch, which runs once per ray.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import nn

from ...ops import composite_packed
from ...ops.ray_marching import (
    FixedSamples,
    PackedSamples,
    filter_by_transmittance,
    padding_rays,
    ray_marching,
    ray_marching_fixed,
)
from .occupancy_grid import OccupancyGrid


@dataclass(frozen=True)
class MarchingOptions:
    """How marching samples a ray and which samples it skips.

    Attributes:
        step_size: marching step in t (None: the grid's).
        early_stop_eps: drop samples once transmittance is below this (0: keep them all).
        alpha_threshold: drop samples whose alpha is below this (0: keep them all).
        cone_angle: > 0 grows the step with distance (unbounded scenes).
    """

    step_size: float | None = None
    early_stop_eps: float = 1e-4
    alpha_threshold: float = 0.0
    cone_angle: float = 0.0

    def __post_init__(self) -> None:
        if self.step_size is not None and not self.step_size > 0:
            raise ValueError(f"step_size must be positive, got {self.step_size}")
        if not 0 <= self.early_stop_eps < 1 or not 0 <= self.alpha_threshold < 1:
            raise ValueError("early_stop_eps and alpha_threshold must be in [0, 1)")
        if not self.cone_angle >= 0:
            raise ValueError(f"cone_angle must be >= 0, got {self.cone_angle}")

    @property
    def filters(self) -> bool:
        """Whether a density pre-pass can drop marched samples."""
        return self.early_stop_eps > 0 or self.alpha_threshold > 0


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


def field_inputs(field: nn.Module, rays_o, rays_d, samples: PackedSamples):
    """What a field call on packed samples needs: the points ``(N, 3)``, their unit view
    directions ``(N, 3)`` (None when the field takes ``ray_directions``), their rays' ``|d|``
    ``(N,)`` (densities are per unit t) and the keyword arguments of the layout the field declares
    in ``packed_layout``."""
    declared = getattr(field, "packed_layout", ())
    layout = {}
    if "ray_indices" in declared:
        layout.update(ray_indices=samples.ray_indices, num_rays=rays_o.shape[0])
    if "offsets" in declared:
        layout["offsets"] = samples.offsets
    norm = torch.linalg.vector_norm(rays_d, dim=-1)
    viewdirs = rays_d / norm.clamp_min(torch.finfo(rays_d.dtype).tiny)[:, None]
    mid = 0.5 * (samples.t_starts + samples.t_ends)
    rays = samples.ray_indices
    if "ray_directions" in declared:
        layout["ray_directions"], viewdirs = viewdirs, None
    else:
        viewdirs = viewdirs[rays]
    return rays_o[rays] + rays_d[rays] * mid[:, None], viewdirs, norm[rays], layout


@torch.no_grad()
def march_samples(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    grid: OccupancyGrid,
    near: float | torch.Tensor = 0.0,
    far: float | torch.Tensor = float("inf"),
    options: MarchingOptions = MarchingOptions(),
    *,
    stratified: bool = True,
    density_field: nn.Module | None = None,
    generator: torch.Generator | None = None,
    backend: str = "auto",
) -> MarchedSamples:
    """The samples of :func:`render_rays_marched` (no grad): marching through ``grid``, then, when
    ``density_field`` is given and ``options`` filter, a forward-only density pass over them and
    :func:`~mixer_nerf.ops.filter_by_transmittance`.

    Splitting this stage from :func:`shade_samples` lets a trainer prepare the next batch while
    the current one's backward pass runs. Arguments as for :func:`render_rays_marched`;
    ``density_field`` None skips the pre-pass (every marched sample is kept).
    """
    step = grid.step_size if options.step_size is None else options.step_size
    samples = ray_marching(rays_o, rays_d, near, far, grid, step, stratified=stratified,
                           generator=generator, cone_angle=options.cone_angle, backend=backend)
    num_marched = samples.t_starts.shape[0]
    if density_field is None or not options.filters or not num_marched:
        return MarchedSamples(samples, num_marched)
    return MarchedSamples(samples.select(_worth_shading(density_field, rays_o, rays_d, samples, options)),
                          num_marched)


def _worth_shading(density_field: nn.Module, rays_o, rays_d, samples: PackedSamples,
                   options: MarchingOptions) -> torch.Tensor:
    """The pre-pass: ``density_field``'s densities at ``samples`` (its ``density`` when it has
    one: no colour branch), then which samples early termination and the alpha threshold keep
    (N,) bool."""
    x, viewdirs, norm, layout = field_inputs(density_field, rays_o, rays_d, samples)
    if hasattr(density_field, "density"):
        sigma = density_field.density(x, **layout)
    else:
        sigma = density_field(x, viewdirs, **layout)[0]
    return filter_by_transmittance(sigma.float() * norm, samples, options.early_stop_eps,
                                   options.alpha_threshold)


class FixedMarchedSamples(NamedTuple):
    """:func:`march_samples_fixed`'s samples, in buffers of fixed sizes."""

    samples: FixedSamples  # the kept samples (R rays; ``with_padding_rays`` for more)
    marched: FixedSamples  # what marching gave (the pre-pass evaluated every row)

    def intact(self) -> torch.Tensor:
        """(R,) bool: the rays that lost no sample to either capacity."""
        return self.marched.intact() & self.samples.intact()


def with_padding_rays(rays_o: torch.Tensor, rays_d: torch.Tensor,
                      count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R, 3)`` rays and ``count`` more for :meth:`FixedSamples.with_padding_rays`' padding rays:
    at the origin, looking down +z (a unit direction keeps their positions and view directions
    finite)."""
    down_z = rays_d.new_zeros(count, 3)
    down_z[:, 2] = 1.0  # filled on the device: a CUDA graph cannot capture a copy from the host
    return torch.cat([rays_o, rays_o.new_zeros(count, 3)]), torch.cat([rays_d, down_z])


@torch.no_grad()
def march_samples_fixed(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    grid: OccupancyGrid,
    near: float | torch.Tensor,
    far: float | torch.Tensor,
    options: MarchingOptions,
    marched_rows: int,
    kept_rows: int,
    *,
    stratified: bool = True,
    density_field: nn.Module | None = None,
    generator: torch.Generator | None = None,
    backend: str = "auto",
) -> FixedMarchedSamples:
    """:func:`march_samples` with no host synchronisation and the same shapes every call (a CUDA
    graph can capture it): marching into ``marched_rows`` rows, the density pre-pass over all of
    them, the samples it keeps into ``kept_rows`` rows (``FixedSamples.select_fixed``). Rays past
    either cut lose samples: :meth:`FixedMarchedSamples.intact` names the rays that kept all."""
    step = grid.step_size if options.step_size is None else options.step_size
    marched = ray_marching_fixed(rays_o, rays_d, near, far, grid, step, marched_rows, stratified=stratified,
                                 generator=generator, cone_angle=options.cone_angle, backend=backend)
    if density_field is not None and options.filters and marched_rows:
        rays = with_padding_rays(rays_o, rays_d, padding_rays(marched_rows))
        keep = _worth_shading(density_field, *rays, marched.with_padding_rays(), options)
    else:
        keep = torch.ones_like(marched.samples.t_starts, dtype=torch.bool)
    return FixedMarchedSamples(marched.samples.select_fixed(keep, kept_rows), marched)


def shade_samples(
    field: nn.Module,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    samples: PackedSamples,
    background: torch.Tensor | None = None,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Evaluate ``field`` at packed ``samples`` of rays ``(R, 3)`` and composite them:
    ``(color (R, 3), depth (R,), opacity (R,), weights (N,))``, differentiable through the field."""
    x, viewdirs, norm, layout = field_inputs(field, rays_o, rays_d, samples)
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
    options: MarchingOptions = MarchingOptions(),
    *,
    stratified: bool = True,
    background: torch.Tensor | None = None,
    density_field: nn.Module | None = None,
    generator: torch.Generator | None = None,
    backend: str = "auto",
) -> MarchedResult:
    """Render rays through ``field`` evaluating it only where ``grid`` says there is something:
    :func:`march_samples`, then :func:`shade_samples`.

    Args:
        field: see the module docstring. ``field.density(x)`` is used for the no-grad pre-pass
            when it exists (skips the colour branch).
        rays_o, rays_d: ``(R, 3)``; depths are in units of ``|rays_d|``.
        grid: the occupancy grid (its box clips the rays).
        near, far: floats or ``(R,)`` tensors, further clipped to the box.
        options: step size and what to skip (:class:`MarchingOptions`).
        stratified: jitter each ray's first sample (training).
        background: ``(3,)`` or ``(R, 3)``; None renders on black.
        density_field: what the no-grad pre-pass evaluates (default ``field``), e.g. the same
            MLP under bf16 autocast: the pre-pass only decides which samples to keep.

    Returns:
        :class:`MarchedResult`; color, depth and opacity are differentiable through the field.
    """
    marched = march_samples(
        rays_o, rays_d, grid, near, far, options, stratified=stratified,
        density_field=field if density_field is None else density_field, generator=generator,
        backend=backend)
    color, depth, opacity, weights = shade_samples(
        field, rays_o, rays_d, marched.samples, background, backend)
    return MarchedResult(color, depth, opacity, marched.samples, weights, marched.num_marched)
