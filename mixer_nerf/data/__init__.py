"""Datasets: scene loaders (Blender, LLFF, built-in procedural scene), rays and the Scene type."""

from __future__ import annotations

from pathlib import Path

from .blender import load_blender
from .errors import DatasetError, MissingFileError
from .llff import load_llff
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
    "load_llff",
    "load_scene",
    "ndc_rays",
    "pixel_rays",
]

FORMATS = ("auto", "blender", "llff")


def detect_format(path: str | Path) -> str:
    """Scene format of folder ``path``: "blender" (``transforms_train.json``) or "llff"
    (``poses_bounds.npy``)."""
    path = Path(path)
    if not path.is_dir():
        raise MissingFileError(f"{path}: scene folder not found")
    if (path / "transforms_train.json").is_file():
        return "blender"
    if (path / "poses_bounds.npy").is_file():
        return "llff"
    raise DatasetError(
        f"{path}: unknown scene format (expected transforms_train.json for Blender or "
        "poses_bounds.npy for LLFF)"
    )


def load_scene(path: str | Path | None = None, format: str = "auto", split: str = "train", **kwargs) -> Scene:
    """Load one split of a scene.

    Args:
        path: scene folder; None loads the built-in procedural scene (rendered on first use with
            :func:`ensure_procedural_scene`'s defaults; call it yourself for other settings).
        format: "blender", "llff" or "auto" (detected from the files in ``path``).
        split: passed to the loader.
        **kwargs: passed to :func:`load_blender` or :func:`load_llff`.
    """
    if format not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {format!r}")
    if path is None:
        path, format = ensure_procedural_scene(), "blender"
    if format == "auto":
        format = detect_format(path)
    loader = load_blender if format == "blender" else load_llff
    return loader(path, split=split, **kwargs)
