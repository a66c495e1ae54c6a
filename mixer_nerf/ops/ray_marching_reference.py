"""Pure-PyTorch ray marching through an occupancy grid: the definition the kernels are tested against.

Every ray gets its whole lattice of candidate samples as a dense row; samples whose midpoint lies
in an empty cell are masked out and the rest packed with ``nonzero``. Memory is R times the
longest ray's lattice: fine for tests and benchmarks, not for training. Arithmetic follows
``csrc/ray_marching_math.h`` operation for operation (float32 for half/bfloat16/float32 rays,
float64 for float64), so for ``cone_angle == 0`` the kernels reproduce this sample set exactly.
"""

from __future__ import annotations

import math

import torch

from .bitfield import cell_bits

_MAX_INDEX = float(2**40)  # kMaxIndex of ray_marching_math.h


def march_dtype(dtype: torch.dtype) -> torch.dtype:
    """Arithmetic type of the march for rays of ``dtype``."""
    return torch.float64 if dtype == torch.float64 else torch.float32


def clip_to_box(o, d, near, far, lo, hi):
    """[t_lo, t_hi] = [near, far] clipped to the box, and whether that is a non-empty finite range."""
    t_lo, t_hi = near, far
    hit = torch.isfinite(near) & ~torch.isnan(far) & torch.isfinite(o).all(-1) & torch.isfinite(d).all(-1)
    moving = torch.zeros_like(hit)
    for a in range(3):
        parallel = d[:, a] == 0
        hit &= ~parallel | ((o[:, a] >= lo[a]) & (o[:, a] <= hi[a]))
        moving |= ~parallel
        safe_d = torch.where(parallel, torch.ones_like(d[:, a]), d[:, a])
        t_a, t_b = (lo[a] - o[:, a]) / safe_d, (hi[a] - o[:, a]) / safe_d
        t_lo = torch.where(parallel, t_lo, torch.maximum(t_lo, torch.minimum(t_a, t_b)))
        t_hi = torch.where(parallel, t_hi, torch.minimum(t_hi, torch.maximum(t_a, t_b)))
    hit &= moving & (t_lo < t_hi) & torch.isfinite(t_hi)
    zero = torch.zeros_like(t_lo)
    return torch.where(hit, t_lo, zero), torch.where(hit, t_hi, zero), hit


