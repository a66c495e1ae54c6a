"""Blender / nerf_synthetic format: ``transforms_{split}.json`` + RGBA PNGs.

The JSON holds ``camera_angle_x`` (horizontal field of view, radians) and ``frames``, each with a
``file_path`` relative to the scene folder and without extension (".png" is appended) and a 4x4
camera-to-world ``transform_matrix`` already in the OpenGL convention.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from .errors import DatasetError, MissingFileError
from .images import IMAGE_SUFFIXES, check_downscale, composite, read_image, stack_same_size, write_png
from .images import downscale as downscale_image
from .scene import Scene

BLENDER_BBOX = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
BLENDER_NEAR, BLENDER_FAR = 2.0, 6.0
BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def load_blender(
    root: str | Path, split: str = "train", background: str = "white", downscale: float = 1.0,
    val_holdout: int = 0,
) -> Scene:
    """Load one split of a Blender-format scene.

    Args:
        root: scene folder holding ``transforms_{split}.json``.
        split: "train", "val" or "test" (any name with a transforms file works).
        background: "white" or "black", the colour transparent pixels are composited on.
        downscale: any number >= 1; images shrink by area averaging (:func:`.images.downscale`)
            and the intrinsics with them.
        val_holdout: 0, or a val split carved out of the training views (:func:`holdout_split`),
            to tune on views other than the scene's own held-out ones.

    Returns:
        A Scene with bbox [-1.5, 1.5]^3, near 2 and far 6 (the nerf_synthetic conventions), and
        float32 images (compositing makes values 8 bits would round).
    """
    root = Path(root)
    if background not in BACKGROUNDS:
        raise ValueError(f"background must be one of {sorted(BACKGROUNDS)}, got {background!r}")
    downscale = check_downscale(downscale)
    bg = np.array(BACKGROUNDS[background], dtype=np.float32)
    file_split, keep = holdout_split(root, split, val_holdout)
    meta_path = root / f"transforms_{file_split}.json"
    angle_x, frames = _read_transforms(meta_path)
    if keep is not None:
        frames = [frames[k] for k in keep(len(frames), meta_path)]

    paths, images, poses = [], [], []
    for k, frame in enumerate(frames):
        path = frame_image_path(root, frame["file_path"])
        poses.append(frame_pose(frame["transform_matrix"], meta_path, k))
        images.append(composite(read_image(path), bg))
        paths.append(path)
    stacked = stack_same_size(images, paths)
    _, full_h, full_w, _ = stacked.shape
    if downscale != 1:
        pairs = zip(stacked, paths, strict=True)
        stacked = np.stack([downscale_image(img, downscale, path) for img, path in pairs])
    _, H, W, _ = stacked.shape
    return Scene(
        images=torch.from_numpy(stacked),
        poses=torch.from_numpy(np.stack(poses)),
        H=H,
        W=W,
        focal=0.5 * full_w / math.tan(0.5 * angle_x) / downscale,
        cx=full_w / 2 / downscale,
        cy=full_h / 2 / downscale,
        near=BLENDER_NEAR,
        far=BLENDER_FAR,
        bbox=torch.tensor(BLENDER_BBOX, dtype=torch.float32),
        ndc=False,
        background=torch.from_numpy(bg),
        name=root.name,
        split=split,
        image_paths=paths,
    )


def holdout_split(
    root: Path, split: str, val_holdout: int
) -> tuple[str, Callable[[int, Path], Sequence[int]] | None]:
    """Where ``split`` of a scene with a carved val split (``val_holdout`` K > 0) comes from: the
    transforms file's split and which of its frames to keep (None: all). val is every K-th training
    frame from the first and train the others; test is the scene's test split, or its own val split
    when it ships no test views (those are then the views nothing was tuned on)."""
    if val_holdout < 0:
        raise ValueError(f"val_holdout must be >= 0, got {val_holdout}")
    if not val_holdout:
        return split, None
    if split == "test":
        return ("test" if (root / "transforms_test.json").is_file() else "val"), None
    if split not in ("train", "val"):
        return split, None

    def keep(n: int, path: Path) -> Sequence[int]:
        val = range(0, n, val_holdout)
        kept = val if split == "val" else sorted(set(range(n)) - set(val))
        if not kept:
            raise DatasetError(f"{path}: val_holdout {val_holdout} leaves the {split!r} split empty "
                               f"({n} frames)")
        return kept

    return "train", keep


def write_blender_split(
    root: str | Path,
    split: str,
    images: Sequence[np.ndarray],
    poses: np.ndarray,
    camera_angle_x: float,
) -> Path:
    """Write one split in Blender format: images as ``{split}/r_{k}.png`` plus the JSON.

    Args:
        images: N float (H, W, 3|4) images in [0, 1] (RGBA with straight alpha for transparency).
        poses: (N, 4, 4) camera-to-world, OpenGL convention.
        camera_angle_x: horizontal field of view in radians.

    Returns:
        The path of ``transforms_{split}.json``.
    """
    root = Path(root)
    frames = []
    for k, (img, pose) in enumerate(zip(images, poses, strict=True)):
        rel = f"./{split}/r_{k}"
        write_png(root / (rel + ".png"), img)
        frames.append({"file_path": rel, "transform_matrix": np.asarray(pose, dtype=float).tolist()})
    meta_path = root / f"transforms_{split}.json"
    meta_path.write_text(json.dumps({"camera_angle_x": float(camera_angle_x), "frames": frames}, indent=1))
    return meta_path


def _read_transforms(path: Path) -> tuple[float, list[dict]]:
    """Parse and validate a transforms JSON: (camera_angle_x, non-empty frames)."""
    meta = read_json_object(path)
    if "camera_angle_x" not in meta:
        raise DatasetError(f"{path}: missing key 'camera_angle_x'")
    angle = meta["camera_angle_x"]
    if not isinstance(angle, (int, float)) or not 0 < angle < math.pi:
        raise DatasetError(f"{path}: camera_angle_x must be a number in (0, pi), got {angle!r}")
    return float(angle), checked_frames(meta, path)


def read_json_object(path: Path) -> dict:
    """The JSON object in ``path`` (MissingFileError / DatasetError naming it otherwise)."""
    if not path.is_file():
        raise MissingFileError(f"{path}: transforms file not found")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    return meta


def checked_frames(meta: dict, path: Path) -> list[dict]:
    """``meta["frames"]``: a non-empty list of objects, each with a string ``file_path`` and a
    ``transform_matrix``."""
    if "frames" not in meta:
        raise DatasetError(f"{path}: missing key 'frames'")
    frames = meta["frames"]
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: 'frames' must be a non-empty list (the dataset is empty)")
    for k, frame in enumerate(frames):
        for key in ("file_path", "transform_matrix"):
            if not isinstance(frame, dict) or key not in frame:
                raise DatasetError(f"{path}: frames[{k}] is missing key {key!r}")
        if not isinstance(frame["file_path"], str):
            raise DatasetError(f"{path}: frames[{k}].file_path must be a string")
    return frames


def frame_image_path(root: Path, file_path: str) -> Path:
    """nerf_synthetic omits the extension; files that name one are taken as they are."""
    path = root / file_path
    return path if path.suffix.lower() in IMAGE_SUFFIXES else path.with_name(path.name + ".png")


def frame_pose(matrix: object, path: Path, k: int) -> np.ndarray:
    """A frame's transform_matrix as a finite float32 (4, 4) array."""
    try:
        pose = np.asarray(matrix, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: frames[{k}].transform_matrix is not a numeric matrix") from exc
    if pose.shape != (4, 4):
        raise DatasetError(f"{path}: frames[{k}].transform_matrix must be 4x4, got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise DatasetError(f"{path}: frames[{k}].transform_matrix has non-finite values")
    return pose
