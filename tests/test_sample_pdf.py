"""sample_pdf and hierarchical_samples: kernels (CPU, CUDA) against the reference path, hand-written
gradients against autograd and finite differences, adversarial PDFs, input validation."""

from __future__ import annotations

import functools

import pytest
import torch
from torch.library import opcheck

from mixer_nerf.ops import check_pending
from mixer_nerf.ops._dispatch import use_kernel
from mixer_nerf.ops.hierarchical_samples import hierarchical_samples
from mixer_nerf.ops.hierarchical_samples_reference import hierarchical_samples_reference
from mixer_nerf.ops.sample_pdf import sample_pdf, sample_pdf_packed
from mixer_nerf.ops.sample_pdf_reference import (
    accumulation_dtype,
    sample_pdf_packed_reference,
    sample_pdf_reference,
)
from dispatch_count import dispatched_ops

CPU = torch.device("cpu")
HAS_CUDA = torch.cuda.is_available()
cuda = pytest.mark.cuda
needs_cuda = pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA GPU")

# (R, B, N): single ray, single bin, single sample, empty batch, no samples, NeRF-sized, ragged.
SHAPES = [(1, 1, 1), (1, 8, 1), (5, 1, 7), (0, 4, 3), (6, 5, 0), (40, 63, 128), (17, 37, 45)]


def tolerance(dtype: torch.dtype, num_bins: int, scale: float = 1.0) -> float:
    """Absolute tolerance of samples of magnitude <= scale against the float64 reference.

    The kernels carry the CDF, v = u W and t in float64 for every dtype, so a float32 (or half)
    sample is the float64 one up to the rounding of e_k + t (e_{k+1} - e_k) and of the output: a
    few ulps. Comparing with a reference in the input dtype instead would be wrong near flat
    stretches of the CDF (zero-weight bins), where the quantile jumps: a float32 v = u W can round
    onto the other side of such a jump (seen 3 times in 8.4M samples). In float64 the kernel's
    grouped CDF and torch.cumsum differ by ~B ulp(W), which moves a sample by
    ~B eps W / w_k <= 11 B^2 eps (test weights are 0 or in [0.1, 1.1]).
    """
    rounding = 4 * torch.finfo(dtype).eps if dtype != torch.float64 else 0.0
    return (rounding + 12 * (num_bins + 2) ** 2 * torch.finfo(torch.float64).eps) * scale


def grad_tolerance(dtype: torch.dtype) -> float:
    """Gradient tolerance relative to the largest gradient of a tensor: each gradient sums up to
    N = 128 per-sample terms carrying ~eps relative error each, in another order than autograd."""
    return {torch.float64: 1e-10, torch.float32: 1e-4}.get(dtype, 0.02)


def reference_samples(bins, weights, u, weight_padding=0.0):
    """The reference evaluated in float64 (what the kernels approximate), cast to the input dtype."""
    return sample_pdf_reference(bins.double(), weights.double(), u.double(), weight_padding).to(bins.dtype)


def reference_merged(z, weights, u, weight_padding=0.0):
    return hierarchical_samples_reference(z.double(), weights.double(), u.double(), weight_padding).to(
        z.dtype
    )


def random_pdf(rays, bins, dtype=torch.float32, device=CPU, zero_fraction=0.3):
    """Sorted edges in [0, 1] and weights that are 0 or in [0.1, 1.1]."""
    edges = torch.sort(torch.rand(rays, bins + 1, dtype=torch.float64, device=device), dim=-1).values
    edges[:, 0], edges[:, -1] = 0.0, 1.0
    weights = 0.1 + torch.rand(rays, bins, dtype=torch.float64, device=device)
    weights = weights * (torch.rand_like(weights) >= zero_fraction)
    return edges.to(dtype), weights.to(dtype)


def sorted_u(rays, samples, dtype=torch.float32, device=CPU):
    return torch.sort(
        torch.rand(rays, samples, dtype=accumulation_dtype(dtype), device=device), dim=-1
    ).values


def assert_valid_samples(samples, bins):
    """Finite, sorted along rays, within [bins[:, 0], bins[:, -1]]."""
    assert torch.isfinite(samples).all()
    if samples.numel():
        assert (samples[:, 1:] >= samples[:, :-1]).all()
        assert (samples >= bins[:, :1]).all() and (samples <= bins[:, -1:]).all()


@pytest.fixture(scope="module", autouse=True)
def kernels():
    # Raises with the build error if the extension is missing; registers the fake kernels.
    if not use_kernel("kernel", CPU):
        pytest.fail("no CPU kernels")


# ---------------------------------------------------------------------------------------------
# Forward: CPU kernel against the reference path


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("u_kind", ["per_ray", "shared", "deterministic", "stratified"])
def test_sample_pdf_forward_matches_reference(shape, dtype, u_kind):
    R, B, N = shape
    bins, weights = random_pdf(R, B, dtype)
    acc = accumulation_dtype(dtype)
    strata = torch.arange(N, dtype=acc)
    kwargs, u = {
        "per_ray": ({}, sorted_u(R, N, dtype)),
        "shared": ({}, sorted_u(1, N, dtype)[0]),
        # the documented positions: (i + 1/2) / N, and (i + xi) / N with xi drawn by torch.rand
        "deterministic": ({"deterministic": True}, (strata + 0.5) / N),
        "stratified": (
            {"generator": torch.Generator().manual_seed(3)},
            (strata + torch.rand(R, N, generator=torch.Generator().manual_seed(3), dtype=acc)) / N,
        ),
    }[u_kind]
    if u_kind in ("per_ray", "shared"):
        kwargs = {"u": u}
    ours = sample_pdf(bins, weights, N, backend="kernel", **kwargs)
    assert ours.shape == (R, N) and ours.dtype == dtype
    torch.testing.assert_close(ours, reference_samples(bins, weights, u), atol=tolerance(dtype, B), rtol=0)
    assert_valid_samples(ours, bins)
    if u_kind == "stratified":
        kwargs = {"generator": torch.Generator().manual_seed(3)}  # the same draws again
    ref = sample_pdf(bins, weights, N, backend="torch", **kwargs)
    if ours.numel():  # the reference path in the input dtype agrees but at jumps of the quantile
        assert (ours - ref).abs().gt(1e-4).float().mean() < 1e-3


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_low_precision_forward_and_backward(dtype):
    bins, weights = random_pdf(9, 12, dtype)
    u = sorted_u(9, 20, dtype)
    ours = sample_pdf(bins, weights, 20, u=u, backend="kernel")
    assert ours.dtype == dtype
    torch.testing.assert_close(ours, reference_samples(bins, weights, u), atol=tolerance(dtype, 12), rtol=0)
    assert_valid_samples(ours, bins)
    for ours_g, ref_g in zip(
        _grads("kernel", bins, weights, u), _reference_grads(bins, weights, u), strict=True
    ):
        assert ours_g.dtype == dtype
        # float32 (kernel) vs float64 (reference) math, then one rounding of each gradient
        torch.testing.assert_close(
            ours_g.float(), ref_g.float(), atol=0.02 * ref_g.float().abs().max() + 1e-3, rtol=0.02
        )
    z = torch.sort(torch.rand(9, 12), dim=-1).values.to(dtype)
    merged = hierarchical_samples(z, weights, 20, u=u, backend="kernel")
    torch.testing.assert_close(merged, reference_merged(z, weights, u), atol=tolerance(dtype, 12), rtol=0)


def test_weight_padding_matches_reference():
    bins, weights = random_pdf(20, 16, zero_fraction=0.9)
    u = sorted_u(20, 33)
    ours = sample_pdf(bins, weights, 33, u=u, weight_padding=1e-5, backend="kernel")
    # The kernels pad in the weights' dtype: a float32 weight of ~0.5 keeps 1e-5 to ~0.5%, and in a
    # padded zero bin a sample moves by (bin width) / 1e-5 per unit of CDF, so the truth is the
    # float64 quantile of the weights as padded in float32 (1% of seeds failed against float64 padding).
    torch.testing.assert_close(
        ours, reference_samples(bins, weights + 1e-5, u), atol=tolerance(torch.float32, 16), rtol=0
    )
    assert not torch.equal(ours, sample_pdf(bins, weights, 33, u=u, backend="kernel"))


def test_quantiles_are_exact():
    """Independent of the reference: with deterministic u, bin k receives exactly the u_i in
    (C_k / W, C_{k+1} / W], and inside a bin samples are linear in u."""
    edges = torch.tensor([[0.0, 1.0, 3.0, 4.0, 8.0]], dtype=torch.float64)
    weights = torch.tensor([[1.0, 0.0, 2.0, 1.0]], dtype=torch.float64)  # CDF 0, 1/4, 1/4, 3/4, 1
    u = (torch.arange(8, dtype=torch.float64) + 0.5) / 8
    expected = torch.tensor([[0.25, 0.75, 3.125, 3.375, 3.625, 3.875, 5.0, 7.0]], dtype=torch.float64)
    for backend in ("kernel", "torch"):
        got = sample_pdf(edges, weights, 8, deterministic=True, backend=backend)
        torch.testing.assert_close(got, expected, rtol=0, atol=1e-15)
        torch.testing.assert_close(sample_pdf(edges, weights, 8, u=u, backend=backend), got, rtol=0, atol=0)


