"""nerfstudio / instant-ngp captures: one ``transforms.json`` for every view.

Each frame has a ``file_path`` (relative to the scene folder; without an extension ".png" is
appended, as in nerf_synthetic) and a 4x4 camera-to-world ``transform_matrix`` in the OpenGL
convention. Intrinsics come from the frame, else from the top level, so one shared camera and
per-frame cameras both work:

- ``w``, ``h``: image size (default: read from the image file);
- ``fl_x``, ``fl_y``: focal lengths in pixels, or ``camera_angle_x`` / ``camera_angle_y``: fields
  of view in radians (``fl_y`` defaults to ``fl_x``);
- ``cx``, ``cy``: principal point (default: the image centre);
- ``k1``, ``k2``, ``p1``, ``p2``: OpenCV radial-tangential distortion, removed by resampling the
  images (:mod:`.camera`); ``k3`` / ``k4`` and fisheye or equirectangular ``camera_model``\\ s are
  refused with a one-line error.

The optional top-level ``ply_file_path`` names the sparse point cloud nerfstudio writes; forward-
facing captures need it for their depth range. Framing and splits are those of :mod:`.captures`.
"""

from __future__ import annotations

import math
from pathlib import Path

from PIL import Image

from .blender import checked_frames, frame_image_path, frame_pose, read_json_object
from .camera import Camera
from .captures import View, load_capture
from .errors import DatasetError, MissingFileError
from .ply import read_ply_points
from .scene import Scene

TRANSFORMS = "transforms.json"
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
UNSUPPORTED_TERMS = ("k3", "k4")
INTRINSIC_KEYS = ("w", "h", "fl_x", "fl_y", "camera_angle_x", "camera_angle_y", "cx", "cy",
                  "k1", "k2", "p1", "p2", *UNSUPPORTED_TERMS)  # fmt: skip


def load_nerfstudio(
    root: str | Path,
    split: str = "train",
    holdout: int = 8,
    downscale: float = 1.0,
    val_holdout: int = 0,
    ndc: bool | None = None,
    background: str = "black",
) -> Scene:
    """Load the capture of ``root/transforms.json``: arguments and result as for
    :func:`.colmap.load_colmap` (splits go by frame file name)."""
    root = Path(root)
    path = root / TRANSFORMS
    meta = read_json_object(path)
    views = []
    for k, frame in enumerate(checked_frames(meta, path)):
        image = frame_image_path(root, frame["file_path"])
        values = {key: value for key, value in {**meta, **frame}.items() if value is not None}
        views.append(
            View(image, frame_pose(frame["transform_matrix"], path, k), _camera(values, image, path, k))
        )
    points = None
    if "ply_file_path" in meta:
        if not isinstance(meta["ply_file_path"], str):
            raise DatasetError(f"{path}: ply_file_path must be a string")
        points = read_ply_points(root / meta["ply_file_path"])
    return load_capture(
        views, points, where=path, name=root.resolve().name, split=split, holdout=holdout,
        downscale=downscale, val_holdout=val_holdout, ndc=ndc, background=background,
    )  # fmt: skip


def _camera(values: dict, image: Path, path: Path, k: int) -> Camera:
    """Frame ``k``'s camera from its keys merged over the top-level ones (nulls dropped)."""
    where = f"{path}: frames[{k}]"
    model = values.get("camera_model", "OPENCV")
    if model not in PINHOLE_MODELS:
        raise DatasetError(
            f"{where}: camera_model {model!r} is not supported (supported: {', '.join(PINHOLE_MODELS)}); "
            "undistort the images first"
        )
    for key in INTRINSIC_KEYS:
        value = values.get(key, 0.0)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise DatasetError(f"{where}: {key} must be a number, got {value!r}")
    for key in UNSUPPORTED_TERMS:
        if values.get(key):
            raise DatasetError(f"{where}: distortion term {key} is not supported (only k1, k2, p1, p2)")
    w, h = (values["w"], values["h"]) if "w" in values and "h" in values else _image_size(image)
    fx = _focal(values, "fl_x", "camera_angle_x", w)
    if fx is None:
        raise DatasetError(f"{where}: needs fl_x or camera_angle_x")
    fy = _focal(values, "fl_y", "camera_angle_y", h) or fx
    try:
        return Camera(
            int(w), int(h), fx, fy, values.get("cx", w / 2), values.get("cy", h / 2),
            *(float(values.get(key, 0.0)) for key in ("k1", "k2", "p1", "p2")),
        )  # fmt: skip
    except ValueError as exc:
        raise DatasetError(f"{where}: {exc}") from exc


def _focal(values: dict, focal_key: str, angle_key: str, size: float) -> float | None:
    """Focal length in pixels from ``focal_key``, else from the field of view ``angle_key``."""
    if focal_key in values:
        return float(values[focal_key])
    if angle_key in values:
        return 0.5 * size / math.tan(0.5 * values[angle_key])
    return None


def _image_size(image: Path) -> tuple[int, int]:
    if not image.is_file():
        raise MissingFileError(f"{image}: image file not found")
    try:
        with Image.open(image) as img:
            return img.size
    except OSError as exc:
        raise DatasetError(f"{image}: cannot decode image ({type(exc).__name__}: {exc})") from exc
