"""The skipping renderer: occupancy-grid marching, early termination, packed compositing."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from mixer_nerf.model import MixerNeRF, preset_config
from mixer_nerf.render.skipping import MarchingOptions, OccupancyGrid, render_rays_marched


class BallField(nn.Module):
    """A ball of radius 0.5 at the origin with density ``sigma`` and a position-dependent colour."""

    def __init__(self, sigma: float) -> None:
        super().__init__()
        self.sigma = nn.Parameter(torch.tensor(sigma))

    def forward(self, x, d):
        inside = (x.norm(dim=-1) < 0.5).to(x.dtype)
        return self.sigma.to(x.dtype) * inside, torch.sigmoid(x + d)


def rays_towards_ball(R: int, spread: float = 1.4):
    xy = (torch.rand(R, 2) * 2 - 1) * spread
    rays_o = torch.cat([xy, torch.full((R, 1), 4.0)], dim=-1)
    return rays_o, torch.tensor([0.0, 0.0, -1.0]).expand(R, 3).clone()


def ball_grid(resolution: int = 32) -> OccupancyGrid:
    grid = OccupancyGrid([-1.5, -1.5, -1.5, 1.5, 1.5, 1.5], resolution, step_size=3 / 256)
    centres = grid.aabb[0] + (torch.stack(torch.meshgrid(*[torch.arange(resolution)] * 3, indexing="ij"), -1)
                              + 0.5) * (3 / resolution)
    grid.occupied = centres.norm(dim=-1) < 0.5 + 3 / resolution
    return grid


KEEP_ALL = MarchingOptions(early_stop_eps=0.0)
EARLY_STOP = MarchingOptions(early_stop_eps=1e-4)


def full_grid(resolution: int = 8) -> OccupancyGrid:
    return OccupancyGrid([-1.5, -1.5, -1.5, 1.5, 1.5, 1.5], resolution, step_size=3 / 256)


def test_empty_space_skip_keeps_the_image_and_drops_samples():
    rays_o, rays_d = rays_towards_ball(256)
    field, background = BallField(3.0), torch.tensor([1.0, 1.0, 1.0])
    dense = render_rays_marched(field, rays_o, rays_d, full_grid(), stratified=False, background=background,
                                options=KEEP_ALL, backend="torch")
    skipped = render_rays_marched(field, rays_o, rays_d, ball_grid(), stratified=False, background=background,
                                  options=KEEP_ALL, backend="torch")
    assert skipped.samples.t_starts.numel() < dense.samples.t_starts.numel() / 4
    torch.testing.assert_close(skipped.color, dense.color, atol=1e-5, rtol=0)
    torch.testing.assert_close(skipped.opacity, dense.opacity, atol=1e-5, rtol=0)


def test_rays_that_miss_the_box_cost_nothing_but_background():
    rays_o = torch.tensor([[5.0, 5.0, 4.0], [0.0, 0.0, 4.0]])
    rays_d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])  # beside the box; pointing away
    background = torch.tensor([0.1, 0.2, 0.3])
    out = render_rays_marched(BallField(3.0), rays_o, rays_d, full_grid(), background=background, backend="torch")
    assert out.samples.t_starts.numel() == 0
    torch.testing.assert_close(out.color, background.expand(2, 3))
    assert out.opacity.abs().max() == 0


def test_early_termination_changes_the_image_by_at_most_its_threshold():
    rays_o, rays_d = rays_towards_ball(256, spread=0.3)  # every ray hits the opaque ball
    field = BallField(200.0)
    kept = render_rays_marched(field, rays_o, rays_d, ball_grid(), stratified=False, options=KEEP_ALL,
                               backend="torch")
    stopped = render_rays_marched(field, rays_o, rays_d, ball_grid(), stratified=False, options=EARLY_STOP,
                                  backend="torch")
    assert stopped.samples.t_starts.numel() < kept.samples.t_starts.numel() / 2
    # What is dropped lies behind transmittance < 1e-4: at most that much light per channel.
    assert (stopped.color - kept.color).abs().max() <= 1e-4


def test_gradients_reach_the_field_and_packed_model_gets_ray_indices():
    torch.manual_seed(0)
    cfg = preset_config("D", depth=3, width=32, skips=(2,), view_width=16, pos_freqs=4, dir_freqs=2,
                        se_reduction=4, backend="torch")
    field = MixerNeRF(cfg)
    rays_o, rays_d = rays_towards_ball(64)
    out = render_rays_marched(field, rays_o, rays_d, ball_grid(16), background=torch.ones(3), backend="torch")
    out.color.sum().backward()
    grads = [p.grad for p in field.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


class RecordingBall(BallField):
    """An opaque ball that records the packed layout each call of it gets."""

    packed_layout = ("ray_indices", "offsets")

    def __init__(self) -> None:
        super().__init__(200.0)
        self.calls = []

    def forward(self, x, d, ray_indices=None, num_rays=None, offsets=None):
        self.calls.append((x.shape[0], ray_indices, num_rays, offsets))
        return super().forward(x, d)

    def density(self, x, ray_indices=None, num_rays=None, offsets=None):
        self.calls.append((x.shape[0], ray_indices, num_rays, offsets))
        return super().forward(x, torch.zeros_like(x))[0]


def test_packed_field_gets_the_layout_of_exactly_the_samples_it_evaluates():
    """The pre-pass sees every marched sample, the second pass the survivors of early termination:
    each with its own offsets (recomputed by select), consistent with its ray_indices."""
    rays_o, rays_d = rays_towards_ball(64, spread=0.6)
    field = RecordingBall()
    render_rays_marched(field, rays_o, rays_d, ball_grid(), stratified=False, options=EARLY_STOP,
                        backend="torch")
    assert len(field.calls) == 2 and field.calls[1][0] < field.calls[0][0]
    for rows, ray_indices, num_rays, offsets in field.calls:
        assert num_rays == 64 and offsets.shape == (65,) and offsets[0] == 0 and offsets[-1] == rows
        torch.testing.assert_close(torch.repeat_interleave(torch.arange(64), offsets.diff()), ray_indices)


def test_density_field_runs_the_pre_pass_and_the_field_the_rest():
    rays_o, rays_d = rays_towards_ball(64, spread=0.6)
    field, pre = RecordingBall(), RecordingBall()
    out = render_rays_marched(field, rays_o, rays_d, ball_grid(), stratified=False, options=EARLY_STOP,
                              backend="torch", density_field=pre)
    alone = render_rays_marched(RecordingBall(), rays_o, rays_d, ball_grid(), stratified=False,
                                options=EARLY_STOP, backend="torch")
    assert len(pre.calls) == 1 and len(field.calls) == 1 and field.calls[0][0] < pre.calls[0][0]
    assert out.num_marched == pre.calls[0][0] and out.samples.t_starts.numel() == field.calls[0][0]
    torch.testing.assert_close(out.color, alone.color, atol=0, rtol=0)


class IndicesOnly(nn.Module):
    """A field that declares only ray_indices: the renderer passes it no offsets."""

    packed_layout = ("ray_indices",)

    def __init__(self, field: nn.Module) -> None:
        super().__init__()
        self.field = field

    def forward(self, x, d, ray_indices=None, num_rays=None):
        return self.field(x, d, ray_indices=ray_indices, num_rays=num_rays)

    def density(self, x, ray_indices=None, num_rays=None):
        return self.field.density(x, ray_indices=ray_indices, num_rays=num_rays)


@pytest.mark.parametrize("backend", ["torch", "auto"])
@pytest.mark.parametrize("preset", ["B", "D"])
def test_model_renders_the_same_through_offsets_and_ray_indices(backend, preset):
    """MixerNeRF's SE takes the fused ops given offsets, index_add and a gather given ray_indices;
    its view branch runs once per ray on ray_directions, or per sample on d."""
    torch.manual_seed(0)
    cfg = preset_config(preset, depth=3, width=32, skips=(2,), view_width=16, pos_freqs=4, dir_freqs=2,
                        se_reduction=4, backend=backend)
    field = MixerNeRF(cfg)
    rays_o, rays_d = rays_towards_ball(64)
    images = []
    for f in (field, IndicesOnly(field)):
        out = render_rays_marched(f, rays_o, rays_d, ball_grid(16), stratified=False,
                                  background=torch.ones(3), backend=backend)
        grads = torch.autograd.grad(out.color.sum(), [field.se.reduce.weight, field.view_direction.weight])
        images.append((out.color, *grads))
    torch.testing.assert_close(images[0], images[1], rtol=1e-5, atol=1e-6)


@pytest.mark.skipif(not __import__("mixer_nerf._extension", fromlist=["x"]).available(), reason="no kernels")
def test_kernel_and_torch_backends_render_the_same_image():
    rays_o, rays_d = rays_towards_ball(300)
    field = BallField(5.0)
    images = [render_rays_marched(field, rays_o, rays_d, ball_grid(), stratified=False, background=torch.ones(3),
                                  backend=backend).color for backend in ("kernel", "torch")]
    torch.testing.assert_close(images[0], images[1], atol=1e-5, rtol=0)


def test_constant_density_in_a_full_grid_matches_beer_lambert():
    sigma = 0.7
    rays_o = torch.tensor([[0.0, 0.0, 4.0]])
    rays_d = torch.tensor([[0.0, 0.0, -1.0]])

    class Constant(nn.Module):
        def forward(self, x, d):
            return torch.full(x.shape[:-1], sigma), torch.full_like(x, 0.5)

    out = render_rays_marched(Constant(), rays_o, rays_d, full_grid(), stratified=False, options=KEEP_ALL,
                              backend="torch")
    # The ray crosses the 3-unit box: opacity 1 - exp(-sigma * 3), exactly (samples tile the chord).
    assert out.opacity.item() == pytest.approx(1 - math.exp(-sigma * 3), rel=1e-5)
