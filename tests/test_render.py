"""The renderer: samplers, intervals, analytic fields, backgrounds, chunking, determinism, backends."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from mixer_nerf.model import MixerNeRF, preset_config
from mixer_nerf.render import render_image, render_rays, sample_intervals, stratified_depths


class ConstantField(nn.Module):
    """Density ``sigma`` (a parameter) and colour ``rgb`` everywhere."""

    def __init__(self, sigma: float, rgb=(0.2, 0.4, 0.8)) -> None:
        super().__init__()
        self.sigma = nn.Parameter(torch.tensor(sigma, dtype=torch.float64))
        self.register_buffer("rgb", torch.tensor(rgb, dtype=torch.float64))

    def forward(self, x, d):
        sigma = self.sigma.to(x.dtype).expand(x.shape[:-1])
        return sigma, self.rgb.to(x.dtype).expand(*x.shape[:-1], 3)


class SphereField(nn.Module):
    """A dense ball of radius 1 at the origin whose colour shows the (unit) view direction."""

    def forward(self, x, d):
        sigma = torch.where(x.norm(dim=-1) < 1.0, 200.0, 0.0).to(x.dtype)
        return sigma, ((d + 1) / 2).expand_as(x)


class ConcatField(nn.Module):
    """A plain user MLP that concatenates x and d: needs d materialisable as (R, S, 3)."""

    def __init__(self) -> None:
        super().__init__()
        self.mlp = nn.Linear(6, 4)

    def forward(self, x, d):
        out = self.mlp(torch.cat([x, d], dim=-1))
        return F.softplus(out[..., 0]), torch.sigmoid(out[..., 1:])


def camera_rays_towards_origin(R: int, dtype=torch.float64, length: float = 1.0):
    """Rays from z = 4 looking down -z, spread over [-1.5, 1.5]^2, directions of norm ``length``."""
    xy = torch.rand(R, 2, dtype=dtype) * 3 - 1.5
    rays_o = torch.cat([xy, torch.full((R, 1), 4.0, dtype=dtype)], dim=-1)
    rays_d = torch.tensor([0.0, 0.0, -length], dtype=dtype).expand(R, 3).clone()
    return rays_o, rays_d


def small_field(preset: str = "D") -> MixerNeRF:
    cfg = preset_config(
        preset,
        depth=3,
        width=32,
        skips=(2,),
        view_width=16,
        pos_freqs=4,
        dir_freqs=2,
        se_reduction=4,
        backend="torch",
    )
    return MixerNeRF(cfg)


def random_unit_rays(R: int):
    return torch.randn(R, 3) * 0.3, F.normalize(torch.randn(R, 3), dim=-1)


# ---------------------------------------------------------------- sampler stage


def test_stratified_depths_one_per_bin_sorted_and_deterministic_centres():
    near, far = torch.full((5, 1), 2.0), torch.full((5, 1), 6.0)
    depths = stratified_depths(near, far, 8, stratified=True)
    bins = ((depths - 2.0) / 0.5).floor()
    assert torch.equal(bins, torch.arange(8.0).expand(5, 8))
    assert (depths[:, 1:] >= depths[:, :-1]).all()
    centres = stratified_depths(near, far, 8, stratified=False)
    torch.testing.assert_close(centres, (2.25 + 0.5 * torch.arange(8.0)).expand(5, 8))


def test_lindisp_is_uniform_in_disparity():
    near, far = torch.full((2, 1), 1.0, dtype=torch.float64), torch.full((2, 1), 100.0, dtype=torch.float64)
    depths = stratified_depths(near, far, 10, stratified=False, lindisp=True)
    steps = torch.diff(1 / depths, dim=-1)
    torch.testing.assert_close(steps, steps[:, :1].expand_as(steps))
    assert (depths > 1.0).all() and (depths < 100.0).all()


def test_midpoint_intervals_tile_near_to_far():
    depths = torch.sort(torch.rand(4, 6) * 4 + 2, dim=-1).values
    near, far = torch.full((4, 1), 2.0), torch.full((4, 1), 6.0)
    t_starts, t_ends = sample_intervals(depths, near, far)
    assert (t_starts[:, 0] == 2.0).all() and (t_ends[:, -1] == 6.0).all()
    assert torch.equal(t_ends[:, :-1], t_starts[:, 1:])
    assert ((t_starts <= depths) & (depths <= t_ends)).all()


def test_nerf_intervals_extend_the_last_one():
    depths = torch.tensor([[2.0, 3.0, 5.0]])
    t_starts, t_ends = sample_intervals(depths, torch.tensor([[1.0]]), torch.tensor([[6.0]]), last_delta=1e10)
    assert torch.equal(t_starts, depths)
    assert torch.equal(t_ends, torch.tensor([[3.0, 5.0, 5.0 + 1e10]]))


# ---------------------------------------------------------------- analytic fields


@pytest.mark.parametrize("stratified", [True, False])
@pytest.mark.parametrize("num_fine", [0, 16])
def test_constant_density_opacity_is_exact(stratified, num_fine):
    # Midpoint intervals tile [near, far] and the density is scaled by |d|, so the optical depth of
    # every ray is sigma * |d| * (far - near) whatever the samples are.
    sigma, length, near, far = 0.3, 2.5, 2.0, 5.0
    rays_o, rays_d = camera_rays_towards_origin(7, length=length)
    field = ConstantField(sigma)
    background = torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64)
    out = render_rays(
        field,
        rays_o,
        rays_d,
        near,
        far,
        num_coarse=8,
        num_fine=num_fine,
        stratified=stratified,
        background=background,
        backend="torch",
    )
    opacity = 1 - math.exp(-sigma * length * (far - near))
    for result in filter(None, out):
        torch.testing.assert_close(result.opacity, torch.full((7,), opacity, dtype=torch.float64))
        expected = field.rgb * opacity + background * (1 - opacity)
        torch.testing.assert_close(result.color, expected.expand(7, 3))


def test_nerf_last_delta_makes_the_last_sample_opaque():
    rays_o, rays_d = camera_rays_towards_origin(3)
    out = render_rays(
        ConstantField(1e-3),
        rays_o,
        rays_d,
        2.0,
        6.0,
        num_coarse=8,
        num_fine=8,
        stratified=False,
        background=torch.ones(3, dtype=torch.float64),
        backend="torch",
        last_delta=1e10,
    )
    torch.testing.assert_close(out.fine.opacity, torch.ones(3, dtype=torch.float64))
    # NeRF's depth: sum_i w_i t_i, within [near, far] (not dragged to 5e9 by the last interval).
    assert ((out.fine.depth >= 2.0) & (out.fine.depth <= 6.0)).all()


def test_sphere_depth_colour_and_misses():
    R = 64
    rays_o, rays_d = camera_rays_towards_origin(R, length=2.0)  # depth in units of |d| = 2
    background = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    out = render_rays(
        SphereField(),
        rays_o,
        rays_d,
        0.5,
        3.0,
        num_coarse=64,
        num_fine=64,
        stratified=False,
        background=background,
        backend="torch",
    )
    r2 = (rays_o[:, :2] ** 2).sum(-1)
    hit = r2 < 0.95**2
    miss = r2 > 1.05**2
    surface = (4.0 - torch.sqrt((1 - r2).clamp_min(0))) / 2.0
    fine = out.fine
    torch.testing.assert_close(fine.opacity[hit], torch.ones(int(hit.sum()), dtype=torch.float64))
    # The fine pass concentrates samples at the surface: depth within a small fraction of a coarse bin.
    assert ((fine.depth[hit] - surface[hit]).abs() < 2.5 / 64).all()
    # Colour shows the unit view direction (0, 0, -1) -> (0.5, 0.5, 0).
    torch.testing.assert_close(
        fine.color[hit], torch.tensor([0.5, 0.5, 0.0], dtype=torch.float64).expand(int(hit.sum()), 3)
    )
    assert (fine.opacity[miss] == 0).all()
    torch.testing.assert_close(fine.color[miss], background.expand(int(miss.sum()), 3))


def test_background_none_renders_on_black_and_per_ray_background():
    rays_o, rays_d = camera_rays_towards_origin(4)
    field = ConstantField(0.2)
    black = render_rays(field, rays_o, rays_d, 2.0, 6.0, num_coarse=8, num_fine=0, backend="torch").coarse
    torch.testing.assert_close(black.color, field.rgb * black.opacity[:, None])
    per_ray_bg = torch.rand(4, 3, dtype=torch.float64)
    out = render_rays(
        field, rays_o, rays_d, 2.0, 6.0, num_coarse=8, num_fine=0, background=per_ray_bg, backend="torch"
    ).coarse
    torch.testing.assert_close(out.color, black.color + (1 - black.opacity[:, None]) * per_ray_bg)
    empty = render_rays(
        ConstantField(0.0),
        rays_o,
        rays_d,
        2.0,
        6.0,
        num_coarse=8,
        num_fine=8,
        background=per_ray_bg,
        backend="torch",
    )
    assert torch.equal(empty.fine.color, per_ray_bg)


def test_per_ray_near_far():
    rays_o, rays_d = camera_rays_towards_origin(3)
    near = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    far = near + torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64)
    out = render_rays(
        ConstantField(0.5), rays_o, rays_d, near, far, num_coarse=8, num_fine=8, backend="torch"
    )
    torch.testing.assert_close(out.fine.opacity, 1 - torch.exp(-0.5 * (far - near)))


# ---------------------------------------------------------------- fields and passes


def test_field_sees_positions_and_unit_directions():
    seen = {}

    class Recorder(nn.Module):
        def forward(self, x, d):
            seen["x"], seen["d"] = x, d
            return x.new_zeros(x.shape[:-1]), x.new_zeros(x.shape)

    rays_o, rays_d = camera_rays_towards_origin(2, length=3.0)
    render_rays(
        Recorder(), rays_o, rays_d, 1.0, 2.0, num_coarse=4, num_fine=0, stratified=False, backend="torch"
    )
    assert seen["x"].shape == seen["d"].shape == (2, 4, 3)
    torch.testing.assert_close(seen["d"].norm(dim=-1), torch.ones(2, 4, dtype=torch.float64))
    depths = 1.0 + (torch.arange(4, dtype=torch.float64) + 0.5) / 4
    torch.testing.assert_close(seen["x"], rays_o[:, None] + depths[None, :, None] * rays_d[:, None])


def test_plain_user_field_and_fine_field():
    rays_o, rays_d = random_unit_rays(5)
    coarse_field, fine_field = ConcatField(), ConcatField()
    out = render_rays(
        coarse_field,
        rays_o,
        rays_d,
        0.5,
        2.0,
        num_coarse=8,
        num_fine=8,
        fine_field=fine_field,
        backend="torch",
    )
    out.fine.color.sum().backward()
    assert coarse_field.mlp.weight.grad is None, "fine samples are drawn without gradient"
    assert fine_field.mlp.weight.grad.abs().sum() > 0
    out = render_rays(coarse_field, rays_o, rays_d, 0.5, 2.0, num_coarse=8, num_fine=8, backend="torch")
    (out.coarse.color.sum() + out.fine.color.sum()).backward()
    assert coarse_field.mlp.weight.grad.abs().sum() > 0


def test_num_fine_zero_and_final():
    rays_o, rays_d = random_unit_rays(3)
    out = render_rays(ConstantField(0.1), rays_o, rays_d, 0.0, 1.0, num_coarse=4, num_fine=0, backend="torch")
    assert out.fine is None and out.final is out.coarse and out.coarse.weights.shape == (3, 4)
    out = render_rays(ConstantField(0.1), rays_o, rays_d, 0.0, 1.0, num_coarse=4, num_fine=5, backend="torch")
    assert out.final is out.fine and out.fine.weights.shape == (3, 9)


@pytest.mark.parametrize("R, num_coarse, num_fine", [(1, 3, 1), (0, 8, 8), (2, 1, 0)])
def test_small_and_empty_batches(R, num_coarse, num_fine):
    rays_o, rays_d = random_unit_rays(R)
    out = render_rays(
        small_field(),
        rays_o,
        rays_d,
        0.5,
        2.0,
        num_coarse=num_coarse,
        num_fine=num_fine,
        background=torch.ones(3),
        backend="torch",
    )
    assert out.final.color.shape == (R, 3) and out.final.weights.shape == (R, num_coarse + num_fine)
    assert torch.isfinite(out.final.color).all()


def test_model_renders_and_trains():
    field = small_field("D")
    rays_o, rays_d = random_unit_rays(16)
    optimizer = torch.optim.Adam(field.parameters(), lr=1e-3)
    out = render_rays(
        field, rays_o, rays_d, 0.5, 2.0, num_coarse=8, num_fine=8, background=torch.ones(3), backend="torch"
    )
    loss = F.mse_loss(out.coarse.color, torch.zeros(16, 3)) + F.mse_loss(out.fine.color, torch.zeros(16, 3))
    assert torch.isfinite(loss)
    loss.backward()
    optimizer.step()
    assert all(torch.isfinite(p).all() for p in field.parameters())


# ---------------------------------------------------------------- determinism, chunking, backends


def test_deterministic_sampling_is_reproducible_and_generators_seed_jitter():
    field = small_field("D")
    rays_o, rays_d = random_unit_rays(6)
    kw = dict(num_coarse=8, num_fine=8, backend="torch")
    a = render_rays(field, rays_o, rays_d, 0.5, 2.0, stratified=False, **kw)
    b = render_rays(field, rays_o, rays_d, 0.5, 2.0, stratified=False, **kw)
    assert all(torch.equal(x, y) for x, y in zip(a.fine, b.fine, strict=True))

    def run(seed: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(seed)
        return render_rays(field, rays_o, rays_d, 0.5, 2.0, generator=generator, **kw).fine.color

    assert torch.equal(run(1), run(1))
    assert not torch.equal(run(1), run(2))


def test_chunked_render_image_equals_unchunked_and_render_rays():
    field = small_field("D")
    H, W = 3, 5
    rays_o, rays_d = random_unit_rays(H * W)
    near = torch.rand(H, W) * 0.2 + 0.4
    background = torch.rand(H, W, 3)
    kw = dict(num_coarse=8, num_fine=8, backend="torch")
    whole = render_image(
        field,
        rays_o.reshape(H, W, 3),
        rays_d.reshape(H, W, 3),
        near,
        2.0,
        chunk=1000,
        background=background,
        **kw,
    )
    chunked = render_image(
        field,
        rays_o.reshape(H, W, 3),
        rays_d.reshape(H, W, 3),
        near,
        2.0,
        chunk=4,
        background=background,
        **kw,
    )
    assert whole.color.shape == (H, W, 3) and whole.depth.shape == whole.opacity.shape == (H, W)
    for a, b in zip(whole, chunked, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6)
    direct = render_rays(
        field,
        rays_o,
        rays_d,
        near.reshape(-1),
        2.0,
        stratified=False,
        background=background.reshape(-1, 3),
        **kw,
    ).fine
    torch.testing.assert_close(chunked.color.reshape(-1, 3), direct.color, rtol=1e-6, atol=1e-6)
    assert not chunked.color.requires_grad


def test_render_image_shared_background_and_coarse_only():
    field = ConstantField(0.4)
    rays_o, rays_d = camera_rays_towards_origin(10)
    image = render_image(
        field,
        rays_o,
        rays_d,
        2.0,
        6.0,
        chunk=3,
        num_coarse=4,
        num_fine=0,
        background=torch.ones(3, dtype=torch.float64),
        backend="torch",
    )
    opacity = 1 - math.exp(-0.4 * 4.0)
    torch.testing.assert_close(image.opacity, torch.full((10,), opacity, dtype=torch.float64))


def _kernels_or_skip() -> None:
    from mixer_nerf import _extension

    if not _extension.available():
        pytest.skip("compiled kernels unavailable")
    for op in ("composite_fwd", "hierarchical_samples_fwd"):
        if not torch._C._dispatch_has_kernel_for_dispatch_key(f"mixer_nerf::{op}", "CPU"):
            pytest.skip(f"no CPU kernel for {op} yet")


@pytest.mark.parametrize("stratified", [False, True])
def test_kernel_and_torch_backends_render_the_same_image(stratified):
    _kernels_or_skip()
    field = small_field("D")
    rays_o, rays_d = random_unit_rays(32)
    kw = dict(num_coarse=16, num_fine=16, stratified=stratified, background=torch.ones(3))
    seed = torch.seed()
    kernel = render_rays(
        field, rays_o, rays_d, 0.5, 2.0, backend="kernel", generator=torch.Generator().manual_seed(seed), **kw
    )
    torch_ = render_rays(
        field, rays_o, rays_d, 0.5, 2.0, backend="torch", generator=torch.Generator().manual_seed(seed), **kw
    )
    # Same samples (both draw their jitter from the same generator stream) and the same
    # maths; float32 accumulations in another order differ by a few ulps, and a fine sample moved
    # by an ulp moves the colour by about as much: 1e-5 is ~100 ulps at colours <= 1.
    for a, b in zip(kernel.coarse, torch_.coarse, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    for a, b in zip(kernel.fine, torch_.fine, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


# ---------------------------------------------------------------- bad input


def _call(**overrides):
    rays_o, rays_d = random_unit_rays(4)
    kw = dict(field=ConstantField(0.1), rays_o=rays_o, rays_d=rays_d, near=0.5, far=2.0, backend="torch")
    kw.update(overrides)
    return render_rays(**kw)


@pytest.mark.parametrize(
    "overrides, error, match",
    [
        ({"rays_o": torch.zeros(4, 2)}, ValueError, "rays_o"),
        ({"rays_d": torch.zeros(3, 3)}, ValueError, "rays_d"),
        ({"rays_o": torch.zeros(4, 3, dtype=torch.int64)}, TypeError, "rays_o"),
        ({"rays_d": torch.zeros(4, 3, dtype=torch.float64)}, TypeError, "rays_d"),
        ({"near": 3.0}, ValueError, "near"),
        ({"near": "0"}, TypeError, "near"),
        ({"far": torch.ones(5)}, ValueError, "far"),
        ({"far": torch.ones(4, dtype=torch.int64)}, TypeError, "far"),
        ({"num_coarse": 2}, ValueError, "num_coarse"),
        ({"num_coarse": 0, "num_fine": 0}, ValueError, "num_coarse"),
        ({"num_fine": -1}, ValueError, "num_fine"),
        ({"num_fine": 2.0}, TypeError, "num_fine"),
        ({"background": torch.ones(4)}, ValueError, "background"),
        ({"background": torch.ones(3, dtype=torch.int64)}, TypeError, "background"),
        ({"backend": "cuda"}, ValueError, "backend"),
        ({"lindisp": True, "near": 0.0}, ValueError, "lindisp"),
    ],
)
def test_bad_inputs_name_the_argument(overrides, error, match):
    with pytest.raises(error, match=match):
        _call(**overrides)


def test_render_image_bad_chunk_and_shapes():
    rays_o, rays_d = random_unit_rays(4)
    with pytest.raises(ValueError, match="chunk"):
        render_image(ConstantField(0.1), rays_o, rays_d, 0.5, 2.0, chunk=0)
    with pytest.raises(ValueError, match="rays_d"):
        render_image(ConstantField(0.1), rays_o, rays_d[:3], 0.5, 2.0)
    with pytest.raises(ValueError, match="near"):
        render_image(ConstantField(0.1), rays_o, rays_d, torch.ones(3), 2.0)
