"""The precision a run's fields compute in: bf16 autocast around the MLP, TF32 matmuls."""

from __future__ import annotations

import torch
from torch import nn


class MixedPrecisionField(nn.Module):
    """Runs a field under bf16 autocast (``dtype``; None: as it is) and hands float32 back.

    Only the MLP runs in reduced precision: sampling and compositing kernels take float32, so the
    outputs are cast back before they reach them.
    """

    packed_layout = ("ray_indices", "offsets", "ray_directions")

    def __init__(self, field: nn.Module, device_type: str, dtype: torch.dtype | None) -> None:
        super().__init__()
        self.field = field
        self.device_type = device_type
        self.dtype = dtype

    def _autocast(self):
        return torch.autocast(self.device_type, dtype=self.dtype or torch.float32, enabled=self.dtype is not None)

    def forward(
        self,
        x: torch.Tensor,
        d: torch.Tensor,
        ray_indices: torch.Tensor | None = None,
        num_rays: int | None = None,
        offsets: torch.Tensor | None = None,
        ray_directions: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The field's ``(sigma, rgb)`` in float32; packed-layout arguments as for
        :meth:`~mixer_nerf.model.MixerNeRF.forward`."""
        with self._autocast():
            sigma, rgb = self.field(x, d, ray_indices=ray_indices, num_rays=num_rays, offsets=offsets,
                                    ray_directions=ray_directions)
        return sigma.float(), rgb.float()

    def density(
        self,
        x: torch.Tensor,
        ray_indices: torch.Tensor | None = None,
        num_rays: int | None = None,
        offsets: torch.Tensor | None = None,
        ray_directions: torch.Tensor | None = None,
    ) -> torch.Tensor:
        with self._autocast():
            return self.field.density(x, ray_indices=ray_indices, num_rays=num_rays, offsets=offsets,
                                      ray_directions=ray_directions).float()


def set_matmul_precision(precision: str) -> None:
    """TF32 tensor-core matmuls for "tf32" and "bf16" (outside autocast); exact float32 for "fp32"."""
    torch.backends.cuda.matmul.allow_tf32 = precision != "fp32"
    torch.backends.cudnn.allow_tf32 = precision != "fp32"
