"""Pure-PyTorch positional encoding: the formulation users write, and what ``backend="torch"`` runs.

``sin(scale * 2**k * x)`` rounds its argument to the working precision first, so in float32 the
phase error grows like ``|scale * 2**k * x| * 2**-24``: at high frequencies the encoding loses
its digits. The kernels avoid that (see :mod:`mixer_nerf.ops.positional_encoding`); this path is
kept as the plain baseline they are compared with. Autograd gives its gradients.
"""

from __future__ import annotations

import math

import torch


def positional_encoding_reference(
    x: torch.Tensor, num_freqs: int, include_input: bool = True, scale: float = math.pi
) -> torch.Tensor:
    """x ``(..., D)`` -> ``(..., D * (include_input + 2 * num_freqs))``, laid out
    ``[x, sin(scale 2^0 x), cos(scale 2^0 x), sin(scale 2^1 x), cos(scale 2^1 x), ...]``."""
    parts = [x] if include_input else []
    for k in range(num_freqs):
        angle = scale * 2.0**k * x
        parts += [torch.sin(angle), torch.cos(angle)]
    if not parts:
        return x.new_empty(*x.shape[:-1], 0)
    return torch.cat(parts, dim=-1)
