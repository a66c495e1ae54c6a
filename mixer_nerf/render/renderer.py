"""NeRF's two-pass renderer (coarse stratified samples, fine importance samples) on our ops.

Stages, each a small function a later sampler (occupancy-grid marching, packed samples) can
replace: :func:`~mixer_nerf.render.samplers.stratified_depths` /
:func:`~mixer_nerf.ops.hierarchical_samples` (where to sample),
:func:`~mixer_nerf.render.samplers.sample_intervals` (what each sample stands for),
:func:`~mixer_nerf.render.volume.query_field` (the field), and
:func:`~mixer_nerf.render.volume.composite_samples` (volume rendering).
"""

from __future__ import annotations

import math
import numbers
from typing import NamedTuple

import torch
from torch import nn

from ..ops import hierarchical_samples
from ..ops._checks import check_backend, check_floating, check_same_device, check_same_dtype, check_shape
from .image_renderer import ChunkResult, ImageResult, render_in_chunks
from .samplers import sample_intervals, stratified_depths
from .volume import RayBundleResult, composite_samples, query_field


class RenderOutput(NamedTuple):
    coarse: RayBundleResult
    fine: RayBundleResult | None  # None when num_fine == 0

    @property
    def final(self) -> RayBundleResult:
        """The fine pass, or the coarse one when there is none."""
        return self.coarse if self.fine is None else self.fine


def render_rays(
    field: nn.Module,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: float | torch.Tensor,
    far: float | torch.Tensor,
    num_coarse: int = 64,
    num_fine: int = 128,
    fine_field: nn.Module | None = None,
    stratified: bool = True,
    background: torch.Tensor | None = None,
    backend: str = "auto",
    generator: torch.Generator | None = None,
    lindisp: bool = False,
    last_delta: float | None = None,
    weight_padding: float = 0.0,
    check_field: bool = True,
) -> RenderOutput:
    """Render rays with a coarse pass and a hierarchical fine pass.

    Args:
        field: any module ``field(x (R, S, 3), d (R, S, 3) unit) -> (sigma (R, S) >= 0, rgb (R, S, 3))``.
        rays_o, rays_d: ``(R, 3)`` origins and directions (any length; depths are in units of it).
        near, far: floats or ``(R,)`` tensors, ``near <= far``.
        num_coarse: S, stratified samples per ray (>= 3 when ``num_fine > 0``: the fine PDF lives
            on the S - 2 interior coarse intervals, as in NeRF).
        num_fine: importance samples per ray; the fine pass renders the S + num_fine merged depths.
        fine_field: field of the fine pass (default ``field``).
        stratified: jitter the coarse samples within their bins and draw the fine ones
            stratified; False places both deterministically (bin centres, mid-quantiles).
        background: ``(3,)`` or ``(R, 3)`` colour behind the rays; None renders on black.
        backend: for the ops (``"auto"``, ``"kernel"``, ``"torch"``).
        generator: random source for both passes (on the rays' device).
        lindisp: sample uniformly in disparity (``1/t``) instead of depth; needs ``near > 0``.
        last_delta: None for midpoint intervals tiling ``[near, far]``; a float for NeRF's
            intervals ``[t_i, t_{i+1}]`` whose last one is ``last_delta`` long (NeRF: 1e10). See
            :mod:`mixer_nerf.render.samplers`.
        weight_padding: added to the coarse weights before fine sampling (NeRF's code: 1e-5).
        check_field: refuse a negative density from the field (one reduction per pass: a GPU
            sync; the shapes it returns are always checked).

    Returns:
        :class:`RenderOutput` ``(coarse, fine)``; each :class:`RayBundleResult` holds color
        ``(R, 3)``, depth ``(R,)``, opacity ``(R,)``, weights ``(R, S)``, differentiable through
        the field. The fine samples depend on the coarse weights only through a no-grad resampling.
    """
    near_t, far_t = _validate(field, rays_o, rays_d, near, far, num_coarse, num_fine, background, backend, lindisp)
    depths = stratified_depths(near_t, far_t, num_coarse, stratified, lindisp, generator)
    coarse = _render_pass(field, rays_o, rays_d, depths, near_t, far_t, background, backend, last_delta,
                          check_field)
    if num_fine == 0:
        return RenderOutput(coarse, None)
    depths = hierarchical_samples(
        depths,
        coarse.weights.detach(),
        num_fine,
        deterministic=not stratified,
        weight_padding=weight_padding,
        generator=generator,
        backend=backend,
        check_values=False,
    )
    fine = _render_pass(
        fine_field or field, rays_o, rays_d, depths, near_t, far_t, background, backend, last_delta, check_field
    )
    return RenderOutput(coarse, fine)