def ray_marching_reference(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: torch.Tensor,
    far: torch.Tensor,
    jitter: torch.Tensor | None,
    bitfield: torch.Tensor,
    aabb: torch.Tensor,
    resolution: tuple[int, int, int],
    step_size: float,
    cone_angle: float = 0.0,
    max_samples_per_ray: int | None = None,
    capacity: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Packed samples of R rays; arguments as ``torch.ops.mixer_nerf.ray_marching_fwd``.

    Args:
        rays_o, rays_d: (R, 3). near, far: (R,). jitter: (R,) in [0, 1) or None.
        bitfield: (ceil(X*Y*Z / 8),) uint8 occupancy bits. aabb: (2, 3) box corners.
        resolution: (X, Y, Z) cells. capacity: rows of the outputs (None: as many as samples).

    Returns:
        t_starts (N,), t_ends (N,) in the rays' dtype, ray_indices (N,) int64, offsets (R+1,)
        int64 (ray r's samples are rows offsets[r]:offsets[r+1], in order along the ray) and
        total (1,) int64, the number of samples. With ``capacity`` N = capacity: the first
        ``capacity`` samples, offsets clamped to it, zero rows after the samples.
    """
    *samples, offsets = _march(rays_o, rays_d, near, far, jitter, bitfield, aabb, resolution, step_size,
                               cone_angle, max_samples_per_ray)
    total = offsets[-1:].clone()
    if capacity is None:
        return (*samples, offsets, total)
    kept = [x[:capacity] for x in samples]
    padded = [torch.cat([x, x.new_zeros(capacity - x.shape[0])]) for x in kept]
    return (*padded, offsets.clamp_max(capacity), total)


def _march(rays_o, rays_d, near, far, jitter, bitfield, aabb, resolution, step_size, cone_angle,
           max_samples_per_ray):
    """t_starts, t_ends, ray_indices and offsets of every sample (see :func:`ray_marching_reference`)."""
    R, device, dtype = rays_o.shape[0], rays_o.device, march_dtype(rays_o.dtype)
    o, d = rays_o.to(dtype), rays_d.to(dtype)
    box = aabb.to(dtype).reshape(2, 3)
    lo, hi = box[0], box[1]
    t_lo, t_hi, hit = clip_to_box(o, d, near.to(dtype), far.to(dtype), lo, hi)
    o, d = (torch.where(hit[:, None], x, torch.zeros_like(x)) for x in (o, d))  # no NaN into cell indices

    step = torch.tensor(step_size, dtype=dtype, device=device)
    cone = torch.tensor(cone_angle, dtype=dtype, device=device)
    u = torch.zeros_like(t_lo) if jitter is None else jitter.to(dtype)
    t0 = t_lo + u * step
    if cone_angle > 0:
        k0 = torch.ceil((step / cone - t0) / step).clamp(0, _MAX_INDEX)
        geo_t0 = t0 + k0 * step
    else:
        k0 = torch.full_like(t0, _MAX_INDEX)
        geo_t0 = torch.full_like(t0, math.inf)

    # Lattice points t_0 .. t_K of every ray, K covering the longest one.
    K = _lattice_length(t0, t_hi, hit, step, cone, k0, geo_t0) + 1
    k = torch.arange(K + 1, device=device, dtype=dtype)
    linear = t0[:, None] + k * step
    if cone_angle > 0:
        growth = torch.ones((), dtype=dtype, device=device) + cone
        exponent = (k - k0[:, None]).clamp_min(0)
        lattice = torch.where(k <= k0[:, None], linear, geo_t0[:, None] * torch.pow(growth, exponent))
    else:
        lattice = linear
    t_start, t_end = lattice[:, :-1], torch.minimum(lattice[:, 1:], t_hi[:, None])
    valid = hit[:, None] & (t_start < t_hi[:, None])

    mid = torch.where(valid, (t_start + t_end) * 0.5, torch.zeros_like(t_start))
    position = o[:, None, :] + mid[..., None] * d[:, None, :]
    res = torch.tensor(resolution, device=device)
    scale = res.to(dtype) / (hi - lo)
    cell_xyz = (
        torch.floor((position - lo) * scale)
        .clamp(min=torch.zeros_like(scale), max=(res - 1).to(dtype))
        .long()
    )
    cell = (cell_xyz[..., 0] * resolution[1] + cell_xyz[..., 1]) * resolution[2] + cell_xyz[..., 2]
    occupied = cell_bits(bitfield, cell)
    keep = valid & occupied
    if max_samples_per_ray is not None:
        keep &= keep.cumsum(1) <= max_samples_per_ray

    ray_indices, index = keep.nonzero(as_tuple=True)
    offsets = torch.zeros(R + 1, dtype=torch.int64, device=device)
    torch.cumsum(keep.sum(1), 0, out=offsets[1:])
    return (
        t_start[ray_indices, index].to(rays_o.dtype),
        t_end[ray_indices, index].to(rays_o.dtype),
        ray_indices,
        offsets,
    )


def _lattice_length(t0, t_hi, hit, step, cone, k0, geo_t0) -> int:
    """Lattice points below t_hi on the longest ray (a bound, off by a few; one host sync)."""
    if not bool(hit.any()):
        return 0
    span = torch.where(hit, t_hi - t0, torch.zeros_like(t0)).clamp_min(0)
    n = torch.ceil(torch.minimum(span, (geo_t0 - t0).clamp_min(0)) / step)
    if bool(torch.isfinite(geo_t0).any()):
        beyond = torch.log(torch.maximum(t_hi, geo_t0) / geo_t0.clamp_min(torch.finfo(t0.dtype).tiny))
        n = n + torch.where(
            torch.isfinite(geo_t0) & hit, torch.ceil(beyond / torch.log1p(cone)), torch.zeros_like(n)
        )
    return int(n.max().item()) + 2


def padding_rays_reference(offsets: torch.Tensor, ray_indices: torch.Tensor,
                           rows_per_ray: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``FixedSamples.with_padding_rays``'s layout: (ray_indices (N,), offsets (R + 1 + P,)) with P =
    ceil(N / rows_per_ray) rays after the R, row i past the samples' end (``offsets[R]``) owned by
    ray R + (i - end) // rows_per_ray, padding ray k ending at min(end + k * rows_per_ray, N)."""
    rows, num_rays = ray_indices.shape[0], offsets.shape[0] - 1
    end = offsets[-1:].clamp(0, rows)
    index = torch.arange(rows, device=offsets.device)
    padding_ray = num_rays + (index - end).div(rows_per_ray, rounding_mode="floor")
    steps = torch.arange(1, -(-rows // rows_per_ray) + 1, device=offsets.device)
    ends = (end + rows_per_ray * steps).clamp_max(rows)
    return torch.where(index < end, ray_indices, padding_ray), torch.cat([offsets, ends])


def filter_by_transmittance_reference(sigmas, t_starts, t_ends, offsets, ray_indices, threshold: float,
                                      alpha_threshold: float) -> torch.Tensor:
    """``filter_by_transmittance``'s mask (N,) bool: per-ray exclusive sums of tau = sigma dt (float64,
    NaN as 0, each term capped at -log(threshold) + 1) from one cumsum over all samples minus its value
    at each ray's first sample (the cancellation error stays below N * 11 * 2^-53), rows past
    ``offsets[-1]`` dropped."""
    tau = torch.nan_to_num(sigmas.double() * (t_ends - t_starts).double(), nan=0.0).clamp_min(0)
    keep = torch.arange(tau.shape[0], device=tau.device) < offsets[-1]
    if threshold > 0:
        limit = -math.log(threshold)
        running = torch.nn.functional.pad(tau.clamp(max=limit + 1).cumsum(0), (1, 0))
        optical_depth_before = running[:-1] - running[offsets[ray_indices]]
        keep &= optical_depth_before <= limit
    if alpha_threshold > 0:
        keep &= -torch.expm1(-tau) >= alpha_threshold
    return keep


def select_fixed_reference(keep, t_starts, t_ends, ray_indices, offsets, capacity: int):
    """``PackedSamples.select_fixed``'s layout: ((t_starts, t_ends, ray_indices, offsets), total (1,)): the
    kept rows before ``offsets[-1]`` in order in ``capacity`` rows, then zero rows; offsets clamped to
    ``capacity``; total the kept rows before the cut."""
    rows = torch.arange(keep.shape[0], device=keep.device)
    keep = keep & (rows < offsets[-1])
    kept_before = torch.nn.functional.pad(keep.cumsum(0), (1, 0))
    # Each kept row to its place; dropped rows and those past the capacity to a spare last row.
    place = torch.where(keep, kept_before[:-1], capacity).clamp_max(capacity)

    def placed(values: torch.Tensor) -> torch.Tensor:
        return values.new_zeros(capacity + 1).scatter_(0, place, values)[:capacity]

    offsets = kept_before[offsets].clamp_max(capacity)
    samples = (placed(t_starts), placed(t_ends), placed(ray_indices), offsets)
    return samples, kept_before[-1:]
