"""Pure-PyTorch ``relu(x W^T + b)``: the readable formulation, and what ``backend="torch"`` runs.
Autograd gives its gradients."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def linear_relu_reference(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """x ``(..., in)``, weight ``(out, in)``, bias ``(out,)`` -> ``(..., out)``."""
    return torch.relu(F.linear(x, weight, bias))
