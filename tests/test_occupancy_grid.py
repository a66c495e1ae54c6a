"""Tests of OccupancyGrid: warm-up, EMA updates, thresholding, checkpoints, and marching through it."""

from __future__ import annotations

import io
import math

import pytest
import torch

from mixer_nerf.render.skipping import OccupancyGrid
from mixer_nerf.ops.ray_marching import ray_marching

AABB = [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]
on_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")


def constant(sigma):
    return lambda x: torch.full(x.shape[:1], float(sigma), device=x.device)


def sphere(radius=0.8, sigma=100.0):
    return lambda x: (x.norm(dim=-1) < radius).float() * sigma


def cell_corners(grid):
    """(X, Y, Z, 8, 3) corners of every cell."""
    lo, hi = grid.aabb
    axes = [torch.linspace(lo[a].item(), hi[a].item(), n + 1) for a, n in enumerate(grid.resolution)]
    edges = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)
    X, Y, Z = grid.resolution
    return torch.stack(
        [edges[i : i + X, j : j + Y, k : k + Z] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dim=3
    )


def test_starts_dense_and_packs_bits():
    grid = OccupancyGrid(AABB, (8, 5, 3))
    assert grid.bitfield.dtype == torch.uint8 and grid.bitfield.shape == (15,)
    assert grid.occupied.all() and grid.occupied.shape == (8, 5, 3)
    pattern = torch.rand(8, 5, 3) < 0.5
    grid.occupied = pattern
    assert torch.equal(grid.occupied, pattern)
    assert grid.step_size == pytest.approx(math.sqrt(27) / 1000)


def test_update_only_every_n_steps(gen):
    grid = OccupancyGrid(AABB, 8)
    assert not grid.update(3, constant(1.0), every=16, generator=gen)
    assert (grid.opacity == 0).all()
    assert grid.update(32, constant(1.0), every=16, generator=gen)
    assert (grid.opacity > 0).all()


def test_warmup_is_dense_and_updates_every_cell(gen):
    grid = OccupancyGrid(AABB, 8)
    grid.update(0, constant(0.0), warmup_steps=256, generator=gen)
    assert grid.occupied.all(), "during warm-up every cell counts as occupied"
    grid.update(16, sphere(), warmup_steps=256, generator=gen)
    assert grid.occupied.all()
    assert (grid.opacity > 0).sum() > 0


def test_ema_decay_is_exact(gen):
    grid = OccupancyGrid(AABB, 6, step_size=0.01)
    opacity = -math.expm1(-5.0 * 0.01)
    grid.update(0, constant(5.0), generator=gen)
    torch.testing.assert_close(grid.opacity, torch.full_like(grid.opacity, opacity))
    grid.update(16, constant(0.0), decay=0.9, generator=gen)  # still warming up: every cell
    torch.testing.assert_close(grid.opacity, torch.full_like(grid.opacity, 0.9 * opacity))
    grid.update(32, constant(50.0), decay=0.9, generator=gen)  # a larger opacity replaces it
    torch.testing.assert_close(grid.opacity, torch.full_like(grid.opacity, -math.expm1(-0.5)))


def test_sphere_gives_the_expected_cells(gen):
    grid = OccupancyGrid(AABB, 16)
    field = sphere(radius=0.8)
    grid.update(0, field, warmup_steps=1, generator=gen)  # warm-up: every cell measured
    grid.update(16, field, warmup_steps=1, generator=gen)  # thresholded from now on
    distance = cell_corners(grid).norm(dim=-1)
    inside = (distance < 0.8).all(-1)  # cells entirely in the sphere: any jittered point hits it
    touching = distance.amin(-1) < 0.8 + 3 / 16 * math.sqrt(3)  # a superset of those it meets
    occupied = grid.occupied
    assert occupied[inside].all()
    assert not occupied[~touching].any()


def test_threshold_is_capped_by_the_mean(gen):
    """A faint field (opacity far below the threshold in a few cells) stays visible: the
    threshold is min(threshold, mean)."""
    grid = OccupancyGrid(AABB, 8, step_size=0.01)
    faint = lambda x: (x[:, 0] > 1.125).float() * 0.01  # noqa: E731  opacity 1e-4 in the last cells
    grid.update(0, faint, warmup_steps=1, generator=gen)
    grid.update(16, faint, warmup_steps=1, generator=gen)
    expected = torch.zeros(grid.resolution, dtype=torch.bool)
    expected[-1] = True  # x in [1.125, 1.5]
    assert torch.equal(grid.occupied, expected)


def test_measured_copy_holds_the_field_and_leaves_the_grid(gen):
    """A render of a run in warm-up marches a measured copy: the sphere's cells, the same ones each
    time, while the training grid stays dense and unmeasured."""
    grid = OccupancyGrid(AABB, 16)
    measured = grid.measured(sphere(radius=0.8))
    distance = cell_corners(grid).norm(dim=-1)
    assert measured.occupied[(distance < 0.8).all(-1)].all()
    assert not measured.occupied[~(distance.amin(-1) < 0.8 + 3 / 16 * math.sqrt(3))].any()
    assert torch.equal(measured.bitfield, grid.measured(sphere(radius=0.8)).bitfield)
    assert grid.occupied.all() and (grid.opacity == 0).all()


def test_measured_threshold_is_capped_by_the_mean():
    """As a refresh after warm-up: a faint field keeps its cells (a young field is faint)."""
    grid = OccupancyGrid(AABB, 8, step_size=0.01)
    faint = grid.measured(lambda x: (x[:, 0] > 1.125).float() * 0.01, threshold=0.01)
    expected = torch.zeros(grid.resolution, dtype=torch.bool)
    expected[-1] = True
    assert torch.equal(faint.occupied, expected)


def test_after_warmup_only_a_subset_is_measured(gen):
    grid = OccupancyGrid(AABB, 16)
    grid.update(0, constant(1.0), warmup_steps=1, generator=gen)
    before = grid.opacity.clone()
    grid.update(16, constant(0.0), warmup_steps=1, decay=0.5, generator=gen)
    decayed = grid.opacity < before
    # A random quarter plus (all cells being occupied before) as many occupied ones: <= half.
    assert 0.15 < decayed.float().mean() <= 0.5
    torch.testing.assert_close(grid.opacity[decayed], 0.5 * before[decayed])


def test_nan_densities_count_as_empty(gen):
    grid = OccupancyGrid(AABB, 8)
    grid.update(0, lambda x: torch.full(x.shape[:1], math.nan), warmup_steps=1, generator=gen)
    grid.update(16, lambda x: torch.full(x.shape[:1], -math.inf), warmup_steps=1, generator=gen)
    assert torch.isfinite(grid.opacity).all() and not grid.occupied.any()


def test_chunks_and_autocast(gen):
    """Chunked evaluation gives what one chunk gives; a bf16 model under autocast works."""
    model = torch.nn.Sequential(
        torch.nn.Linear(3, 16), torch.nn.ReLU(), torch.nn.Linear(16, 1), torch.nn.Softplus()
    )
    calls = []

    def density_fn(x):
        calls.append(x.shape[0])
        return model(x).squeeze(-1)

    a, b = OccupancyGrid(AABB, 8), OccupancyGrid(AABB, 8)
    a.update(0, density_fn, chunk_size=100, generator=torch.Generator().manual_seed(1))
    assert max(calls) == 100 and sum(calls) == 512
    b.update(0, density_fn, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(a.opacity, b.opacity)
    a.update(16, density_fn, autocast_dtype=torch.bfloat16, generator=gen)
    assert a.opacity.dtype == torch.float32 and torch.isfinite(a.opacity).all()


def test_checkpoint_round_trip(gen):
    grid = OccupancyGrid(AABB, (8, 6, 4))
    grid.update(0, sphere(), warmup_steps=1, generator=gen)
    grid.update(16, sphere(), warmup_steps=1, generator=gen)
    buffer = io.BytesIO()
    torch.save(grid.state_dict(), buffer)
    buffer.seek(0)
    restored = OccupancyGrid(AABB, (8, 6, 4))
    restored.load_state_dict(torch.load(buffer))
    for name in ("aabb", "opacity", "bitfield"):
        assert torch.equal(getattr(restored, name), getattr(grid, name))
    # A checkpoint from before the "density" -> "opacity" rename still loads.
    legacy = {("density" if k == "opacity" else k): v for k, v in grid.state_dict().items()}
    renamed = OccupancyGrid(AABB, (8, 6, 4))
    renamed.load_state_dict(legacy)
    assert torch.equal(renamed.opacity, grid.opacity)
    rays_o, rays_d = torch.randn(100, 3, generator=gen) * 3, torch.randn(100, 3, generator=gen)
    for x, y in zip(
        ray_marching(rays_o, rays_d, 0.0, 10.0, grid, 0.01),
        ray_marching(rays_o, rays_d, 0.0, 10.0, restored, 0.01),
        strict=True,
    ):
        assert torch.equal(x, y)
    with pytest.raises(RuntimeError, match="size mismatch"):
        OccupancyGrid(AABB, 8).load_state_dict(grid.state_dict())


def test_marching_skips_empty_space(gen):
    """With a sphere's grid, every sample lies in a cell that meets the sphere, and rays through
    the centre get ~diameter / step samples instead of ~box / step (cells at the poles are
    measured at one random point each, so some of those are missed)."""
    grid = OccupancyGrid(AABB, 32)
    grid.update(0, sphere(0.5), warmup_steps=1, generator=gen)
    grid.update(16, sphere(0.5), warmup_steps=1, generator=gen)
    rays_o = torch.randn(500, 3, generator=gen) * 0.05 + torch.tensor([0.0, 0.0, -4.0])
    rays_d = torch.tensor([0.0, 0.0, 1.0]).expand(500, 3)
    s = ray_marching(rays_o, rays_d, 0.0, 10.0, grid, grid.step_size)
    midpoints = rays_o[s.ray_indices] + ((s.t_starts + s.t_ends) / 2)[:, None] * rays_d[s.ray_indices]
    assert (midpoints.norm(dim=-1) < 0.5 + 2 * 3 / 32 * math.sqrt(3)).all()
    counts = s.offsets.diff().float()
    assert counts.min() >= 0.7 / grid.step_size and counts.max() <= 1.6 / grid.step_size


@pytest.mark.parametrize(
    "kwargs,name",
    [
        ({"aabb": [1, 1, 1, -1, -1, -1]}, "aabb"),
        ({"aabb": [0, 0, 0, 1, 1, math.inf]}, "aabb"),
        ({"resolution": 0}, "resolution"),
        ({"resolution": (4, 4)}, "resolution"),
        ({"step_size": -1.0}, "step_size"),
    ],
)
def test_bad_arguments(kwargs, name):
    with pytest.raises(ValueError, match=name):
        OccupancyGrid(**{"aabb": AABB, **kwargs})


def test_bad_occupied_shape():
    with pytest.raises(ValueError, match="occupied"):
        OccupancyGrid(AABB, 4).occupied = torch.ones(4, 4, dtype=torch.bool)


@pytest.mark.cuda
@on_cuda
def test_cuda_update_and_march(gen):
    grid = OccupancyGrid(AABB, 64).cuda()
    cuda_gen = torch.Generator("cuda").manual_seed(0)
    grid.update(0, sphere(), warmup_steps=1, generator=cuda_gen, autocast_dtype=torch.bfloat16)
    grid.update(16, sphere(), warmup_steps=1, generator=cuda_gen)
    assert grid.bitfield.is_cuda and 0 < grid.occupied.float().mean() < 0.2
    rays_o, rays_d = torch.randn(1000, 3, device="cuda") * 3, torch.randn(1000, 3, device="cuda")
    got = ray_marching(rays_o, rays_d, 0.0, 10.0, grid, grid.step_size)
    want = ray_marching(rays_o.cpu(), rays_d.cpu(), 0.0, 10.0, grid.cpu(), grid.step_size)
    for x, y in zip(got, want, strict=True):
        assert torch.equal(x.cpu(), y)
