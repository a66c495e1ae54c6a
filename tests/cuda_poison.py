"""Shared by the CUDA tests: poison the caching allocator so unwritten outputs show up as NaN."""

from __future__ import annotations

import torch


def poison_allocator(shapes_and_dtypes, copies=2):
    """Leave NaN-filled blocks of exactly the sizes the op will allocate in CUDA's caching
    allocator: its torch.empty outputs then reuse NaN memory, so any element the kernel does not
    write stays NaN and fails the finiteness checks. The mechanism itself is asserted."""
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    blocks = [
        torch.full(shape, float("nan"), dtype=dtype, device="cuda")
        for shape, dtype in shapes_and_dtypes
        for _ in range(copies)
        if torch.Size(shape).numel()
    ]
    if not blocks:
        return
    probe_shape, probe_dtype = blocks[0].shape, blocks[0].dtype
    del blocks
    probe = torch.empty(probe_shape, dtype=probe_dtype, device="cuda")
    assert torch.isnan(probe).all(), "poisoning did not reach the allocator"
