"""Pure-PyTorch segment mean and per-ray scale on packed rows (``backend="torch"``); autograd
gives their gradients.

The definitions the kernels must match, for ray r owning rows ``offsets[r]:offsets[r+1]`` (n_r
of them) of an ``(N, C)`` tensor:

    segment_mean(v)[r] = (1 / n_r) sum_{i in r} v_i      (0 for a ray with no row)
    ray_scale(f, s)[i] = f_i * s_{ray(i)}

Sums and products are computed in float32 for half/bfloat16/float32 inputs (float64 for float64)
and rounded to the input dtype once.
"""

from __future__ import annotations

import torch


def ray_of_rows(offsets: torch.Tensor, num_rows: int) -> torch.Tensor:
    """(N,) int64 ray of each of the ``num_rows`` rows of CSR ``offsets`` (R+1,); no host sync (the
    output size is given)."""
    counts = offsets[1:] - offsets[:-1]
    rays = torch.arange(counts.numel(), device=offsets.device)
    return torch.repeat_interleave(rays, counts, output_size=num_rows)


def segment_mean_reference(values: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """values (N, C), offsets (R+1,) int64 -> (R, C) per-ray mean in values' dtype."""
    compute = torch.promote_types(values.dtype, torch.float32)
    counts = (offsets[1:] - offsets[:-1]).clamp_min(1).to(compute)
    ray = ray_of_rows(offsets, values.shape[0])
    sums = values.new_zeros(offsets.numel() - 1, values.shape[1], dtype=compute)
    sums = sums.index_add(0, ray, values.to(compute))
    return (sums / counts[:, None]).to(values.dtype)


def ray_scale_reference(features: torch.Tensor, scale: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """features (N, C), scale (R, C), offsets (R+1,) int64 -> (N, C): each row times its ray's scale."""
    compute = torch.promote_types(features.dtype, torch.float32)
    ray = ray_of_rows(offsets, features.shape[0])
    return (features.to(compute) * scale.to(compute)[ray]).to(features.dtype)
