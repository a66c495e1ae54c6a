"""Mixer-NeRF model: MLCA, SE (per-ray, per-point, packed), the field, presets, config."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode

from mixer_nerf import _extension
from mixer_nerf.model import MLCA, MixerNeRF, ModelConfig, SqueezeExcitation, mean_over_ray_indices, preset_config
from dispatch_count import dispatched_ops

# Small networks keep the file fast; the structure (skips, SE, MLCA, heads) is the full one.
SMALL = dict(
    depth=4, width=32, skips=(2,), view_width=16, pos_freqs=4, dir_freqs=2, se_reduction=4, backend="torch"
)


def small_model(preset: str = "D", **overrides) -> MixerNeRF:
    return MixerNeRF(preset_config(preset, **{**SMALL, **overrides}))


def random_rays(R: int, S: int, dtype=torch.float32):
    x = torch.rand(R, S, 3, dtype=dtype) * 3 - 1.5
    d = F.normalize(torch.randn(R, 1, 3, dtype=dtype), dim=-1)
    return x, d


def randomize_(module: torch.nn.Module) -> torch.nn.Module:
    """Non-zero values everywhere (MLCA's mixing weights start at zero: a test at init would not
    exercise them)."""
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn_like(p) * 0.3)
    return module


# ---------------------------------------------------------------- MLCA


def test_mlca_shapes_and_identity_at_init():
    mlca = MLCA(num_tokens=5, token_dim=3, channels=8)
    x = torch.randn(4, 7, 15)
    out = mlca(x)
    assert out.shape == (4, 7, 40) and mlca.out_features == 40
    # Starts as the lift [I; 0] of every token: coordinates copied, extra channels zero.
    tokens = out.reshape(4, 7, 5, 8)
    torch.testing.assert_close(tokens[..., :3], x.reshape(4, 7, 5, 3), rtol=0, atol=0)
    assert (tokens[..., 3:] == 0).all()


def test_mlca_gradient_reaches_zero_initialised_mixing_weights():
    mlca = MLCA(num_tokens=5, token_dim=3, channels=4)
    mlca(torch.randn(16, 15)).pow(2).sum().backward()
    for name in ("token_weight", "token_bias", "channel_weight", "channel_bias", "lift"):
        assert getattr(mlca, name).grad.abs().sum() > 0, name


def test_mlca_matches_explicit_token_and_channel_mixing():
    mlca = randomize_(MLCA(num_tokens=5, token_dim=3, channels=4))
    x = torch.randn(6, 15)
    tokens = x.reshape(6, 5, 3) @ mlca.lift.T  # (N, T, C)
    tokens = tokens + F.gelu(
        torch.einsum("ts,nsc->ntc", mlca.token_weight, tokens) + mlca.token_bias[:, None]
    )
    tokens = tokens + F.gelu(tokens @ mlca.channel_weight.T + mlca.channel_bias)
    torch.testing.assert_close(mlca(x), tokens.reshape(6, 20), rtol=1e-5, atol=1e-5)


def test_mlca_gradcheck():
    mlca = randomize_(MLCA(num_tokens=3, token_dim=3, channels=4)).double()
    x = torch.randn(2, 9, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(mlca, (x,))
    params = list(mlca.parameters())
    assert torch.autograd.gradcheck(
        lambda *p: torch.func.functional_call(
            mlca, dict(zip(dict(mlca.named_parameters()), p, strict=True)), (x,)
        ),
        params,
    )


def test_mlca_rejects_wrong_width_and_too_few_channels():
    with pytest.raises(ValueError, match="encoded"):
        MLCA(5, 3, 8)(torch.randn(2, 14))
    with pytest.raises(ValueError, match="channels"):
        MLCA(5, 3, 2)


# ---------------------------------------------------------------- SE


def test_se_per_ray_gates_every_sample_of_a_ray_alike():
    se = randomize_(SqueezeExcitation(16, reduction=4))
    features = torch.rand(5, 7, 16) + 0.1
    gate = se(features) / features
    torch.testing.assert_close(gate, gate[:, :1].expand_as(gate))
    torch.testing.assert_close(gate[:, 0], se.gate(features.mean(dim=1)))


def test_se_per_point_gates_each_sample_by_itself():
    se = randomize_(SqueezeExcitation(16, reduction=4, per_point=True))
    features = torch.rand(5, 7, 16) + 0.1
    torch.testing.assert_close(se(features), se.gate(features) * features)
    gate = se(features) / features
    assert not torch.allclose(gate, gate[:, :1].expand_as(gate))


@pytest.mark.parametrize("backend", ["torch", "kernel"])
def test_se_that_gates_colour_only_leaves_each_point_its_own_density(backend):
    """se_gates_density=False: the density a ray's sample gets does not depend on the ray's other
    samples and equals what the grid and the pre-pass see (density(x) with no layout); the colour
    still takes the ray's gate. The default gates both (the density moves with the others)."""
    R, S = 4, 6
    x, d = random_rays(R, S)
    x, d = x.reshape(-1, 3), d.expand(R, S, 3).reshape(-1, 3)
    offsets = torch.arange(0, R * S + 1, S)
    moved = x.clone()
    moved[1::S] += 0.4  # every ray's second sample elsewhere: its other samples keep their places
    others = torch.ones(R * S, dtype=torch.bool)
    others[1::S] = False
    for gates_density in (False, True):
        torch.manual_seed(0)
        model = randomize_(small_model("D", se_gates_density=gates_density, backend=backend))
        with torch.no_grad():
            sigma, rgb = model(x, d, offsets=offsets)
            sigma_moved, rgb_moved = model(moved, d, offsets=offsets)
            alone = model.density(x)
        assert not torch.allclose(rgb[others], rgb_moved[others])  # the colour sees the whole ray
        if gates_density:
            assert not torch.allclose(sigma[others], sigma_moved[others])
        else:
            torch.testing.assert_close(sigma[others], sigma_moved[others], rtol=0, atol=0)
            torch.testing.assert_close(sigma, alone)
            torch.testing.assert_close(model.density(x, offsets=offsets), alone)


