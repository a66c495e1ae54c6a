"""Rebuilding a trained model from its checkpoint, for evaluation and rendering."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..render import ImageRenderer
from .checkpoint import CheckpointError, load_checkpoint
from .config import TrainConfig
from .fields import RadianceFields, model_config_from_dict
from .precision import set_matmul_precision
from .sampling import image_renderer, make_fields


@dataclass
class TrainedRun:
    """A checkpoint's fields ready to render, with the settings and scene facts it was trained on."""

    path: Path
    cfg: TrainConfig
    step: int
    scene: dict[str, Any]  # see scenes.scene_info
    render: ImageRenderer
    device: torch.device
    fields: RadianceFields  # in eval mode, on ``device``


def load_trained(
    path: str | Path, device: str | None = None, backend: str | None = None, render_samples: int | None = None
) -> TrainedRun:
    """Load ``path`` onto ``device`` (default: the training device if present here, else CPU),
    rendering at most ``render_samples`` samples at once (default: the run's setting).

    Raises:
        CheckpointError: naming ``path``, when it is unreadable or does not match the model.
    """
    path = Path(path)
    state = load_checkpoint(path)
    try:
        saved = TrainConfig.from_dict(state["train_config"])
        model_cfg = model_config_from_dict(state["model_config"])
    except (TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: settings in the checkpoint are not understood: {e}") from e
    cuda = torch.cuda.is_available()
    if device is None:
        device = "cuda" if (saved.device or "").startswith("cuda") and cuda else "cpu"
    precision = saved.precision if device.startswith("cuda") else "fp32"  # bf16 autocast is slow on CPUs
    cfg = dataclasses.replace(
        saved, device=device, precision=precision, backend=backend or saved.backend,
        render_samples=render_samples or saved.render_samples,
    ).resolved(cuda)
    set_matmul_precision(cfg.precision)
    bbox = state["scene"].get("bbox")
    fields = make_fields(cfg, model_cfg, bbox)
    try:
        fields.load_state_dict(state["model"])
    except RuntimeError as e:
        raise CheckpointError(f"{path}: weights do not match the model they claim: {e}") from e
    dev = torch.device(cfg.device)
    fields.to(dev).eval()
    scene, step = state["scene"], int(state["step"])
    renderer = image_renderer(cfg, fields, scene["near"], scene["far"], scene["background"].to(dev, torch.float32),
                              step=lambda: step)
    return TrainedRun(path, cfg, step, scene, renderer, dev, fields)
