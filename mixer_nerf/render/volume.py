"""Field-query and compositing stages of the renderer, for dense samples ``(R, S)``."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from ..ops import composite


class RayBundleResult(NamedTuple):
    """One rendering pass over R rays of S samples."""

    color: torch.Tensor  # (R, 3)
    depth: torch.Tensor  # (R,) expected depth (unnormalised: divide by opacity for the hit depth)
    opacity: torch.Tensor  # (R,)
    weights: torch.Tensor  # (R, S)


def query_field(
    field: nn.Module, rays_o: torch.Tensor, rays_d: torch.Tensor, depths: torch.Tensor, check_sign: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Evaluate ``field(x, d)`` at ``x = o + t d`` for depths ``(R, S)``.

    The field sees positions ``(R, S, 3)`` and unit directions as an expanded ``(R, S, 3)`` view of
    one per ray (any field works; :class:`~mixer_nerf.model.MixerNeRF` detects the broadcast).
    ``rays_d`` need not be unit length (camera rays have unit z): depths are in units of
    ``|rays_d|``, so the density per unit length is multiplied by ``|rays_d|`` to make
    ``sigma * (t_end - t_start)`` the optical thickness of the interval.

    Returns:
        sigma ``(R, S)`` per unit of ``t``, rgb ``(R, S, 3)``, in the rays' dtype.

    Raises:
        ValueError: naming the field, when it returns other shapes or (with ``check_sign``, one
            reduction: a GPU sync) a negative density.
    """
    norm = torch.linalg.vector_norm(rays_d, dim=-1, keepdim=True)  # (R, 1)
    viewdirs = rays_d / norm.clamp_min(torch.finfo(rays_d.dtype).tiny)
    positions = rays_o[:, None, :] + depths[..., None] * rays_d[:, None, :]
    sigma, rgb = field(positions, viewdirs[:, None, :].expand_as(positions))
    check_field_output(field, sigma, rgb, tuple(depths.shape), check_sign)
    return sigma.to(depths.dtype) * norm, rgb.to(depths.dtype)


def check_field_output(
    field: nn.Module, sigma: torch.Tensor, rgb: torch.Tensor, shape: tuple[int, ...], check_sign: bool
) -> None:
    """Raise ValueError naming ``field`` unless it gave sigma ``shape`` and rgb ``(*shape, 3)``
    (and, with ``check_sign``, no negative sigma: compositing would make opacities outside [0, 1])."""
    name = type(field).__name__
    if tuple(sigma.shape) != shape or tuple(rgb.shape) != (*shape, 3):
        raise ValueError(f"field {name} returned sigma {tuple(sigma.shape)} and rgb {tuple(rgb.shape)} for "
                         f"{shape} samples; expected sigma {shape} and rgb {(*shape, 3)}")
    if check_sign and bool((sigma < 0).any()):
        raise ValueError(f"field {name} returned a negative density (min {float(sigma.min()):.3g}); "
                         "densities must be >= 0 (e.g. softplus or ReLU the raw output)")


def composite_samples(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    background: torch.Tensor | None = None,
    backend: str = "auto",
    depths: torch.Tensor | None = None,
) -> RayBundleResult:
    """Volume-render dense samples with :func:`mixer_nerf.ops.composite`.

    ``depth`` is ``sum_i w_i (t_start_i + t_end_i) / 2``, or ``sum_i w_i depths_i`` when ``depths``
    ``(R, S)`` is given (NeRF's definition; needed with a 1e10-long last interval). The value checks
    (a GPU sync each) are skipped: intervals are sorted by construction, and fields must return
    non-negative densities.
    """
    color, depth, opacity, weights = composite(
        sigmas, rgbs, t_starts, t_ends, background, backend=backend, check_values=False
    )
    if depths is not None:
        depth = (weights * depths).sum(dim=-1)
    return RayBundleResult(color, depth, opacity, weights)