@torch.no_grad()
def render_image(
    field: nn.Module,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: float | torch.Tensor,
    far: float | torch.Tensor,
    chunk: int = 8192,
    fine_field: nn.Module | None = None,
    stratified: bool = False,
    background: torch.Tensor | None = None,
    **kwargs,
) -> ImageResult:
    """Render many rays in chunks of ``chunk`` rays, without gradients, in bounded memory.

    ``rays_o``, ``rays_d`` are ``(..., 3)`` (e.g. ``(H, W, 3)`` or ``(H*W, 3)``); ``near``/``far``
    floats or tensors of shape ``(...)``; ``background`` ``(3,)`` or ``(..., 3)``. Deterministic
    sampling by default; other keywords go to :func:`render_rays`. Only one chunk's samples are
    alive at a time; the result is written into preallocated outputs.

    Returns:
        :class:`ImageResult` of the final pass: color ``(..., 3)``, depth ``(...)``, opacity ``(...)``.
    """
    if isinstance(chunk, bool) or not isinstance(chunk, numbers.Integral) or chunk < 1:
        raise ValueError(f"chunk must be a positive int, got {chunk!r}")
    check_floating("rays_o", rays_o)
    check_floating("rays_d", rays_d)
    check_shape("rays_d", rays_d, rays_o.shape, " (like rays_o)")
    if rays_o.dim() < 1 or rays_o.shape[-1] != 3:
        raise ValueError(f"rays_o must have shape (..., 3), got {tuple(rays_o.shape)}")
    batch = rays_o.shape[:-1]
    flat_o, flat_d = rays_o.reshape(-1, 3), rays_d.reshape(-1, 3)
    per_ray, shared = {}, {}  # per-ray tensors are flattened and chunked, the rest passed as is
    for name, value, trailing in (("near", near, ()), ("far", far, ()), ("background", background, (3,))):
        if isinstance(value, torch.Tensor) and value.dim() > len(trailing):
            check_shape(name, value, (*batch, *trailing))
            per_ray[name] = value.reshape(-1, *trailing)
        else:
            shared[name] = value

    def render_chunk(o, d, **chunked):
        out = render_rays(field, o, d, fine_field=fine_field, stratified=stratified, **shared, **chunked,
                          **kwargs)
        return chunk_result(out)

    result, _, _ = render_in_chunks(render_chunk, flat_o, flat_d, chunk, per_ray)
    color, depth, opacity = result
    return ImageResult(color.reshape(*batch, 3), depth.reshape(batch), opacity.reshape(batch))


def chunk_result(out: RenderOutput) -> ChunkResult:
    """The final pass of ``out`` with the samples both passes shaded (all of them: dense)."""
    shaded = sum(p.weights.numel() for p in out if p is not None)
    final = out.final
    return ChunkResult(final.color, final.depth, final.opacity, shaded, shaded)


def _render_pass(
    field, rays_o, rays_d, depths, near, far, background, backend, last_delta, check_field
) -> RayBundleResult:
    background = None if background is None else background.to(depths.dtype)
    sigmas, rgbs = query_field(field, rays_o, rays_d, depths, check_field)
    t_starts, t_ends = sample_intervals(depths, near, far, last_delta)
    nerf_depth = depths if last_delta is not None else None
    return composite_samples(sigmas, rgbs, t_starts, t_ends, background, backend, depths=nerf_depth)


def _ray_bound(value, name: str, rays_o: torch.Tensor) -> torch.Tensor:
    """A float, 0-d or ``(R,)`` tensor -> ``(R, 1)`` tensor (maybe an expanded view) in the rays' dtype."""
    num_rays = rays_o.shape[0]
    if isinstance(value, torch.Tensor):
        check_floating(name, value)
        check_same_device(rays_o=rays_o, **{name: value})
        if value.dim() == 0:
            return value.to(rays_o.dtype).expand(num_rays, 1)
        check_shape(name, value, (num_rays,), " (a float or one value per ray)")
        return value.to(rays_o.dtype)[:, None]
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise TypeError(f"{name} must be a finite float or an (R,) tensor, got {value!r}")
    return torch.full((1, 1), float(value), dtype=rays_o.dtype, device=rays_o.device).expand(num_rays, 1)


def _validate(field, rays_o, rays_d, near, far, num_coarse, num_fine, background, backend, lindisp):
    if not callable(field):
        raise TypeError(f"field must be a callable nn.Module field(x, d) -> (sigma, rgb), got {type(field).__name__}")
    check_backend(backend)
    check_floating("rays_o", rays_o)
    check_floating("rays_d", rays_d)
    check_shape("rays_o", rays_o, (None, 3))
    check_shape("rays_d", rays_d, (rays_o.shape[0], 3), " (like rays_o)")
    check_same_device(rays_o=rays_o, rays_d=rays_d, background=background)
    check_same_dtype(rays_o=rays_o, rays_d=rays_d)
    for name, value, least in (("num_coarse", num_coarse, 1), ("num_fine", num_fine, 0)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise TypeError(f"{name} must be an int, got {type(value).__name__}")
        if value < least:
            raise ValueError(f"{name} must be >= {least}, got {value}")
    if num_fine > 0 and num_coarse < 3:
        raise ValueError(f"num_coarse must be >= 3 for a fine pass (got {num_coarse}); or set num_fine=0")
    if background is not None:
        check_floating("background", background)
        if background.shape not in ((3,), (rays_o.shape[0], 3)):
            raise ValueError(
                f"background must have shape (3,) or ({rays_o.shape[0]}, 3), got {tuple(background.shape)}"
            )
    near_t, far_t = _ray_bound(near, "near", rays_o), _ray_bound(far, "far", rays_o)
    if not isinstance(near, torch.Tensor) and not isinstance(far, torch.Tensor):
        if near > far:
            raise ValueError(f"near must be <= far, got near={near}, far={far}")
    elif bool((near_t > far_t).any()):  # per-ray bounds: one reduction (a sync on GPUs)
        raise ValueError("near must be <= far for every ray")
    if lindisp and not isinstance(near, torch.Tensor) and near <= 0:
        raise ValueError(f"lindisp needs near > 0, got near={near}")
    return near_t, far_t