def test_stratified_positions_are_sorted_strata():
    bins = torch.linspace(0, 1, 2).expand(64, 2).contiguous()  # one bin on [0, 1]: samples == u
    weights = torch.ones(64, 1)
    samples = sample_pdf(bins, weights, 16, generator=torch.Generator().manual_seed(0), backend="kernel")
    strata = torch.arange(16) / 16
    assert ((samples >= strata - 1e-7) & (samples <= strata + 1 / 16 + 1e-7)).all()
    again = sample_pdf(bins, weights, 16, generator=torch.Generator().manual_seed(0), backend="kernel")
    assert torch.equal(samples, again)


# ---------------------------------------------------------------------------------------------
# Gradients


def _grads(backend, bins, weights, u, weight_padding=0.0, upstream=None):
    bins = bins.detach().clone().requires_grad_()
    weights = weights.detach().clone().requires_grad_()
    out = sample_pdf(bins, weights, u.shape[-1], u=u, weight_padding=weight_padding, backend=backend)
    if upstream is None:
        upstream = torch.linspace(-1, 1, out.numel(), dtype=out.dtype, device=out.device).reshape(out.shape)
    return torch.autograd.grad(out, (bins, weights), upstream, allow_unused=True)


def _reference_grads(bins, weights, u, weight_padding=0.0, upstream=None):
    """Autograd through the reference evaluated in float64, cast back to the input dtype.

    The kernels carry v = u W and the CDF in float64 whatever the input dtype, so at an exact tie
    (u W == C_j, where the gradient jumps from one bin's formula to the next) they pick the bin a
    float64 evaluation picks; a float32 reference can round v onto the other side."""
    upstream = None if upstream is None else upstream.double()
    grads = _grads("torch", bins.double(), weights.double(), u.double(), weight_padding, upstream)
    return tuple(g.to(bins.dtype) for g in grads)


@pytest.mark.parametrize("shape", [(3, 1, 4), (4, 6, 5), (2, 9, 1)])
@pytest.mark.parametrize("shared_u", [False, True])
def test_gradcheck_cpu_kernel(shape, shared_u):
    R, B, N = shape
    bins, weights = random_pdf(R, B, torch.float64, zero_fraction=0.0)
    u = sorted_u(1, N, torch.float64)[0] if shared_u else sorted_u(R, N, torch.float64)
    bins.requires_grad_()
    weights.requires_grad_()
    torch.autograd.gradcheck(
        lambda b, w: sample_pdf(b, w, N, u=u, weight_padding=0.01, backend="kernel"), (bins, weights)
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", SHAPES)
def test_backward_matches_reference_autograd(shape, dtype):
    R, B, N = shape
    bins, weights = random_pdf(R, B, dtype)
    u = sorted_u(R, N, dtype)
    ours = _grads("kernel", bins, weights, u)
    ref = _reference_grads(bins, weights, u)
    for got, want in zip(ours, ref, strict=True):
        scale = want.abs().max().item() if want.numel() else 1.0
        torch.testing.assert_close(got, want, atol=grad_tolerance(dtype) * max(scale, 1.0), rtol=0)
        assert torch.isfinite(got).all()


def _row_relative_errors(got, want):
    """|got - want| / max(|want|, half a float32 ulp of the row's largest |want|) (the metric of
    benchmarks/error_budget.py)."""
    got, want = got.double(), want.double()
    floor = want.abs().amax(dim=-1, keepdim=True) * torch.finfo(torch.float32).eps / 2
    return (got - want).abs() / torch.maximum(want.abs(), floor.clamp_min(torch.finfo(torch.float32).tiny))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=[cuda, needs_cuda])])
def test_float32_gradients_at_least_as_accurate_as_reference(device):
    """NeRF-like coarse weights (1e-4..1, 30% zeros) on jittered bins, B = 63, N = 128, float32.
    dL/dw_i = sum a_n u_n - sum_{k_n > i} a_n - sum_{k_n = i} a_n t_n cancels; with the sums in
    float32 the kernel's weight gradients were ~2 ulps off in the median, twice the reference
    path's error. Computed in double and rounded once, the kernel's gradients of weights and edges
    must be at least as accurate as the reference's against the float64 truth, in the worst
    element and in the median, and within an ulp of the truth."""
    seed = int(torch.randint(2**31, ()).item())
    print(f"seed={seed}")
    gen = torch.Generator().manual_seed(seed)
    R, B, N = 512, 63, 128
    widths = 4.0 / B * (0.5 + torch.rand(R, B, generator=gen, dtype=torch.float64))
    bins = torch.cat([torch.full((R, 1), 2.0, dtype=torch.float64), 2.0 + widths.cumsum(1)], dim=1).float()
    weights = 10.0 ** (-4 + 4 * torch.rand(R, B, generator=gen, dtype=torch.float64))
    weights = (weights * (torch.rand(R, B, generator=gen, dtype=torch.float64) >= 0.3)).float()
    u = torch.sort(torch.rand(R, N, generator=gen), dim=-1).values
    upstream = torch.randn(R, N, generator=gen)
    want = _grads("torch", bins.double(), weights.double(), u.double(), upstream=upstream.double())
    bins, weights, u, upstream = (t.to(device) for t in (bins, weights, u, upstream))
    kernel = [g.cpu() for g in _grads("kernel", bins, weights, u, upstream=upstream)]
    reference = [g.cpu() for g in _grads("torch", bins, weights, u, upstream=upstream)]
    for name, k_grad, r_grad, truth in zip(("d bins", "d weights"), kernel, reference, want, strict=True):
        kernel_err, reference_err = _row_relative_errors(k_grad, truth), _row_relative_errors(r_grad, truth)
        for stat in ("max", "median"):
            k, r = getattr(kernel_err, stat)().item(), getattr(reference_err, stat)().item()
            assert k <= r, f"{name} {stat}: kernel {k:.2e} > reference {r:.2e}"
        assert kernel_err.max().item() <= torch.finfo(torch.float32).eps, f"{name}: {kernel_err.max().item():.2e}"


# ---------------------------------------------------------------------------------------------
# Adversarial PDFs


def _both(bins, weights, u, float64_reference=True, **kwargs):
    """Kernel against reference: samples, validity, gradients. float64_reference=False keeps the
    reference in the input dtype, for cases whose meaning depends on it (flushed or overflowing
    weights)."""
    N = u.shape[-1]
    ours = sample_pdf(bins, weights, N, u=u, backend="kernel", **kwargs)
    if float64_reference:
        ref = reference_samples(bins, weights, u, **kwargs)
    else:
        ref = sample_pdf(bins, weights, N, u=u, backend="torch", **kwargs)
    torch.testing.assert_close(ours, ref, rtol=0, atol=tolerance(bins.dtype, weights.shape[1]))
    assert_valid_samples(ours, bins)
    reference_grads = _reference_grads if float64_reference else functools.partial(_grads, "torch")
    for got, want in zip(
        _grads("kernel", bins, weights, u, **kwargs), reference_grads(bins, weights, u, **kwargs), strict=True
    ):
        assert torch.isfinite(got).all()
        scale = want.abs().max().item() if want.numel() else 0.0
        torch.testing.assert_close(got, want, rtol=0, atol=grad_tolerance(bins.dtype) * max(scale, 1.0))
    return ours


