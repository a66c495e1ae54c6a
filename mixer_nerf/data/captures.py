"""Photo captures with solved poses (COLMAP models, nerfstudio transforms) -> a normalised Scene.

What the loaders of such captures share:

- Views are ordered by file name; the test split is every ``holdout``-th view from view 0, as for
  LLFF, and val is the same views unless ``val_holdout`` carves a val split of its own out of train.
- Every photo is resampled into one pinhole camera (:func:`.camera.shared_pinhole`): lens
  distortion is removed from the images, not the rays. Images are stored as uint8.
- Forward-facing or 360: a capture is forward-facing when every camera looks within
  FORWARD_FACING_DEGREES of the cameras' mean viewing direction.

  * Forward-facing captures are framed as LLFF's: depths are scaled so that the nearest content
    (the NEAR_PERCENTILE of the sparse points' depths in the view that sees them closest) lies at
    1 / BD_FACTOR, and poses are recentred on their average pose. With ``ndc`` (the default for
    them) rays are warped to NDC (near 0, far 1, box [-1, 1]^3); without, they stay world rays
    from 0.9 x the nearest depth to the farthest (FAR_PERCENTILE), with no box.
  * 360 captures get their box from the camera positions (sparse points of a real capture also
    hold the far background, which no box should enclose): the world is centred on the point
    closest to every optical axis (what the cameras circle), turned so that the cameras' mean
    up vector is +z, and scaled so that the farthest camera is at distance 1. The box is
    [-1, 1]^3: it holds every camera and what they look at; rays run from NEAR_360 to the box's
    diagonal.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .blender import BACKGROUNDS
from .camera import Camera, resample, shared_pinhole
from .errors import DatasetError
from .images import check_downscale, composite, downscale, read_image, to_uint8
from .llff import BD_FACTOR, SPLITS, average_pose, recenter_poses, split_indices
from .scene import Scene

FORWARD_FACING_DEGREES = 30.0
NEAR_PERCENTILE, FAR_PERCENTILE = 1.0, 99.0
NEAR_360 = 0.05  # in units of the farthest camera's distance from the centre


@dataclass(frozen=True)
class View:
    """One photo: its file, camera-to-world (4, 4) in the OpenGL convention and its camera."""

    path: Path
    c2w: np.ndarray
    camera: Camera


def load_capture(
    views: Sequence[View],
    points: np.ndarray | None,
    *,
    where: Path,
    name: str,
    split: str,
    holdout: int,
    downscale: float,
    val_holdout: int = 0,
    ndc: bool | None,
    background: str,
) -> Scene:
    """One split of a capture as a Scene (see the module docstring for the conventions).

    Args:
        views: every view of the capture (splits share the frame computed from all of them).
        points: (P, 3) sparse scene points in the poses' world frame, or None. Forward-facing
            captures need them (they set the depth scale).
        where: the file or folder named in errors.
        name: the scene's name.
        split: "train", "test", "val" or "all".
        holdout: test stride (0: no test views).
        val_holdout: 0 (val is the test views) or a val stride among the other views (see
            :func:`.llff.split_indices`).
        downscale: image shrink factor, any number >= 1.
        ndc: None decides from the cameras (NDC exactly for forward-facing captures); True frames
            the capture as forward-facing with NDC rays; False uses world rays (forward-facing
            framing without NDC, or the 360 framing).
        background: "black" or "white", what transparent pixels are composited on.
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if background not in BACKGROUNDS:
        raise ValueError(f"background must be one of {sorted(BACKGROUNDS)}, got {background!r}")
    factor = check_downscale(downscale)
    if not views:
        raise DatasetError(f"{where}: no views (the dataset is empty)")
    views = sorted(views, key=lambda v: str(v.path))
    cameras = [v.camera.downscaled(factor) for v in views]
    target = shared_pinhole(cameras, str(where))
    c2w = np.stack([v.c2w for v in views]).astype(np.float64)
    forward = is_forward_facing(c2w) if ndc is None else ndc or is_forward_facing(c2w)
    if forward:
        c2w, near, far = _frame_forward_facing(c2w, points, target, where)
        use_ndc = ndc is not False
        near, far = (0.0, 1.0) if use_ndc else (0.9 * near, far)
        bbox = torch.tensor([[-1.0] * 3, [1.0] * 3]) if use_ndc else None
    else:
        c2w, use_ndc = _frame_360(c2w), False
        near, far, bbox = NEAR_360, 2.0 * math.sqrt(3.0), torch.tensor([[-1.0] * 3, [1.0] * 3])

    idx = split_indices(len(views), split, holdout, where, val_holdout)
    bg = np.array(BACKGROUNDS[background], dtype=np.float32)
    images = np.empty((len(idx), target.height, target.width, 3), dtype=np.uint8)
    for row, i in enumerate(idx):
        images[row] = to_uint8(_photo(views[i], factor, cameras[i], target, bg))
    return Scene(
        images=torch.from_numpy(images),
        poses=torch.from_numpy(c2w[idx].astype(np.float32)),
        H=target.height,
        W=target.width,
        focal=target.fx,
        cx=target.cx,
        cy=target.cy,
        near=near,
        far=far,
        bbox=bbox,
        ndc=use_ndc,
        background=torch.from_numpy(bg),
        name=name,
        split=split,
        image_paths=[views[i].path for i in idx],
    )