def test_mean_over_ray_indices_equals_dense_mean_for_full_rays_in_any_order():
    R, S, C = 6, 5, 8
    dense = torch.randn(R, S, C)
    order = torch.randperm(R * S)
    packed, ray_indices = dense.reshape(-1, C)[order], torch.arange(R).repeat_interleave(S)[order]
    torch.testing.assert_close(mean_over_ray_indices(packed, ray_indices, R), dense.mean(dim=1))


def test_mean_over_ray_indices_handles_ragged_and_empty_rays():
    values = torch.tensor([[1.0], [3.0], [5.0]])
    ray_indices = torch.tensor([0, 0, 2])
    torch.testing.assert_close(
        mean_over_ray_indices(values, ray_indices, 4), torch.tensor([[2.0], [0.0], [5.0], [0.0]])
    )


def test_se_packed_equals_dense_for_full_rays():
    se = randomize_(SqueezeExcitation(16, reduction=4))
    R, S = 4, 6
    dense = torch.randn(R, S, 16)
    ray_indices = torch.arange(R).repeat_interleave(S)
    packed = se(dense.reshape(-1, 16), ray_indices, num_rays=R)
    torch.testing.assert_close(packed, se(dense).reshape(-1, 16))
    torch.testing.assert_close(se(dense.reshape(-1, 16), ray_indices), packed)  # num_rays inferred


def test_se_dense_squeeze_dispatches_no_reshapes():
    """The gate runs on the squeezed (R, C), so its linears need no views of an (R, 1, C)."""
    se = randomize_(SqueezeExcitation(16, reduction=4))
    with dispatched_ops() as ops:
        se(torch.randn(4, 6, 16))
    assert ops["aten.addmm"] == 2 and not ops["aten.view"] and not ops["aten._to_copy"], ops