U_WITH_ENDS = torch.tensor([0.0, 0.0, 0.3, 0.5, 1.0, 1.0])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_all_zero_weights_sample_uniformly(dtype):
    bins = torch.tensor([[0.0, 1.0, 2.0, 6.0], [-1.0, -1.0, -1.0, -1.0]], dtype=dtype)
    weights = torch.zeros(2, 3, dtype=dtype)
    samples = _both(bins, weights, U_WITH_ENDS.to(accumulation_dtype(dtype)))
    torch.testing.assert_close(samples[0], (6 * U_WITH_ENDS).to(dtype))
    assert (samples[1] == -1).all()
    tiny = torch.full((1, 3), 1e-39 if dtype == torch.float32 else 1e-309, dtype=dtype)  # subnormal total
    torch.testing.assert_close(
        _both(bins[:1], tiny, U_WITH_ENDS.to(accumulation_dtype(dtype)), False)[0], samples[0]
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("num_bins", [62, 255, 2000])
def test_grouped_cdf_never_samples_inside_an_empty_bin(dtype, num_bins):
    """The kernels sum the CDF in groups of ~sqrt(B) bins (csrc/sample_pdf_math.h): weights over
    60 orders of magnitude with runs of zeros across the groups' ends must still give a CDF flat
    over every empty bin and monotone, so no sample lands strictly inside an empty bin and the
    samples of sorted positions are sorted."""
    gen = torch.Generator().manual_seed(torch.seed() % 2**32)
    rays = 8
    weights = 10.0 ** (torch.rand(rays, num_bins, generator=gen, dtype=torch.float64) * 60 - 30)
    weights[:, ::3] = 0.0
    weights[:, 5:9] = 0.0  # a run around the first group's end for B = 62 (groups of 8)
    if dtype == torch.float32:
        weights = weights.clamp(1e-30, 1e30) * (weights > 0)
    bins = torch.cumsum(torch.rand(rays, num_bins + 1, generator=gen, dtype=torch.float64) + 0.01, dim=-1)
    bins, weights = bins.to(dtype), weights.to(dtype)
    u = torch.linspace(0, 1, 4097, dtype=accumulation_dtype(dtype))
    samples = sample_pdf(bins, weights, u.numel(), u=u, backend="kernel")
    assert (samples.diff(dim=-1) >= 0).all()
    k = (torch.searchsorted(bins, samples, right=True) - 1).clamp(0, num_bins - 1)
    inside = (samples > bins.gather(-1, k)) & (samples < bins.gather(-1, k + 1))
    assert not (inside & (weights.gather(-1, k) == 0)).any()


@pytest.mark.parametrize("hot", [0, 2, 4])
def test_one_hot_weights_stay_in_their_bin(hot):
    bins = torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]])
    weights = torch.nn.functional.one_hot(torch.tensor([hot]), 5).float()
    samples = _both(bins, weights, U_WITH_ENDS)
    expected = hot + U_WITH_ENDS
    expected[:2] = 0.0  # the quantile at u = 0 is inf{x : F(x) >= 0}, the first edge
    torch.testing.assert_close(samples[0], expected)


def test_u_at_zero_and_one():
    bins = torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0]])
    weights = torch.tensor([[0.0, 2.0, 1.0, 0.0]])  # leading and trailing empty bins
    samples = _both(bins, weights, U_WITH_ENDS)
    assert samples[0, 0] == 0.0 and samples[0, 1] == 0.0  # inf{x : F(x) >= 0}
    assert samples[0, -1] == 3.0 and samples[0, -2] == 3.0  # right edge of the last weighted bin


def test_duplicate_edges_zero_width_bins():
    bins = torch.tensor([[0.0, 0.0, 1.0, 1.0, 1.0, 2.0], [0.5, 0.5, 0.5, 0.5, 0.5, 0.5]])
    weights = torch.tensor([[1.0, 1.0, 3.0, 0.0, 1.0], [1.0, 0.0, 2.0, 1.0, 1.0]])
    u = torch.linspace(0, 1, 11)
    samples = _both(bins, weights, u)
    assert (samples[1] == 0.5).all()
    assert (samples[0, :2] == 0.0).all()  # u <= 1/6 falls in the zero-width first bin at 0


def test_scale_invariance_tiny_and_huge_weights():
    bins, weights = random_pdf(8, 10, torch.float64)
    u = sorted_u(8, 12, torch.float64)
    base = sample_pdf(bins, weights, 12, u=u, backend="kernel")
    for scale in (1e-300, 1e-30, 1e30, 1e300):
        torch.testing.assert_close(sample_pdf(bins, weights * scale, 12, u=u, backend="kernel"), base)
    bins32, weights32 = bins.float(), weights.float()
    for scale in (1e-30, 1e30):
        torch.testing.assert_close(
            _both(bins32, weights32 * scale, u.float()), base.float(), atol=1e-4, rtol=0
        )


def test_overflowing_total_is_finite():
    bins = torch.tensor([[0.0, 1.0, 2.0, 3.0]])
    weights = torch.full((1, 3), 3e38)  # sums to inf in float32
    samples = _both(bins, weights, U_WITH_ENDS, float64_reference=False)
    torch.testing.assert_close(samples[0], 3 * U_WITH_ENDS)


def test_single_bin_single_sample_empty_batch():
    bins = torch.tensor([[2.0, 4.0]])
    torch.testing.assert_close(
        _both(bins, torch.tensor([[0.7]]), torch.tensor([0.25])), torch.tensor([[2.5]])
    )
    empty = sample_pdf(torch.zeros(0, 4), torch.zeros(0, 3), 5, backend="kernel")
    assert empty.shape == (0, 5)
    bins.requires_grad_()
    sample_pdf(bins, torch.ones(1, 1), 0, backend="kernel").sum().backward()
    assert torch.equal(bins.grad, torch.zeros_like(bins))


# ---------------------------------------------------------------------------------------------
# hierarchical_samples


def random_coarse(rays, samples, dtype=torch.float32, device=CPU):
    z = torch.sort(torch.rand(rays, samples, dtype=torch.float64, device=device) * 4 + 2, dim=-1).values
    weights = torch.rand(rays, samples, dtype=torch.float64, device=device)
    weights = weights * (torch.rand_like(weights) > 0.3)
    return z.to(dtype), weights.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 3, 1), (0, 5, 4), (3, 3, 0), (1, 64, 128), (23, 37, 19)])
@pytest.mark.parametrize("shared_u", [False, True])
def test_hierarchical_matches_reference(shape, dtype, shared_u):
    R, S, N = shape
    z, weights = random_coarse(R, S, dtype)
    u = sorted_u(1, N, dtype)[0] if shared_u else sorted_u(R, N, dtype)
    ours = hierarchical_samples(z, weights, N, u=u, backend="kernel")
    assert ours.shape == (R, S + N) and ours.dtype == dtype
    torch.testing.assert_close(
        ours, reference_merged(z, weights, u), atol=tolerance(dtype, S, scale=8), rtol=0
    )
    assert_valid_samples(ours, z)
    # the coarse depths are all there, bit for bit, and the fine ones are sample_pdf's
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    fine = sample_pdf(mids, weights[:, 1:-1], N, u=u, backend="kernel")
    assert torch.equal(ours, torch.sort(torch.cat([z, fine], dim=-1), dim=-1).values)


def test_hierarchical_adversarial():
    z = torch.tensor(
        [[1.0, 1.0, 2.0, 2.0, 2.0, 3.0], [0.0, 1.0, 2.0, 3.0, 4.0, 5.0], [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]]
    )
    weights = torch.tensor([[0.2, 1.0, 0.0, 1.0, 0.0, 0.3], [0.0] * 6, [9.0, 0.0, 0.0, 1.0, 0.0, 9.0]])
    for u in (U_WITH_ENDS, torch.tensor([0.5]), torch.linspace(0, 1, 40)):
        ours = hierarchical_samples(z, weights, u.numel(), u=u, backend="kernel")
        ref = hierarchical_samples(z, weights, u.numel(), u=u, backend="torch")
        torch.testing.assert_close(ours, ref, rtol=0, atol=1e-6)
        assert_valid_samples(ours, z)
    # midpoint edges 0.5 ... 4.5, only the bin [2.5, 3.5] has weight; u = 0 gives the first edge
    merged = hierarchical_samples(z[2:], weights[2:], 6, u=U_WITH_ENDS, backend="kernel")
    fine = torch.tensor([0.5, 0.5, 2.8, 3.0, 3.5, 3.5])
    torch.testing.assert_close(merged[0], torch.sort(torch.cat([z[2], fine])).values)


def test_hierarchical_carries_no_grad():
    z, weights = random_coarse(4, 8)
    z.requires_grad_()
    weights.requires_grad_()
    for backend in ("kernel", "torch"):
        out = hierarchical_samples(z, weights, 5, deterministic=True, backend=backend)
        assert not out.requires_grad and out.grad_fn is None


# ---------------------------------------------------------------------------------------------
# Registered ops


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opcheck(dtype):
    bins, weights = random_pdf(5, 7, dtype)
    acc = accumulation_dtype(dtype)
    for u in (sorted_u(5, 9, dtype), sorted_u(1, 9, dtype)[0]):
        opcheck(torch.ops.mixer_nerf.sample_pdf_fwd.default, (bins, weights, u, 0.0))
        opcheck(
            torch.ops.mixer_nerf.sample_pdf_bwd.default,
            (torch.randn(5, 9, dtype=dtype), bins, weights, u, 1e-5),
        )
        z, coarse_weights = random_coarse(5, 8, dtype)
        opcheck(torch.ops.mixer_nerf.hierarchical_samples_fwd.default, (z, coarse_weights, u.to(acc), 0.0))


# ---------------------------------------------------------------------------------------------
# Bad input


def _bins(*shape, dtype=torch.float32):
    return torch.sort(torch.rand(*shape, dtype=dtype), dim=-1).values


