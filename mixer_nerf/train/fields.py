"""The radiance fields of a run (coarse MLP, optional fine MLP, the occupancy grid) and the
model configuration they are built from."""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import nn

from ..model import MixerNeRF, ModelConfig, preset_config
from ..render.skipping import OccupancyGrid, ProposalSampler
from .precision import MixedPrecisionField


class RadianceFields(nn.Module):
    """Coarse and fine fields of one run. ``fine`` is None when the coarse field is reused.
    ``grid`` is the occupancy sampler's grid, ``proposal`` the proposal sampler (each None when
    the run uses another sampler).

    ``state_dict`` holds the MLPs' parameters (under ``coarse.`` and ``fine.``), the grid's
    buffers and the proposal networks, independent of the precision the MLPs run at.
    """

    def __init__(
        self,
        model_cfg: ModelConfig,
        fine_network: bool,
        grid: OccupancyGrid | None = None,
        proposal: ProposalSampler | None = None,
    ) -> None:
        super().__init__()
        self.model_cfg = model_cfg
        self.coarse = MixerNeRF(model_cfg)
        self.fine = MixerNeRF(model_cfg) if fine_network else None
        self.grid = grid
        self.proposal = proposal

    def mlps(self) -> list[MixerNeRF]:
        """The run's MLPs: the coarse one, and the fine one where there is one."""
        return [self.coarse] if self.fine is None else [self.coarse, self.fine]

    def runners(self, precision: str, device: torch.device) -> tuple[nn.Module, nn.Module | None]:
        """(coarse, fine) callables for the renderers at ``precision``."""
        dtype = torch.bfloat16 if precision == "bf16" else None
        coarse = MixedPrecisionField(self.coarse, device.type, dtype)
        fine = None if self.fine is None else MixedPrecisionField(self.fine, device.type, dtype)
        return coarse, fine


def model_config(
    preset: str, overrides: dict[str, Any], bbox: torch.Tensor | None, backend: str, ndc: bool = False
) -> ModelConfig:
    """The preset's model configuration for a scene: positions are normalised by the centre and
    largest half-size of the scene box ``bbox`` (2, 3), the encoding uses ``backend``, and a
    forward-facing (``ndc``) scene gets no MLCA on PE(d): its views span a narrow cone, and the
    direction mixer let the colour branch fit the few training views at the held-out ones' cost
    (docs/model.md, "Where MLCA costs"). Explicit ``overrides`` win."""
    derived: dict[str, Any] = {"backend": backend, "mlca_directions": not ndc}
    if bbox is not None:
        derived["scene_center"] = tuple(((bbox[0] + bbox[1]) / 2).tolist())
        derived["scene_scale"] = float(((bbox[1] - bbox[0]) / 2).abs().max())
    return preset_config(preset, **{**derived, **overrides})


def model_notes(cfg: ModelConfig) -> list[str]:
    """What a reader of a run's results needs to know about its model beyond the preset letter."""
    notes = []
    if cfg.use_mlca and not cfg.mlca_directions:
        notes.append("MLCA mixes PE(x) only (mlca_directions=false: the default on forward-facing scenes)")
    if cfg.use_se and not cfg.se_gates_density:
        notes.append("SE gates the colour branch only (se_gates_density=false)")
    return notes


def model_config_to_dict(cfg: ModelConfig) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def model_config_from_dict(values: dict[str, Any]) -> ModelConfig:
    return ModelConfig(**values)
