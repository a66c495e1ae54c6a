"""Raw depth and opacity maps of rendered views: NPY (and EXR when OpenEXR is installed) beside
colour-mapped previews."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..train.output import ensure_writable_folder
from ..train.restore import load_trained
from ..video import colorize_depth, depth_range, path_cameras, render_frames, write_png
from .errors import ExportError


def export_depth(
    ckpt: str | Path,
    out: str | Path | None = None,
    path: str = "test",
    frames: int = 30,
    scale: float = 1.0,
    device: str | None = None,
    backend: str | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Render the cameras of ``path`` (as ``render --path``) and write, per view ``NNNN`` in ``out``
    (default ``<checkpoint folder>/depth_<path>``): ``depth_NNNN.npy`` and ``opacity_NNNN.npy``
    (float32 (H, W)), ``depth_NNNN.png`` (colour-mapped) and, with OpenEXR installed,
    ``depth_NNNN.exr`` (channels Z and A).

    Depth is the expected ray parameter sum_i w_i t_i (z-depth for the camera's rays: they have
    unit z in camera space; in NDC for NDC scenes); divide by opacity for the depth given a hit.

    Returns:
        {"out", "views", "exr", "depth_range"}.
    """
    if not scale > 0 or frames < 1:
        raise ExportError(f"need scale > 0 and frames >= 1, got {scale} and {frames}")
    run = load_trained(ckpt, device=device, backend=backend)
    cameras = path_cameras(run, path, frames).scaled(scale)
    out = Path(out) if out is not None else run.path.parent / f"depth_{Path(cameras.kind).stem}"
    ensure_writable_folder(out)
    exr = exr_writer()
    log(f"rendering depth of {len(cameras)} views of the {cameras.kind} path into {out}")
    depths, opacities = [], []
    for i, frame in enumerate(render_frames(run, cameras)):
        depth, opacity = frame.depth.float().numpy(), frame.opacity.float().numpy()
        np.save(out / f"depth_{i:04d}.npy", depth)
        np.save(out / f"opacity_{i:04d}.npy", opacity)
        if exr is not None:
            exr(out / f"depth_{i:04d}.exr", depth, opacity)
        depths.append(frame.depth)
        opacities.append(frame.opacity)
    lo, hi = depth_range(depths, opacities, fallback=(run.scene["near"], run.scene["far"]))
    for i, (depth, opacity) in enumerate(zip(depths, opacities, strict=True)):
        write_png(out / f"depth_{i:04d}.png", colorize_depth(depth, opacity, lo, hi))
    return {"out": str(out), "views": len(cameras), "exr": exr is not None, "depth_range": [lo, hi]}


def exr_writer() -> Callable[[Path, np.ndarray, np.ndarray], None] | None:
    """A writer of (depth, opacity) as the Z and A channels of an EXR file, or None without OpenEXR."""
    try:
        import OpenEXR
    except ImportError:
        return None

    def write(path: Path, depth: np.ndarray, opacity: np.ndarray) -> None:
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        OpenEXR.File(header, {"Z": depth, "A": opacity}).write(str(path))

    return write