BAD_SAMPLE_PDF = [
    (lambda: sample_pdf(_bins(3, 5)[0], torch.rand(4), 2), ValueError, "bins"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 5), 2), ValueError, "weights"),
    (lambda: sample_pdf(_bins(3, 1), torch.rand(3, 0), 2), ValueError, "bins"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(4, 4), 2), ValueError, "weights"),
    (lambda: sample_pdf(torch.arange(15).reshape(3, 5), torch.rand(3, 4), 2), TypeError, "bins"),
    (lambda: sample_pdf(_bins(3, 5), torch.ones(3, 4, dtype=torch.int64), 2), TypeError, "weights"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4, dtype=torch.float64), 2), TypeError, "weights"),
    (lambda: sample_pdf(_bins(3, 5).flip(-1), torch.rand(3, 4), 2), ValueError, "bins"),
    (lambda: sample_pdf(_bins(3, 5), -torch.rand(3, 4), 2), ValueError, "weights"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), -1), ValueError, "num_samples"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2.0), TypeError, "num_samples"),
    (
        lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, weight_padding=-1e-5),
        ValueError,
        "weight_padding",
    ),
    (
        lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, weight_padding=float("nan")),
        ValueError,
        "weight_padding",
    ),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, weight_padding="1"), TypeError, "weight_padding"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, u=torch.tensor([0.1, 0.2, 0.3])), ValueError, "u"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, u=_bins(2, 2)), ValueError, "u"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, u=_bins(3, 2, 2)), ValueError, "u"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, u=torch.tensor([0.5, 0.2])), ValueError, "u"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, u=torch.tensor([0.5, 1.5])), ValueError, "u"),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, u=torch.tensor([0, 1])), TypeError, "u"),
    (
        lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, u=torch.tensor([0.2, 0.5]), deterministic=True),
        ValueError,
        "u",
    ),
    (lambda: sample_pdf(_bins(3, 5), torch.rand(3, 4), 2, backend="cuda"), ValueError, "backend"),
    (lambda: sample_pdf([[0.0, 1.0]], torch.rand(1, 1), 2), TypeError, "bins"),
    (lambda: hierarchical_samples(_bins(3, 2), torch.rand(3, 2), 2), ValueError, "z_coarse"),
    (lambda: hierarchical_samples(_bins(3, 6), torch.rand(3, 5), 2), ValueError, "weights_coarse"),
    (lambda: hierarchical_samples(_bins(3, 6)[0], torch.rand(6), 2), ValueError, "z_coarse"),
    (lambda: hierarchical_samples(_bins(3, 6).flip(-1), torch.rand(3, 6), 2), ValueError, "z_coarse"),
    (lambda: hierarchical_samples(_bins(3, 6), -torch.rand(3, 6), 2), ValueError, "weights_coarse"),
    (lambda: hierarchical_samples(_bins(3, 6), torch.rand(3, 6).half(), 2), TypeError, "weights_coarse"),
    (lambda: hierarchical_samples(_bins(3, 6), torch.rand(3, 6), -2), ValueError, "num_fine"),
    (lambda: hierarchical_samples(_bins(3, 6), torch.rand(3, 6), 2, u=torch.rand(3, 3)), ValueError, "u"),
]


@pytest.mark.parametrize("call,error,name", BAD_SAMPLE_PDF)
def test_bad_input(call, error, name):
    with pytest.raises(error, match=name):
        call()


# ---------------------------------------------------------------------------------------------
# CUDA: kernel against the CPU kernel and the reference, forward and gradients


@cuda
@needs_cuda
def test_cuda_rejects_mixed_devices():
    dev = torch.device("cuda")
    with pytest.raises(ValueError, match="weights"):
        sample_pdf(_bins(3, 5).to(dev), torch.rand(3, 4), 2)
    with pytest.raises(ValueError, match="u"):
        sample_pdf(_bins(3, 5).to(dev), torch.rand(3, 4, device=dev), 2, u=torch.tensor([0.1, 0.2]))
    with pytest.raises(ValueError, match="weights_coarse"):
        hierarchical_samples(_bins(3, 6).to(dev), torch.rand(3, 6), 2)
    with pytest.raises(ValueError, match="generator"):
        sample_pdf(_bins(3, 5).to(dev), torch.rand(3, 4, device=dev), 2, generator=torch.Generator())


def _poisoned(*specs):
    """Fill the CUDA caching allocator with NaN blocks of the (shape, dtype)s the op allocates,
    in its allocation order, so an output element a kernel forgets to write reads back as NaN.
    The cache is emptied first, so the op's allocations reuse exactly these blocks; the caller
    asserts its outputs landed at the returned addresses, which proves the poison was there."""
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    blocks = [torch.full(shape, float("nan"), dtype=dtype, device="cuda") for shape, dtype in specs]
    addresses = {b.data_ptr() for b in blocks}
    del blocks
    return addresses


CUDA_SHAPES = [(1, 1, 1), (1, 63, 128), (3, 31, 33), (1000, 37, 5), (65536, 62, 128), (0, 4, 3)]


@cuda
@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", CUDA_SHAPES, ids=lambda s: "x".join(map(str, s)))
def test_cuda_forward_and_grads(shape, dtype):
    R, B, N = shape
    dev = torch.device("cuda")
    bins, weights = random_pdf(R, B, dtype, device=dev)
    u = sorted_u(R, N, dtype, device=dev)
    addresses = _poisoned(((R, N), dtype))
    samples = torch.ops.mixer_nerf.sample_pdf_fwd(bins, weights, u, 0.0)
    assert R * N == 0 or samples.data_ptr() in addresses
    assert_valid_samples(samples, bins)
    cpu = torch.ops.mixer_nerf.sample_pdf_fwd(bins.cpu(), weights.cpu(), u.cpu(), 0.0)
    # same sequential CDF as the CPU kernel; only FMA contraction differs (a few ulp)
    torch.testing.assert_close(samples.cpu(), cpu, atol=1e-6 if dtype == torch.float32 else 1e-14, rtol=0)
    torch.testing.assert_close(samples, reference_samples(bins, weights, u), atol=tolerance(dtype, B), rtol=0)

    grad = torch.randn(R, N, dtype=dtype, device=dev)
    addresses = _poisoned((bins.shape, dtype), (weights.shape, dtype))
    grad_bins, grad_weights = torch.ops.mixer_nerf.sample_pdf_bwd(grad, bins, weights, u, 0.0)
    assert R == 0 or {grad_bins.data_ptr(), grad_weights.data_ptr()} <= addresses
    assert torch.isfinite(grad_bins).all() and torch.isfinite(grad_weights).all()
    cpu_grads = torch.ops.mixer_nerf.sample_pdf_bwd(grad.cpu(), bins.cpu(), weights.cpu(), u.cpu(), 0.0)
    for got, want in zip((grad_bins, grad_weights), cpu_grads, strict=True):
        scale = max(want.abs().max().item(), 1.0) if want.numel() else 1.0
        torch.testing.assert_close(got.cpu(), want, atol=grad_tolerance(dtype) * scale, rtol=0)
    if R <= 1000:
        ref = _reference_grads(bins, weights, u, upstream=grad)
        for got, want in zip((grad_bins, grad_weights), ref, strict=True):
            scale = max(want.abs().max().item(), 1.0) if want.numel() else 1.0
            torch.testing.assert_close(got, want, atol=grad_tolerance(dtype) * scale, rtol=0)


@cuda
@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
@pytest.mark.parametrize(
    "shape",
    [(1, 3, 1), (5, 64, 128), (3, 33, 31), (65536, 64, 128), (0, 5, 2), (7, 200, 300)],
    ids=lambda s: "x".join(map(str, s)),
)
@pytest.mark.parametrize("shared_u", [False, True])
def test_cuda_hierarchical(shape, dtype, shared_u):
    R, S, N = shape
    dev = torch.device("cuda")
    z, weights = random_coarse(R, S, dtype, device=dev)
    u = sorted_u(1, N, dtype, device=dev)[0] if shared_u else sorted_u(R, N, dtype, device=dev)
    addresses = _poisoned(((R, S + N), dtype))
    merged = torch.ops.mixer_nerf.hierarchical_samples_fwd(z, weights, u, 0.0)[0]
    assert R == 0 or merged.data_ptr() in addresses
    assert_valid_samples(merged, z)
    cpu = torch.ops.mixer_nerf.hierarchical_samples_fwd(z.cpu(), weights.cpu(), u.cpu(), 0.0)[0]
    atol = {torch.float32: 1e-6, torch.float64: 1e-14, torch.float16: 4e-3}[dtype]
    torch.testing.assert_close(merged.cpu(), cpu, atol=atol, rtol=0)
    if R <= 1000:
        torch.testing.assert_close(
            merged, reference_merged(z, weights, u), atol=tolerance(dtype, S, scale=8), rtol=0
        )


