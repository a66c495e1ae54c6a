"""Refusing, before any work, sizes that cannot fit: a lower bound of what a setting allocates
against the memory of the device, so that a typo gets one line instead of an allocator traceback."""

from __future__ import annotations

import os

import torch

FLOAT_BYTES = 4


def device_memory(device: torch.device) -> int:
    """Bytes of memory of ``device``: the GPU's total, or the host's physical memory."""
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[1]
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_fits(what: str, needed_bytes: float, device: torch.device) -> None:
    """Raise ValueError naming ``what`` (e.g. "--batch-rays 100000000") when at least
    ``needed_bytes`` do not fit in ``device``'s memory."""
    have = device_memory(device)
    if needed_bytes > have:
        raise ValueError(f"{what} needs at least {_size(needed_bytes)} of memory; {device.type} has "
                         f"{_size(have)}")


def _size(nbytes: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if nbytes < 1024:
            return f"{nbytes:.3g} {unit}"
        nbytes /= 1024
    return f"{nbytes:.3g} TB"
