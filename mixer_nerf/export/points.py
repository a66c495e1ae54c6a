"""A coloured point cloud of a trained scene: the surface point of each opaque pixel of rendered
views (depth given a hit along its ray), written as PLY."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..train.output import ensure_writable_folder
from ..train.restore import load_trained
from ..video import path_cameras, render_frames
from .errors import ExportError, require_trimesh


def export_points(
    ckpt: str | Path,
    out: str | Path,
    path: str = "train",
    frames: int = 30,
    scale: float = 0.5,
    min_opacity: float = 0.5,
    max_points: int = 1_000_000,
    device: str | None = None,
    backend: str | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Render the cameras of ``path`` (as ``render --path``; ``frames`` for a generated path) at
    ``scale`` and write the surface points of pixels at least ``min_opacity`` opaque to ``out``
    (.ply), at most ``max_points`` of them (a random subset, seed 0).

    Returns:
        {"points", "count", "views", "bounds" (2, 3)}.

    Raises:
        ExportError: bad arguments, an NDC scene, or no opaque pixel.
    """
    out = Path(out)
    if out.suffix != ".ply":
        raise ExportError(f"{out}: point clouds are written as .ply")
    if not 0 < min_opacity <= 1 or max_points < 1 or not scale > 0 or frames < 1:
        raise ExportError("need 0 < min_opacity <= 1, max_points >= 1, scale > 0 and frames >= 1")
    trimesh = require_trimesh()
    run = load_trained(ckpt, device=device, backend=backend)
    if run.scene["ndc"]:
        raise ExportError(
            f"{run.path}: a forward-facing (NDC) scene renders depth in NDC space, not world points"
        )
    cameras = path_cameras(run, path, frames).scaled(scale)
    ensure_writable_folder(out.parent)
    log(f"rendering {len(cameras)} views of the {cameras.kind} path at {cameras.W}x{cameras.H}")
    points, colors = [], []
    for frame in render_frames(run, cameras):
        opacity = frame.opacity.reshape(-1)
        hit = opacity >= min_opacity
        t = (frame.depth.reshape(-1)[hit] / opacity[hit])[:, None]
        points.append(frame.rays_o.cpu()[hit] + t * frame.rays_d.cpu()[hit])
        colors.append(frame.color.reshape(-1, 3)[hit])
    xyz, rgb = torch.cat(points), torch.cat(colors)
    if len(xyz) == 0:
        raise ExportError(
            f"no pixel of the {cameras.kind} views is {min_opacity:g} opaque: nothing to export"
        )
    if len(xyz) > max_points:
        keep = torch.randperm(len(xyz), generator=torch.Generator().manual_seed(0))[:max_points]
        xyz, rgb = xyz[keep], rgb[keep]
    cloud = trimesh.PointCloud(
        xyz.double().numpy(), colors=(rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    )
    cloud.export(out)
    return {"points": str(out), "count": len(xyz), "views": len(cameras), "bounds": cloud.bounds.tolist()}