@cuda
@needs_cuda
def test_cuda_adversarial():
    dev = torch.device("cuda")
    cases = [
        (torch.tensor([[0.0, 1.0, 2.0, 6.0]]), torch.zeros(1, 3)),
        (torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]]), torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0]])),
        (torch.tensor([[0.0, 0.0, 1.0, 1.0, 1.0, 2.0]]), torch.tensor([[1.0, 1.0, 3.0, 0.0, 1.0]])),
        (torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0]]), torch.tensor([[0.0, 2.0, 1.0, 0.0]])),
        (torch.tensor([[2.0, 4.0]]), torch.tensor([[0.7]])),
        (torch.tensor([[0.0, 1.0, 2.0, 3.0]]), torch.full((1, 3), 3e38)),
        (torch.tensor([[0.0, 1.0, 2.0, 3.0]]), torch.full((1, 3), 1e-39)),
    ]
    for bins, weights in cases:
        for u in (U_WITH_ENDS, torch.tensor([1.0]), torch.tensor([0.0])):
            gpu = sample_pdf(bins.to(dev), weights.to(dev), u.numel(), u=u.to(dev), backend="kernel")
            cpu = sample_pdf(bins, weights, u.numel(), u=u, backend="kernel")
            torch.testing.assert_close(gpu.cpu(), cpu, rtol=0, atol=1e-6)
            cpu_grads = _grads("kernel", bins, weights, u)
            for got, want in zip(
                _grads("kernel", bins.to(dev), weights.to(dev), u.to(dev)), cpu_grads, strict=True
            ):
                assert torch.isfinite(got).all()
                torch.testing.assert_close(got.cpu(), want, rtol=1e-5, atol=1e-5)
            if bins.shape[1] >= 3:  # as coarse depths: S >= 3
                coarse_w = torch.cat([weights[:, :1], weights], dim=-1)
                gpu = hierarchical_samples(
                    bins.to(dev), coarse_w.to(dev), u.numel(), u=u.to(dev), backend="kernel"
                )
                cpu = hierarchical_samples(bins, coarse_w, u.numel(), u=u, backend="kernel")
                torch.testing.assert_close(gpu.cpu(), cpu, rtol=0, atol=1e-6)


@cuda
@needs_cuda
def test_cuda_opcheck():
    dev = torch.device("cuda")
    bins, weights = random_pdf(5, 7, device=dev)
    u = sorted_u(5, 9, device=dev)
    opcheck(torch.ops.mixer_nerf.sample_pdf_fwd.default, (bins, weights, u, 0.0))
    opcheck(
        torch.ops.mixer_nerf.sample_pdf_bwd.default, (torch.randn(5, 9, device=dev), bins, weights, u, 0.0)
    )
    z, coarse_weights = random_coarse(5, 8, device=dev)
    opcheck(torch.ops.mixer_nerf.hierarchical_samples_fwd.default, (z, coarse_weights, u, 0.0))


