"""Scene contraction for unbounded scenes (mip-NeRF 360): the unit ball stays, everything beyond
it is squeezed into the shell of radius 1 to 2, so an MLP's encoding covers all of space."""

from __future__ import annotations

import torch


def contract(x: torch.Tensor) -> torch.Tensor:
    """``x (..., 3)`` -> ``x`` where ``|x| <= 1``, else ``(2 - 1/|x|) x/|x|``; in the ball of radius 2.
    Continuous with a continuous gradient at ``|x| = 1``; finite for any finite input."""
    norm = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    safe = norm.clamp_min(1.0)
    return torch.where(norm <= 1, x, (2 - 1 / safe) * (x / safe))