def is_forward_facing(c2w: np.ndarray) -> bool:
    """Every camera of (N, 4, 4) OpenGL poses looks within FORWARD_FACING_DEGREES of the mean
    viewing direction (zero when they look every way around: not forward-facing)."""
    looks = -c2w[:, :3, 2]
    mean = looks.mean(axis=0)
    norm = np.linalg.norm(mean)
    if norm < 1e-9:
        return False
    return bool((looks @ (mean / norm) >= math.cos(math.radians(FORWARD_FACING_DEGREES))).all())


def _photo(view: View, factor: float, camera: Camera, target: Camera, bg: np.ndarray) -> np.ndarray:
    """View's photo, composited, downscaled and resampled into ``target``: float (H, W, 3)."""
    img = read_image(view.path)
    if img.shape[:2] != (view.camera.height, view.camera.width):
        raise DatasetError(
            f"{view.path}: image is {img.shape[1]}x{img.shape[0]} but its camera is "
            f"{view.camera.width}x{view.camera.height}"
        )
    return resample(downscale(composite(img, bg), factor, view.path), camera, target)


def _frame_forward_facing(
    c2w: np.ndarray, points: np.ndarray | None, camera: Camera, where: Path
) -> tuple[np.ndarray, float, float]:
    """LLFF's framing: (recentred poses, nearest depth, farthest depth) after the rescale."""
    if points is None or len(points) == 0:
        raise DatasetError(
            f"{where}: a forward-facing capture needs sparse points to set its depth range (NDC); "
            "use a COLMAP model or a transforms.json with ply_file_path"
        )
    depths = [d for d in (_visible_depths(pose, points, camera) for pose in c2w) if d.size]
    if not depths:
        raise DatasetError(f"{where}: no sparse point lies in front of any camera")
    near = min(np.percentile(d, NEAR_PERCENTILE) for d in depths)
    far = max(np.percentile(d, FAR_PERCENTILE) for d in depths)
    scale = 1.0 / (near * BD_FACTOR)
    c2w = c2w.copy()
    c2w[:, :3, 3] *= scale
    if ((c2w[:, :3, 2] @ average_pose(c2w)[:3, 2]) <= 0).any():
        raise DatasetError(
            f"{where}: some cameras look away from the others; NDC needs a forward-facing capture"
        )
    return recenter_poses(c2w), near * scale, far * scale


def _visible_depths(c2w: np.ndarray, points: np.ndarray, camera: Camera) -> np.ndarray:
    """Depths along the optical axis of the points in front of pinhole ``camera`` at ``c2w``
    that project inside its image."""
    local = (points - c2w[:3, 3]) @ c2w[:3, :3]  # world -> camera (OpenGL axes)
    depth = -local[:, 2]
    ahead = depth > 1e-9
    u = camera.fx * local[ahead, 0] / depth[ahead] + camera.cx
    v = -camera.fy * local[ahead, 1] / depth[ahead] + camera.cy
    inside = (u >= 0) & (u <= camera.width) & (v >= 0) & (v <= camera.height)
    return depth[ahead][inside]


def _frame_360(c2w: np.ndarray) -> np.ndarray:
    """Poses centred on their focus point, mean up along +z, farthest camera at distance 1."""
    centre = _focus_point(c2w)
    up = c2w[:, :3, 1].mean(axis=0)
    up /= np.linalg.norm(up)
    helper = np.eye(3)[np.argmin(np.abs(up))]  # the world axis least aligned with up
    x = np.cross(helper, up)
    x /= np.linalg.norm(x)
    rotation = np.stack([x, np.cross(up, x), up])  # rows: the new axes in old coordinates
    scale = 1.0 / np.linalg.norm(c2w[:, :3, 3] - centre, axis=1).max()
    out = c2w.copy()
    out[:, :3, :3] = rotation @ c2w[:, :3, :3]
    out[:, :3, 3] = scale * (c2w[:, :3, 3] - centre) @ rotation.T
    return out


def _focus_point(c2w: np.ndarray) -> np.ndarray:
    """The point with the least summed squared distance to every camera's optical axis."""
    axes = c2w[:, :3, 2]
    projectors = np.eye(3) - axes[:, :, None] * axes[:, None, :]  # onto each axis's normal plane
    return np.linalg.solve(projectors.sum(axis=0), (projectors @ c2w[:, :3, 3, None]).sum(axis=0))[:, 0]
