"""Tests of ray_marching (CPU/CUDA kernels against the reference) and filter_by_transmittance.

Marching is discrete: a sample is kept or not. The kernels and the reference do the same IEEE
operations in the same order with no FMA contraction (csrc/ray_marching_math.h), so their outputs
are compared for exact equality, not within a tolerance. With cone_angle > 0 the lattice uses pow,
which may round differently between libm, CUDA and PyTorch; those comparisons allow a few
samples to differ (see assert_nearly_same).
"""

from __future__ import annotations

import math

import pytest
import torch

from mixer_nerf import _extension
from mixer_nerf.ops.ray_marching import (
    PADDING_ROWS,
    FixedSamples,
    PackedSamples,
    filter_by_transmittance,
    padding_rays,
    ray_marching,
    ray_marching_fixed,
)
from mixer_nerf.ops import composite_packed
from mixer_nerf.ops.bitfield import pack_bits
from mixer_nerf.ops.ray_marching_reference import (
    clip_to_box,
    march_dtype,
    padding_rays_reference,
    ray_marching_reference,
    select_fixed_reference,
)
from cuda_poison import poison_allocator

needs_kernels = pytest.mark.skipif(not _extension.available(), reason="mixer_nerf kernels not built")
on_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")

AABB = [[-1.0, -0.5, -2.0], [1.5, 0.7, 1.0]]
RES = (12, 7, 9)  # non-cubic, not powers of two: catches swapped axes and bit-packing slips


def random_grid(gen, fraction=0.3, res=RES, device="cpu"):
    occupied = torch.rand(res, generator=gen) < fraction
    return pack_bits(occupied).to(device), torch.tensor(AABB, device=device), res


def random_rays(R, gen, dtype=torch.float32, device="cpu"):
    """Origins inside and around the box, random directions and [near, far] ranges."""
    o = torch.randn(R, 3, generator=gen, dtype=torch.float64) * 2
    d = torch.randn(R, 3, generator=gen, dtype=torch.float64)
    near = torch.rand(R, generator=gen, dtype=torch.float64) * 0.5
    far = near + torch.rand(R, generator=gen, dtype=torch.float64) * 6
    return [t.to(device, dtype) for t in (o, d, near, far)]


def march(rays, grid, step=0.013, backend="kernel", seed=None, **kwargs):
    generator = None if seed is None else torch.Generator(rays[0].device).manual_seed(seed)
    return ray_marching(
        *rays, grid, step, stratified=seed is not None, generator=generator, backend=backend, **kwargs
    )


def assert_same(a: PackedSamples, b: PackedSamples):
    for name, x, y in zip(PackedSamples._fields, a, b, strict=True):
        assert x.dtype == y.dtype and x.device == y.device, name
        assert torch.equal(x, y), f"{name} differ ({x.shape[0]} vs {y.shape[0]} entries)"


def assert_nearly_same(a: PackedSamples, b: PackedSamples, max_rays=0.01, rtol=1e-5):
    """Per-ray sample counts equal on all but a fraction max_rays of the rays (an ulp of pow can
    move a midpoint across a cell face); on the others, t within rtol."""
    counts_a, counts_b = a.offsets.diff().cpu(), b.offsets.diff().cpu()
    differ = counts_a != counts_b
    assert differ.float().mean() <= max_rays
    same_rays = (~differ).nonzero().squeeze(1)
    take = lambda s: torch.isin(s.ray_indices.cpu(), same_rays)  # noqa: E731
    for x, y in ((a.t_starts, b.t_starts), (a.t_ends, b.t_ends)):
        torch.testing.assert_close(x.cpu()[take(a)], y.cpu()[take(b)], rtol=rtol, atol=1e-6)


def check_layout(s: PackedSamples, R: int):
    """CSR invariants every result must satisfy."""
    N = s.t_starts.shape[0]
    assert s.offsets.shape == (R + 1,) and s.offsets[0] == 0 and s.offsets[-1] == N
    assert (s.offsets.diff() >= 0).all()
    assert torch.equal(
        s.ray_indices, torch.repeat_interleave(torch.arange(R, device=s.offsets.device), s.offsets.diff())
    )
    assert torch.isfinite(s.t_starts).all() and torch.isfinite(s.t_ends).all()
    assert (s.t_ends >= s.t_starts).all()
    same_ray = s.ray_indices[1:] == s.ray_indices[:-1]
    assert (s.t_starts[1:][same_ray] >= s.t_ends[:-1][same_ray]).all(), "samples out of order"
    for t in s:
        assert not t.requires_grad


# --- CPU kernel vs reference -------------------------------------------------------------------


