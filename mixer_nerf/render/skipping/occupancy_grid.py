"""Occupancy grid: which cells of the scene's box can hold anything, so marching skips the rest.

The grid keeps, per cell, an exponential moving maximum of the opacity of one marching step
(``1 - exp(-sigma * step_size)``) at jittered points in the cell, and a packed bitfield of the cells
above a threshold: one bit per cell, 256 KiB at 128^3, so the marching kernel's lookups stay in
cache. Both are buffers: the grid checkpoints and moves with the model.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from ...ops.bitfield import cell_bits, pack_bits, unpack_bits


@dataclass(frozen=True)
class CellShare:
    """One of ``count`` processes refreshing the same grid: process ``index`` measures its share of
    the cells and ``max_reduce`` (in place, over the processes) merges what they measured, so every
    process ends with the same grid."""

    index: int
    count: int
    max_reduce: Callable[[torch.Tensor], object]


class OccupancyGrid(nn.Module):
    """An axis-aligned box split into ``resolution`` cells, each occupied or empty.

    Args:
        aabb: (2, 3) box corners (min, max), or 6 numbers in that order.
        resolution: cells per axis, one int or three.
        step_size: the marching step the opacities are measured over; defaults to 1/1000 of the
            box diagonal (nerfacc's Lego recipe: 5e-3 for a 3-unit cube).

    Until the first :meth:`update` past warm-up every cell is occupied (marching is dense).
    """

    aabb: torch.Tensor
    opacity: torch.Tensor
    bitfield: torch.Tensor

    def __init__(
        self,
        aabb: torch.Tensor | Sequence[float],
        resolution: int | Sequence[int] = 128,
        step_size: float | None = None,
    ) -> None:
        super().__init__()
        box = torch.as_tensor(aabb, dtype=torch.float32).detach().clone().reshape(2, 3)
        if not bool(torch.isfinite(box).all()) or not bool((box[1] > box[0]).all()):
            raise ValueError(f"aabb must be finite with max > min on every axis, got {box.tolist()}")
        res = (resolution,) * 3 if isinstance(resolution, int) else tuple(resolution)
        if len(res) != 3 or not all(isinstance(n, int) and n > 0 for n in res):
            raise ValueError(f"resolution must be a positive int or 3 of them, got {resolution!r}")
        diagonal = float((box[1] - box[0]).norm())
        self.step_size = diagonal / 1000 if step_size is None else float(step_size)
        if not (math.isfinite(self.step_size) and self.step_size > 0):
            raise ValueError(f"step_size must be positive and finite, got {step_size!r}")
        self.resolution: tuple[int, int, int] = res
        self.register_buffer("aabb", box)
        # On the grid's device, so that a cell's size needs no host-to-device copy (a host wait).
        self.register_buffer("cells_per_axis", torch.tensor(res, dtype=torch.float32), persistent=False)
        # Moving maximum of each cell's opacity over one marching step.
        self.register_buffer("opacity", torch.zeros(res))
        self.register_buffer("bitfield", pack_bits(torch.ones(self.num_cells, dtype=torch.bool)))

    @property
    def num_cells(self) -> int:
        return self.resolution[0] * self.resolution[1] * self.resolution[2]

    @property
    def occupied(self) -> torch.Tensor:
        """(X, Y, Z) bool: the cells marching samples in."""
        return unpack_bits(self.bitfield, self.num_cells).reshape(self.resolution)

    @occupied.setter
    def occupied(self, value: torch.Tensor) -> None:
        if tuple(value.shape) != self.resolution:
            raise ValueError(f"occupied must have shape {self.resolution}, got {tuple(value.shape)}")
        self.bitfield.copy_(pack_bits(value.to(self.bitfield.device, torch.bool)))

    @torch.no_grad()
    def update(
        self,
        step: int,
        density_fn: Callable[[torch.Tensor], torch.Tensor],
        every: int = 16,
        decay: float = 0.95,
        threshold: float = 0.01,
        warmup_steps: int = 256,
        chunk_size: int = 1 << 18,
        autocast_dtype: torch.dtype | None = None,
        generator: torch.Generator | None = None,
        share: CellShare | None = None,
    ) -> bool:
        """Refresh the grid from the model's density; a no-op unless ``step % every == 0``.

        Evaluates ``density_fn(x (n, 3)) -> sigma (n,)`` without grad at one jittered point per
        chosen cell, ``chunk_size`` points at a time (under autocast to ``autocast_dtype`` if
        given): every cell during warm-up (``step < warmup_steps``), afterwards a random quarter
        of the cells plus as many of the occupied ones (nerfacc's recipe: its cost stays a half
        of a full pass). Chosen cells take ``max(decay * old, opacity)``. The bitfield is then
        every cell during warm-up, afterwards the cells above ``min(threshold, mean)``. With
        ``share``, this process measures 1/count of those cells (every count-th during warm-up,
        else its own random draws) and the measurements of all processes are max-reduced.

        Returns:
            Whether the grid was updated.
        """
        if step % every != 0:
            return False
        warm = step < warmup_steps
        cells = self._cells_to_update(warm, generator, share)
        opacity = self._opacity(
            self._jittered_points(cells, generator), density_fn, chunk_size, autocast_dtype
        )
        flat = self.opacity.view(-1)
        fresh = torch.full_like(flat, -1.0).scatter_reduce_(0, cells, opacity, "amax")
        if share is not None:
            share.max_reduce(fresh)
        flat.copy_(torch.where(fresh >= 0, torch.maximum(flat * decay, fresh), flat))
        occupied = (
            torch.ones_like(flat, dtype=torch.bool) if warm else flat > flat.mean().clamp(max=threshold)
        )
        self.bitfield.copy_(pack_bits(occupied))
        return True

    @torch.no_grad()
    def measured(
        self,
        density_fn: Callable[[torch.Tensor], torch.Tensor],
        threshold: float = 0.01,
        chunk_size: int = 1 << 18,
        seed: int = 0,
    ) -> OccupancyGrid:
        """A copy whose cells say what ``density_fn(x (n, 3)) -> sigma (n,)`` holds now: every cell
        measured at one jittered point (``seed``: the same points each time, so renders repeat)
        and occupied above ``min(threshold, mean)``, the rule of a refresh after warm-up. This
        grid is left as it is (training goes on with it)."""
        generator = torch.Generator(self.opacity.device).manual_seed(seed)
        cells = torch.arange(self.num_cells, device=self.opacity.device)
        opacity = self._opacity(self._jittered_points(cells, generator), density_fn, chunk_size, None)
        grid = copy.deepcopy(self)
        grid.opacity.copy_(opacity.view(self.resolution))
        grid.bitfield.copy_(pack_bits(opacity > opacity.mean().clamp(max=threshold)))
        return grid

    def _cells_to_update(
        self, everything: bool, generator: torch.Generator | None, share: CellShare | None
    ) -> torch.Tensor:
        device = self.opacity.device
        index, count = (0, 1) if share is None else (share.index, share.count)
        if everything:
            return torch.arange(index, self.num_cells, count, device=device)
        quarter = -(-(self.num_cells // 4) // count)  # ceil: together at least a quarter
        random_cells = torch.randint(self.num_cells, (quarter,), device=device, generator=generator)
        # As many occupied cells, drawn with replacement by rank among the occupied: a fixed count
        # and no host sync (a CUDA graph can capture the refresh). With none occupied they are
        # random cells too.
        occupied_before = unpack_bits(self.bitfield, self.num_cells).cumsum(0)
        total = occupied_before[-1:]
        ranks = (torch.rand(quarter, device=device, generator=generator) * total).long().clamp_max(total - 1)
        occupied = torch.searchsorted(occupied_before, ranks + 1)
        return torch.cat([random_cells, torch.where(total > 0, occupied, random_cells)])

    def random_points(
        self, count: int, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` uniform random points in the box ``(count, 3)`` and whether each lies in an
        empty cell ``(count,)`` bool (no host sync). Training pushes the density down at the empty
        ones: marching never samples there, so nothing else keeps haze out of those cells, and a
        render without the grid would show it."""
        cells = torch.randint(self.num_cells, (count,), device=self.opacity.device, generator=generator)
        return self._jittered_points(cells, generator), ~cell_bits(self.bitfield, cells)

    def _jittered_points(self, cells: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """(n,) flat cell indices -> (n, 3) uniform random points inside those cells."""
        _, Y, Z = self.resolution
        ijk = torch.stack([cells // (Y * Z), (cells // Z) % Y, cells % Z], dim=-1)
        u = torch.rand(ijk.shape, device=cells.device, generator=generator)
        lo, hi = self.aabb[0], self.aabb[1]
        size = (hi - lo) / self.cells_per_axis
        return lo + (ijk + u) * size

    def _opacity(
        self, points, density_fn, chunk_size: int, autocast_dtype: torch.dtype | None
    ) -> torch.Tensor:
        """Opacity of one marching step at each point; NaN densities count as empty."""
        out = torch.empty(points.shape[0], device=points.device)
        with torch.autocast(points.device.type, dtype=autocast_dtype, enabled=autocast_dtype is not None):
            for start in range(0, points.shape[0], chunk_size):
                sigma = density_fn(points[start : start + chunk_size]).reshape(-1).float()
                out[start : start + chunk_size] = sigma
        tau = torch.nan_to_num(out * self.step_size, nan=0.0).clamp_min(0)
        return -torch.expm1(-tau)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # Checkpoints written before the buffer was renamed call it "density".
        old = prefix + "density"
        if old in state_dict and prefix + "opacity" not in state_dict:
            state_dict[prefix + "opacity"] = state_dict.pop(old)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return f"resolution={self.resolution}, step_size={self.step_size:.3g}, aabb={self.aabb.tolist()}"
