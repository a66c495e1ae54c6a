"""Loading the scene a run trains on, and the camera facts a checkpoint keeps about it."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from ..data import DatasetError, MissingFileError, Scene, detect_format, ensure_procedural_scene, load_split
from ..data.colmap import find_model
from ..data.colmap_model import model_suffix
from ..data.nerfstudio import TRANSFORMS
from .config import TrainConfig

PROCEDURAL_HELD_OUT_VIEWS = 4  # val and test views of the built-in scene


def scene_source(cfg: TrainConfig) -> tuple[Path, str]:
    """(folder, format) of the scene ``cfg`` names; renders the built-in scene if needed."""
    if cfg.data is None:
        folder = ensure_procedural_scene(
            resolution=cfg.procedural_resolution,
            n_train=cfg.procedural_views,
            n_val=PROCEDURAL_HELD_OUT_VIEWS,
            n_test=PROCEDURAL_HELD_OUT_VIEWS,
        )
        return folder, "blender"
    folder = Path(cfg.data)
    if not folder.is_dir():
        raise MissingFileError(f"{folder}: scene folder not found")
    return folder, detect_format(folder) if cfg.format == "auto" else cfg.format


def locate_scene(cfg: TrainConfig, scene: dict[str, Any], data: str | Path | None, ckpt: Path) -> tuple[Path, str]:
    """(folder, format) of the scene a checkpoint at ``ckpt`` was trained on: ``data`` when given
    (the scene moved), else the folder it stored. The folder must hold the same cameras.

    Raises:
        MissingFileError: the folder is gone (the message says to pass --data).
        DatasetError: ``data`` holds another scene than the one trained on (other cameras).
    """
    if data is not None:
        folder, fmt = scene_source(TrainConfig(**{**cfg.to_dict(), "data": str(data), "format": "auto"}))
    elif cfg.data is None:
        folder, fmt = scene_source(cfg)  # the built-in scene is re-rendered when its cache was cleared
    else:
        folder, fmt = Path(scene["folder"]), scene["format"]
        if not folder.is_dir():
            raise MissingFileError(f"{folder}: the scene {ckpt} was trained on is not there; "
                                   "pass --data where it is now")
    expected = scene.get("identity")  # absent from checkpoints of earlier versions
    if expected is not None and scene_identity(folder, fmt) != expected:
        raise DatasetError(f"{folder}: not the scene {ckpt} was trained on (its cameras differ from "
                           f"{scene['folder']}'s)")
    return folder, fmt


def scene_identity(folder: Path, format: str) -> str:
    """sha256 of the scene's camera file (a moved scene keeps it, another scene has another)."""
    return hashlib.sha256(camera_file(folder, format).read_bytes()).hexdigest()


def camera_file(folder: Path, format: str) -> Path:
    """The file holding the cameras of a scene in ``format``."""
    if format == "colmap":
        model = find_model(folder)
        if model is None:
            raise MissingFileError(f"{folder}: no COLMAP model")
        return model / f"images{model_suffix(model)}"
    return folder / {"blender": "transforms_train.json", "llff": "poses_bounds.npy", "nerfstudio": TRANSFORMS}[format]


def held_out_split(folder: Path, format: str, preferred: str, downscale: float = 1,
                   val_holdout: int = 0) -> tuple[Scene, str]:
    """``preferred`` split ("test" or "val"), else the other one when that one does not exist
    (e.g. a scene shipped without its test views). Returns the scene and the split used."""
    other = {"test": "val", "val": "test"}[preferred]
    try:
        return load_split(folder, format, preferred, downscale, val_holdout), preferred
    except MissingFileError:
        return load_split(folder, format, other, downscale, val_holdout), other


def scene_info(scene: Scene, folder: Path, format: str, cfg: TrainConfig) -> dict[str, Any]:
    """What rendering needs to know about the training scene, without its images."""
    return {
        "name": scene.name,
        "folder": str(folder.resolve()),
        "identity": scene_identity(folder, format),
        "format": format,
        "procedural": cfg.data is None,
        "H": scene.H,
        "W": scene.W,
        "focal": float(scene.focal),
        "cx": float(scene.cx),
        "cy": float(scene.cy),
        "near": float(scene.near),
        "far": float(scene.far),
        "ndc": bool(scene.ndc),
        "background": scene.background.detach().cpu().float(),
        "bbox": None if scene.bbox is None else scene.bbox.detach().cpu().float(),
        "train_poses": scene.poses.detach().cpu().float(),
    }