def _stratified_u(R: int, N: int, generator: torch.Generator, device: torch.device,
                  dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The Python path's stratified positions: (n + U[0, 1)) / N from torch.rand."""
    jitter = torch.rand(R, N, generator=generator, device=device, dtype=dtype)
    return (torch.arange(N, device=device, dtype=dtype) + jitter) / N


def test_stratified_kernel_draws_the_stream_torch_rand_draws_on_the_cpu():
    if not use_kernel("auto", torch.device("cpu")):
        pytest.skip("no CPU kernels")
    z, weights = random_coarse(33, 17)
    seed = torch.seed()
    drawn = hierarchical_samples(z, weights, 40, generator=torch.Generator().manual_seed(seed), backend="kernel")
    u = _stratified_u(33, 40, torch.Generator().manual_seed(seed), z.device)
    assert torch.equal(drawn, hierarchical_samples(z, weights, 40, u=u, backend="kernel"))


@cuda
@needs_cuda
def test_cuda_stratified_positions_are_drawn_in_the_kernel():
    dev = torch.device("cuda")
    R, S, N = 65536, 64, 128
    z, weights = random_coarse(R, S, device=dev)
    seed = torch.seed()
    first = hierarchical_samples(z, weights, N, generator=torch.Generator(dev).manual_seed(seed))
    again = hierarchical_samples(z, weights, N, generator=torch.Generator(dev).manual_seed(seed))
    assert torch.equal(first, again)  # the generator's seed decides the draws
    gen = torch.Generator(dev).manual_seed(seed)
    assert not torch.equal(hierarchical_samples(z, weights, N, generator=gen),
                           hierarchical_samples(z, weights, N, generator=gen))  # and its offset advances
    assert_valid_samples(first, z)
    # Each fine sample lies in its stratum: between the samples at u = n/N and u = (n+1)/N (a
    # sorted union is monotone in its members, so the merged rows are bounded the same way).
    strata = torch.arange(N, device=dev, dtype=torch.float32)
    low = hierarchical_samples(z, weights, N, u=strata / N)
    high = hierarchical_samples(z, weights, N, u=(strata + 1) / N)
    assert (low <= first).all() and (first <= high).all()
    # Spread over the strata, not stuck at an end: where a stratum has width, the sample's place
    # in it averages about 1/2 (the merge can swap a fine sample with a coarse one, hence the slack).
    wide = high - low > 1e-4
    place = ((first - low) / (high - low))[wide]
    assert wide.float().mean() > 0.5 and abs(place.mean().item() - 0.5) < 0.05 and place.std().item() > 0.2
    for dtype in (torch.float64, torch.float16):
        zd, wd = random_coarse(257, S, dtype, device=dev)
        assert_valid_samples(hierarchical_samples(zd, wd, N), zd)


@cuda
@needs_cuda
@pytest.mark.parametrize("op, inputs", [(hierarchical_samples, random_coarse), (sample_pdf, random_pdf)],
                         ids=["hierarchical_samples", "sample_pdf"])
def test_cuda_stratified_sampling_replays_in_a_graph_with_fresh_draws(op, inputs):
    dev = torch.device("cuda")
    edges, weights = inputs(1024, 64, device=dev)
    op(edges, weights, 128)  # warm-up outside the capture
    graph, stream = torch.cuda.CUDAGraph(), torch.cuda.Stream()
    with torch.cuda.stream(stream), torch.cuda.graph(graph):
        out = op(edges, weights, 128)
    graph.replay()
    first = out.clone()
    graph.replay()
    torch.cuda.synchronize()
    assert not torch.equal(first, out)
    assert_valid_samples(out, edges)
    assert_valid_samples(first, edges)


# ---------------------------------------------------------------------------------------------
# Packed bins: sample_pdf_packed


def pack_pdf(bins, weights, counts):
    """Dense (R, B+1) edges and (R, B) weights -> packed: ray r keeps its first counts[r] bins and
    counts[r] + 1 edges. Returns bins (N + R,), weights (N,), offsets (R+1,)."""
    slots = torch.arange(bins.shape[1], device=bins.device)
    counts = counts.to(bins.device)
    packed_bins = bins[slots <= counts[:, None]]
    packed_weights = weights[slots[:-1] < counts[:, None]]
    offsets = torch.nn.functional.pad(counts.cumsum(0), (1, 0))
    return packed_bins.contiguous(), packed_weights.contiguous(), offsets


def random_packed_pdf(counts, dtype=torch.float32, device=CPU, **kwargs):
    counts = torch.as_tensor(counts, dtype=torch.int64)
    width = max(int(counts.max()) if counts.numel() else 0, 1)
    return pack_pdf(*random_pdf(counts.numel(), width, dtype, device, **kwargs), counts)


def packed_reference_samples(bins, weights, offsets, u, weight_padding=0.0):
    return sample_pdf_packed_reference(
        bins.double(), weights.double(), offsets, u.double(), weight_padding
    ).to(bins.dtype)


def _packed_grads(backend, bins, weights, offsets, u, upstream):
    bins = bins.detach().clone().requires_grad_()
    weights = weights.detach().clone().requires_grad_()
    out = sample_pdf_packed(bins, weights, offsets, u.shape[-1], u=u, backend=backend)
    return torch.autograd.grad(out, (bins, weights), upstream, allow_unused=True)


PACKED_COUNTS = {
    "one ray": [5],
    "one bin": [1],
    "no bins": [0],
    "ragged": [3, 0, 7, 1, 0, 12, 40],
    "no rays": [],
    "many": list(range(0, 70, 3)),
}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("counts", list(PACKED_COUNTS))
@pytest.mark.parametrize("shared_u", [False, True])
def test_packed_matches_reference(dtype, counts, shared_u):
    counts = torch.tensor(PACKED_COUNTS[counts], dtype=torch.int64)
    R, N = counts.numel(), 17
    bins, weights, offsets = random_packed_pdf(counts, dtype)
    u = sorted_u(1, N, dtype)[0] if shared_u else sorted_u(R, N, dtype)
    ours = sample_pdf_packed(bins, weights, offsets, N, u=u, backend="kernel")
    assert ours.shape == (R, N) and ours.dtype == dtype
    width = int(counts.max()) if R else 1
    want = packed_reference_samples(bins, weights, offsets, u)
    torch.testing.assert_close(ours, want, atol=tolerance(dtype, width), rtol=0)
    upstream = torch.randn(R, N, dtype=dtype)
    got = _packed_grads("kernel", bins, weights, offsets, u, upstream)
    want = _packed_grads("torch", bins.double(), weights.double(), offsets, u.double(), upstream.double())
    for g, w in zip(got, want, strict=True):
        scale = max(w.abs().max().item(), 1.0) if w.numel() else 1.0
        torch.testing.assert_close(g.double(), w, atol=grad_tolerance(dtype) * scale, rtol=0)


@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_packed_equals_dense_when_rays_have_B_bins(backend):
    """The same per-ray sampling: the CPU kernel is bit-identical in both layouts."""
    R, B, N = 6, 9, 13
    bins, weights = random_pdf(R, B, torch.float64)
    u = sorted_u(R, N, torch.float64)
    packed = pack_pdf(bins, weights, torch.full((R,), B))
    upstream = torch.randn(R, N, dtype=torch.float64)
    dense_out = sample_pdf(bins, weights, N, u=u, backend=backend)
    packed_out = sample_pdf_packed(*packed, N, u=u, backend=backend)
    dense_grads = _grads(backend, bins, weights, u, upstream=upstream)
    packed_grads = _packed_grads(backend, *packed, u, upstream)
    pairs = [
        (packed_out, dense_out),
        (packed_grads[0].reshape(R, B + 1), dense_grads[0]),
        (packed_grads[1].reshape(R, B), dense_grads[1]),
    ]
    for got, want in pairs:
        assert (
            torch.equal(got, want)
            if backend == "kernel"
            else torch.allclose(got, want, rtol=1e-13, atol=1e-15)
        )


@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_packed_ray_without_bins_samples_its_edge(backend):
    bins = torch.tensor([0.0, 1.0, 2.0, 5.0, 7.0, 9.0], dtype=torch.float64)  # rays: [0,1,2] [5] [7,9]
    weights = torch.tensor([1.0, 3.0, 0.0], dtype=torch.float64)
    offsets = torch.tensor([0, 2, 2, 3])
    samples = sample_pdf_packed(bins, weights, offsets, 4, deterministic=True, backend=backend)
    assert torch.equal(samples[1], torch.full((4,), 5.0, dtype=torch.float64))
    torch.testing.assert_close(
        samples[2], 7 + 2 * (torch.arange(4, dtype=torch.float64) + 0.5) / 4
    )  # uniform
    upstream = torch.randn(3, 4, dtype=torch.float64)
    u = ((torch.arange(4) + 0.5) / 4).double()
    grad_bins, grad_weights = _packed_grads(backend, bins, weights, offsets, u, upstream)
    torch.testing.assert_close(grad_bins[3], upstream[1].sum())
    assert grad_weights[2] == 0


@pytest.mark.parametrize("counts", [[2, 0, 3, 1], [5]])
def test_packed_gradcheck_cpu_kernel(counts):
    bins, weights, offsets = random_packed_pdf(counts, torch.float64, zero_fraction=0.0)
    u = sorted_u(len(counts), 4, torch.float64)
    torch.autograd.gradcheck(
        lambda b, w: sample_pdf_packed(b, w, offsets, 4, u=u, weight_padding=0.01, backend="kernel"),
        (bins.requires_grad_(), weights.requires_grad_()),
    )


def test_packed_adversarial():
    """The dense adversarial PDFs (all-zero, one-hot, zero-width bins, overflowing and subnormal
    weights) side by side with other rays in one packed batch."""
    cases = [
        ([0.0, 1.0, 2.0, 6.0], [0.0, 0.0, 0.0]),
        ([0.0, 1.0, 2.0, 3.0, 4.0, 5.0], [0.0, 0.0, 1.0, 0.0, 0.0]),
        ([0.0, 0.0, 1.0, 1.0, 1.0, 2.0], [1.0, 1.0, 3.0, 0.0, 1.0]),
        ([2.0, 4.0], [0.7]),
        ([0.0, 1.0, 2.0, 3.0], [3e38] * 3),
        ([0.0, 1.0, 2.0, 3.0], [1e-39] * 3),
        ([3.0], []),
    ]
    bins = torch.tensor([e for edges, _ in cases for e in edges])
    weights = torch.tensor([w for _, ws in cases for w in ws])
    offsets = torch.nn.functional.pad(torch.tensor([len(ws) for _, ws in cases]).cumsum(0), (1, 0))
    for u in (U_WITH_ENDS, torch.tensor([1.0]), torch.tensor([0.0])):
        ours = sample_pdf_packed(bins, weights, offsets, u.numel(), u=u, backend="kernel")
        assert torch.isfinite(ours).all()
        torch.testing.assert_close(
            ours, packed_reference_samples(bins, weights, offsets, u), atol=1e-6, rtol=0
        )
        upstream = torch.randn(len(cases), u.numel())
        for g in _packed_grads("kernel", bins, weights, offsets, u, upstream):
            assert torch.isfinite(g).all()


def test_packed_unchecked_bad_offsets_stay_in_bounds():
    bins, weights, _ = random_packed_pdf([3, 2])
    for bad in ([0, 100, 5], [-7, 2, 5], [0, 4, 2], [3, 1, 0]):
        out = sample_pdf_packed(
            bins, weights, torch.tensor(bad), 4, deterministic=True, backend="kernel", check_values=False
        )
        assert torch.isfinite(out).all()


def _valid_packed():
    """bins, weights, offsets for rays of 2, 0 and 3 bins."""
    return [torch.tensor([0.0, 0.5, 1.0, 2.0, 0.0, 1.0, 2.0, 3.0]), torch.rand(5), torch.tensor([0, 2, 2, 5])]


@pytest.mark.parametrize(
    "index, bad, error, name",
    [
        (0, torch.rand(8, 1), ValueError, "bins"),
        (0, torch.arange(9.0), ValueError, "bins"),
        (0, torch.tensor([0.0, 0.5, 0.2, 2.0, 0.0, 1.0, 2.0, 3.0]), ValueError, "bins"),
        (1, torch.rand(5, 1), ValueError, "weights"),
        (1, -torch.rand(5), ValueError, "weights"),
        (1, torch.rand(5, dtype=torch.float64), TypeError, "weights"),
        (0, torch.arange(8), TypeError, "bins"),
        (2, torch.tensor([0, 2, 2, 5], dtype=torch.int32), TypeError, "offsets"),
        (2, [0, 2, 2, 5], TypeError, "offsets"),
        (2, torch.tensor([[0, 2, 2, 5]]), ValueError, "offsets"),
        (2, torch.tensor([0, 2, 2, 4]), ValueError, "offsets"),
        (2, torch.tensor([0, 3, 2, 5]), ValueError, "offsets"),
        (2, torch.tensor([0, 2, 2, 5], device="meta"), ValueError, "offsets"),
    ],
)
@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_packed_bad_input(index, bad, error, name, backend):
    args = _valid_packed()
    args[index] = bad
    with pytest.raises(error, match=name):
        sample_pdf_packed(*args, 3, deterministic=True, backend=backend)


def test_packed_bad_u():
    with pytest.raises(ValueError, match="u"):
        sample_pdf_packed(*_valid_packed(), 3, u=torch.rand(2, 3))


def test_packed_opcheck():
    bins, weights, offsets = random_packed_pdf([3, 0, 5, 1])
    for u in (sorted_u(4, 6), sorted_u(1, 6)[0]):
        opcheck(torch.ops.mixer_nerf.sample_pdf_packed_fwd.default, (bins, weights, offsets, u, 0.0))
        grad = torch.randn(4, 6)
        opcheck(torch.ops.mixer_nerf.sample_pdf_packed_bwd.default, (grad, bins, weights, offsets, u, 0.0))


@cuda
@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "R, max_bins, N", [(1, 1, 1), (7, 40, 33), (50, 70, 5), (3, 300, 64), (0, 4, 3), (65536, 64, 128)]
)
def test_packed_cuda_forward_and_grads(dtype, R, max_bins, N):
    dev = torch.device("cuda")
    counts = torch.randint(0, max_bins + 1, (R,))
    if R > 2:
        counts[0], counts[1] = max_bins, 0
    bins, weights, offsets = random_packed_pdf(counts, dtype, device=dev)
    u = sorted_u(R, N, dtype, device=dev)
    # Poisoned outputs (see _poisoned): the op allocates them before any temporary.
    addresses = _poisoned(((R, N), dtype))
    samples = torch.ops.mixer_nerf.sample_pdf_packed_fwd(bins, weights, offsets, u, 0.0)
    assert R * N == 0 or samples.data_ptr() in addresses
    assert torch.isfinite(samples).all()
    cpu = torch.ops.mixer_nerf.sample_pdf_packed_fwd(bins.cpu(), weights.cpu(), offsets.cpu(), u.cpu(), 0.0)
    torch.testing.assert_close(samples.cpu(), cpu, atol=1e-6 if dtype == torch.float32 else 1e-14, rtol=0)

    grad = torch.randn(R, N, dtype=dtype, device=dev)
    addresses = _poisoned((bins.shape, dtype), (weights.shape, dtype))
    grad_bins, grad_weights = torch.ops.mixer_nerf.sample_pdf_packed_bwd(grad, bins, weights, offsets, u, 0.0)
    assert R == 0 or {grad_bins.data_ptr(), grad_weights.data_ptr()} <= addresses
    assert torch.isfinite(grad_bins).all() and torch.isfinite(grad_weights).all()
    cpu_grads = torch.ops.mixer_nerf.sample_pdf_packed_bwd(
        grad.cpu(), bins.cpu(), weights.cpu(), offsets.cpu(), u.cpu(), 0.0
    )
    for got, want in zip((grad_bins, grad_weights), cpu_grads, strict=True):
        scale = max(want.abs().max().item(), 1.0) if want.numel() else 1.0
        torch.testing.assert_close(got.cpu(), want, atol=grad_tolerance(dtype) * scale, rtol=0)


