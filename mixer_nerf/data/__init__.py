"""Datasets: scene loaders (Blender, LLFF, COLMAP, nerfstudio, built-in procedural scene), rays and
the Scene type."""

from __future__ import annotations

from pathlib import Path

from .blender import load_blender
from .colmap import find_model, load_colmap
from .errors import DatasetError, MissingFileError
from .llff import load_llff
from .nerfstudio import TRANSFORMS, load_nerfstudio
from .procedural import ensure_procedural_scene
from .rays import camera_rays, ndc_rays, pixel_rays
from .scene import Scene

__all__ = [
    "DatasetError",
    "MissingFileError",
    "Scene",
    "camera_rays",
    "detect_format",
    "ensure_procedural_scene",
    "load_blender",
    "load_colmap",
    "load_llff",
    "load_nerfstudio",
    "load_scene",
    "load_split",
    "ndc_rays",
    "pixel_rays",
]

LOADERS = {"blender": load_blender, "llff": load_llff, "colmap": load_colmap, "nerfstudio": load_nerfstudio}
FORMATS = ("auto", *LOADERS)


def detect_format(path: str | Path) -> str:
    """Scene format of folder ``path``: "blender" (``transforms_train.json``), "llff"
    (``poses_bounds.npy``), "nerfstudio" (``transforms.json``) or "colmap" (a sparse model in
    ``sparse/0/``, ``sparse/`` or the folder), checked in that order."""
    path = Path(path)
    if not path.is_dir():
        raise MissingFileError(f"{path}: scene folder not found")
    if (path / "transforms_train.json").is_file():
        return "blender"
    if (path / "poses_bounds.npy").is_file():
        return "llff"
    if (path / TRANSFORMS).is_file():
        return "nerfstudio"
    if find_model(path) is not None:
        return "colmap"
    raise DatasetError(
        f"{path}: unknown scene format (expected transforms_train.json for Blender, "
        f"poses_bounds.npy for LLFF, {TRANSFORMS} for nerfstudio, or a COLMAP model in sparse/0/)"
    )


def load_scene(path: str | Path | None = None, format: str = "auto", split: str = "train", **kwargs) -> Scene:
    """Load one split of a scene.

    Args:
        path: scene folder; None loads the built-in procedural scene (rendered on first use with
            :func:`ensure_procedural_scene`'s defaults; call it yourself for other settings).
        format: "blender", "llff", "colmap", "nerfstudio" or "auto" (detected from the files in
            ``path``).
        split: passed to the loader.
        **kwargs: passed to the loader (every one takes ``downscale``).
    """
    if format not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {format!r}")
    if path is None:
        path, format = ensure_procedural_scene(), "blender"
    if format == "auto":
        format = detect_format(path)
    return LOADERS[format](path, split=split, **kwargs)


def load_split(
    folder: str | Path, format: str, split: str, downscale: float = 1, val_holdout: int = 0
) -> Scene:
    """One split, refusing an empty one (a loader may return zero views for a short capture).
    ``val_holdout`` > 0: a val split carved out of the training views (captures:
    :func:`.llff.split_indices`; Blender: :func:`.blender.holdout_split`)."""
    kwargs = {"val_holdout": val_holdout} if val_holdout else {}
    # every loader takes downscale
    scene = load_scene(folder, format=format, split=split, downscale=downscale, **kwargs)
    if len(scene) == 0:
        raise DatasetError(f"{folder}: the {split!r} split has no images")
    return scene