@needs_kernels
@pytest.mark.parametrize("R", [0, 1, 7, 1000])
@pytest.mark.parametrize("stratified", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_matches_reference(gen, R, stratified, dtype):
    rays, grid = random_rays(R, gen, dtype), random_grid(gen)
    seed = 7 if stratified else None
    got, want = march(rays, grid, seed=seed), march(rays, grid, seed=seed, backend="torch")
    check_layout(got, R)
    assert_same(got, want)


@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_kernel_matches_reference_half(gen, dtype):
    """Half inputs march in float32 in both; outputs are rounded to the input dtype."""
    rays, grid = random_rays(300, gen, dtype), random_grid(gen)
    got = march(rays, grid, step=0.05)
    assert got.t_starts.dtype == dtype
    assert_same(got, march(rays, grid, step=0.05, backend="torch"))


@needs_kernels
@pytest.mark.parametrize("cone_angle", [0.004, 0.1])
def test_cone_angle_matches_reference(gen, cone_angle):
    rays, grid = random_rays(1000, gen), random_grid(gen)
    got = march(rays, grid, cone_angle=cone_angle, seed=3)
    check_layout(got, 1000)
    assert_nearly_same(got, march(rays, grid, cone_angle=cone_angle, seed=3, backend="torch"))


@needs_kernels
@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_max_samples_per_ray(gen, backend):
    rays, grid = random_rays(500, gen), random_grid(gen, fraction=0.8)
    full = march(rays, grid, backend=backend)
    capped = march(rays, grid, backend=backend, max_samples_per_ray=5)
    assert (capped.offsets.diff() == full.offsets.diff().clamp(max=5)).all()
    first = torch.arange(full.t_starts.shape[0]) - full.offsets[full.ray_indices] < 5
    assert torch.equal(capped.t_starts, full.t_starts[first])


# --- behaviour (both backends) -----------------------------------------------------------------

BACKENDS = ["torch", pytest.param("kernel", marks=needs_kernels)]


def full_grid(res=RES):
    return pack_bits(torch.ones(res, dtype=torch.bool)), torch.tensor(AABB), res


def empty_grid(res=RES):
    return pack_bits(torch.zeros(res, dtype=torch.bool)), torch.tensor(AABB), res


def chord(rays):
    """[t_lo, t_hi] of each ray within the box, in float64, and whether it hits."""
    o, d, near, far = (t.double() for t in rays)
    box = torch.tensor(AABB).double()  # the box as the op sees it: float32 corners
    return clip_to_box(o, d, near, far, box[0], box[1])


@pytest.mark.parametrize("backend", BACKENDS)
def test_full_grid_tiles_the_chord(gen, backend):
    """Every cell occupied: samples are uniform steps covering [t_lo, t_hi] exactly."""
    rays = random_rays(400, gen, torch.float64)
    step = 0.07
    s = march(rays, full_grid(), step=step, backend=backend)
    check_layout(s, 400)
    t_lo, t_hi, hit = chord(rays)
    counts = s.offsets.diff()
    assert torch.equal(counts, torch.where(hit, torch.ceil((t_hi - t_lo) / step), 0).long())
    hit_rays = hit.nonzero().squeeze(1)
    first, last = s.offsets[hit_rays], s.offsets[hit_rays + 1] - 1
    assert torch.equal(s.t_starts[first], t_lo[hit_rays])
    assert torch.equal(s.t_ends[last], t_hi[hit_rays])
    same_ray = s.ray_indices[1:] == s.ray_indices[:-1]
    assert torch.equal(s.t_starts[1:][same_ray], s.t_ends[:-1][same_ray]), "samples must tile"
    lengths = s.t_ends - s.t_starts
    not_last = torch.ones_like(lengths, dtype=torch.bool)
    not_last[last] = False
    torch.testing.assert_close(
        lengths[not_last], torch.full_like(lengths[not_last], step), rtol=1e-9, atol=1e-12
    )


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_grid_and_misses_give_no_samples(gen, backend):
    rays = random_rays(300, gen)
    s = march(rays, empty_grid(), backend=backend)
    assert s.t_starts.shape == (0,) and torch.equal(s.offsets, torch.zeros(301, dtype=torch.int64))
    # Rays pointing away from the box, or whose [near, far] ends before it, miss it.
    o = torch.tensor([[5.0, 0, 0], [5.0, 0, 0], [0.0, 0, 5]])
    d = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0.0, 1, 0]])
    s = ray_marching(
        o, d, torch.tensor([0.0, 0, 0]), torch.tensor([10.0, 2.0, 10]), full_grid(), 0.01, backend=backend
    )
    assert s.offsets.tolist() == [0, 0, 0, 0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_occupied_cell(gen, backend):
    occupied = torch.zeros(RES, dtype=torch.bool)
    cell = (5, 3, 4)
    occupied[cell] = True
    grid = pack_bits(occupied), torch.tensor(AABB), RES
    box = torch.tensor(AABB)
    size = (box[1] - box[0]) / torch.tensor(RES)
    lo = box[0] + torch.tensor(cell) * size
    rays = random_rays(2000, gen)
    s = march(rays, grid, step=0.01, backend=backend)
    check_layout(s, 2000)
    mid = rays[0][s.ray_indices] + ((s.t_starts + s.t_ends) / 2)[:, None] * rays[1][s.ray_indices]
    assert ((mid >= lo - 1e-5) & (mid <= lo + size + 1e-5)).all()
    # A ray along x through the cell's centre crosses it in size_x / step samples.
    centre = lo + size / 2
    o = torch.stack([torch.tensor(-3.0), centre[1], centre[2]])[None]
    s = ray_marching(o, torch.tensor([[1.0, 0, 0]]), 0.0, 10.0, grid, 0.01, backend=backend)
    assert abs(s.t_starts.shape[0] - size[0].item() / 0.01) <= 1


@pytest.mark.parametrize("backend", BACKENDS)
def test_degenerate_directions(backend):
    """Axis-aligned rays, rays along faces, edges and cell boundaries, diagonals through corners,
    zero and non-finite inputs: finite outputs, the expected counts, the reference's samples."""
    lo, hi = torch.tensor(AABB)
    step = 0.05
    o, d, expected = [], [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            direction = torch.zeros(3)
            direction[axis] = sign
            start = (lo + hi) / 2
            start[axis] = (lo if sign > 0 else hi)[axis] - sign * 1.0
            o.append(start)
            d.append(direction)
            expected.append((hi[axis] - lo[axis]).item() / step)
    # The box's diagonal (corner to corner for t in [1, 2]); along an edge, a face, a cell face.
    o += [
        lo - (hi - lo),
        torch.tensor([-3.0, lo[1], lo[2]]),
        torch.tensor([-3.0, 0.0, hi[2]]),
        torch.tensor([-3.0, 0.1, -1.0]),
    ]
    d += [hi - lo, torch.tensor([1.0, 0, 0]), torch.tensor([1.0, 0, 0]), torch.tensor([1.0, 0, 0])]
    expected += [1 / step, None, None, None]
    # Zero direction, NaN and inf origins/directions, NaN near: no samples.
    o += [
        torch.zeros(3),
        torch.tensor([math.nan, 0, 0]),
        torch.tensor([0.0, 0, 0]),
        torch.tensor([-3.0, 0, 0]),
    ]
    d += [
        torch.zeros(3),
        torch.tensor([1.0, 0, 0]),
        torch.tensor([math.inf, 0, 0]),
        torch.tensor([1e-45, 1e-45, 1e-45]),
    ]
    expected += [0, 0, 0, 0]
    o, d = torch.stack(o), torch.stack(d)
    far = torch.full((len(o),), math.inf)
    s = ray_marching(o, d, 0.0, far, full_grid(), step, backend=backend)
    check_layout(s, len(o))
    counts = s.offsets.diff().tolist()
    for i, want in enumerate(expected):
        if want is not None:  # the last lattice point may round to either side of the box's face
            assert abs(counts[i] - want) <= 1, f"ray {i}: {counts[i]} samples, expected {want}"
    assert all(c > 0 for c in counts[7:10]), "rays along the box's faces and edges are inside it"
    assert_same(s, ray_marching(o, d, 0.0, far, full_grid(), step, backend="torch"))
    assert_same(
        ray_marching(o, d, 0.0, far, random_grid(torch.Generator().manual_seed(0)), step, backend=backend),
        ray_marching(o, d, 0.0, far, random_grid(torch.Generator().manual_seed(0)), step, backend="torch"),
    )


@pytest.mark.parametrize("backend", BACKENDS)
def test_stratified_offsets(gen, backend):
    rays, step = random_rays(500, gen, torch.float64), 0.05
    s = march(rays, full_grid(), step=step, backend=backend, seed=11)
    t_lo, _, hit = chord(rays)
    hit_rays = (hit & (s.offsets.diff() > 0)).nonzero().squeeze(1)
    offset = s.t_starts[s.offsets[hit_rays]] - t_lo[hit_rays]
    assert (offset >= 0).all() and (offset < step).all() and offset.std() > step / 5
    assert_same(s, march(rays, full_grid(), step=step, backend=backend, seed=11))


@pytest.mark.parametrize("backend", BACKENDS)
def test_cone_angle_steps_grow(gen, backend):
    o = torch.tensor([[0.0, 0.1, -1.9]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    step, cone = 0.01, 0.02
    s = ray_marching(o, d, 0.0, 10.0, full_grid(), step, cone_angle=cone, backend=backend)
    lengths = (s.t_ends - s.t_starts)[:-1]
    want = torch.clamp(s.t_starts[:-1] * cone, min=step)
    torch.testing.assert_close(lengths, want, rtol=0.03, atol=1e-6)  # steps grow within one step of t*cone
    assert s.t_ends[-1] == 2.9 and s.t_starts[0] == 0.0


# --- filter_by_transmittance -------------------------------------------------------------------


def naive_keep(sigmas, s: PackedSamples, threshold, alpha_threshold):
    keep = torch.zeros_like(sigmas, dtype=torch.bool)
    for r in range(s.offsets.shape[0] - 1):
        optical_depth = 0.0
        for i in range(s.offsets[r], s.offsets[r + 1]):
            tau = sigmas[i].item() * (s.t_ends[i] - s.t_starts[i]).item()
            alpha = -math.expm1(-tau)
            keep[i] = math.exp(-optical_depth) >= threshold and alpha >= alpha_threshold
            optical_depth += tau
    return keep


FILTER_BACKENDS = pytest.mark.parametrize("backend", [
    "torch", pytest.param("kernel", marks=pytest.mark.skipif(not _extension.available(), reason="kernels not built"))])


@FILTER_BACKENDS
@pytest.mark.parametrize("threshold,alpha_threshold",
                         [(1e-4, 0.0), (1e-2, 1e-3), (0.0, 0.0), (0.0, 0.5), (1.0, 0.0)])
def test_filter_by_transmittance_matches_naive(gen, threshold, alpha_threshold, backend):
    rays = random_rays(40, gen, torch.float64)
    s = march(rays, full_grid(), step=0.1, backend="torch")
    sigmas = torch.rand(s.t_starts.shape, generator=gen, dtype=torch.float64) * 20
    sigmas[torch.rand(sigmas.shape, generator=gen) < 0.3] = 0
    keep = filter_by_transmittance(sigmas, s, threshold, alpha_threshold, backend=backend)
    assert torch.equal(keep, naive_keep(sigmas, s, threshold, alpha_threshold))
    kept = s.select(keep)
    check_layout(kept, 40)
    assert torch.equal(
        kept.offsets.diff(), torch.zeros(40, dtype=torch.int64).index_add_(0, s.ray_indices, keep.long())
    )


@FILTER_BACKENDS
def test_filter_by_transmittance_adversarial(gen, backend):
    """inf, 1e30 and NaN densities end (or, NaN, don't touch) their own ray only."""
    R = 20
    rays_o = torch.rand(R, 3, generator=gen) * 0.4 + torch.tensor([-0.2, -0.2, -5.0])  # all cross the box
    rays_d = torch.tensor([0.0, 0.0, 1.0]).expand(R, 3)
    s = ray_marching(rays_o, rays_d, 0.0, 10.0, full_grid(), 0.1, backend="torch")
    assert (s.offsets.diff() == 30).all()
    sigmas = torch.full(s.t_starts.shape, 1e-3)
    adversarial = {3: math.inf, 7: 1e30, 11: math.nan}
    for r, value in adversarial.items():
        sigmas[s.offsets[r]] = value
    keep = filter_by_transmittance(sigmas, s, backend=backend)
    for r, value in adversarial.items():
        ray_keep = keep[s.offsets[r] : s.offsets[r + 1]]
        assert ray_keep[0] and (ray_keep[1:].all() if math.isnan(value) else not ray_keep[1:].any())
    others = ~torch.isin(s.ray_indices, torch.tensor(list(adversarial)))
    assert keep[others].all()


@pytest.mark.skipif(not _extension.available(), reason="kernels not built")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_filter_kernel_matches_the_reference_and_drops_rows_of_no_ray(gen, dtype):
    """The kernel (per-ray sums) against the reference (one cumsum) on a fixed layout with spare rows,
    densities from 0 to 1e3, NaN and inf among them; equal except where a depth sits within 1e-9 of
    the limit (the two sums round differently); the spare rows dropped by both."""
    rays = random_rays(60, gen)
    fixed = ray_marching_fixed(*rays, full_grid(), 0.05, 4000, backend="torch").samples
    t_starts, t_ends = fixed.t_starts.to(dtype), fixed.t_ends.to(dtype)
    sigmas = (10 ** (torch.rand(4000, generator=gen) * 6 - 3)).to(dtype)
    sigmas[::97], sigmas[::89] = math.nan, math.inf
    s = PackedSamples(t_starts, t_ends, fixed.ray_indices, fixed.offsets)
    end = int(fixed.offsets[-1])
    assert end < 4000
    for threshold, alpha in ((1e-4, 0.0), (1e-2, 1e-3), (0.0, 0.2)):
        got = filter_by_transmittance(sigmas, s, threshold, alpha, backend="kernel")
        want = filter_by_transmittance(sigmas, s, threshold, alpha, backend="torch")
        assert not got[end:].any() and not want[end:].any()
        tau = torch.nan_to_num(sigmas.double() * (t_ends - t_starts).double(), nan=0.0).clamp_min(0)
        depth = torch.cat([tau.new_zeros(1), tau.cumsum(0)])
        before = depth[:-1] - depth[fixed.offsets[fixed.ray_indices]]
        near_limit = (before - (-math.log(threshold) if threshold else math.inf)).abs() < 1e-9
        assert torch.equal(got[~near_limit], want[~near_limit])
    torch.library.opcheck(torch.ops.mixer_nerf.transmittance_filter_fwd.default,
                          (sigmas, t_starts, t_ends, fixed.offsets, 1e-4, 0.0))


@on_cuda
@pytest.mark.cuda
def test_cuda_filter_matches_the_cpu_kernel(gen):
    rays = random_rays(500, gen)
    fixed = ray_marching_fixed(*rays, full_grid(), 0.02, 40000, backend="torch").samples
    sigmas = 10 ** (torch.rand(40000, generator=gen) * 6 - 3)
    sigmas[::97] = math.nan
    for threshold, alpha in ((1e-4, 0.0), (1e-2, 1e-3), (0.0, 0.2)):
        cpu = filter_by_transmittance(sigmas, fixed, threshold, alpha, backend="kernel")
        on_gpu = PackedSamples(*(t.cuda() for t in fixed))
        cuda = filter_by_transmittance(sigmas.cuda(), on_gpu, threshold, alpha, backend="kernel")
        assert torch.equal(cpu, cuda.cpu())


# --- input validation and op registration ------------------------------------------------------


def valid_args():
    gen = torch.Generator().manual_seed(0)
    return random_rays(4, gen), random_grid(gen)


@pytest.mark.parametrize(
    "change,error,name",
    [
        (lambda r, g: ((r[0][0], *r[1:]), g), ValueError, "rays_o"),
        (lambda r, g: ((r[0][:, :2], *r[1:]), g), ValueError, "rays_o"),
        (lambda r, g: ((r[0], r[1][:3], *r[2:]), g), ValueError, "rays_d"),
        (lambda r, g: ((r[0].long(), *r[1:]), g), TypeError, "rays_o"),
        (lambda r, g: ((r[0], r[1].double(), *r[2:]), g), TypeError, "rays_d"),
        (lambda r, g: ((*r[:2], r[2][:3], r[3]), g), ValueError, "near"),
        (lambda r, g: ((*r[:3], r[3].long()), g), TypeError, "far"),
        (lambda r, g: (r, g[0]), TypeError, "grid"),
        (lambda r, g: (r, (g[0].long(), *g[1:])), TypeError, "bitfield"),
        (lambda r, g: (r, (g[0][:-1], *g[1:])), ValueError, "bitfield"),
        (lambda r, g: (r, (g[0], g[1][0], g[2])), ValueError, "aabb"),
        (lambda r, g: (r, (g[0], g[1].long(), g[2])), TypeError, "aabb"),
        (lambda r, g: (r, (*g[:2], (4, 4))), ValueError, "resolution"),
    ],
)
def test_bad_inputs(change, error, name):
    rays, grid = change(*valid_args())
    for backend in ("torch", "auto"):
        with pytest.raises(error, match=name):
            ray_marching(*rays, grid, 0.1, backend=backend)


@pytest.mark.parametrize(
    "kwargs,name",
    [
        ({"step_size": 0.0}, "step_size"),
        ({"step_size": math.nan}, "step_size"),
        ({"cone_angle": -0.1}, "cone_angle"),
        ({"max_samples_per_ray": 0}, "max_samples_per_ray"),
        ({"backend": "cuda"}, "backend"),
    ],
)
def test_bad_options(kwargs, name):
    rays, grid = valid_args()
    with pytest.raises(ValueError, match=name):
        ray_marching(*rays, grid, **{"step_size": 0.1, **kwargs})


def test_filter_bad_inputs():
    rays, grid = valid_args()
    s = ray_marching(*rays, full_grid(), 0.1, backend="torch")
    with pytest.raises(ValueError, match="sigmas"):
        filter_by_transmittance(torch.zeros(s.t_starts.shape[0] + 1), s)
    with pytest.raises(TypeError, match="sigmas"):
        filter_by_transmittance(torch.zeros(s.t_starts.shape[0], dtype=torch.long), s)
    with pytest.raises(ValueError, match="threshold"):
        filter_by_transmittance(torch.zeros(s.t_starts.shape[0]), s, threshold=2.0)


def test_no_grad_outputs(gen):
    o, d, near, far = random_rays(20, gen)
    s = ray_marching(o.requires_grad_(), d.requires_grad_(), near, far, full_grid(), 0.1)
    check_layout(s, 20)


@needs_kernels
def test_opcheck(gen):
    rays, grid = random_rays(50, gen), random_grid(gen)
    ray_marching(*rays, grid, 0.05, backend="kernel")  # registers the fake
    aabb = grid[1]
    for jitter, cone, cap, capacity in ((None, 0.0, None, None), (torch.rand(50, generator=gen), 0.05, 4, None),
                                        (None, 0.0, None, 64)):
        args = (*rays, jitter, grid[0], aabb, list(grid[2]), 0.05, cone, cap, capacity)
        torch.library.opcheck(torch.ops.mixer_nerf.ray_marching_fwd.default, args)


# --- fixed-size outputs ------------------------------------------------------------------------


def assert_fixed(fixed: FixedSamples, exact: PackedSamples, capacity: int):
    """What ray_marching_fixed promises against ray_marching's samples: the first ``capacity`` of
    them, offsets clamped, zero rows after them, the uncut count in ``total``."""
    N, s = exact.t_starts.shape[0], fixed.samples
    kept = min(N, capacity)
    assert torch.equal(s.offsets, exact.offsets.clamp_max(capacity))
    assert fixed.total.dtype == torch.int64 and fixed.total.tolist() == [N]
    for name in ("t_starts", "t_ends", "ray_indices"):
        got, want = getattr(s, name), getattr(exact, name)
        assert got.shape == (capacity,) and got.dtype == want.dtype, name
        assert torch.equal(got[:kept], want[:kept]), name
        assert not got[kept:].any(), f"{name}: padding rows are not zero"


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("room", ["spare", "exact", "cut", "none"])
@pytest.mark.parametrize("R, stratified, dtype", [(1000, False, torch.float32), (300, True, torch.float64),
                                                  (0, False, torch.float32)])
def test_fixed_capacity_holds_the_first_samples(gen, backend, room, R, stratified, dtype):
    rays, grid = random_rays(R, gen, dtype), random_grid(gen)
    exact = march(rays, grid, backend=backend, seed=3 if stratified else None)
    N = exact.t_starts.shape[0]
    capacity = {"spare": N + 17, "exact": N, "cut": N // 2, "none": 0}[room]
    generator = torch.Generator().manual_seed(3) if stratified else None
    fixed = ray_marching_fixed(*rays, grid, 0.013, capacity, stratified=stratified, generator=generator,
                               backend=backend)
    assert_fixed(fixed, exact, capacity)
    if room == "cut" and R:
        assert N // 2 < N and int(fixed.samples.offsets[-1]) == N // 2  # some rays lost samples


@needs_kernels
def test_fixed_capacity_kernel_matches_reference(gen):
    rays, grid = random_rays(2000, gen), random_grid(gen, 0.6)
    for capacity in (0, 1, 777, 10**6):
        got, want = (ray_marching_fixed(*rays, grid, 0.02, capacity, max_samples_per_ray=9, backend=backend)
                     for backend in ("kernel", "torch"))
        assert_same(got.samples, want.samples)
        assert torch.equal(got.total, want.total)


@pytest.mark.parametrize("capacity", [-1, 2.5, None, "8"])
def test_fixed_capacity_must_be_a_count(gen, capacity):
    with pytest.raises(ValueError, match="capacity must be an int >= 0"):
        ray_marching_fixed(*random_rays(4, gen), random_grid(gen), 0.1, capacity)
    samples = ray_marching(*random_rays(4, gen), full_grid(), 0.1)
    with pytest.raises(ValueError, match="capacity must be an int >= 0"):
        samples.select_fixed(torch.ones_like(samples.t_starts, dtype=torch.bool), capacity)


@pytest.mark.parametrize("room", ["spare", "exact", "cut", "none"])
@pytest.mark.parametrize("fixed_input", [False, True])
def test_select_fixed_keeps_what_select_keeps(gen, room, fixed_input):
    """The sync-free selection into fixed rows against select(): the same samples, cut and padded
    as ray_marching_fixed's are; a fixed-size input's padding rows are never kept."""
    rays, grid = random_rays(500, gen), random_grid(gen, 0.5)
    exact = march(rays, grid, backend="torch")
    N = exact.t_starts.shape[0]
    if fixed_input:  # the same samples in a fixed layout with 50 padding rows
        source = ray_marching_fixed(*rays, grid, 0.013, N + 50, backend="torch").samples
    else:
        source = exact
    keep = torch.rand(source.t_starts.shape[0], generator=gen) < 0.6
    selected = exact.select(keep[:N])
    kept = selected.t_starts.shape[0]
    capacity = {"spare": kept + 9, "exact": kept, "cut": kept // 3, "none": 0}[room]
    assert_fixed(source.select_fixed(keep, capacity), selected, capacity)


@pytest.mark.parametrize("room", ["spare", "many", "exact", "cut", "none"])
def test_fixed_samples_name_the_intact_rays_and_pad_to_short_rays(gen, room):
    """intact(): the rays whose samples all fit (those past the cut, and the ray across it, lost
    some); with_padding_rays(): short rays own the zero rows, so the composite of the padded
    layout gives every real ray what the exact samples give it and the padding rays nothing."""
    rays, grid = random_rays(400, gen), random_grid(gen, 0.5)
    exact = march(rays, grid, backend="torch")
    N = exact.t_starts.shape[0]
    capacity = {"spare": N + 30, "many": 3 * N + 5, "exact": N, "cut": N // 2, "none": 0}[room]
    fixed = ray_marching_fixed(*rays, grid, 0.013, capacity, backend="torch")
    ends = exact.offsets[1:]
    assert torch.equal(fixed.intact(), (ends < capacity) | (N <= capacity))
    assert room != "cut" or not fixed.intact()[ends > capacity].any() and fixed.intact()[ends < capacity].all()
    padded = fixed.with_padding_rays()
    R, P = rays[0].shape[0], padding_rays(capacity)
    assert padded.offsets.shape == (R + P + 1,) and torch.equal(padded.offsets[: R + 1], fixed.samples.offsets)
    assert int(padded.offsets[-1]) == capacity and (padded.offsets.diff()[R:] <= PADDING_ROWS).all()
    assert torch.equal(padded.ray_indices, torch.repeat_interleave(torch.arange(R + P), padded.offsets.diff()))
    sigma_all, rgb_all = torch.rand(N, generator=gen) * 5, torch.rand(N, 3, generator=gen)
    kept = min(N, capacity)  # the fixed rows hold the first samples, then zero rows
    sigma = torch.cat([sigma_all[:kept], sigma_all.new_full((capacity - kept,), 7.0)])
    rgb = torch.cat([rgb_all[:kept], rgb_all.new_ones(capacity - kept, 3)])
    color = composite_packed(sigma, rgb, padded.t_starts, padded.t_ends, padded.offsets, backend="torch")[0]
    full = composite_packed(sigma_all, rgb_all, exact.t_starts, exact.t_ends, exact.offsets, backend="torch")[0]
    intact = fixed.intact()
    torch.testing.assert_close(color[:R][intact], full[intact])
    assert not color[R:].any()


def select_cases(gen):
    """(keep, t_starts, t_ends, ray_indices, offsets): a fixed layout's samples with spare rows (keep
    True on some of them: never kept), then no row."""
    rays = random_rays(80, gen)
    fixed = ray_marching_fixed(*rays, full_grid(), 0.05, 5000, backend="torch").samples
    keep = torch.rand(5000, generator=gen) < 0.6
    yield keep, *fixed
    yield torch.zeros(0, dtype=torch.bool), *(t[:0] for t in fixed[:3]), torch.zeros(5, dtype=torch.int64)


@pytest.mark.skipif(not _extension.available(), reason="kernels not built")
def test_select_fixed_kernel_matches_the_reference(gen):
    for keep, *samples in select_cases(gen):
        N, end = keep.shape[0], int(samples[3][-1])
        for capacity in {0, 1, N // 3, end, N + 7}:
            got = torch.ops.mixer_nerf.select_fixed_fwd(keep, *samples, capacity)
            want, want_total = select_fixed_reference(keep, *samples, capacity)
            assert all(torch.equal(g, w) for g, w in zip(got, (*want, want_total), strict=True)), capacity
    keep, *samples = next(select_cases(gen))
    PackedSamples(*samples).select_fixed(keep, 100)  # registers the fake
    torch.library.opcheck(torch.ops.mixer_nerf.select_fixed_fwd.default, (keep, *samples, 100))


@on_cuda
@pytest.mark.cuda
def test_cuda_select_fixed_matches_the_cpu(gen):
    for keep, *samples in select_cases(gen):
        for capacity in (0, 17, 3000, 6000):
            cpu = torch.ops.mixer_nerf.select_fixed_fwd(keep, *samples, capacity)
            cuda = torch.ops.mixer_nerf.select_fixed_fwd(keep.cuda(), *(t.cuda() for t in samples), capacity)
            assert all(torch.equal(c, g.cpu()) for c, g in zip(cpu, cuda, strict=True))


def padding_cases(gen, device="cpu"):
    """(offsets, ray_indices, rows_per_ray): random ragged rays in a buffer with spare rows, the
    buffer exactly full, no spare row of a ray, no ray, no row, and an unchecked end past N."""
    counts = torch.randint(0, 9, (50,), generator=gen)
    offsets = torch.nn.functional.pad(counts.cumsum(0), (1, 0))
    end = int(offsets[-1])
    spare = int(torch.randint(1, 200, (1,), generator=gen))
    rays = torch.repeat_interleave(torch.arange(50), counts)
    for rows, per_ray in ((end + spare, 32), (end + spare, 1), (end + spare, 7), (end, 32)):
        yield offsets, torch.cat([rays, torch.zeros(rows - end, dtype=torch.int64)]), per_ray
    yield torch.zeros(1, dtype=torch.int64), torch.zeros(70, dtype=torch.int64), 32  # no ray
    yield torch.zeros(4, dtype=torch.int64), torch.zeros(0, dtype=torch.int64), 32  # no row
    yield torch.tensor([0, 3, 90]), torch.zeros(40, dtype=torch.int64), 8  # end past N: clamped


@pytest.mark.skipif(not _extension.available(), reason="kernels not built")
def test_padding_rays_kernel_matches_the_reference(gen):
    for offsets, ray_indices, per_ray in padding_cases(gen):
        got = torch.ops.mixer_nerf.padding_rays_fwd(offsets, ray_indices, per_ray)
        want = padding_rays_reference(offsets, ray_indices, per_ray)
        assert all(torch.equal(g, w) for g, w in zip(got, want, strict=True)), (offsets, per_ray)
        R, N = offsets.shape[0] - 1, ray_indices.shape[0]
        padded_offsets = got[1]
        assert padded_offsets.shape == (R + 1 + -(-N // per_ray),) and int(padded_offsets[-1]) == N
    offsets, ray_indices, per_ray = next(padding_cases(gen))
    FixedSamples(PackedSamples(ray_indices.float(), ray_indices.float(), ray_indices, offsets),
                 offsets[-1:]).with_padding_rays()  # registers the fake
    torch.library.opcheck(torch.ops.mixer_nerf.padding_rays_fwd.default, (offsets, ray_indices, per_ray))
    with pytest.raises(RuntimeError, match="int64"):
        torch.ops.mixer_nerf.padding_rays_fwd(offsets.int(), ray_indices, 32)
    with pytest.raises(RuntimeError, match="rows_per_ray"):
        torch.ops.mixer_nerf.padding_rays_fwd(offsets, ray_indices, 0)


@on_cuda
@pytest.mark.cuda
def test_cuda_padding_rays_match_the_cpu(gen):
    for offsets, ray_indices, per_ray in padding_cases(gen):
        cpu = torch.ops.mixer_nerf.padding_rays_fwd(offsets, ray_indices, per_ray)
        cuda = torch.ops.mixer_nerf.padding_rays_fwd(offsets.cuda(), ray_indices.cuda(), per_ray)
        assert all(torch.equal(c, g.cpu()) for c, g in zip(cpu, cuda, strict=True))


def test_select_fixed_rejects_a_mask_of_another_length(gen):
    samples = ray_marching(*random_rays(8, gen), full_grid(), 0.1)
    with pytest.raises(ValueError, match="keep"):
        samples.select_fixed(torch.ones(samples.t_starts.shape[0] + 1, dtype=torch.bool), 4)


# --- CUDA --------------------------------------------------------------------------------------


def check_cuda(
    rays, grid, stratified=False, exact=True, step=0.013, cone_angle=0.0, max_samples_per_ray=None, capacity=None
):
    """CUDA kernel vs CPU kernel vs the reference on either device, all on the same jitter (the
    registered op takes it explicitly: CPU and CUDA generators draw different numbers)."""
    _extension.load()
    R, dtype = rays[0].shape[0], rays[0].dtype
    jitter = torch.rand(R).to(dtype) if stratified else None
    bitfield, aabb, resolution = grid

    def run(fn, device):
        def to(t):
            return None if t is None else t.to(device)

        aabb_ = to(aabb.to(march_dtype(dtype)))
        options = (list(resolution), step, cone_angle, max_samples_per_ray, capacity)
        *samples, total = (t.cpu() for t in fn(*map(to, rays), to(jitter), to(bitfield), aabb_, *options))
        return PackedSamples(*samples), total

    kernel = torch.ops.mixer_nerf.ray_marching_fwd
    (cpu, cpu_total), (reference, reference_total) = run(kernel, "cpu"), run(ray_marching_reference, "cpu")
    poison_allocator(list(cpu))
    got, total = run(kernel, "cuda")
    if capacity is None:
        check_layout(got, R)
    same = assert_same if exact else assert_nearly_same
    same(got, cpu)
    same(cpu, reference)
    assert torch.equal(total, cpu_total) and torch.equal(cpu_total, reference_total)
    same(run(ray_marching_reference, "cuda")[0], reference)  # eager PyTorch on the GPU agrees too


@pytest.mark.cuda
@on_cuda
@pytest.mark.parametrize("R", [1, 31, 1000, 70001])
@pytest.mark.parametrize("stratified", [False, True])
def test_cuda_matches_cpu_and_reference(gen, R, stratified):
    check_cuda(random_rays(R, gen), random_grid(gen), stratified=stratified)


@pytest.mark.cuda
@on_cuda
@pytest.mark.parametrize("dtype", [torch.float64, torch.float16])
def test_cuda_dtypes(gen, dtype):
    check_cuda(random_rays(500, gen, dtype), random_grid(gen), step=0.05)


@pytest.mark.cuda
@on_cuda
def test_cuda_cone_and_cap(gen):
    check_cuda(random_rays(2000, gen), random_grid(gen), exact=False, cone_angle=0.02)
    check_cuda(random_rays(2000, gen), random_grid(gen, 0.9), max_samples_per_ray=7)


@pytest.mark.cuda
@on_cuda
@pytest.mark.parametrize("capacity", [0, 5000, 10**6])
def test_cuda_fixed_capacity_matches_cpu_and_reference(gen, capacity):
    check_cuda(random_rays(3000, gen), random_grid(gen), stratified=True, capacity=capacity)
    check_cuda([t[:0] for t in random_rays(1, gen)], random_grid(gen), capacity=capacity)


@pytest.mark.cuda
@on_cuda
def test_cuda_fixed_capacity_needs_no_sync_and_replays_in_a_graph(gen):
    """No host read of a count (the march, the filter and the fixed selection), so the march can
    be captured once and replayed on new rays."""
    rays = [t.cuda() for t in random_rays(3000, gen)]
    grid = tuple(t.cuda() if isinstance(t, torch.Tensor) else t for t in random_grid(gen))
    exact = ray_marching(*rays, grid, 0.013)
    capacity = exact.t_starts.shape[0]
    torch.cuda.synchronize()
    sigmas = torch.rand(capacity, device="cuda") * 50
    torch.cuda.set_sync_debug_mode("error")
    try:
        fixed = ray_marching_fixed(*rays, grid, 0.013, capacity // 2)
        whole = ray_marching_fixed(*rays, grid, 0.013, capacity)
        keep = filter_by_transmittance(sigmas, whole.samples)
        selected = whole.samples.select_fixed(keep, capacity // 3)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert_fixed(fixed, exact, capacity // 2)
    assert_fixed(selected, exact.select(filter_by_transmittance(sigmas, exact)), capacity // 3)

    static = [t.clone() for t in rays]
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        ray_marching_fixed(*static, grid, 0.013, capacity)  # loads and warms up outside the capture
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = ray_marching_fixed(*static, grid, 0.013, capacity)
    new_rays = [t.cuda() for t in random_rays(3000, gen)]
    for held, new in zip(static, new_rays):
        held.copy_(new)
    graph.replay()
    assert_fixed(out, ray_marching(*new_rays, grid, 0.013), capacity)


@pytest.mark.cuda
@on_cuda
def test_cuda_edge_grids(gen):
    rays = random_rays(3000, gen)
    check_cuda(rays, full_grid())
    check_cuda(rays, empty_grid())
    check_cuda([t[:0] for t in rays], full_grid())


@pytest.mark.cuda
@on_cuda
def test_cuda_128_grid_and_mixed_devices(gen):
    grid = random_grid(gen, 0.05, res=(128, 128, 128))
    rays = random_rays(20000, gen)
    check_cuda(rays, grid, step=0.005)
    cuda_grid = (grid[0].cuda(), grid[1].cuda(), grid[2])
    through_wrapper = march([t.cuda() for t in rays], cuda_grid, step=0.005)
    assert_same(PackedSamples(*(t.cpu() for t in through_wrapper)), march(rays, grid, step=0.005))
    with pytest.raises(ValueError, match="device"):
        ray_marching(*random_rays(4, gen), cuda_grid, 0.1)
