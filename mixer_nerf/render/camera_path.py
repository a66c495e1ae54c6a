"""Camera paths to render along: nerfstudio's camera-path JSON (its per-frame cameras, or its
keyframes interpolated) and a dataset split's own cameras.

nerfstudio's file (written by its viewer or by hand)::

    {"render_height": 480, "render_width": 640, "seconds": 4, "fps": 30,
     "camera_path": [{"camera_to_world": [16 numbers, row-major], "fov": 50}, ...],
     "keyframes": [{"matrix": [16 numbers, column-major as three.js writes them], "fov": 50}, ...]}

``camera_path`` frames are used as they are; without them the keyframes are interpolated to
``seconds * fps`` frames (rotations by spherical linear interpolation, positions and field of view
linearly, keyframes evenly spaced in time). ``fov`` is the vertical field of view in degrees.
Poses are OpenGL camera-to-world matrices in the scene's own world coordinates.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data import load_split


class CameraPathError(ValueError):
    """A camera-path file is unreadable or does not follow nerfstudio's schema."""


@dataclass
class CameraPath:
    """Cameras to render, all of one image size.

    Attributes:
        poses: (N, 4, 4) float32 OpenGL camera-to-world matrices.
        focals: (N,) float32 focal lengths in pixels at H x W.
        H, W: image size; cx, cy: principal point in pixels.
        kind: where the path came from ("turntable", "test", a file name, ...).
    """

    poses: torch.Tensor
    focals: torch.Tensor
    H: int
    W: int
    cx: float
    cy: float
    kind: str

    def __len__(self) -> int:
        return self.poses.shape[0]

    def scaled(self, scale: float) -> CameraPath:
        """The same cameras at ``scale`` times the resolution."""
        H, W = max(1, round(self.H * scale)), max(1, round(self.W * scale))
        return CameraPath(self.poses, self.focals * scale, H, W, self.cx * scale, self.cy * scale, self.kind)


def fixed_intrinsics_path(poses: torch.Tensor, scene: dict[str, Any], kind: str) -> CameraPath:
    """``poses`` (N, 4, 4) seen through the training camera of a checkpoint's ``scene``."""
    focals = torch.full((len(poses),), float(scene["focal"]))
    return CameraPath(poses.float(), focals, scene["H"], scene["W"], scene["cx"], scene["cy"], kind)


def split_path(folder: Path, format: str, split: str, downscale: float, val_holdout: int = 0) -> CameraPath:
    """The cameras of a dataset split, with their own intrinsics (``val_holdout``: the splits of a
    run that carved its val views out of the training views, as its ``eval`` scores them)."""
    scene = load_split(folder, format, split, downscale, val_holdout)
    focals = torch.full((len(scene),), float(scene.focal))
    return CameraPath(scene.poses.float().cpu(), focals, scene.H, scene.W, scene.cx, scene.cy, split)


def read_nerfstudio_path(path: str | Path) -> CameraPath:
    """The cameras of nerfstudio's camera-path JSON file ``path`` (schema in the module docstring).

    Raises:
        CameraPathError: naming ``path`` and what is wrong, before anything is rendered.
    """
    path = Path(path)
    try:
        spec = json.loads(path.read_text())
    except OSError as e:
        raise CameraPathError(f"{path}: cannot read the camera path: {e.strerror}") from e
    except ValueError as e:
        raise CameraPathError(f"{path}: not valid JSON: {e}") from e
    if not isinstance(spec, dict):
        raise CameraPathError(
            f"{path}: expected a JSON object with render_height, render_width and camera_path"
        )
    H, W = (_positive_int(path, spec, key) for key in ("render_height", "render_width"))
    if spec.get("camera_path"):
        frames = _list(path, spec, "camera_path")
        poses = np.stack(
            [_matrix(path, f"camera_path[{i}]", f, "camera_to_world") for i, f in enumerate(frames)]
        )
        fovs = np.array([_fov(path, f"camera_path[{i}]", f) for i, f in enumerate(frames)])
    elif spec.get("keyframes"):
        keys = _list(path, spec, "keyframes")
        key_poses = np.stack([_matrix(path, f"keyframes[{i}]", k, "matrix").T for i, k in enumerate(keys)])
        key_fovs = np.array([_fov(path, f"keyframes[{i}]", k) for i, k in enumerate(keys)])
        n = round(_positive_number(path, spec, "seconds") * _positive_number(path, spec, "fps"))
        poses, fovs = interpolate_keyframes(key_poses, key_fovs, max(n, 1))
    else:
        raise CameraPathError(f"{path}: needs a non-empty 'camera_path' or 'keyframes' list")
    focals = (H / 2) / np.tan(np.radians(fovs) / 2)
    return CameraPath(
        torch.from_numpy(poses).float(), torch.from_numpy(focals).float(), H, W, W / 2, H / 2, path.name
    )


def interpolate_keyframes(poses: np.ndarray, fovs: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` cameras through the keyframes (K, 4, 4) and fields of view (K,), evenly spaced in
    time: rotations by spherical linear interpolation, positions and fields of view linearly."""
    from scipy.spatial.transform import Rotation, Slerp

    t = np.linspace(0.0, 1.0, n)
    if len(poses) == 1:
        return np.repeat(poses, n, axis=0), np.repeat(fovs, n)
    key_t = np.linspace(0.0, 1.0, len(poses))
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Slerp(key_t, Rotation.from_matrix(poses[:, :3, :3]))(t).as_matrix()
    for axis in range(3):
        out[:, axis, 3] = np.interp(t, key_t, poses[:, axis, 3])
    return out, np.interp(t, key_t, fovs)


def _list(path: Path, spec: dict, key: str) -> list:
    if not isinstance(spec[key], list):
        raise CameraPathError(f"{path}: '{key}' must be a list")
    return spec[key]


def _positive_int(path: Path, spec: dict, key: str) -> int:
    value = spec.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise CameraPathError(f"{path}: '{key}' must be a positive integer, got {value!r}")
    return value


def _positive_number(path: Path, spec: dict, key: str) -> float:
    value = spec.get(key)
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not value > 0:
        raise CameraPathError(f"{path}: '{key}' must be a positive number, got {value!r}")
    return float(value)


def _fov(path: Path, where: str, camera: Any) -> float:
    fov = camera.get("fov") if isinstance(camera, dict) else None
    if not isinstance(fov, (int, float)) or isinstance(fov, bool) or not 0 < fov < 180:
        raise CameraPathError(
            f"{path}: {where}.fov must be a vertical field of view in (0, 180) degrees, got {fov!r}"
        )
    return float(fov)


def _matrix(path: Path, where: str, camera: Any, key: str) -> np.ndarray:
    """A 4x4 matrix from 16 numbers (a list, or a string holding one as nerfstudio's keyframes do)."""
    value = camera.get(key) if isinstance(camera, dict) else None
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except ValueError:
            value = None
    try:
        matrix = np.array(value, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        matrix = None
    if matrix is None or not np.isfinite(matrix).all():
        raise CameraPathError(f"{path}: {where}.{key} must be 16 finite numbers (a 4x4 matrix)")
    rotation = matrix[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3) or not math.isclose(
        np.linalg.det(rotation), 1.0, abs_tol=1e-3
    ):
        raise CameraPathError(f"{path}: {where}.{key} does not hold a rotation (orthonormal, determinant 1)")
    return matrix