def test_se_gradcheck_dense_and_packed():
    se = randomize_(SqueezeExcitation(8, reduction=2)).double()
    dense = torch.randn(3, 4, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(se, (dense,))
    packed = torch.randn(7, 8, dtype=torch.float64, requires_grad=True)
    ray_indices = torch.tensor([0, 0, 1, 2, 2, 2, 0])
    assert torch.autograd.gradcheck(lambda f: se(f, ray_indices, 3), (packed,))


SE_BACKENDS = ["torch"] + (["kernel"] if _extension.available() else [])


def ragged_layout(counts):
    """ray_indices (N,) and CSR offsets (R+1,) of rays with ``counts`` samples each, in ray order."""
    counts = torch.tensor(counts)
    return torch.arange(counts.numel()).repeat_interleave(counts), F.pad(counts.cumsum(0), (1, 0))


@pytest.mark.parametrize("backend", SE_BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_se_offsets_equals_ray_indices(backend, dtype):
    """The fused ops (offsets) and index_add + gather (ray_indices): same outputs and gradients,
    on rays of 0, 1 and many samples."""
    se = randomize_(SqueezeExcitation(16, reduction=4, backend=backend)).to(dtype)
    ray_indices, offsets = ragged_layout([3, 0, 1, 40, 0, 7])
    features = torch.randn(ray_indices.numel(), 16, dtype=dtype, requires_grad=True)
    upstream = torch.randn_like(features)
    results = []
    for kwargs in ({"offsets": offsets}, {"ray_indices": ray_indices, "num_rays": 6}):
        out = se(features, **kwargs)
        results.append((out, *torch.autograd.grad(out, (features, *se.parameters()), upstream)))
    torch.testing.assert_close(results[0], results[1])


@pytest.mark.parametrize("backend", SE_BACKENDS)
def test_se_offsets_equals_dense_for_full_rays(backend):
    se = randomize_(SqueezeExcitation(16, reduction=4, backend=backend))
    R, S = 4, 6
    dense = torch.randn(R, S, 16)
    _, offsets = ragged_layout([S] * R)
    torch.testing.assert_close(se(dense.reshape(-1, 16), offsets=offsets), se(dense).reshape(-1, 16))


@pytest.mark.parametrize("backend", SE_BACKENDS)
def test_se_offsets_under_bf16_autocast(backend):
    """Under autocast the trunk features are bfloat16: the fused path keeps them so, like the
    ray_indices path, and agrees with it."""
    se = randomize_(SqueezeExcitation(16, reduction=4, backend=backend))
    ray_indices, offsets = ragged_layout([5, 0, 9, 2])
    features = torch.randn(ray_indices.numel(), 16).bfloat16().requires_grad_()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        fused = se(features, offsets=offsets)
        indexed = se(features, ray_indices, 4)
    assert fused.dtype == indexed.dtype == torch.bfloat16
    torch.testing.assert_close(fused, indexed, rtol=2e-2, atol=1e-2)
    fused.float().sum().backward()
    assert torch.isfinite(features.grad).all() and features.grad.dtype == torch.bfloat16


def test_se_gradcheck_offsets():
    se = randomize_(SqueezeExcitation(8, reduction=2, backend=SE_BACKENDS[-1])).double()
    _, offsets = ragged_layout([2, 0, 1, 4])
    packed = torch.randn(7, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f: se(f, offsets=offsets), (packed,))


def test_se_rejects_an_unknown_backend():
    with pytest.raises(ValueError, match="backend"):
        SqueezeExcitation(16, reduction=4, backend="cuda")


# ---------------------------------------------------------------- the field


@pytest.mark.parametrize("preset", "ABCD")
def test_full_size_preset_builds_and_takes_an_optimizer_step(preset):
    model = MixerNeRF(preset_config(preset, backend="torch"))
    assert model.cfg.preset == preset
    x, d = random_rays(4, 8)
    target = torch.rand(4, 8, 3)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    before = [p.detach().clone() for p in model.parameters()]
    sigma, rgb = model(x, d)
    assert sigma.shape == (4, 8) and rgb.shape == (4, 8, 3)
    assert (sigma >= 0).all() and (rgb >= 0).all() and (rgb <= 1).all()
    loss = F.mse_loss(rgb, target) + sigma.mean()
    assert torch.isfinite(loss)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    assert all(torch.isfinite(p).all() for p in model.parameters())
    changed = [not torch.equal(p, b) for p, b in zip(model.parameters(), before, strict=True)]
    assert all(changed), "every parameter receives a gradient"


def test_presets_add_parameters_in_order():
    count = {p: sum(q.numel() for q in MixerNeRF(preset_config(p)).parameters()) for p in "ABCD"}
    assert count["A"] < count["B"] < count["D"] and count["A"] < count["C"] < count["D"]
    assert count["B"] - count["A"] == count["D"] - count["C"]  # SE adds the same in both


def test_initial_density_is_the_same_fog_for_every_seed():
    # softplus(0 - 1) ~ 0.31 everywhere: rays start partly opaque, nothing dead, whatever the seed.
    for preset in "AD":
        sigma, _ = MixerNeRF(preset_config(preset, backend="torch"))(*random_rays(16, 8))
        torch.testing.assert_close(sigma, torch.full_like(sigma, F.softplus(torch.tensor(-1.0)).item()))


def test_relu_density_option():
    model = small_model("A", density_activation="relu")
    x, d = random_rays(8, 8)
    raw = model.head(model._trunk_features(x, None))[..., 0]
    torch.testing.assert_close(model(x, d)[0], torch.relu(raw))


@pytest.mark.parametrize("preset", ["A", "D"])
def test_density_noise_perturbs_the_pre_activation_of_training_passes_only(preset):
    """sigma = softplus(raw + std * N(0, 1) - 1) in training mode, drawn from the model's generator;
    an eval pass, and a model without noise, see raw alone; colour never depends on the noise."""
    model = randomize_(small_model(preset))
    x, d = random_rays(8, 8)
    clean_sigma, clean_rgb = model(x, d)
    model.density_noise, model.noise_generator = 0.5, torch.Generator().manual_seed(3)
    sigma, rgb = model(x, d)
    noise = torch.randn(sigma.shape, generator=torch.Generator().manual_seed(3))
    raw = torch.log(torch.expm1(clean_sigma.double())) + 1.0  # softplus's inverse, then the shift undone
    torch.testing.assert_close(sigma.double(), F.softplus(raw + 0.5 * noise.double() - 1.0), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(rgb, clean_rgb)
    model.eval()
    torch.testing.assert_close(model(x, d)[0], clean_sigma)


def test_under_autocast_the_encoding_is_cast_once_for_the_trunk_and_its_skip():
    """The mixed encoding feeds the first layer and the skip: one cast to autocast's dtype, so one
    cast back in the backward (two casts were two passes each way and a float32 sum of the two)."""
    model = randomize_(small_model("C", backend="kernel"))
    x, d = random_rays(4, 6)
    width = model.trunk[0].in_features
    casts = []

    class Casts(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func.overloadpacket is torch.ops.aten._to_copy and args[0].shape == (*x.shape[:-1], width):
                casts.append(args[0].dtype)
            return func(*args, **(kwargs or {}))

    with Casts():
        with torch.autocast("cpu", dtype=torch.bfloat16):
            sigma, rgb = model(x, d)
        (sigma.float().sum() + rgb.float().sum()).backward()
    assert casts == [torch.float32, torch.bfloat16], casts  # forward to bf16, backward to float32


@pytest.mark.parametrize("width", [32, 31])
def test_padded_head_gives_what_its_linear_gives(width):
    """The head as one GEMM with rows padded to 8 values (and its outputs reordered) computes what
    ``nn.Linear`` then slicing does: outputs and every parameter's gradient, to rounding."""
    torch.manual_seed(0)
    model = randomize_(small_model("D", width=width, backend="torch")).double()
    x, d = (t.double() for t in random_rays(6, 5))

    def sliced(features):
        out = model.head(features)
        return out[..., 1:], out[..., 0]

    results = []
    for head in (model._head, sliced):
        model.zero_grad()
        model._head = head
        sigma, rgb = model(x, d)
        (sigma.square().sum() + rgb.sum()).backward()
        results.append([sigma, rgb] + [p.grad.clone() for p in model.parameters()])
        del model._head
    for got, want in zip(*results, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("preset", "AD")
def test_per_ray_per_sample_and_expanded_directions_agree(preset):
    model = randomize_(small_model(preset))
    x, d = random_rays(5, 6)
    expanded = model(x, d.expand(5, 6, 3))
    per_ray = model(x, d)
    per_sample = model(x, d.expand(5, 6, 3).contiguous())
    for a, b in zip(per_ray, expanded, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    for a, b in zip(per_ray, per_sample, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_packed_layout_equals_dense_for_full_rays():
    model = randomize_(small_model("D"))
    R, S = 4, 5
    x, d = random_rays(R, S)
    dense_sigma, dense_rgb = model(x, d)
    order = torch.randperm(R * S)
    ray_indices = torch.arange(R).repeat_interleave(S)[order]
    packed_x, packed_d = x.reshape(-1, 3)[order], d.expand(R, S, 3).reshape(-1, 3)[order]
    sigma, rgb = model(packed_x, packed_d, ray_indices=ray_indices, num_rays=R)
    torch.testing.assert_close(sigma, dense_sigma.reshape(-1)[order], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(rgb, dense_rgb.reshape(-1, 3)[order], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("backend", SE_BACKENDS)
def test_packed_offsets_equal_ray_indices_in_forward_and_density(backend):
    model = randomize_(small_model("D", backend=backend))
    ray_indices, offsets = ragged_layout([6, 0, 3, 11, 1])
    N = ray_indices.numel()
    x, d = torch.rand(N, 3) * 3 - 1.5, F.normalize(torch.randn(N, 3), dim=-1)
    by_offsets = model(x, d, offsets=offsets)
    by_indices = model(x, d, ray_indices=ray_indices, num_rays=5)
    torch.testing.assert_close(by_offsets, by_indices)
    torch.testing.assert_close(model.density(x, offsets=offsets), by_indices[0])


def outputs_and_grads(model, x, **kwargs):
    sigma, rgb = model(x, **kwargs)
    loss = (sigma * torch.linspace(0.1, 1, sigma.numel(), dtype=sigma.dtype, device=sigma.device)).sum() + (rgb * rgb).sum()
    params = [p for p in model.parameters() if p.requires_grad]
    return [sigma, rgb, *torch.autograd.grad(loss, params, allow_unused=True)]


@pytest.mark.parametrize("preset", "ABCD")
@pytest.mark.parametrize("eq7", [False, True], ids=["default", "eq7"])
@pytest.mark.parametrize("layout", ["offsets", "ray_indices", "both"])
def test_ray_directions_give_what_per_sample_directions_give(preset, eq7, layout):
    """The view branch once per ray, spread to the samples, is the per-sample one: outputs and every
    parameter's gradient, with empty rays and (Eq. 7) the directions in the trunk too."""
    model = randomize_(small_model(preset, mlca_concat_direction=eq7)).double()
    ray_indices, offsets = ragged_layout([6, 0, 3, 11, 1, 0])
    N, R = ray_indices.numel(), 6
    x = torch.rand(N, 3, dtype=torch.float64) * 3 - 1.5
    rays = F.normalize(torch.randn(R, 3, dtype=torch.float64), dim=-1)
    given = {"offsets": {"offsets": offsets}, "ray_indices": {"ray_indices": ray_indices, "num_rays": R},
             "both": {"offsets": offsets, "ray_indices": ray_indices}}[layout]
    want = outputs_and_grads(model, x, d=rays[ray_indices], **given)
    got = outputs_and_grads(model, x, d=None, ray_directions=rays, **given)
    for a, b in zip(got, want, strict=True):
        assert (a is None and b is None) or torch.allclose(a, b, rtol=1e-10, atol=1e-12)
    if eq7:
        torch.testing.assert_close(model.density(x, ray_directions=rays, **given),
                                   model.density(x, d=rays[ray_indices], **given))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
@pytest.mark.parametrize("layout", ["offsets", "ray_indices"])
def test_ray_directions_on_cuda(layout):
    """torch.segment_reduce (offsets) and index_add (ray_indices) sum each ray's rows on the GPU."""
    model = randomize_(small_model("D", backend="auto")).cuda()
    ray_indices, offsets = ragged_layout([6, 0, 3, 11, 1, 0] * 50)
    x = (torch.rand(ray_indices.numel(), 3) * 3 - 1.5).cuda()
    rays = F.normalize(torch.randn(300, 3), dim=-1).cuda()
    given = {"offsets": {"offsets": offsets.cuda()}, "ray_indices": {"ray_indices": ray_indices.cuda(), "num_rays": 300}}[layout]
    want = outputs_and_grads(model, x, d=rays[ray_indices.cuda()], **given)
    got = outputs_and_grads(model, x, d=None, ray_directions=rays, **given)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("preset", "CD")
def test_without_the_direction_mlca_the_view_branch_takes_pe_d(preset):
    """mlca_directions=False removes exactly the MLCA on PE(d): the same field as one whose direction
    MLCA is at its identity start (lift [I; 0], no mixing), with the view weights of the lifted
    coordinates and zeros for the extra channels."""
    plain = randomize_(small_model(preset, mlca_directions=False)).double()
    assert isinstance(plain.direction_mixer, torch.nn.Identity) and isinstance(plain.position_mixer, MLCA)
    mixed = small_model(preset).double()
    C, T = mixed.cfg.mlca_channels, 1 + 2 * mixed.cfg.dir_freqs
    mixed.load_state_dict(
        {k: v for k, v in plain.state_dict().items() if not k.startswith("view_direction")}, strict=False
    )
    with torch.no_grad():
        weight = torch.zeros_like(mixed.view_direction.weight).view(-1, T, C)
        weight[..., :3] = plain.view_direction.weight.view(-1, T, 3)
        mixed.view_direction.weight.copy_(weight.view(-1, T * C))
    x, d = random_rays(4, 5, torch.float64)
    for a, b in zip(plain(x, d), mixed(x, d), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    removed = sum(p.numel() for p in mixed.direction_mixer.parameters()) + (T * C - T * 3) * mixed.cfg.view_width
    assert sum(p.numel() for p in plain.parameters()) == sum(p.numel() for p in mixed.parameters()) - removed
    assert [m for m in plain.modules() if isinstance(m, MLCA)] == [plain.position_mixer]  # what the decay reaches


def test_ray_directions_without_samples():
    model = small_model("D")
    sigma, rgb = model(torch.zeros(0, 3), None, offsets=torch.zeros(3, dtype=torch.int64),
                       ray_directions=torch.zeros(2, 3))
    assert sigma.shape == (0,) and rgb.shape == (0, 3)


def test_spread_to_samples_gradcheck():
    from mixer_nerf.model.ray_rows import spread_to_samples

    ray_indices, offsets = ragged_layout([2, 0, 3, 1])
    values = torch.randn(4, 5, dtype=torch.float64, requires_grad=True)
    for kwargs in ({"offsets": offsets}, {"ray_indices": ray_indices}):
        assert torch.autograd.gradcheck(lambda v: spread_to_samples(v, 6, **kwargs), (values,))
        torch.testing.assert_close(spread_to_samples(values, 6, **kwargs), values[ray_indices])


@pytest.mark.skipif(not _extension.available(), reason="kernels not built")
@pytest.mark.parametrize("preset", ["A", "D"])
def test_kernel_backend_field_equals_the_reference_path(preset):
    """backend="kernel": the fused layers (linear_relu in the trunk, linear in the head and colour
    branch, with the PE, MLCA and SE kernels) give the reference path's outputs and gradients."""
    reference = randomize_(small_model(preset)).double()
    fused = small_model(preset, backend="kernel").double()
    fused.load_state_dict(reference.state_dict())
    x, d = random_rays(4, 5, torch.float64)
    grads = []
    for model in (reference, fused):
        sigma, rgb = model(x, d)
        (sigma.sum() + (rgb * torch.linspace(-1, 1, 3, dtype=rgb.dtype)).sum()).backward()
        grads.append((sigma, rgb, [p.grad for p in model.parameters()]))
    (sigma_ref, rgb_ref, grads_ref), (sigma_fused, rgb_fused, grads_fused) = grads
    torch.testing.assert_close(sigma_fused, sigma_ref)
    torch.testing.assert_close(rgb_fused, rgb_ref)
    for got, want in zip(grads_fused, grads_ref):
        torch.testing.assert_close(got, want)
    with dispatched_ops() as ops:
        sigma, rgb = fused(x, d)
        (sigma.sum() + rgb.sum()).backward()
    assert ops["aten._addmm_activation"] == fused.cfg.depth
    # every per-sample layer's bias gradient from our one-pass kernels (the trunk's with its ReLU mask;
    # head, view feature, rgb), no GEMV, no column sum
    assert ops["mixer_nerf.relu_bias_bwd"] == fused.cfg.depth and ops["mixer_nerf.bias_grad"] == 3
    assert ops["aten.mv"] == ops["aten.sum.dim_IntList"] == 0


def test_frequency_window_weights_each_octave_by_the_cosine_ramp():
    model = small_model("A")  # pos_freqs 4: PE(x) is x, then sin and cos of octaves 0-3, 3 columns each
    model.set_frequency_window(1.5)
    ramp = [1.0, (1 - math.cos(math.pi * 0.5)) / 2, 0.0, 0.0]  # octave k: clamp(1.5 - k, 0, 1)
    expected = torch.tensor([1.0] * 3 + [w for w in ramp for _ in range(6)])
    torch.testing.assert_close(model.octave_weights, expected)
    model.set_frequency_window(model.cfg.pos_freqs)
    assert model.frequency_window is None and bool((model.octave_weights == 1).all())
    with pytest.raises(ValueError, match="alpha"):
        model.set_frequency_window(-1.0)


def test_a_closed_window_leaves_the_trunk_only_x():
    """alpha = 0: the trunk's first layer sees no octave of PE(x), so its weights on them get no
    gradient; an open window gives the full model's outputs."""
    model = randomize_(small_model("A"))
    x, d = random_rays(4, 5)
    full = model(x, d)
    model.set_frequency_window(0.0)
    sigma, rgb = model(x, d)
    (sigma.sum() + rgb.sum()).backward()
    first = model.trunk[0].weight.grad
    assert bool((first[:, 3:] == 0).all()) and bool((first[:, :3] != 0).any())
    model.set_frequency_window(None)
    torch.testing.assert_close(model(x, d), full)


def test_packed_without_ray_indices_gates_per_point():
    per_ray = randomize_(small_model("D"))
    per_point = small_model("D", se_per_point=True)
    per_point.load_state_dict(per_ray.state_dict())
    x, d = random_rays(3, 4)
    expected = per_point(x, d)
    got = per_ray(x.reshape(-1, 3), d.expand(3, 4, 3).reshape(-1, 3))
    torch.testing.assert_close(got[0], expected[0].reshape(-1))
    torch.testing.assert_close(got[1], expected[1].reshape(-1, 3))


def test_density_depends_on_direction_only_with_eq7_concat():
    x, d = random_rays(3, 4)
    other_d = F.normalize(torch.randn(3, 1, 3), dim=-1)
    separate = randomize_(small_model("D"))
    torch.testing.assert_close(separate(x, d)[0], separate(x, other_d)[0])
    concat = randomize_(small_model("D", mlca_concat_direction=True))
    assert concat.position_mixer.num_tokens == (1 + 2 * 4) + (1 + 2 * 2)
    assert not torch.allclose(concat(x, d)[0], concat(x, other_d)[0])
    concat(x, d)[1].sum().backward()
    assert concat.position_mixer.token_weight.grad.abs().sum() > 0


def test_density_method_matches_forward():
    model = randomize_(small_model("D"))
    x, d = random_rays(3, 4)
    torch.testing.assert_close(model.density(x), model(x, d)[0])
    packed = x.reshape(-1, 3)
    torch.testing.assert_close(model.density(packed), model(packed, d.expand(3, 4, 3).reshape(-1, 3))[0])
    concat = small_model("D", mlca_concat_direction=True)
    with pytest.raises(ValueError, match="d is required"):
        concat.density(x)
    torch.testing.assert_close(concat.density(x, d), concat(x, d)[0])


def test_scene_normalisation():
    # The field sees (x - center) / scale: moving and scaling the points with the box (default
    # scale 1.5 -> 3.0) leaves the output unchanged.
    a = small_model("A")
    b = small_model("A", scene_center=(1.0, -2.0, 0.5), scene_scale=3.0)
    b.load_state_dict({**a.state_dict(), "scene_center": b.scene_center})
    x, d = random_rays(2, 3)
    torch.testing.assert_close(
        a(x, d)[0], b(x * 2.0 + torch.tensor([1.0, -2.0, 0.5]), d)[0], rtol=1e-4, atol=1e-5
    )


def test_field_gradcheck_float64():
    model = randomize_(small_model("D", depth=2, skips=(1,), width=8, view_width=4, se_reduction=2)).double()
    x, d = random_rays(2, 3, torch.float64)
    x.requires_grad_(True)
    d.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x, d: model(x, d), (x, d))


def test_bf16_autocast_keeps_outputs_float32_and_close():
    model = small_model("D")
    x, d = random_rays(8, 16)
    sigma, rgb = model(x, d)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        sigma_bf, rgb_bf = model(x, d)
    assert sigma_bf.dtype == rgb_bf.dtype == torch.float32
    # bf16 keeps 8 bits of mantissa; a few roundings through 4 layers stay within a few percent.
    torch.testing.assert_close(sigma_bf, sigma, rtol=0.1, atol=0.05)
    torch.testing.assert_close(rgb_bf, rgb, rtol=0.1, atol=0.05)
    (sigma_bf.sum() + rgb_bf.sum()).backward()


def test_ray_directions_under_bf16_autocast():
    """bf16 rows spread to the samples; their gradient summed per ray in float32, handed back in bf16."""
    model = randomize_(small_model("D"))
    ray_indices, offsets = ragged_layout([6, 0, 3, 11, 1])
    x = torch.rand(ray_indices.numel(), 3) * 3 - 1.5
    rays = F.normalize(torch.randn(5, 3), dim=-1)
    runs = []
    for kwargs in ({"d": rays[ray_indices]}, {"d": None, "ray_directions": rays}):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            runs.append(outputs_and_grads(model, x, offsets=offsets, **kwargs))
    for a, b in zip(*runs, strict=True):
        torch.testing.assert_close(a, b, rtol=0.05, atol=0.05)


def test_empty_and_single_inputs():
    model = small_model("D")
    for R, S in ((0, 4), (1, 1), (3, 0)):
        sigma, rgb = model(*random_rays(R, S))
        assert sigma.shape == (R, S) and rgb.shape == (R, S, 3)
        assert torch.isfinite(sigma).all() and torch.isfinite(rgb).all()
    sigma, rgb = model(torch.zeros(0, 3), torch.zeros(0, 3), ray_indices=torch.zeros(0, dtype=torch.long))
    assert sigma.shape == (0,) and rgb.shape == (0, 3)


def test_kernel_positional_encoding_backend_matches_reference():
    from mixer_nerf import _extension

    if not _extension.available():
        pytest.skip("compiled kernels unavailable")
    model = randomize_(small_model("D"))
    kernel = small_model("D", backend="kernel")
    kernel.load_state_dict(model.state_dict())
    x, d = random_rays(4, 8)
    for a, b in zip(kernel(x, d), model(x, d), strict=True):
        # Same maths; the kernel's phases are exact, the reference's rounded: ~1e-6 apart.
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(
    "x, d, kwargs, error, match",
    [
        (torch.zeros(2, 4, 2), torch.zeros(2, 1, 3), {}, ValueError, "x must"),
        (torch.zeros(2, 4, 3, 1), torch.zeros(2, 1, 3), {}, ValueError, "x must"),
        (torch.zeros(2, 4, 3), torch.zeros(3, 1, 3), {}, ValueError, "d must"),
        (torch.zeros(2, 4, 3), torch.zeros(2, 2, 3), {}, ValueError, "d must"),
        (torch.zeros(5, 3), torch.zeros(4, 3), {}, ValueError, "d must"),
        (torch.zeros(2, 4, 3, dtype=torch.int64), torch.zeros(2, 1, 3), {}, TypeError, "x must"),
        (torch.zeros(2, 4, 3), torch.zeros(2, 1, 3, dtype=torch.int32), {}, TypeError, "d must"),
        (
            torch.zeros(2, 4, 3),
            torch.zeros(2, 1, 3),
            {"ray_indices": torch.zeros(8, dtype=torch.long)},
            ValueError,
            "ray_indices",
        ),
        (torch.zeros(5, 3), torch.zeros(5, 3), {"ray_indices": torch.zeros(5)}, ValueError, "ray_indices"),
        (
            torch.zeros(5, 3),
            torch.zeros(5, 3),
            {"ray_indices": torch.zeros(4, dtype=torch.long)},
            ValueError,
            "ray_indices",
        ),
        (torch.zeros(2, 4, 3), torch.zeros(2, 1, 3), {"offsets": torch.tensor([0, 4])}, ValueError, "packed"),
        (torch.zeros(5, 3), torch.zeros(5, 3), {"offsets": torch.tensor([0, 5.0])}, TypeError, "offsets"),
        (torch.zeros(5, 3), torch.zeros(5, 3), {"offsets": torch.tensor([[0, 5]])}, ValueError, "offsets"),
        (torch.zeros(5, 3), torch.zeros(5, 3), {"offsets": [0, 5]}, TypeError, "offsets"),
        (
            torch.zeros(5, 3),
            torch.zeros(5, 3),
            {"offsets": torch.tensor([0, 5], device="meta")},
            ValueError,
            "offsets on meta",
        ),
        (torch.zeros(5, 3), None, {}, ValueError, "d is required"),
        # ray_directions: packed only, instead of d, with a layout, one row per ray
        (torch.zeros(2, 4, 3), None, {"ray_directions": torch.zeros(2, 3)}, ValueError, "only for packed"),
        (torch.zeros(5, 3), torch.zeros(5, 3), {"ray_directions": torch.zeros(1, 3), "offsets": torch.tensor([0, 5])},
         ValueError, "instead of d"),
        (torch.zeros(5, 3), None, {"ray_directions": torch.zeros(1, 3)}, ValueError, "needs offsets or ray_indices"),
        (torch.zeros(5, 3), None, {"ray_directions": torch.zeros(2, 3), "offsets": torch.tensor([0, 5])},
         ValueError, r"ray_directions must have shape \(1, 3\)"),
        (torch.zeros(5, 3), None, {"ray_directions": torch.zeros(1, 2), "ray_indices": torch.zeros(5, dtype=torch.long)},
         ValueError, r"ray_directions must have shape \(R, 3\)"),
        (torch.zeros(5, 3), None, {"ray_directions": torch.zeros(1, 3), "ray_indices": torch.zeros(5, dtype=torch.long),
                                   "num_rays": 2}, ValueError, r"\(2, 3\)"),
        (torch.zeros(5, 3), None, {"ray_directions": torch.zeros(1, 3, dtype=torch.int32),
                                   "offsets": torch.tensor([0, 5])}, TypeError, "ray_directions must"),
    ],
)
def test_bad_inputs_name_the_argument(x, d, kwargs, error, match):
    with pytest.raises(error, match=match):
        small_model("D")(x, d, **kwargs)


# ---------------------------------------------------------------- config


def test_preset_config_switches_and_overrides():
    assert (preset_config("a").use_se, preset_config("a").use_mlca) == (False, False)
    assert (preset_config("B").use_se, preset_config("B").use_mlca) == (True, False)
    assert (preset_config("C").use_se, preset_config("C").use_mlca) == (False, True)
    assert (preset_config("D").use_se, preset_config("D").use_mlca) == (True, True)
    assert preset_config("D", width=64).width == 64
    assert ModelConfig().preset == "D"


def test_config_round_trips_through_json():
    cfg = preset_config("C", skips=[3], scene_center=[0.5, 0, 0])
    restored = ModelConfig(**json.loads(json.dumps(dataclasses.asdict(cfg))))
    assert restored == cfg and restored.skips == (3,)


@pytest.mark.parametrize(
    "kwargs, error",
    [
        ({"preset": "E"}, ValueError),
        ({"wdth": 3}, TypeError),
        ({"width": 0}, ValueError),
        ({"skips": (8,)}, ValueError),
        ({"scene_scale": 0.0}, ValueError),
        ({"scene_scale": math.inf}, ValueError),
        ({"mlca_channels": 2}, ValueError),
        ({"se_reduction": 512}, ValueError),
        ({"density_activation": "exp"}, ValueError),
        ({"scene_center": (0.0, 0.0)}, ValueError),
    ],
)
def test_bad_config(kwargs, error):
    with pytest.raises(error):
        preset_config(**kwargs)


@pytest.mark.parametrize("variant", [{"se_per_point": True}, {"mlca_concat_direction": True},
                                     {"se_gates_density": False}])
def test_model_variants_train(variant):
    # A few Adam steps on fixed rays: every weight that shapes the colour gets a gradient and the
    # fit improves without going non-finite.
    torch.manual_seed(0)
    model = small_model("D", **variant)
    x, d = random_rays(4, 6)
    target = torch.rand(4, 6, 3)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(20):
        sigma, rgb = model(x, d)
        loss = F.mse_loss(rgb, target) + 1e-3 * sigma.mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert all(math.isfinite(v) for v in losses) and losses[-1] < losses[0]
    assert model.position_mixer.token_weight.grad.abs().sum() > 0
    assert model.se is not None and any(p.grad.abs().sum() > 0 for p in model.se.parameters())
