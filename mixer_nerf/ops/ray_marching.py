"""Ray marching through an occupancy grid, and early ray termination.

:func:`ray_marching` turns rays into packed samples that skip empty space: each ray is clipped to
the grid's box and marched with a fixed step (growing with distance when ``cone_angle > 0``),
keeping only samples whose midpoint lies in an occupied cell and jumping over empty cells. The
definition is in :mod:`mixer_nerf.ops.ray_marching_reference` and ``csrc/ray_marching_math.h``.
Marching is not differentiable: the samples are positions to evaluate a model at, and come back
without grad. :func:`ray_marching_fixed` gives the same samples in buffers of a fixed size, with
their count left on the device (no GPU synchronisation: a CUDA graph can capture it).

:func:`filter_by_transmittance` then drops samples that cannot change the image (behind an
opaque surface, or nearly transparent) once their densities are known.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch

from ._checks import (
    check_floating,
    check_ndim,
    check_same_device,
    check_same_dtype,
    check_shape,
    check_tensor,
)
from ._dispatch import use_kernel
from .ray_marching_reference import (
    filter_by_transmittance_reference,
    march_dtype,
    padding_rays_reference,
    ray_marching_reference,
    select_fixed_reference,
)


class PackedSamples(NamedTuple):
    """Samples of R rays in CSR layout: ray r owns rows ``offsets[r]:offsets[r+1]``, in order."""

    t_starts: torch.Tensor  # (N,) rays' dtype
    t_ends: torch.Tensor  # (N,)
    ray_indices: torch.Tensor  # (N,) int64
    offsets: torch.Tensor  # (R+1,) int64; rays with no sample have equal offsets

    def select(self, keep: torch.Tensor) -> PackedSamples:
        """The samples where ``keep`` (N,) bool is True, offsets recomputed (one host sync: the
        number kept)."""
        kept_before = torch.nn.functional.pad(keep.cumsum(0), (1, 0))
        rows = keep.nonzero().squeeze(1)
        return PackedSamples(
            self.t_starts[rows], self.t_ends[rows], self.ray_indices[rows], kept_before[self.offsets]
        )

    def select_fixed(self, keep: torch.Tensor, capacity: int) -> FixedSamples:
        """:meth:`select` into ``capacity`` rows without a host sync (the layout of
        :func:`ray_marching_fixed`: kept samples in order, cut at ``capacity``, then zero rows;
        ``total``: how many were kept). Rows from ``offsets[-1]`` on (a fixed layout's padding)
        are never kept."""
        _check_capacity(capacity)
        check_shape("keep", keep, (self.t_starts.shape[0],), " (one flag per sample)")
        if keep.dtype == torch.bool and use_kernel("auto", keep.device):  # a cumsum and one launch, not 17
            _register_fakes()
            *samples, total = torch.ops.mixer_nerf.select_fixed_fwd(
                keep.contiguous(), self.t_starts.contiguous(), self.t_ends.contiguous(),
                self.ray_indices.contiguous(), self.offsets.contiguous(), capacity)
            return FixedSamples(PackedSamples(*samples), total)
        samples, total = select_fixed_reference(keep, *self, capacity)
        return FixedSamples(PackedSamples(*samples), total)


def ray_marching(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: torch.Tensor | float,
    far: torch.Tensor | float,
    grid,
    step_size: float,
    stratified: bool = False,
    generator: torch.Generator | None = None,
    cone_angle: float = 0.0,
    max_samples_per_ray: int | None = None,
    backend: str = "auto",
) -> PackedSamples:
    """Samples along rays through the occupied cells of an occupancy grid.

    Args:
        rays_o, rays_d: (R, 3) origins and directions (need not be unit: t is in units of |d|).
        near, far: (R,) tensors or numbers; each ray is marched over [near, far] clipped to the
            grid's box. Rays that miss the box, or have a zero or non-finite direction, get no
            samples. ``far`` may be inf.
        grid: an :class:`~mixer_nerf.render.skipping.OccupancyGrid`, or a tuple
            ``(bitfield, aabb, resolution)``: (ceil(X*Y*Z / 8),) uint8 occupancy bits (cell
            ``(ix * Y + iy) * Z + iz`` is bit ``c % 8`` of byte ``c // 8``), (2, 3) box corners,
            and (X, Y, Z) or one int.
        step_size: marching step (in t) near the origin.
        stratified: start each ray at a random offset in [0, step) past its entry point, drawn
            from ``generator`` (same generator state -> same samples, on every backend).
        cone_angle: 0 for bounded scenes; > 0 makes the step ``max(step_size, t * cone_angle)``.
        max_samples_per_ray: keep at most this many (the first ones) per ray.
        backend: ``"auto"``, ``"kernel"`` or ``"torch"`` (see :mod:`mixer_nerf.ops`).

    Returns:
        :class:`PackedSamples` (t_starts, t_ends, ray_indices, offsets), without grad. Samples
        are [t_k, min(t_{k+1}, t_hi)] on a fixed lattice, so consecutive kept samples share
        their boundary and a fully occupied grid tiles [t_lo, t_hi] exactly (from t_lo + jitter).
    """
    *samples, _ = _march(rays_o, rays_d, near, far, grid, step_size, stratified, generator, cone_angle,
                         max_samples_per_ray, None, backend)
    return PackedSamples(*samples)


class FixedSamples(NamedTuple):
    """:func:`ray_marching_fixed`'s samples in buffers of a fixed size."""

    samples: PackedSamples  # capacity rows: the samples, then zero rows (t_start = t_end = 0, ray 0)
    total: torch.Tensor  # (1,) int64 on the rays' device: how many samples there were before the cut

    def intact(self) -> torch.Tensor:
        """(R,) bool: rays that lost no sample to the cut at the capacity (when samples were cut,
        the rays that end right at it count as cut too: their offsets cannot tell)."""
        capacity = self.samples.t_starts.shape[0]
        return (self.samples.offsets[1:] < capacity) | (self.total <= capacity)

    def with_padding_rays(self) -> PackedSamples:
        """The same rows with :func:`padding_rays` more rays that own the zero rows past the
        samples, :data:`PADDING_ROWS` each: every row then belongs to a ray, as the packed ops
        (``composite_packed``, segment ops) require, and no ray is long (the per-ray kernels walk
        a ray's rows in one thread). Their rows are empty intervals: they composite to the
        background and send no gradient."""
        s = self.samples
        if use_kernel("auto", s.offsets.device):  # one launch where the reference takes eleven
            _register_fakes()
            ray_indices, offsets = torch.ops.mixer_nerf.padding_rays_fwd(
                s.offsets, s.ray_indices, PADDING_ROWS)
        else:
            ray_indices, offsets = padding_rays_reference(s.offsets, s.ray_indices, PADDING_ROWS)
        return PackedSamples(s.t_starts, s.t_ends, ray_indices, offsets)


PADDING_ROWS = 32
"""Rows per padding ray of :meth:`FixedSamples.with_padding_rays` (about a real ray's samples)."""


def padding_rays(capacity: int) -> int:
    """The padding rays :meth:`FixedSamples.with_padding_rays` adds to ``capacity`` rows."""
    return -(-capacity // PADDING_ROWS)


def ray_marching_fixed(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: torch.Tensor | float,
    far: torch.Tensor | float,
    grid,
    step_size: float,
    capacity: int,
    stratified: bool = False,
    generator: torch.Generator | None = None,
    cone_angle: float = 0.0,
    max_samples_per_ray: int | None = None,
    backend: str = "auto",
) -> FixedSamples:
    """:func:`ray_marching` into outputs of ``capacity`` rows, without reading the number of
    samples back to the host: no synchronisation on a GPU, and the same shapes every call (a CUDA
    graph can capture it).

    The samples are those of :func:`ray_marching` with the same arguments, cut at ``capacity``:
    ``samples.offsets`` is clamped to it, so the rays past it lose their samples (the ray that
    crosses it keeps its first ones). Rows from ``samples.offsets[-1]`` on are zero: empty intervals
    at t = 0 owned by no ray (their ray index is 0, a valid index for gathers). ``total`` is the
    number of samples before the cut, on the device: ``total > capacity`` says samples were lost,
    and sizes the next call's batch without a synchronisation now.
    """
    _check_capacity(capacity)
    *samples, total = _march(rays_o, rays_d, near, far, grid, step_size, stratified, generator, cone_angle,
                             max_samples_per_ray, capacity, backend)
    return FixedSamples(PackedSamples(*samples), total)


def _check_capacity(capacity: int) -> None:
    if not (isinstance(capacity, int) and capacity >= 0):
        raise ValueError(f"capacity must be an int >= 0, got {capacity!r}")


def _march(rays_o, rays_d, near, far, grid, step_size, stratified, generator, cone_angle, max_samples_per_ray,
           capacity, backend) -> tuple[torch.Tensor, ...]:
    """Validated inputs into the op or its reference: t_starts, t_ends, ray_indices, offsets, total."""
    bitfield, aabb, resolution = _grid_parts(grid)
    R = _validate(rays_o, rays_d, bitfield, aabb, resolution, step_size, cone_angle, max_samples_per_ray)
    near, far = _per_ray("near", near, rays_o), _per_ray("far", far, rays_o)
    check_same_device(rays_o=rays_o, rays_d=rays_d, near=near, far=far, bitfield=bitfield, aabb=aabb)
    jitter = (
        torch.rand(R, generator=generator, device=rays_o.device, dtype=rays_o.dtype) if stratified else None
    )
    inputs = (
        rays_o.detach().contiguous(),
        rays_d.detach().contiguous(),
        near.detach().contiguous(),
        far.detach().contiguous(),
        jitter,
        bitfield.contiguous(),
        aabb.detach().to(march_dtype(rays_o.dtype)).contiguous(),
        resolution,
        float(step_size),
        float(cone_angle),
        max_samples_per_ray,
        capacity,
    )
    if not use_kernel(backend, rays_o.device):
        return ray_marching_reference(*inputs)
    _register_fakes()
    return torch.ops.mixer_nerf.ray_marching_fwd(*inputs)


@torch.no_grad()
def filter_by_transmittance(
    sigmas: torch.Tensor, samples: PackedSamples, threshold: float = 1e-4, alpha_threshold: float = 0.0,
    backend: str = "auto",
) -> torch.Tensor:
    """Which samples can still change the image, given their densities (e.g. evaluated without grad).

    Drops sample i of a ray once the transmittance before it, T_i = exp(-sum_{j<i} sigma_j dt_j),
    is below ``threshold`` (what lies behind is hidden), and, if ``alpha_threshold > 0``, samples
    with alpha = 1 - exp(-sigma dt) below it. Rows past ``samples.offsets[-1]`` (a fixed layout's
    spare rows) belong to no ray and are dropped. Apply with ``samples.select(mask)``.

    The sums run in float64, each term capped at -log(threshold) + 1: that changes no decision (one
    such term already ends its ray). NaN densities count as empty. The kernel sums each ray in
    order; the reference (:func:`~mixer_nerf.ops.ray_marching_reference.filter_by_transmittance_reference`)
    takes one cumsum over all samples minus its value at each ray's first sample.

    Args:
        sigmas: (N,) densities. samples: the :class:`PackedSamples` they belong to.
        backend: ``"auto"``, ``"kernel"`` or ``"torch"`` (see :mod:`mixer_nerf.ops`).

    Returns:
        (N,) bool mask.
    """
    check_floating("sigmas", sigmas)
    check_shape("sigmas", sigmas, (samples.t_starts.shape[0],), " (one density per sample)")
    if not 0.0 <= threshold <= 1.0:
        raise ValueError(f"threshold must be in [0, 1], got {threshold}")
    if not 0.0 <= alpha_threshold <= 1.0:
        raise ValueError(f"alpha_threshold must be in [0, 1], got {alpha_threshold}")
    kernel = use_kernel(backend, sigmas.device)
    if kernel and sigmas.dtype == samples.t_starts.dtype:
        _register_fakes()  # one launch (and a fill) where the reference takes fifteen
        return torch.ops.mixer_nerf.transmittance_filter_fwd(
            sigmas.contiguous(), samples.t_starts.contiguous(), samples.t_ends.contiguous(),
            samples.offsets.contiguous(), float(threshold), float(alpha_threshold))
    return filter_by_transmittance_reference(sigmas, samples.t_starts, samples.t_ends, samples.offsets,
                                             samples.ray_indices, threshold, alpha_threshold)


def _grid_parts(grid) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int, int]]:
    if all(hasattr(grid, name) for name in ("bitfield", "aabb", "resolution")):
        bitfield, aabb, resolution = grid.bitfield, grid.aabb, grid.resolution
    elif isinstance(grid, (tuple, list)) and len(grid) == 3:
        bitfield, aabb, resolution = grid
    else:
        kind = type(grid).__name__
        raise TypeError(f"grid must be an OccupancyGrid or a (bitfield, aabb, resolution) tuple, got {kind}")
    check_tensor("grid bitfield", bitfield)
    check_tensor("grid aabb", aabb)
    if isinstance(resolution, int):
        resolution = (resolution,) * 3
    resolution = tuple(resolution)
    if len(resolution) != 3 or not all(isinstance(n, int) and n > 0 for n in resolution):
        raise ValueError(f"grid resolution must be 3 positive ints, got {resolution}")
    return bitfield, aabb, resolution


def _validate(rays_o, rays_d, bitfield, aabb, resolution, step_size, cone_angle, max_samples_per_ray) -> int:
    check_floating("rays_o", rays_o)
    check_floating("rays_d", rays_d)
    check_ndim("rays_o", rays_o, 2)
    check_shape("rays_o", rays_o, (None, 3), " (R, 3)")
    check_shape("rays_d", rays_d, tuple(rays_o.shape), " (like rays_o)")
    check_same_dtype(rays_o=rays_o, rays_d=rays_d)
    if bitfield.dtype != torch.uint8:
        raise TypeError(f"grid bitfield must be uint8, got {bitfield.dtype}")
    cells = resolution[0] * resolution[1] * resolution[2]
    check_shape("grid bitfield", bitfield, ((cells + 7) // 8,), f" (one bit per cell of {resolution})")
    check_floating("grid aabb", aabb)
    check_shape("grid aabb", aabb, (2, 3), " (min corner, max corner)")
    if not (isinstance(step_size, (int, float)) and math.isfinite(step_size) and step_size > 0):
        raise ValueError(f"step_size must be a positive finite number, got {step_size!r}")
    if not (isinstance(cone_angle, (int, float)) and math.isfinite(cone_angle) and cone_angle >= 0):
        raise ValueError(f"cone_angle must be a non-negative finite number, got {cone_angle!r}")
    if max_samples_per_ray is not None and not (
        isinstance(max_samples_per_ray, int) and max_samples_per_ray >= 1
    ):
        raise ValueError(f"max_samples_per_ray must be None or an int >= 1, got {max_samples_per_ray!r}")
    return rays_o.shape[0]


def _per_ray(name: str, value, rays_o: torch.Tensor) -> torch.Tensor:
    """A number or (R,) tensor -> (R,) tensor in the rays' dtype."""
    R = rays_o.shape[0]
    if isinstance(value, (int, float)):
        return torch.full((R,), float(value), dtype=rays_o.dtype, device=rays_o.device)
    check_floating(name, value)
    check_shape(name, value, (R,), " (R,) or a number")
    check_same_dtype(rays_o=rays_o, **{name: value})
    return value


@functools.cache
def _register_fakes() -> None:
    """Shape function for torch.compile and opcheck; the op exists only once the extension loaded."""
    torch.library.register_fake("mixer_nerf::ray_marching_fwd", _ray_marching_fwd_fake)
    torch.library.register_fake("mixer_nerf::padding_rays_fwd", _padding_rays_fwd_fake)
    torch.library.register_fake("mixer_nerf::select_fixed_fwd", _select_fixed_fwd_fake)
    torch.library.register_fake("mixer_nerf::transmittance_filter_fwd",
                                lambda sigmas, *rest: torch.empty_like(sigmas, dtype=torch.bool))


def _select_fixed_fwd_fake(keep, t_starts, t_ends, ray_indices, offsets, capacity):
    return (t_starts.new_empty(capacity), t_ends.new_empty(capacity), ray_indices.new_empty(capacity),
            torch.empty_like(offsets), offsets.new_empty(1))


def _padding_rays_fwd_fake(offsets, ray_indices, rows_per_ray):
    rows = ray_indices.shape[0]
    return torch.empty_like(ray_indices), offsets.new_empty(offsets.shape[0] + -(-rows // rows_per_ray))


def _ray_marching_fwd_fake(
    rays_o, rays_d, near, far, jitter, bitfield, aabb, resolution, step_size, cone_angle, max_samples_per_ray,
    capacity=None,
):
    n = torch.library.get_ctx().new_dynamic_size() if capacity is None else capacity
    return (
        rays_o.new_empty(n),
        rays_o.new_empty(n),
        rays_o.new_empty(n, dtype=torch.int64),
        rays_o.new_empty(rays_o.shape[0] + 1, dtype=torch.int64),
        rays_o.new_empty(1, dtype=torch.int64),
    )
