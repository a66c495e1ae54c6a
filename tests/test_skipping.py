"""Tests of the skipping path's pieces: marching options, the sample budget, the occupancy sampler
and the chunked image renderer."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from mixer_nerf.ops.bitfield import pack_bits
from mixer_nerf.render import ChunkResult, ImageRenderer, render_in_chunks
from mixer_nerf.render.skipping import (
    GridRefresh,
    MarchingOptions,
    OccupancyGrid,
    OccupancySampler,
    SampleBudget,
    march_samples,
)


class Ball(nn.Module):
    def density(self, x):
        return 50.0 * (x.norm(dim=-1) < 0.5).float()

    def forward(self, x, d):
        return self.density(x), torch.full_like(x, 0.5)


@pytest.mark.parametrize("kwargs", [{"step_size": 0.0}, {"early_stop_eps": 1.0}, {"alpha_threshold": -0.1},
                                    {"cone_angle": -1.0}, {"step_size": float("nan")}])
def test_marching_options_reject_bad_values(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        MarchingOptions(**kwargs)


def test_marching_options_filter_only_when_a_threshold_is_set():
    assert MarchingOptions().filters
    assert not MarchingOptions(early_stop_eps=0.0).filters
    assert MarchingOptions(early_stop_eps=0.0, alpha_threshold=1e-3).filters


def test_sample_budget_sizes_batches_to_the_target():
    budget = SampleBudget(target=1000, max_rays=500)
    assert budget.first_rays(4096) == 1000 // 256 and budget.first_rays(2) == 2
    assert budget.next_rays(100, 10_000) == 10  # 100 samples a ray: 10 rays make 1000
    assert budget.next_rays(100, 0) == 500  # no samples at all: the largest batch
    assert budget.next_rays(1, 10**9) == 1  # never below one ray
    with pytest.raises(ValueError, match="target"):
        SampleBudget(target=0)


def test_occupancy_sampler_refreshes_on_its_schedule_and_sizes_the_next_batch():
    gen = torch.Generator().manual_seed(0)
    grid = OccupancyGrid([-1, -1, -1, 1, 1, 1], 16)
    sampler = OccupancySampler(grid, MarchingOptions(early_stop_eps=0.0), GridRefresh(every=4, warmup=0),
                               SampleBudget(target=512))
    assert not sampler.update(3, Ball(), gen) and grid.occupied.all()
    assert sampler.update(4, Ball(), gen) and not grid.occupied.all()
    assert sampler.is_refresh_step(8) and not sampler.is_refresh_step(9)
    rays_o = torch.tensor([[0.0, 0.0, -3.0]]).repeat(8, 1)
    rays_d = torch.tensor([[0.0, 0.0, 1.0]]).repeat(8, 1)
    marched = sampler.sample(rays_o, rays_d, 0.0, 10.0, stratified=False, density_field=None)
    direct = march_samples(rays_o, rays_d, grid, 0.0, 10.0, MarchingOptions(early_stop_eps=0.0), stratified=False)
    assert torch.equal(marched.samples.t_starts, direct.samples.t_starts)
    n = marched.samples.t_starts.shape[0]
    assert 0 < n < 8 * 2 * 3 ** 0.5 / grid.step_size  # the ball's cells only
    assert sampler.next_batch_rays(8, marched) == SampleBudget(target=512).next_rays(8, n)
    assert OccupancySampler(grid).next_batch_rays(8, marched) is None


@pytest.mark.parametrize("occupied", [0, 1, 37, 4096])
def test_a_refresh_measures_a_random_quarter_and_as_many_occupied_cells(occupied):
    """After the warm-up a refresh picks a fixed count of cells (no host sync: a CUDA graph can
    capture it): a random quarter, then as many drawn among the occupied cells, every one of them
    occupied (random cells too when none is), and the occupied ones evenly."""
    grid = OccupancyGrid([-1, -1, -1, 1, 1, 1], 16)
    gen = torch.Generator().manual_seed(occupied)
    chosen = torch.randperm(grid.num_cells, generator=gen)[:occupied]
    grid.bitfield.copy_(pack_bits(torch.zeros(grid.num_cells, dtype=torch.bool).index_fill_(0, chosen, True)))
    cells = grid._cells_to_update(False, gen, None)
    quarter = grid.num_cells // 4
    assert cells.shape == (2 * quarter,) and 0 <= cells.min() and cells.max() < grid.num_cells
    drawn = cells[quarter:]
    if occupied:
        assert torch.isin(drawn, chosen).all()
        counts = torch.bincount(drawn, minlength=grid.num_cells)[chosen].float()
        assert counts.min() > 0 if occupied <= 37 else counts.std() < 3 * counts.mean().sqrt()
    else:
        assert torch.equal(drawn, cells[:quarter])  # the random quarter again


def test_render_in_chunks_matches_one_chunk_and_counts_samples():
    calls = []

    def render_chunk(o, d, scale):
        calls.append(o.shape[0])
        color = o * scale[:, None]
        return ChunkResult(color, o[:, 0], d[:, 0], 2 * o.shape[0], 3 * o.shape[0])

    o, d, scale = torch.randn(10, 3), torch.randn(10, 3), torch.rand(10)
    result, shaded, marched = render_in_chunks(render_chunk, o, d, 4, {"scale": scale})
    assert calls == [4, 4, 2] and (shaded, marched) == (20, 30)
    torch.testing.assert_close(result.color, o * scale[:, None])
    torch.testing.assert_close(result.depth, o[:, 0])


def test_image_renderer_renders_in_eval_mode_and_restores_training():
    module = nn.Linear(1, 1)
    modes = []

    def render_chunk(o, d):
        modes.append(module.training)
        return ChunkResult(o, o[:, 0], o[:, 0], 0, 0)

    renderer = ImageRenderer(render_chunk, module, torch.device("cpu"), chunk=3)
    out = renderer(torch.ones(5, 3, dtype=torch.float64), torch.ones(5, 3, dtype=torch.float64))
    assert modes == [False, False] and module.training and out.color.dtype == torch.float32
    with pytest.raises(ValueError, match="chunk"):
        ImageRenderer(render_chunk, module, torch.device("cpu"), chunk=0)
