"""Per-ray rows spread to the packed samples of each ray, for the parts of a field that depend on
the ray alone (the view direction's branch): computed on R rays instead of N samples.

The backward is each ray's sum over its samples. With CSR ``offsets`` (rows of a ray contiguous)
it is ``torch.segment_reduce``, which sums each segment in order (deterministic); with only
``ray_indices`` (rows in any order) it is an ``index_add`` (atomic on a GPU).
"""

from __future__ import annotations

import torch

from ..ops.segment_ops_reference import ray_of_rows


def spread_to_samples(
    values: torch.Tensor,
    num_samples: int,
    offsets: torch.Tensor | None = None,
    ray_indices: torch.Tensor | None = None,
) -> torch.Tensor:
    """``values (R, C)`` -> ``(N, C)``: row i is its ray's row. ``offsets (R+1,)`` int64 CSR (used for
    the backward when given) and/or ``ray_indices (N,)`` int64; trusted, not checked (a GPU sync)."""
    if ray_indices is None:
        if offsets is None:
            raise ValueError("spread_to_samples needs offsets or ray_indices")
        ray_indices = ray_of_rows(offsets, num_samples)
    return _Spread.apply(values, ray_indices, offsets)


class _Spread(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values, ray_indices, offsets):
        ctx.save_for_backward(ray_indices, offsets)
        ctx.num_rays = values.shape[0]
        return values.index_select(0, ray_indices)

    @staticmethod
    def backward(ctx, grad):
        ray_indices, offsets = ctx.saved_tensors
        # float32 sums for half/bfloat16 gradients
        acc = torch.promote_types(grad.dtype, torch.float32)
        if offsets is not None:
            # unsafe: no validation of offsets, which reads them back to the host on a GPU
            summed = torch.segment_reduce(grad.to(acc), "sum", offsets=offsets, axis=0, unsafe=True)
        else:
            summed = grad.new_zeros(ctx.num_rays, grad.shape[1], dtype=acc).index_add_(0, ray_indices, grad.to(acc))
        return summed.to(grad.dtype), None, None
