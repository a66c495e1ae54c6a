"""LLFF forward-facing captures: ``poses_bounds.npy`` + ``images_{factor}/``.

``poses_bounds.npy`` is (N, 17): per view a row-major 3x5 matrix, whose first four columns are the
camera-to-world matrix with its axes in LLFF order [down, right, back] and whose last column is
[H, W, focal] at full resolution, followed by the near and far depth bounds of the view. Images
are the files of ``images_{factor}/`` (``images/`` for factor 1) in name order, one per row.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .errors import DatasetError, MissingFileError
from .images import check_downscale, list_images, read_image, stack_same_size, to_uint8
from .images import downscale as downscale_image
from .scene import Scene

BD_FACTOR = 0.75
"""Poses are rescaled so that the nearest bound becomes 1 / BD_FACTOR: a little beyond the NDC near
plane at depth 1 (as in NeRF)."""

SPLITS = ("train", "test", "val", "all")


def load_llff(
    root: str | Path,
    factor: int = 8,
    split: str = "train",
    holdout: int = 8,
    ndc: bool = True,
    val_holdout: int = 0,
    downscale: float = 1.0,
) -> Scene:
    """Load an LLFF scene.

    Poses are converted to the OpenGL axis order, scaled by 1 / (BD_FACTOR * nearest bound) and
    recentred on their average pose, all computed over every view so splits share one frame.

    Args:
        root: folder holding ``poses_bounds.npy``.
        factor: image downscale; images come from ``images_{factor}/`` and H, W, focal are divided
            by it (checked against the actual image size).
        split: "train" (every view not held out), "test" (every ``holdout``-th view, starting with
            view 0), "val" (the test views, or see ``val_holdout``), or "all".
        holdout: test stride; 0 holds out nothing.
        val_holdout: 0, or a val stride K: every K-th of the views left after the test views is
            the val split, and train loses them (see :func:`split_indices`).
        ndc: use NDC rays (near 0, far 1, bbox [-1, 1]^3); otherwise world rays with near/far from
            the bounds (0.9 x nearest, farthest) and no bbox.
        downscale: a further shrink of the ``images_{factor}/`` images, any number >= 1
            (:func:`.images.downscale`).

    Returns:
        A Scene with uint8 images.
    """
    root = Path(root)
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if not isinstance(factor, int) or factor < 1:
        raise ValueError(f"factor must be a positive integer, got {factor!r}")
    downscale = check_downscale(downscale)
    pb_path = root / "poses_bounds.npy"
    llff_poses, bounds, hwf = read_poses_bounds(pb_path)
    image_dir = root / ("images" if factor == 1 else f"images_{factor}")
    paths = list_images(image_dir)
    if len(paths) != len(llff_poses):
        raise DatasetError(
            f"{image_dir}: holds {len(paths)} images but {pb_path} has {len(llff_poses)} poses"
        )

    c2w = llff_to_opengl(llff_poses)
    scale = 1.0 / (bounds.min() * BD_FACTOR)
    c2w[:, :3, 3] *= scale
    bounds = bounds * scale
    c2w = recenter_poses(c2w)

    idx = split_indices(len(paths), split, holdout, root, val_holdout)
    chosen = [paths[i] for i in idx]
    images = stack_same_size([to_uint8(read_image(p)[..., :3]) for p in chosen], chosen)
    _, H, W, _ = images.shape
    full_h, full_w, full_focal = hwf[0]
    if abs(full_h / factor - H) >= 1 or abs(full_w / factor - W) >= 1:
        raise DatasetError(
            f"{chosen[0]}: image is {W}x{H}, but {pb_path} gives {full_w:g}x{full_h:g} at full "
            f"resolution, i.e. {full_w / factor:g}x{full_h / factor:g} at factor {factor}"
        )
    if downscale != 1:
        pairs = zip(images, chosen, strict=True)
        images = np.stack([to_uint8(downscale_image(img / 255.0, downscale, p)) for img, p in pairs])
    focal, cx, cy = float(full_focal) / factor / downscale, W / 2 / downscale, H / 2 / downscale
    _, H, W, _ = images.shape
    near, far = (0.0, 1.0) if ndc else (float(bounds.min()) * 0.9, float(bounds.max()))
    return Scene(
        images=torch.from_numpy(images),
        poses=torch.from_numpy(c2w[idx].astype(np.float32)),
        H=H,
        W=W,
        focal=focal,
        cx=cx,
        cy=cy,
        near=near,
        far=far,
        bbox=torch.tensor([[-1.0] * 3, [1.0] * 3]) if ndc else None,
        ndc=ndc,
        background=torch.zeros(3),
        name=root.name,
        split=split,
        image_paths=chosen,
    )


def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read and validate ``poses_bounds.npy``.

    Returns:
        poses (N, 3, 4) in LLFF axis order, bounds (N, 2), hwf (N, 3) = [H, W, focal]; float64.
    """
    if not path.is_file():
        raise MissingFileError(f"{path}: poses file not found")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as exc:  # numpy raises ValueError/OSError/EOFError/... for corrupt files
        raise DatasetError(f"{path}: cannot read as a .npy array ({type(exc).__name__}: {exc})") from exc
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise DatasetError(f"{path}: expected an (N, 17) array, got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise DatasetError(f"{path}: has no views (the dataset is empty)")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise DatasetError(f"{path}: has non-finite values")
    mats = arr[:, :15].reshape(-1, 3, 5)
    bounds = arr[:, 15:]
    hwf = mats[:, :, 4]
    if (bounds <= 0).any():
        raise DatasetError(f"{path}: near/far bounds must be positive")
    if (hwf <= 0).any() or not np.allclose(hwf, hwf[0]):
        raise DatasetError(f"{path}: H, W, focal must be positive and the same for every view")
    return mats[:, :, :4], bounds, hwf


def llff_to_opengl(poses: np.ndarray) -> np.ndarray:
    """Reorder rotation columns from LLFF [down, right, back] to OpenGL [right, up, back].

    Args:
        poses: (..., 3, 4) camera-to-world in LLFF order.

    Returns:
        (..., 4, 4) camera-to-world in OpenGL order (a new array).
    """
    down, right, back, centre = (poses[..., :, k] for k in range(4))
    out = np.zeros(poses.shape[:-2] + (4, 4), dtype=poses.dtype)
    out[..., :3, :] = np.stack([right, -down, back, centre], axis=-1)
    out[..., 3, 3] = 1.0
    return out


def average_pose(c2w: np.ndarray) -> np.ndarray:
    """The mean camera of (N, 3|4, 4) poses as a (4, 4) matrix: mean centre, looking back along
    the normalised mean back axis, with the mean up axis made orthogonal to it."""
    centre = c2w[:, :3, 3].mean(axis=0)
    back = _normalize(c2w[:, :3, 2].sum(axis=0))
    right = _normalize(np.cross(c2w[:, :3, 1].sum(axis=0), back))
    up = np.cross(back, right)
    avg = np.eye(4)
    avg[:3, :] = np.stack([right, up, back, centre], axis=-1)
    return avg


def recenter_poses(c2w: np.ndarray) -> np.ndarray:
    """Express (N, 4, 4) poses in the frame of their average pose, which becomes the identity."""
    return np.linalg.inv(average_pose(c2w)) @ c2w


def split_indices(n: int, split: str, holdout: int, root: Path, val_holdout: int = 0) -> np.ndarray:
    """Indices of ``split`` among n views: test is every ``holdout``-th view from view 0. val is
    the test views, unless ``val_holdout`` K > 0: then every K-th of the other views, from their
    first, is a val split of its own that train leaves out, so a recipe can be tuned on val without
    looking at test."""
    if val_holdout < 0:
        raise ValueError(f"val_holdout must be >= 0, got {val_holdout}")
    test = np.arange(n)[::holdout] if holdout > 0 else np.arange(0)
    rest = np.setdiff1d(np.arange(n), test)
    val = rest[::val_holdout] if val_holdout > 0 else test
    if split == "all":
        idx = np.arange(n)
    elif split == "test":
        idx = test
    elif split == "val":
        idx = val
    else:
        idx = np.setdiff1d(rest, val)  # val is among the test views unless carved out of the rest
    if idx.size == 0:
        raise DatasetError(f"{root}: split {split!r} is empty ({n} views, holdout {holdout})")
    return idx


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)