@cuda
@needs_cuda
def test_packed_cuda_adversarial_and_opcheck():
    dev = torch.device("cuda")
    bins, weights, offsets = random_packed_pdf([0, 3, 0, 40, 1], device=dev)
    weights[3:6] = 0.0
    weights[10:12] = 3e38
    u = U_WITH_ENDS.to(dev)
    for layout in ((bins, weights, offsets), (bins.cpu(), weights.cpu(), offsets.cpu())):
        assert torch.isfinite(
            sample_pdf_packed(*layout, u.numel(), u=u.to(layout[0].device), backend="kernel")
        ).all()
    gpu = _packed_grads("kernel", bins, weights, offsets, u, torch.ones(5, u.numel(), device=dev))
    cpu = _packed_grads("kernel", bins.cpu(), weights.cpu(), offsets.cpu(), u.cpu(), torch.ones(5, u.numel()))
    for g, c in zip(gpu, cpu, strict=True):
        torch.testing.assert_close(g.cpu(), c, atol=1e-4 * max(c.abs().max().item(), 1.0), rtol=0)
    opcheck(
        torch.ops.mixer_nerf.sample_pdf_packed_fwd.default,
        (bins, weights, offsets, sorted_u(5, 6, device=dev), 0.0),
    )
    grad = torch.randn(5, 6, device=dev)
    opcheck(
        torch.ops.mixer_nerf.sample_pdf_packed_bwd.default,
        (grad, bins, weights, offsets, sorted_u(5, 6, device=dev), 0.0),
    )


# ---------------------------------------------------------------------------------------------
# Stratified positions drawn by the op (the default call): sample_pdf_stratified_fwd and
# sample_pdf_packed_stratified_fwd


def _draw(bins, weights, N, generator, offsets=None, weight_padding=0.0, keep_positions=True):
    """samples, u, invalid of the stratified op of the layout (packed if offsets are given)."""
    if offsets is None:
        return torch.ops.mixer_nerf.sample_pdf_stratified_fwd(bins, weights, N, generator, weight_padding,
                                                              keep_positions)
    return torch.ops.mixer_nerf.sample_pdf_packed_stratified_fwd(bins, weights, offsets, N, generator,
                                                                 weight_padding, keep_positions)


def _given(bins, weights, u, offsets=None, weight_padding=0.0):
    """The given-positions op of the layout."""
    if offsets is None:
        return torch.ops.mixer_nerf.sample_pdf_fwd(bins, weights, u, weight_padding)
    return torch.ops.mixer_nerf.sample_pdf_packed_fwd(bins, weights, offsets, u, weight_padding)


def assert_stratified(u, N):
    """One position per stratum: u_n = (n + xi) / N in [n / N, (n + 1) / N), hence sorted. Its
    upper end only by rounding: n + xi rounds to n + 1 for xi within half an ulp of n below 1."""
    strata = torch.arange(N, dtype=u.dtype, device=u.device)
    assert ((u >= strata / N) & (u <= (strata + 1) / N)).all()
    assert (u[:, 1:] >= u[:, :-1]).all()
    if u.numel() >= 1000:
        assert (u < (strata + 1) / N).float().mean() > 0.99


def _random_layout(layout, R, B, dtype, device=CPU):
    """bins, weights, offsets (None for dense) of R random rays of up to B bins."""
    if layout == "dense":
        return (*random_pdf(R, B, dtype, device), None)
    counts = torch.randint(0, B + 1, (R,))
    return random_packed_pdf(counts, dtype, device)


@pytest.mark.parametrize("layout", ["dense", "packed"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 1, 1), (5, 1, 7), (0, 4, 3), (6, 5, 0), (40, 63, 128), (17, 37, 45)])
def test_stratified_op_matches_reference_on_the_positions_it_drew(layout, dtype, shape):
    R, B, N = shape
    seed = int(torch.randint(2**31, ()).item())
    print(f"seed={seed}")
    torch.manual_seed(seed)
    bins, weights, offsets = _random_layout(layout, R, B, dtype)
    samples, u, invalid = _draw(bins, weights, N, torch.Generator().manual_seed(seed), offsets)
    assert samples.shape == (R, N) and samples.dtype == dtype
    assert u.shape == (R, N) and u.dtype == accumulation_dtype(dtype)
    assert invalid.dtype == torch.int32 and int(invalid) == 0
    assert_stratified(u, N)
    # On the CPU the positions are the Python path's, bit for bit: torch.rand's stream.
    assert torch.equal(u, _stratified_u(R, N, torch.Generator().manual_seed(seed), CPU, u.dtype))
    assert torch.equal(samples, _given(bins, weights, u, offsets))
    unkept = _draw(bins, weights, N, torch.Generator().manual_seed(seed), offsets, keep_positions=False)
    assert torch.equal(unkept[0], samples) and unkept[1].shape == (R, 0)
    want = (reference_samples(bins, weights, u) if offsets is None
            else packed_reference_samples(bins, weights, offsets, u))
    torch.testing.assert_close(samples, want, atol=tolerance(dtype, B), rtol=0)

    # The default call: these samples, and gradients through the positions drawn.
    pdf = [bins.clone().requires_grad_(), weights.clone().requires_grad_()]
    call = sample_pdf if offsets is None else functools.partial(sample_pdf_packed, offsets=offsets)
    ours = call(*pdf, num_samples=N, generator=torch.Generator().manual_seed(seed), backend="kernel")
    assert torch.equal(ours, samples)
    upstream = torch.randn(R, N, dtype=dtype)
    grads = torch.autograd.grad(ours, pdf, upstream, allow_unused=True)
    if offsets is None:
        want = _reference_grads(bins, weights, u, upstream=upstream)
    else:
        as_double = (bins.double(), weights.double(), offsets, u.double(), upstream.double())
        want = [g.to(dtype) for g in _packed_grads("torch", *as_double)]
    for got, expected in zip(grads, want, strict=True):
        if got is None:  # no samples: no gradient
            assert N == 0 or R == 0
            continue
        scale = expected.abs().max().item() if expected.numel() else 1.0
        torch.testing.assert_close(got, expected, atol=grad_tolerance(dtype) * max(scale, 1.0), rtol=0)


@pytest.mark.parametrize("layout", ["dense", "packed"])
def test_stratified_gradcheck(layout):
    seed = int(torch.randint(2**31, ()).item())
    bins, weights, offsets = _random_layout(layout, 4, 6, torch.float64)
    weights = weights + 0.1  # no empty bin: finite differences across a flat stretch of the CDF jump
    call = sample_pdf if offsets is None else functools.partial(sample_pdf_packed, offsets=offsets)

    def draw(b, w):  # the same positions at every evaluation
        return call(b, w, num_samples=5, generator=torch.Generator().manual_seed(seed), weight_padding=0.01,
                    backend="kernel")

    torch.autograd.gradcheck(draw, (bins.requires_grad_(), weights.requires_grad_()))


def test_stratified_seed_decides_the_draws():
    bins, weights = random_pdf(33, 12)
    seed = torch.seed()
    first = sample_pdf(bins, weights, 40, generator=torch.Generator().manual_seed(seed), backend="kernel")
    again = sample_pdf(bins, weights, 40, generator=torch.Generator().manual_seed(seed), backend="kernel")
    assert torch.equal(first, again)
    gen = torch.Generator().manual_seed(seed)
    assert not torch.equal(sample_pdf(bins, weights, 40, generator=gen, backend="kernel"),
                           sample_pdf(bins, weights, 40, generator=gen, backend="kernel"))  # it advances
    torch.manual_seed(seed)  # generator=None: torch's default generator of the device
    default = sample_pdf(bins, weights, 40, backend="kernel")
    assert torch.equal(default, first)


