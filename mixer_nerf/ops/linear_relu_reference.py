"""Pure-PyTorch ``relu(x W^T + b)`` and ``x W^T + b``: the readable formulations, and what
``backend="torch"`` runs. Autograd gives their gradients."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def linear_relu_reference(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """x ``(..., in)``, weight ``(out, in)``, bias ``(out,)`` -> ``(..., out)``."""
    return torch.relu(F.linear(x, weight, bias))


def linear_reference(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """x ``(..., in)``, weight ``(out, in)``, bias ``(out,)`` -> ``(..., out)``."""
    return F.linear(x, weight, bias)
