"""Packed occupancy bitfields: one bit per cell, bit ``c % 8`` of byte ``c // 8``, the layout the
marching kernels read."""

from __future__ import annotations

import torch


def unpack_bits(bitfield: torch.Tensor, num_cells: int) -> torch.Tensor:
    """(ceil(num_cells / 8),) uint8, bit ``c % 8`` of byte ``c // 8`` per cell -> (num_cells,) bool."""
    shifts = torch.arange(8, device=bitfield.device, dtype=torch.uint8)
    return ((bitfield[:, None] >> shifts) & 1).bool().reshape(-1)[:num_cells]


def cell_bits(bitfield: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """The bits of flat cell indices ``cells`` (int64, any shape) in a bitfield of
    :func:`pack_bits`'s layout, as bool of the same shape."""
    return ((bitfield.long()[cells >> 3] >> (cells & 7)) & 1).bool()


def pack_bits(occupied: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`unpack_bits`: (num_cells,) bool -> (ceil(num_cells / 8),) uint8."""
    flat = occupied.reshape(-1).to(torch.uint8)
    flat = torch.nn.functional.pad(flat, (0, -flat.numel() % 8))
    weights = 1 << torch.arange(8, device=flat.device, dtype=torch.int32)  # made on the device: no host wait
    return (flat.view(-1, 8) * weights).sum(-1).to(torch.uint8)
