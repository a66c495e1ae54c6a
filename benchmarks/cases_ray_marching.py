"""Benchmark cases for ray_marching through an occupancy grid (forward only: it has no gradient).

Scene: nerfacc's Lego recipe, a 128^3 grid over [-1.5, 1.5]^3, step 5e-3, near 2, far 6, with a
Lego-like occupancy pattern (a base plate, a cab, a tilted arm and a bucket: ~4% of the cells).
Rays come from cameras on a sphere of radius 4 aimed at random points of [-1, 1]^3, so most cross
the object and some miss it. Sizes: CPU R=4096, CUDA R=65536.

What is compared: a march's output has a data-dependent length (one sample more or fewer where a
midpoint sits within rounding of a cell face), so the harness compares per-ray summaries, the
sample count and the marched length sum(t_end - t_start), against the float64 reference march.
They are computed only when the harness compares, never inside the timed calls.
"""

from __future__ import annotations

import torch

from benchmarks.harness import Case, Variant
from mixer_nerf.ops.ray_marching import PackedSamples, ray_marching, ray_marching_fixed
from mixer_nerf.ops.bitfield import pack_bits
from mixer_nerf.ops.ray_marching_reference import ray_marching_reference

AABB = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
RESOLUTION = 128
STEP = 5e-3
NEAR, FAR = 2.0, 6.0


def lego_like_occupancy(device: torch.device, n: int = RESOLUTION) -> torch.Tensor:
    """(n, n, n) bool: boxes and a cylinder shaped roughly like the Lego bulldozer."""
    axis = (torch.arange(n, device=device) + 0.5) / n * 3.0 - 1.5
    x, y, z = torch.meshgrid(axis, axis, axis, indexing="ij")

    def box(lo, hi):
        return (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2])

    base = box((-0.7, -0.45, -0.6), (0.5, 0.45, -0.35))
    cab = box((-0.45, -0.3, -0.35), (0.1, 0.3, 0.25))
    arm_axis = x - 0.6 * (z + 0.1)  # a slab tilted in x-z
    arm = (arm_axis.abs() < 0.06) & (y.abs() < 0.3) & (z > -0.35) & (z < 0.35) & (x > 0.0)
    bucket = ((x - 0.75) ** 2 + (z + 0.35) ** 2 < 0.2**2) & (y.abs() < 0.42) & (x > 0.62)
    return base | cab | arm | bucket


def camera_rays(R: int, device: torch.device, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator(device=device).manual_seed(seed)
    direction = torch.randn(R, 3, generator=gen, device=device)
    origins = 4.0 * direction / direction.norm(dim=-1, keepdim=True)
    targets = torch.rand(R, 3, generator=gen, device=device) * 2 - 1
    d = targets - origins
    return origins, d / d.norm(dim=-1, keepdim=True)


class PerRaySummary:
    """Per-ray sample count and marched length of a march, computed when iterated (the harness
    iterates a result only to compare it)."""

    def __init__(self, samples: PackedSamples):
        self.samples = samples

    def __iter__(self):
        s = self.samples
        R = s.offsets.shape[0] - 1
        yield s.offsets.diff().double()
        lengths = (s.t_ends - s.t_starts).double()
        yield torch.zeros(R, dtype=torch.float64, device=lengths.device).index_add_(0, s.ray_indices, lengths)


def nerfacc_march(rays_o, rays_d, occupancy):
    """nerfacc 0.5.3's OccGridEstimator.sampling over the same binary grid (no density filter)."""
    import nerfacc

    estimator = nerfacc.OccGridEstimator(roi_aabb=[*AABB[0], *AABB[1]], resolution=RESOLUTION, levels=1)
    estimator = estimator.to(rays_o.device)
    estimator.binaries.copy_(occupancy[None])

    def run():
        ray_indices, t_starts, t_ends = estimator.sampling(
            rays_o, rays_d, near_plane=NEAR, far_plane=FAR, render_step_size=STEP
        )
        counts = torch.bincount(ray_indices, minlength=rays_o.shape[0])
        offsets = torch.nn.functional.pad(counts.cumsum(0), (1, 0))
        return PackedSamples(t_starts, t_ends, ray_indices, offsets)

    return run


def cases(device: torch.device) -> list[Case]:
    R = 65536 if device.type == "cuda" else 4096
    occupancy = lego_like_occupancy(device)
    bitfield = pack_bits(occupancy)
    grid = (bitfield, torch.tensor(AABB, device=device), (RESOLUTION,) * 3)
    rays_o, rays_d = camera_rays(R, device)

    def march(backend):
        return lambda: PerRaySummary(ray_marching(rays_o, rays_d, NEAR, FAR, grid, STEP, backend=backend))

    # N is the float32 march's sample count; the fixed-size call gets 5% more rows, as a trainer would.
    N = int(ray_marching(rays_o, rays_d, NEAR, FAR, grid, STEP).offsets[-1])
    capacity = N + N // 20

    def march_fixed():
        return PerRaySummary(ray_marching_fixed(rays_o, rays_d, NEAR, FAR, grid, STEP, capacity).samples)

    variants = [Variant("kernel", march("kernel")), Variant("torch", march("torch")),
                Variant("kernel, fixed capacity (no sync)", march_fixed)]
    if device.type == "cuda":
        compiled = torch.compile(ray_marching_reference)
        near, far = torch.full((R,), NEAR, device=device), torch.full((R,), FAR, device=device)
        args = (rays_o, rays_d, near, far, None, bitfield, grid[1], grid[2], STEP)
        variants.append(Variant("torch.compile", lambda: PerRaySummary(PackedSamples(*compiled(*args)[:4]))))
        try:
            import nerfacc  # noqa: F401

            run_nerfacc = nerfacc_march(rays_o, rays_d, occupancy)
            variants.append(Variant("nerfacc", lambda: PerRaySummary(run_nerfacc())))
        except ImportError:
            pass

    def truth():
        return PerRaySummary(
            ray_marching(rays_o.double(), rays_d.double(), NEAR, FAR, grid, STEP, backend="torch")
        )

    # Rays (o, d, near, far) and the bitfield read once; samples (two floats, one int64) and
    # offsets written once.
    min_bytes = R * 8 * 4 + bitfield.numel() + N * (4 + 4 + 8) + (R + 1) * 8
    occupied = occupancy.float().mean().item()
    size = f"R={R}, 128^3 grid ({100 * occupied:.1f}% occupied), step {STEP:g}, {N / R:.1f} samples/ray"
    return [
        Case(op="ray_marching", mode="fwd", size=size, variants=variants, truth=truth, min_bytes=min_bytes)
    ]
