"""Pinhole camera rays and the NDC warp for forward-facing scenes.

Conventions (those of NeRF): camera-to-world matrices ``c2w`` are OpenGL-style, the camera's
x axis points right, y up, and it looks down -z. Pixel (column i, row j) has its centre at
continuous image coordinates (i + 0.5, j + 0.5); the principal point defaults to (W/2, H/2), the
centre of the image. Directions are *not* normalised: in camera space they are
((x - cx) / focal, -(y - cy) / focal, -1), so a ray parameter t is depth along the optical axis.
"""

from __future__ import annotations

import torch


def pixel_rays(
    x: torch.Tensor,
    y: torch.Tensor,
    focal: float,
    c2w: torch.Tensor,
    cx: float,
    cy: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through continuous image points.

    Args:
        x, y: image coordinates (pixel centres are at i + 0.5), any shape S; computed in their
            own dtype, then cast to that of ``c2w``.
        focal: focal length in pixels.
        c2w: camera-to-world matrices (*B, 4, 4) or (*B, 3, 4); *B must broadcast with S.
        cx, cy: principal point in pixels.

    Returns:
        origins, dirs: each (*broadcast(B, S), 3), dtype of ``c2w``.
    """
    if not c2w.is_floating_point():
        raise TypeError(f"c2w must be a floating-point tensor, got {c2w.dtype}")
    dx = ((x - cx) / focal).to(c2w.dtype)[..., None]
    dy = (-(y - cy) / focal).to(c2w.dtype)[..., None]
    # R @ d written as a sum of R's columns: broadcasting then never materialises a 3x3 per ray.
    dirs = dx * c2w[..., :3, 0] + dy * c2w[..., :3, 1] - c2w[..., :3, 2]
    origins = c2w[..., :3, 3].expand_as(dirs)
    return origins, dirs


def camera_rays(
    H: int,
    W: int,
    focal: float,
    c2w: torch.Tensor,
    cx: float | None = None,
    cy: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One ray through the centre of every pixel of one or more cameras.

    Args:
        H, W: image size in pixels.
        focal: focal length in pixels.
        c2w: camera-to-world (4, 4) / (3, 4), or a batch (*B, 4, 4).
        cx, cy: principal point; default W / 2, H / 2.

    Returns:
        origins, dirs: each (*B, H, W, 3); ``dirs[..., j, i, :]`` goes through pixel (i, j).
    """
    cx = W / 2 if cx is None else cx
    cy = H / 2 if cy is None else cy
    y, x = torch.meshgrid(
        torch.arange(H, dtype=torch.float64, device=c2w.device) + 0.5,
        torch.arange(W, dtype=torch.float64, device=c2w.device) + 0.5,
        indexing="ij",
    )
    # (*B, 1, 1, 4, 4) broadcasts against the (H, W) grid.
    return pixel_rays(x, y, focal, c2w[..., None, None, :, :], cx, cy)


def ndc_rays(
    H: int,
    W: int,
    focal: float,
    near: float,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp camera-space-aligned rays into normalised device coordinates (forward-facing scenes).

    The perspective projection of a camera looking down -z with the principal point at the image
    centre maps the frustum between z = -near and z = -inf onto the cube [-1, 1]^3: the near plane
    goes to z_ndc = -1 and infinity to z_ndc = +1. Each ray is first moved to start on the near
    plane; in NDC it then runs from ``o`` (t = 0) to the far end ``o + d`` (t = 1), so samples in
    NDC use near = 0, far = 1.

    Args:
        H, W, focal: image size and focal length in pixels of the camera defining the NDC space.
        near: depth of the near plane (NeRF uses 1.0 for LLFF, after rescaling).
        rays_o, rays_d: world rays (..., 3), in the frame whose -z the NDC camera looks down.

    Returns:
        origins, dirs in NDC: each (..., 3).
    """
    ox, oy, oz = rays_o.unbind(-1)
    dx, dy, dz = rays_d.unbind(-1)
    t = -(near + oz) / dz  # shift origins onto the plane z = -near
    ox, oy, oz = ox + t * dx, oy + t * dy, oz + t * dz
    sx, sy = 2.0 * focal / W, 2.0 * focal / H  # projection scale to [-1, 1]
    origins = torch.stack([-sx * ox / oz, -sy * oy / oz, 1.0 + 2.0 * near / oz], dim=-1)
    dirs = torch.stack([-sx * (dx / dz - ox / oz), -sy * (dy / dz - oy / oz), -2.0 * near / oz], dim=-1)
    return origins, dirs
