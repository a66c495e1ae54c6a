"""A small density-only MLP that proposes where along a ray the main field should be sampled."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..ops import positional_encoding
from .contraction import contract


class ProposalNetwork(nn.Module):
    """``density(x (..., 3)) -> sigma (...)``: positions mapped by ``(x - center) / scale`` (then
    contracted and halved into [-1, 1] when ``contract_space``), a positional encoding of
    ``num_freqs`` octaves and ``depth`` ReLU layers of ``width``. Trained only through the
    proposal loss; it never sees colour."""

    def __init__(
        self,
        center: tuple[float, float, float] = (0.0, 0.0, 0.0),
        scale: float = 1.0,
        num_freqs: int = 8,
        width: int = 64,
        depth: int = 2,
        contract_space: bool = False,
        backend: str = "auto",
    ) -> None:
        super().__init__()
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be positive and finite, got {scale}")
        if width < 1 or depth < 1 or num_freqs < 0:
            raise ValueError(f"need width, depth >= 1 and num_freqs >= 0, got {width}, {depth}, {num_freqs}")
        self.register_buffer("center", torch.tensor(center, dtype=torch.float32))
        self.scale, self.num_freqs, self.contract_space, self.backend = scale, num_freqs, contract_space, backend
        layers, size = [], 3 * (1 + 2 * num_freqs)
        for _ in range(depth):
            layers += [nn.Linear(size, width), nn.ReLU()]
            size = width
        self.mlp = nn.Sequential(*layers, nn.Linear(size, 1))

    def density(self, x: torch.Tensor) -> torch.Tensor:
        u = (x - self.center.to(x.dtype)) / self.scale
        if self.contract_space:
            u = contract(u) / 2
        encoded = positional_encoding(u, self.num_freqs, backend=self.backend)
        return F.softplus(self.mlp(encoded).squeeze(-1) - 1.0)
