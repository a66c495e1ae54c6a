"""COLMAP captures: a sparse model (``sparse/0/``, ``sparse/`` or the scene folder itself) beside
the photos in ``images/``, each image's name being its path inside ``images/``.

Camera models PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV are read (distorted
photos are undistorted while loading, see :mod:`.camera`); any other model is refused with a
one-line error. Poses become OpenGL camera-to-world matrices and the capture is framed as
:mod:`.captures` describes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .camera import Camera
from .captures import View, load_capture
from .colmap_model import ColmapCamera, model_suffix, quaternion_to_matrix, read_model
from .errors import DatasetError, MissingFileError
from .scene import Scene

MODEL_FOLDERS = ("sparse/0", "sparse", ".")
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
CV_TO_GL = np.diag([1.0, -1.0, -1.0])  # COLMAP's camera axes (x right, y down, z ahead) -> OpenGL's


def find_model(root: Path) -> Path | None:
    """The first folder of MODEL_FOLDERS under ``root`` that holds a COLMAP model, or None."""
    for sub in MODEL_FOLDERS:
        if model_suffix(root / sub) is not None:
            return root / sub
    return None


def load_colmap(
    root: str | Path,
    split: str = "train",
    holdout: int = 8,
    downscale: float = 1.0,
    val_holdout: int = 0,
    ndc: bool | None = None,
    background: str = "black",
) -> Scene:
    """Load a COLMAP capture (every registered image of the model).

    Args:
        root: scene folder holding ``images/`` and the model (see the module docstring).
        split: "train", "test" (every ``holdout``-th image by name, from the first), "val" (the
            test images, or see ``val_holdout``) or "all".
        holdout: test stride; 0 holds out nothing.
        val_holdout: 0, or a val split of its own: every K-th of the other images (train leaves them out).
        downscale: image shrink factor, any number >= 1.
        ndc: None: NDC exactly for forward-facing captures (see :mod:`.captures`); True/False force it.
        background: "black" or "white", for photos with an alpha channel.

    Returns:
        A Scene with uint8 images.
    """
    root = Path(root)
    if not root.is_dir():
        raise MissingFileError(f"{root}: scene folder not found")
    folder = find_model(root)
    if folder is None:
        raise MissingFileError(
            f"{root}: no COLMAP model in sparse/0/, sparse/ or the folder itself "
            "(expected cameras, images and points3D as .bin or .txt)"
        )
    model = read_model(folder)
    image_dir = root / "images"
    if not image_dir.is_dir():
        raise MissingFileError(f"{image_dir}: image folder not found")
    cameras = {k: colmap_camera(c, folder) for k, c in model.cameras.items()}
    views = []
    for image in model.images:
        if image.camera_id not in cameras:
            raise DatasetError(
                f"{folder}: image {image.name} uses camera {image.camera_id}, which is not in the model"
            )
        views.append(
            View(image_dir / image.name, colmap_to_opengl(image.qvec, image.tvec), cameras[image.camera_id])
        )
    return load_capture(
        views, model.points, where=folder, name=root.resolve().name, split=split, holdout=holdout,
        downscale=downscale, val_holdout=val_holdout, ndc=ndc, background=background,
    )  # fmt: skip


def colmap_camera(camera: ColmapCamera, where: Path) -> Camera:
    """A COLMAP camera as a :class:`.camera.Camera` (DatasetError for unsupported models)."""
    p = camera.params
    if camera.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        values = (p[0], *p)  # one focal length for both axes
    elif camera.model in ("PINHOLE", "OPENCV"):
        values = p
    else:
        raise DatasetError(
            f"{where}: camera {camera.id} uses COLMAP model {camera.model}, which is not supported "
            f"(supported: {', '.join(SUPPORTED_MODELS)}); undistort the capture first "
            "(colmap image_undistorter) or re-run COLMAP with one of those"
        )
    try:
        return Camera(camera.width, camera.height, *values)
    except ValueError as exc:
        raise DatasetError(f"{where}: camera {camera.id}: {exc}") from exc


def colmap_to_opengl(qvec: tuple[float, ...], tvec: tuple[float, ...]) -> np.ndarray:
    """COLMAP's world-to-camera (qw, qx, qy, qz), t -> OpenGL camera-to-world (4, 4) float64."""
    rotation = quaternion_to_matrix(np.asarray(qvec, dtype=np.float64))
    c2w = np.eye(4)
    c2w[:3, :3] = rotation.T @ CV_TO_GL
    c2w[:3, 3] = -rotation.T @ np.asarray(tvec, dtype=np.float64)
    return c2w
