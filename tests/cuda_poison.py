"""Shared by the CUDA tests: poison the caching allocator so unwritten outputs show up."""

from __future__ import annotations

import gc

import torch


def poison_allocator(like, max_copies=64):
    """Fill the CUDA caching allocator's free blocks of the sizes of the tensors `like` (the
    op's expected outputs, on any device) with 0xFF bytes: NaN as any float dtype, -1 as an
    integer. The op's torch.empty outputs then reuse that memory, so an element the kernel does
    not write keeps the poison and fails the comparisons.

    Two copies per size are not enough: earlier tests leave cached free blocks of stale data
    inside segments that live tensors keep, and the allocator may hand one of those out instead
    (seen on an H100 after the segment-op and mlca tests). So each size is allocated until the
    allocator has to reserve new memory, which proves no cached free block of that size was left
    unpoisoned. Freed poisoned blocks can still merge with stale fragments too small to hold a
    size, and the merged block may start in stale bytes: so finally the sizes are allocated in
    order, all alive at once as the op's outputs will be, and filled, which poisons exactly the
    blocks the allocator hands out next. The mechanism itself is asserted by allocating that
    sequence again."""
    nbytes = [t.numel() * t.element_size() for t in like if t.numel()]
    if not nbytes:
        return
    gc.collect()  # tensors of earlier tests held only by reference cycles
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    blocks = []
    for n in nbytes:
        for copy in range(max_copies):
            reserved = torch.cuda.memory_reserved()
            blocks.append(torch.full((n,), 255, dtype=torch.uint8, device="cuda"))
            if copy >= 1 and torch.cuda.memory_reserved() > reserved:
                break
    del blocks
    in_order = [torch.empty(n, dtype=torch.uint8, device="cuda").fill_(255) for n in nbytes]
    del in_order
    probes = [torch.empty(n, dtype=torch.uint8, device="cuda") for n in nbytes]
    # min(), not p == 255: a comparison's bool result would take (and unpoison) a block of p's size.
    assert all(int(p.min()) == 255 for p in probes), "poisoning did not reach the allocator"
