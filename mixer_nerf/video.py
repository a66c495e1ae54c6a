"""Camera paths (turntable, spiral, a dataset split's cameras, a nerfstudio camera-path file),
rendering them from a checkpoint, and writing videos and colour-mapped depth maps.

Videos are MP4 (H.264) when ``imageio-ffmpeg`` is installed (it ships its own ffmpeg binary from
PyPI), else animated GIF; :func:`write_video` returns the path it actually wrote.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from .data.llff import BD_FACTOR
from .data.rays import camera_rays, ndc_rays
from .data.scene import NDC_NEAR
from .render.camera_path import CameraPath, fixed_intrinsics_path, read_nerfstudio_path, split_path
from .train.memory import FLOAT_BYTES, check_fits
from .train.output import OutputError, atomic_path, ensure_writable_folder
from .train.restore import TrainedRun, load_trained
from .train.scenes import scene_source

GENERATED_PATHS = ("auto", "turntable", "spiral")
DATASET_PATHS = ("train", "test", "val")
PATHS = GENERATED_PATHS + DATASET_PATHS
"""Named camera paths; ``render --path`` also takes a nerfstudio camera-path JSON file."""
SPIRAL_ROTATIONS = 2
SPIRAL_Z_RATE = 0.5  # the spiral's in-and-out motion runs at half its angular speed
DEPTH_COLORMAP = "turbo"
AXIS_SNAP_DEGREES = 30.0


# -- camera paths ---------------------------------------------------------------------------------


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """(N, 4, 4) OpenGL camera-to-world matrices at ``eye`` (N, 3) looking at ``target`` (N, 3) or (3,)."""
    back = _normalize(eye - target)
    right = _normalize(torch.linalg.cross(up.expand_as(back), back))
    cam_up = torch.linalg.cross(back, right)
    c2w = torch.eye(4, dtype=eye.dtype).repeat(len(eye), 1, 1)
    c2w[:, :3, :] = torch.stack([right, cam_up, back, eye], dim=-1)
    return c2w


def turntable_poses(
    train_poses: torch.Tensor, n_frames: int, center: torch.Tensor | None = None
) -> torch.Tensor:
    """(n_frames, 4, 4) cameras circling ``center`` (default: the origin) once.

    The rotation axis is the training cameras' mean up vector, snapped to the nearest world axis
    when within ``AXIS_SNAP_DEGREES`` of it (captures are usually made z-up or y-up, and a few
    random views average to a tilted axis); radius and elevation are the training cameras' mean
    distance from ``center`` and mean elevation above the plane normal to that axis (an
    object-centred capture such as a Blender scene).
    """
    poses = train_poses.double()
    center = torch.zeros(3, dtype=torch.float64) if center is None else center.double()
    up = _snap_to_axis(_normalize(poses[:, :3, 1].mean(0)))
    offsets = poses[:, :3, 3] - center
    radius = offsets.norm(dim=-1).mean()
    elevation = torch.asin((_normalize(offsets) @ up).clamp(-1, 1)).mean()
    e1 = _normalize(torch.linalg.cross(up, _any_perpendicular(up)))
    e2 = torch.linalg.cross(up, e1)
    theta = torch.arange(n_frames, dtype=torch.float64) * (2 * math.pi / n_frames)
    ring = torch.cos(theta)[:, None] * e1 + torch.sin(theta)[:, None] * e2
    eye = center + radius * (torch.cos(elevation) * ring + torch.sin(elevation) * up)
    return look_at(eye, center, up).float()


def spiral_poses(train_poses: torch.Tensor, n_frames: int, focus_depth: float) -> torch.Tensor:
    """(n_frames, 4, 4) cameras on NeRF's spiral for forward-facing captures.

    The cameras move on an ellipse (radii: 90th percentile of the training cameras' offsets from
    their mean pose, in its frame) with an in-and-out component, ``SPIRAL_ROTATIONS`` turns,
    always looking at the point ``focus_depth`` in front of the mean pose.
    """
    poses = train_poses.double()
    center = poses[:, :3, 3].mean(0)
    back = _normalize(poses[:, :3, 2].mean(0))
    right = _normalize(torch.linalg.cross(poses[:, :3, 1].mean(0), back))
    up = torch.linalg.cross(back, right)
    frame = torch.stack([right, up, back], dim=-1)  # mean pose's axes as columns
    local = (poses[:, :3, 3] - center) @ frame
    radii = torch.quantile(local.abs(), 0.9, dim=0)
    theta = torch.arange(n_frames, dtype=torch.float64) * (2 * math.pi * SPIRAL_ROTATIONS / n_frames)
    wave = torch.stack([torch.cos(theta), -torch.sin(theta), -torch.sin(SPIRAL_Z_RATE * theta)], dim=-1)
    eye = center + (wave * radii) @ frame.T
    focus = center - focus_depth * back
    return look_at(eye, focus, up).float()


def spiral_focus_depth(scene: dict[str, Any]) -> float:
    """NeRF's focus depth 1 / (0.25 / near + 0.75 / (5 far)) of a forward-facing scene.

    For NDC scenes the world is rescaled so that the nearest content is at 1 / BD_FACTOR and the
    far bound is unknown (treated as infinite), giving near / 0.25 with near = 0.9 / BD_FACTOR.
    """
    if scene["ndc"]:
        return (0.9 / BD_FACTOR) / 0.25
    return 1.0 / (0.25 / scene["near"] + 0.75 / (5.0 * scene["far"]))


def camera_path(scene: dict[str, Any], n_frames: int, kind: str = "auto") -> tuple[torch.Tensor, str]:
    """Poses for a video of a trained scene and the path kind used ("auto": spiral for
    forward-facing (NDC or LLFF) scenes, turntable otherwise)."""
    if kind not in GENERATED_PATHS:
        raise ValueError(f"path must be one of {GENERATED_PATHS}, got {kind!r}")
    if kind == "auto":
        kind = "spiral" if scene["ndc"] or scene["format"] == "llff" else "turntable"
    if kind == "spiral":
        return spiral_poses(scene["train_poses"], n_frames, spiral_focus_depth(scene)), kind
    bbox = scene["bbox"]
    center = None if bbox is None else (bbox[0] + bbox[1]) / 2
    return turntable_poses(scene["train_poses"], n_frames, center), kind


def path_cameras(run: TrainedRun, path: str, n_frames: int) -> CameraPath:
    """The cameras of ``path``: a generated path (``n_frames`` of them), "train" or "test" (the
    dataset's own cameras) or a nerfstudio camera-path JSON file."""
    if path in GENERATED_PATHS:
        poses, kind = camera_path(run.scene, n_frames, path)
        return fixed_intrinsics_path(poses, run.scene, kind)
    if path == "train":
        return fixed_intrinsics_path(run.scene["train_poses"], run.scene, "train")
    if path in DATASET_PATHS:
        folder, fmt = scene_source(run.cfg)
        return split_path(folder, fmt, path, run.cfg.downscale, run.cfg.val_holdout)
    return read_nerfstudio_path(path)


def frame_rays(scene: dict[str, Any], cameras: CameraPath, i: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays (H*W, 3) of camera ``i`` of ``cameras``, warped to NDC for an NDC ``scene``."""
    focal = float(cameras.focals[i])
    c2w = cameras.poses[i].double()
    origins, dirs = camera_rays(cameras.H, cameras.W, focal, c2w, cameras.cx, cameras.cy)
    origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    if scene["ndc"]:
        origins, dirs = ndc_rays(cameras.H, cameras.W, focal, NDC_NEAR, origins, dirs)
    return origins.float(), dirs.float()


class Frame(NamedTuple):
    """One rendered camera: colour (H, W, 3), depth and opacity (H, W) on the CPU, and its rays
    (H*W, 3) as rendered (in NDC for NDC scenes)."""

    color: torch.Tensor
    depth: torch.Tensor
    opacity: torch.Tensor
    rays_o: torch.Tensor
    rays_d: torch.Tensor


def render_frames(run: TrainedRun, cameras: CameraPath) -> Iterator[Frame]:
    """Render each camera of ``cameras`` in turn."""
    H, W = cameras.H, cameras.W
    for i in range(len(cameras)):
        rays_o, rays_d = frame_rays(run.scene, cameras, i)
        result = run.render(rays_o, rays_d)
        yield Frame(result.color.reshape(H, W, 3).cpu(), result.depth.reshape(H, W).cpu(),
                    result.opacity.reshape(H, W).cpu(), rays_o, rays_d)  # fmt: skip


# -- images and videos ----------------------------------------------------------------------------


def to_uint8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] -> uint8 (values outside are clipped)."""
    array = image.detach().float().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    return (np.clip(array, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def depth_range(
    depths: list[torch.Tensor], opacities: list[torch.Tensor], fallback: tuple[float, float]
) -> tuple[float, float]:
    """Robust (2nd, 98th percentile) depth range over pixels that are mostly opaque."""
    solid = torch.cat([d[o > 0.5].flatten().float().cpu() for d, o in zip(depths, opacities, strict=True)])
    if solid.numel() < 2:
        return fallback
    lo, hi = torch.quantile(solid[:1_000_000], torch.tensor([0.02, 0.98])).tolist()
    return (lo, hi) if hi > lo else fallback


def colorize_depth(depth: torch.Tensor, opacity: torch.Tensor, lo: float, hi: float) -> np.ndarray:
    """(H, W) depth -> (H, W, 3) uint8, near = dark end of the colour map, faded to black where
    the ray hit nothing (weighted by opacity)."""
    from matplotlib import colormaps

    t = ((depth.float().cpu() - lo) / max(hi - lo, 1e-12)).clamp(0, 1).numpy()
    rgb = colormaps[DEPTH_COLORMAP](t)[..., :3] * opacity.float().cpu().clamp(0, 1).numpy()[..., None]
    return to_uint8(rgb)


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write a PNG atomically (a killed run leaves the old file or the new one)."""
    import imageio.v3 as iio

    with atomic_path(path) as tmp:
        iio.imwrite(tmp, image)


def video_format() -> str:
    """ "mp4" when imageio-ffmpeg is installed, else "gif"."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return "gif"
    return "mp4"


def write_video(stem: str | Path, frames: list[np.ndarray], fps: int) -> Path:
    """Write uint8 (H, W, 3) ``frames`` to ``stem``.mp4, or ``stem``.gif without ffmpeg, atomically
    (an earlier video there stays whole until the new one is complete). Returns the path."""
    check_fps(fps)
    stem = Path(stem)
    if video_format() == "mp4":
        import imageio.v2 as iio2

        path = stem.with_suffix(".mp4")
        # H.264 in yuv420p needs even sizes: pad by repeating the last row/column.
        h, w = frames[0].shape[:2]
        even = [np.pad(f, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") for f in frames]
        try:
            with atomic_path(path) as tmp:
                iio2.mimwrite(tmp, even, fps=fps, macro_block_size=1, ffmpeg_log_level="error")
                if not tmp.is_file() or tmp.stat().st_size == 0:  # ffmpeg failures do not always raise
                    raise OSError("ffmpeg wrote nothing")
            return path
        except OutputError:
            pass  # fall back to a GIF
    import imageio.v3 as iio

    path = stem.with_suffix(".gif")
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, np.stack(frames), duration=1000.0 / fps, loop=0)
    return path


def check_fps(fps: int) -> None:
    """Raise ValueError unless ``fps`` is a positive whole number of frames per second."""
    if isinstance(fps, bool) or not isinstance(fps, int) or fps < 1:
        raise ValueError(f"fps must be a positive whole number, got {fps!r}")


def render_video(
    ckpt: str | Path,
    out: str | Path | None = None,
    frames: int = 120,
    path: str = "auto",
    fps: int = 30,
    scale: float = 1.0,
    device: str | None = None,
    backend: str | None = None,
    render_samples: int | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Render a camera path from a checkpoint: ``video.mp4|gif``, ``depth.mp4|gif`` and
    ``depth/frame_NNNN.png`` in ``out`` (default: ``<checkpoint folder>/video``).

    ``path`` is one of ``PATHS`` or a nerfstudio camera-path JSON file (see :func:`path_cameras`);
    ``frames`` counts the frames of a generated path only.

    Returns:
        {"video", "depth_video", "depth_frames", "path", "frames", "format", "depth_range"}.
    """
    if frames < 1:
        raise ValueError(f"frames must be positive, got {frames}")
    if not 0 < scale < math.inf:
        raise ValueError(f"scale must be positive and finite, got {scale}")
    check_fps(fps)
    run = load_trained(ckpt, device=device, backend=backend, render_samples=render_samples)
    cameras = path_cameras(run, path, frames).scaled(scale)
    pixels, n = cameras.H * cameras.W, len(cameras)
    # Per pixel: one frame's rays in float64 then float32 (18 numbers) and its renders (5); every
    # frame's colour, depth and opacity until the videos are written (3 bytes and 2 floats).
    check_fits(f"--scale {scale:g} with {n} frames", pixels * (23 * FLOAT_BYTES + n * (3 + 2 * FLOAT_BYTES)),
               torch.device("cpu"))
    check_fits(f"--scale {scale:g}", pixels * 11 * FLOAT_BYTES, run.device)  # rays and renders
    out = Path(out) if out is not None else run.path.parent / "video"
    depth_dir = out / "depth"
    ensure_writable_folder(depth_dir)
    log(f"rendering {len(cameras)} frames on the {cameras.kind} path from {run.path} (step {run.step})")
    colors, depths, opacities = [], [], []
    for frame in render_frames(run, cameras):
        colors.append(to_uint8(frame.color))
        depths.append(frame.depth)
        opacities.append(frame.opacity)
    lo, hi = depth_range(depths, opacities, fallback=(run.scene["near"], run.scene["far"]))
    depth_frames = [colorize_depth(d, o, lo, hi) for d, o in zip(depths, opacities, strict=True)]
    for i, image in enumerate(depth_frames):
        write_png(depth_dir / f"frame_{i:04d}.png", image)
    video = write_video(out / "video", colors, fps)
    depth_video = write_video(out / "depth", depth_frames, fps)
    return {
        "video": str(video),
        "depth_video": str(depth_video),
        "depth_frames": str(depth_dir),
        "path": cameras.kind,
        "frames": len(cameras),
        "format": video.suffix[1:],
        "depth_range": [lo, hi],
    }


def _normalize(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _snap_to_axis(v: torch.Tensor) -> torch.Tensor:
    """The signed world axis nearest the unit vector ``v`` if within AXIS_SNAP_DEGREES, else ``v``."""
    k = int(v.abs().argmax())
    if v[k].abs() < math.cos(math.radians(AXIS_SNAP_DEGREES)):
        return v
    axis = torch.zeros_like(v)
    axis[k] = torch.sign(v[k])
    return axis


def _any_perpendicular(v: torch.Tensor) -> torch.Tensor:
    """A unit vector not parallel to ``v`` (the world axis least aligned with it)."""
    axis = torch.zeros_like(v)
    axis[v.abs().argmin()] = 1.0
    return axis
