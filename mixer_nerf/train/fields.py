"""The radiance fields of a run (coarse MLP + optional fine MLP) and the precision they run at."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ..model import MixerNeRF, ModelConfig, preset_config
from ..render import render_image


class MixedPrecisionField(nn.Module):
    """Runs a field under bf16 autocast and hands float32 back.

    Only the MLP runs in reduced precision: sampling and compositing kernels take float32, so the
    outputs are cast back before they reach them.
    """

    def __init__(self, field: nn.Module, device_type: str, dtype: torch.dtype | None) -> None:
        super().__init__()
        self.field = field
        self.device_type = device_type
        self.dtype = dtype

    def forward(self, x: torch.Tensor, d: torch.Tensor, **kwargs: Any) -> tuple[torch.Tensor, torch.Tensor]:
        if self.dtype is None:
            return self.field(x, d, **kwargs)
        with torch.autocast(self.device_type, dtype=self.dtype):
            sigma, rgb = self.field(x, d, **kwargs)
        return sigma.float(), rgb.float()


class RadianceFields(nn.Module):
    """Coarse and fine fields of one run. ``fine`` is None when the coarse field is reused.

    ``state_dict`` holds only the MLPs' parameters (under ``coarse.`` and ``fine.``), independent of
    the precision they run at.
    """

    def __init__(self, model_cfg: ModelConfig, fine_network: bool) -> None:
        super().__init__()
        self.model_cfg = model_cfg
        self.coarse = MixerNeRF(model_cfg)
        self.fine = MixerNeRF(model_cfg) if fine_network else None

    def runners(self, precision: str, device: torch.device) -> tuple[nn.Module, nn.Module | None]:
        """(coarse, fine) callables for ``render_rays`` at ``precision``."""
        dtype = torch.bfloat16 if precision == "bf16" else None
        coarse = MixedPrecisionField(self.coarse, device.type, dtype)
        fine = None if self.fine is None else MixedPrecisionField(self.fine, device.type, dtype)
        return coarse, fine


def model_config(preset: str, overrides: dict[str, Any], bbox: torch.Tensor | None, backend: str) -> ModelConfig:
    """The preset's model configuration for a scene: positions are normalised by the centre and
    largest half-size of the scene box ``bbox`` (2, 3), and the encoding uses ``backend``.
    Explicit ``overrides`` win."""
    derived: dict[str, Any] = {"backend": backend}
    if bbox is not None:
        derived["scene_center"] = tuple(((bbox[0] + bbox[1]) / 2).tolist())
        derived["scene_scale"] = float(((bbox[1] - bbox[0]) / 2).abs().max())
    return preset_config(preset, **{**derived, **overrides})


def model_config_to_dict(cfg: ModelConfig) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def model_config_from_dict(values: dict[str, Any]) -> ModelConfig:
    return ModelConfig(**values)


def set_matmul_precision(precision: str) -> None:
    """TF32 tensor-core matmuls for "tf32" and "bf16" (outside autocast); exact float32 for "fp32"."""
    torch.backends.cuda.matmul.allow_tf32 = precision != "fp32"
    torch.backends.cudnn.allow_tf32 = precision != "fp32"


@dataclass
class ImageRenderer:
    """Renders many rays of trained fields in chunks with deterministic samples (no grad)."""

    fields: RadianceFields
    precision: str
    near: float
    far: float
    background: torch.Tensor
    num_coarse: int
    num_fine: int
    chunk: int
    backend: str

    @torch.no_grad()
    def __call__(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> Any:
        """color (R, 3), depth (R,), opacity (R,) of rays (R, 3) (float32, on the fields' device)."""
        device = self.background.device
        coarse, fine = self.fields.runners(self.precision, device)
        was_training = self.fields.training
        self.fields.eval()
        try:
            return render_image(
                coarse, rays_o.to(device, torch.float32), rays_d.to(device, torch.float32), self.near,
                self.far, chunk=self.chunk, fine_field=fine, num_coarse=self.num_coarse,
                num_fine=self.num_fine, stratified=False, background=self.background, backend=self.backend)
        finally:
            self.fields.train(was_training)