def test_stratified_adversarial_pdfs():
    """Zero weights, one bin, tiny and huge weights, and a NaN weight (its ray samples NaN and gets
    NaN gradients; the other rays are untouched), through the positions the op drew."""
    bins = torch.tensor([[0.0, 1.0, 2.0, 6.0], [0.0, 1.0, 2.0, 6.0], [0.0, 1.0, 2.0, 6.0],
                         [0.0, 1.0, 2.0, 6.0], [-1.0, -1.0, -1.0, -1.0]], dtype=torch.float64)
    weights = torch.tensor([[0.0, 0.0, 0.0], [1e-300, 0.0, 1e-300], [1e300, 1.0, 1e300],
                            [1.0, float("nan"), 1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    samples, u, invalid = _draw(bins, weights, 9, torch.Generator().manual_seed(1))
    assert int(invalid) == 0  # NaN is not negative: the documented NaN rows, not an error
    want = reference_samples(bins, weights, u)
    torch.testing.assert_close(samples, want, rtol=0, atol=1e-12, equal_nan=True)
    torch.testing.assert_close(samples[0], 6 * u[0])  # no PDF: uniform over the ray
    assert samples[3].isnan().all() and not samples[[0, 1, 2, 4]].isnan().any()
    assert (samples[4] == -1).all()
    single = _draw(torch.tensor([[2.0, 4.0]]), torch.tensor([[0.7]]), 3, torch.Generator().manual_seed(2))
    torch.testing.assert_close(single[0], 2 + 2 * single[1])
    pdf = [bins.clone().requires_grad_(), weights.clone().requires_grad_()]
    out = sample_pdf(*pdf, 9, generator=torch.Generator().manual_seed(1), backend="kernel")
    grad_bins, grad_weights = torch.autograd.grad(out.nan_to_num().sum() + out[3].sum(), pdf)
    assert grad_bins[3].isnan().all() and grad_weights[3].isnan().all()
    assert grad_bins[[0, 1, 2, 4]].isfinite().all() and grad_weights[[0, 1, 2, 4]].isfinite().all()


def test_stratified_opcheck():
    bins, weights = random_pdf(5, 7)
    # Each call draws afresh, so only the checks that compare no two calls' values.
    utils = ("test_schema", "test_faketensor")
    packed = random_packed_pdf([3, 0, 5, 1])
    for keep in (True, False):
        opcheck(torch.ops.mixer_nerf.sample_pdf_stratified_fwd.default, (bins, weights, 9, None, 0.0, keep),
                test_utils=utils)
        opcheck(torch.ops.mixer_nerf.sample_pdf_packed_stratified_fwd.default, (*packed, 6, None, 0.0, keep),
                test_utils=utils)


@cuda
@needs_cuda
@pytest.mark.parametrize("layout", ["dense", "packed"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
@pytest.mark.parametrize(
    "shape",
    [(1, 1, 1), (3, 31, 33), (1000, 37, 5), (65536, 62, 128), (0, 4, 3), (6, 5, 0)],
    ids=lambda s: "x".join(map(str, s)),
)
def test_cuda_stratified_op_matches_the_cpu_op_on_its_positions(layout, dtype, shape):
    R, B, N = shape
    dev = torch.device("cuda")
    bins, weights, offsets = _random_layout(layout, R, B, dtype, dev)
    # Poisoned outputs (see _poisoned): an element the kernel forgets to write reads back as NaN.
    addresses = _poisoned(((R, N), dtype), ((R, N), accumulation_dtype(dtype)))
    samples, u, invalid = _draw(bins, weights, N, None, offsets)
    assert R * N == 0 or {samples.data_ptr(), u.data_ptr()} <= addresses
    assert samples.isfinite().all() and u.isfinite().all()
    assert samples.shape == (R, N) and samples.dtype == dtype and u.dtype == accumulation_dtype(dtype)
    assert int(invalid) == 0
    assert_stratified(u, N)
    unkept = _draw(bins, weights, N, torch.Generator(dev).manual_seed(3), offsets, keep_positions=False)
    kept = _draw(bins, weights, N, torch.Generator(dev).manual_seed(3), offsets)
    assert torch.equal(unkept[0], kept[0]) and unkept[1].shape == (R, 0)
    to_cpu = [None if t is None else t.cpu() for t in (bins, weights, u, offsets)]
    cpu = _given(*to_cpu[:3], to_cpu[3])
    atol = {torch.float32: 1e-6, torch.float64: 1e-14, torch.float16: 1e-3}[dtype]  # FMA on the GPU
    torch.testing.assert_close(samples.cpu(), cpu, atol=atol, rtol=0)
    # The backward takes the positions drawn: the default call's gradients are the CPU op's on u.
    pdf = [bins.clone().requires_grad_(), weights.clone().requires_grad_()]
    call = sample_pdf if offsets is None else functools.partial(sample_pdf_packed, offsets=offsets)
    gen = torch.Generator(dev).manual_seed(7)
    out = call(*pdf, num_samples=N, generator=gen)
    u = _draw(bins, weights, N, torch.Generator(dev).manual_seed(7), offsets)[1]
    upstream = torch.randn(R, N, dtype=dtype, device=dev)
    if not out.numel():
        return
    grads = torch.autograd.grad(out, pdf, upstream)
    ops = torch.ops.mixer_nerf
    backward = ops.sample_pdf_bwd if offsets is None else ops.sample_pdf_packed_bwd
    layout_args = () if offsets is None else (offsets.cpu(),)
    want = backward(upstream.cpu(), bins.cpu(), weights.cpu(), *layout_args, u.cpu(), 0.0)
    for got, expected in zip(grads, want, strict=True):
        scale = max(expected.abs().max().item(), 1.0) if expected.numel() else 1.0
        torch.testing.assert_close(got.cpu(), expected, atol=grad_tolerance(dtype) * scale, rtol=0)


@cuda
@needs_cuda
def test_cuda_stratified_sample_pdf_is_reproducible_and_spread():
    dev = torch.device("cuda")
    R, B, N = 65536, 63, 128
    bins, weights = random_pdf(R, B, device=dev)
    seed = torch.seed()
    first = sample_pdf(bins, weights, N, generator=torch.Generator(dev).manual_seed(seed))
    again = sample_pdf(bins, weights, N, generator=torch.Generator(dev).manual_seed(seed))
    assert torch.equal(first, again)
    gen = torch.Generator(dev).manual_seed(seed)
    assert not torch.equal(sample_pdf(bins, weights, N, generator=gen),
                           sample_pdf(bins, weights, N, generator=gen))  # its offset advances
    # Each sample's place in its stratum averages about 1/2 and is spread over it.
    u = _draw(bins, weights, N, torch.Generator(dev).manual_seed(seed))[1]
    place = u * N - torch.arange(N, device=dev)
    assert abs(place.mean().item() - 0.5) < 0.01 and abs(place.std().item() - 12 ** -0.5) < 0.01


@pytest.mark.parametrize("layout", ["dense", "packed"])
def test_stratified_call_is_one_op(layout):
    """Without value checks (on the CPU they run before the op) the default call is the op alone:
    no separate draw of the positions."""
    bins, weights, offsets = _random_layout(layout, 7, 9, torch.float32)
    call = sample_pdf if offsets is None else functools.partial(sample_pdf_packed, offsets=offsets)
    with dispatched_ops() as ops:
        call(bins, weights, num_samples=16, backend="kernel", check_values=False)
    assert ops == {f"mixer_nerf.sample_pdf{'' if offsets is None else '_packed'}_stratified_fwd": 1}


@cuda
@needs_cuda
def test_cuda_stratified_sample_pdf_is_one_launch_without_a_host_sync():
    dev = torch.device("cuda")
    bins, weights = random_pdf(4096, 63, device=dev)
    sample_pdf(bins, weights, 128)  # warm-up: the extension, the deferred checks' buffers
    check_pending()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        with dispatched_ops() as ops:  # the checks too: the first of a new batch reads nothing back
            out = sample_pdf(bins, weights, 128)
        for _ in range(3):
            out = sample_pdf(bins, weights, 128)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert ops == {"mixer_nerf.sample_pdf_stratified_fwd": 1}
    assert_valid_samples(out, bins)


@cuda
@needs_cuda
def test_cuda_packed_shared_memory_covers_the_clamped_rays():
    """Unchecked offsets that do not start at 0 or end at N: the kernels run the first ray from 0
    and the last to N, longer than any difference of the offsets; shared memory must hold them."""
    dev = torch.device("cuda")
    bins, weights, _ = random_packed_pdf([3, 60, 2, 1])  # N = 66
    for bad in ([40, 63, 65, 65, 66], [0, 1, 2, 6, 7]):  # the first ray 63 bins long; the last 60
        bad = torch.tensor(bad)
        unchecked = {"deterministic": True, "backend": "kernel", "check_values": False}
        cpu = sample_pdf_packed(bins, weights, bad, 16, **unchecked)
        gpu = sample_pdf_packed(bins.to(dev), weights.to(dev), bad.to(dev), 16, **unchecked)
        assert gpu.isfinite().all()
        torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-6, rtol=0)
