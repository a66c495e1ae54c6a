"""Property-based stress tests (hypothesis) of the CPU kernels of positional_encoding, sample_pdf,
hierarchical_samples and composite: random shapes (empty, R=1, S=1), inputs spanning many decades
(densities and interval lengths 0..1e10, weights 1e-30..1e30, coordinates up to 1e4 with up to 16
octaves), degenerate PDFs (all-zero, one-hot, duplicated edges) and non-finite inputs.

Hypothesis draws the structure of each case (sizes, magnitudes, which degeneracy) and a seed; the
values come from a torch generator seeded with it, so a failure prints a reproducible example while
a case costs microseconds to build. Every kernel result is checked against the reference path
evaluated in float64 on the same (float32) input values, and against the invariants of the op.

Profiles: ``MIXER_NERF_HYPOTHESIS=ci`` (default: 50 examples a test, the file runs in well under two
minutes) or ``dev`` (500 examples a test, for a thorough local search).
"""

from __future__ import annotations

import itertools
import math
import os

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mixer_nerf import _extension
from mixer_nerf.ops import (
    composite,
    composite_packed,
    hierarchical_samples,
    positional_encoding,
    sample_pdf,
    sample_pdf_packed,
)
from mixer_nerf.ops.composite import CompositeResult
from mixer_nerf.ops.hierarchical_samples_reference import hierarchical_samples_reference
from mixer_nerf.ops.sample_pdf_reference import sample_pdf_reference

settings.register_profile(
    "ci", max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow], print_blob=True
)
settings.register_profile(
    "dev", max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
PROFILE = settings.get_profile(os.environ.get("MIXER_NERF_HYPOTHESIS", "ci"))

pytestmark = pytest.mark.skipif(not _extension.available(), reason="mixer_nerf CPU kernels not built")

F32_EPS = torch.finfo(torch.float32).eps
NAN, INF = float("nan"), float("inf")

seeds = st.integers(0, 2**63 - 1)


def log_uniform(gen: torch.Generator, shape, lo_exp: float, hi_exp: float) -> torch.Tensor:
    """float64 values 10^U(lo_exp, hi_exp)."""
    return 10.0 ** (lo_exp + (hi_exp - lo_exp) * torch.rand(shape, generator=gen, dtype=torch.float64))


def with_zeros(gen: torch.Generator, values: torch.Tensor, fraction: float) -> torch.Tensor:
    return values * (torch.rand(values.shape, generator=gen, dtype=torch.float64) >= fraction)


def decades(lo: int, hi: int):
    """A sub-range [a, b] of the exponents lo..hi (a narrow one tests a scale, a wide one a spread)."""
    return st.tuples(st.integers(lo, hi), st.integers(lo, hi)).map(sorted)


def relative_to_max(truth: torch.Tensor) -> float:
    return float(truth.abs().max()) if truth.numel() else 0.0


# ---------------------------------------------------------------------------------------------
# composite


@st.composite
def composite_cases(draw):
    """sigmas, rgbs, t_starts, t_ends (float32) and background (None, (C,) or (R, C))."""
    R, S, C = draw(st.integers(0, 6)), draw(st.integers(1, 9)), draw(st.integers(1, 4))
    gen = torch.Generator().manual_seed(draw(seeds))
    sigma_lo, sigma_hi = draw(decades(-10, 10))
    delta_lo, delta_hi = draw(decades(-10, 10))
    sigmas = with_zeros(gen, log_uniform(gen, (R, S), sigma_lo, sigma_hi), draw(st.sampled_from([0, 0.3, 1])))
    deltas = with_zeros(gen, log_uniform(gen, (R, S), delta_lo, delta_hi), draw(st.sampled_from([0, 0.3, 1])))
    if draw(st.booleans()):
        deltas[:, -1] = 1e10  # NeRF's last interval
    near = float(draw(st.sampled_from([0.0, 2.0, 1e4])))
    t_starts = near + torch.cumsum(deltas, dim=1) - deltas  # intervals tile [near, ...]
    t_ends = t_starts + deltas
    rgbs = torch.rand(R, S, C, generator=gen, dtype=torch.float64)
    background = draw(st.sampled_from([None, (C,), (R, C)]))
    if background is not None:
        background = torch.rand(background, generator=gen, dtype=torch.float64).float()
    return (*(x.float() for x in (sigmas, rgbs, t_starts, t_ends)), background)


def composite_truth(sigmas, rgbs, t_starts, t_ends, background) -> CompositeResult:
    """The reference's formulas in float64, differentiable (autograd) to full relative accuracy.

    The reference path itself is not, for opaque samples: autograd of ``expm1`` forms d alpha /
    d tau = exp(-tau) as ``expm1(-tau) + 1``, which is exactly 0 beyond tau ~ 37 in float64 (~17
    in float32) although exp(-tau) is not; here alpha's gradient comes from exp(-tau) itself.
    """
    sigmas, rgbs, t_starts, t_ends = (x.double() for x in (sigmas, rgbs, t_starts, t_ends))
    tau = sigmas * (t_ends - t_starts)
    alpha = straight_through(-torch.expm1(-tau), -torch.exp(-tau))
    optical_depth = torch.cumsum(tau, dim=1)
    before = torch.cat([torch.zeros_like(tau[:, :1]), optical_depth[:, :-1]], dim=1)
    weights = torch.exp(-before) * alpha
    color = (weights[..., None] * rgbs).sum(dim=1)
    if background is not None:
        color = color + torch.exp(-optical_depth[:, -1:]) * background.double()
    depth = (weights * 0.5 * (t_starts + t_ends)).sum(dim=1)
    return CompositeResult(color, depth, weights.sum(dim=1), weights)


def straight_through(value: torch.Tensor, carrier: torch.Tensor) -> torch.Tensor:
    """``value``, with the gradient of ``carrier``."""
    return value.detach() + (carrier - carrier.detach())


def assert_composite_close(result, truth, t_ends):
    """Float32 kernel against the float64 reference: weights, opacity and colours lie in [0, 1] and
    come from an S-term float32 cumsum and exp/expm1 (each ~eps relative; exp(-x) turns an error
    of x eps into x eps exp(-x) <= eps), so 8 S eps absolute covers them; depth sums weights times
    midpoints, so its error is relative to the largest depth of the ray's intervals."""
    color, depth, opacity, weights = result
    S = weights.shape[1]
    atol = 8 * S * F32_EPS
    torch.testing.assert_close(weights.double(), truth.weights, atol=atol, rtol=0)
    torch.testing.assert_close(opacity.double(), truth.opacity, atol=atol, rtol=0)
    torch.testing.assert_close(color.double(), truth.color, atol=2 * atol, rtol=0)
    depth_scale = t_ends.double().abs().amax(dim=1) if t_ends.numel() else torch.zeros(0, dtype=torch.float64)
    assert ((depth.double() - truth.depth).abs() <= atol * depth_scale + 1e-30).all()


@PROFILE
@given(case=composite_cases())
def test_composite_invariants_and_float64_agreement(case):
    sigmas, rgbs, t_starts, t_ends, background = case
    result = composite(sigmas, rgbs, t_starts, t_ends, background, backend="kernel")
    for x in result:
        assert torch.isfinite(x).all()
    _, _, opacity, weights = result
    assert ((weights >= 0) & (weights <= 1)).all()
    assert ((opacity >= 0) & (opacity <= 1)).all()
    # opacity = -expm1(-sum tau) in closed form; sum w_i telescopes to it up to S roundings.
    torch.testing.assert_close(opacity, weights.sum(dim=1), atol=4 * weights.shape[1] * F32_EPS, rtol=0)
    truth = composite_truth(*case)
    assert_composite_close(result, truth, t_ends)
    # The reference path in float32 meets the same bound: kernel and reference agree through it.
    assert_composite_close(composite(*case, backend="torch"), truth, t_ends)


@PROFILE
@given(case=composite_cases(), upstream_seed=seeds)
def test_composite_gradients_finite_and_match_float64(case, upstream_seed):
    """Hand-written backward against float64 autograd of :func:`composite_truth`, for a random
    upstream gradient on all four outputs. Every input gradient is a sum over the samples j of
    d w_j / d x times an upstream factor (g_w_j, g_opacity, g_color . rgb_j, g_depth mid_j), which
    partly cancel (e.g. depth at t ~ 1e4 along a ray: terms of 1e4 summing to a few units), so
    the float32 error is bounded relative to the sum of the terms' magnitudes, not to the result."""
    sigmas, rgbs, t_starts, t_ends, background = case
    gen = torch.Generator().manual_seed(upstream_seed)
    leaves = [None if x is None else x.clone().requires_grad_() for x in case]
    outputs = composite(*leaves, backend="kernel")
    upstream = [torch.randn(o.shape, generator=gen, dtype=torch.float64) for o in outputs]
    present = [x for x in leaves if x is not None]
    grads = torch.autograd.grad(outputs, present, [g.float() for g in upstream], allow_unused=True)
    if sigmas.numel() == 0:
        assert all(g is None or not g.any() for g in grads)  # a shared background gets zeros
        return
    has_background = background is not None
    inputs64 = [x.detach().double().requires_grad_() for x in present]
    truths = torch.autograd.grad(
        composite_truth(*_with_background(inputs64, has_background)), inputs64, upstream, allow_unused=True
    )
    scales = gradient_term_scales([x.detach() for x in inputs64], has_background, upstream)
    S = sigmas.shape[1]
    for grad, truth, scale in zip(grads, truths, scales, strict=True):
        if truth is None:  # e.g. rgbs of an empty batch
            continue
        assert grad is not None and torch.isfinite(grad).all()
        atol = 64 * (S + 1) * F32_EPS * scale + 1e-30
        assert ((grad.double() - truth).abs() <= atol).all()


def _with_background(inputs: list, has_background: bool) -> list:
    """composite's five arguments from the present ones (background last, when there is one)."""
    return inputs if has_background else [*inputs, None]


def gradient_term_scales(inputs64, has_background, upstream):
    """Per input element, sum_j |d w_j / d x| (|g_w_j| + |g_opacity| + |g_color| + |g_depth| |mid_j|)
    plus the direct terms of colour (w_j |g_color|, T_end |g_color|) and depth (w_j |g_depth| / 2),
    from float64 Jacobians (the cases are small)."""
    g_color, g_depth, g_opacity, g_weights = (g.abs() for g in upstream)
    t_starts, t_ends = inputs64[2], inputs64[3]
    factor = (
        g_weights
        + g_opacity[:, None]
        + g_color.sum(-1, keepdim=True)
        + g_depth[:, None] * 0.5 * (t_starts.abs() + t_ends.abs())
    )  # (R, S): the upstream weight of sample j

    def weights_of(*xs):
        return composite_truth(*_with_background(list(xs), has_background)).weights

    jacobians = torch.autograd.functional.jacobian(weights_of, tuple(inputs64))
    truth = composite_truth(*_with_background(inputs64, has_background))
    direct = g_color.sum(-1, keepdim=True) + g_depth[:, None] * 0.5 * (t_starts.abs() + t_ends.abs())
    scales = []
    for x, jac in zip(inputs64, jacobians, strict=True):
        dims = tuple(range(factor.dim()))
        scale = (jac.abs() * factor.reshape(*factor.shape, *([1] * x.dim()))).sum(dim=dims)
        scales.append(scale + direct.max() * truth.weights.max() + g_color.max())
    return scales


@PROFILE
@given(
    case=composite_cases(),
    bad=st.sampled_from([NAN, INF, -INF]),
    where=st.sampled_from(["sigmas", "rgbs", "t_ends"]),
)
def test_composite_non_finite_rays_do_not_touch_their_neighbours(case, bad, where):
    """Poison one ray's input: no crash, the other rays' outputs and gradients are bit-identical to
    those computed without the poisoned ray (a shared (C,) background is replaced by a per-ray one:
    its gradient sums over all rays by definition). A NaN density makes the ray's opacity NaN."""
    sigmas, rgbs, t_starts, t_ends, background = case
    R = sigmas.shape[0]
    if R < 2:
        return
    if background is not None and background.dim() == 1:
        background = background.expand(R, -1).contiguous()
    poisoned = [x.clone() for x in (sigmas, rgbs, t_starts, t_ends)]
    index = {"sigmas": 0, "rgbs": 1, "t_ends": 3}[where]
    poisoned[index][0, -1] = bad
    full = _composite_with_grads(*poisoned, background)
    alone = _composite_with_grads(*(x[1:] for x in poisoned), None if background is None else background[1:])
    for a, b in zip(full, alone, strict=True):
        if a is not None:
            assert torch.equal(a[1:], b)
    if where == "sigmas" and math.isnan(bad):
        assert torch.isnan(full[2][0])


def _composite_with_grads(sigmas, rgbs, t_starts, t_ends, background):
    leaves = [
        None if x is None else x.clone().requires_grad_()
        for x in (sigmas, rgbs, t_starts, t_ends, background)
    ]
    outputs = composite(*leaves, backend="kernel", check_values=False)
    sum(o.sum() for o in outputs).backward()
    return (*outputs, *(None if x is None else x.grad for x in leaves))


# ---------------------------------------------------------------------------------------------
# sample_pdf and hierarchical_samples


@st.composite
def pdf_cases(draw, max_spread: int = 30):
    """bins (R, B+1) sorted with duplicated edges, weights (R, B) in one of several degenerate or
    wide-range modes, and how to place the samples. ``max_spread`` bounds the decades between a
    ray's lightest and heaviest non-zero weight."""
    R, B, N = draw(st.integers(0, 5)), draw(st.integers(1, 8)), draw(st.integers(0, 9))
    gen = torch.Generator().manual_seed(draw(seeds))
    start = float(draw(st.sampled_from([0.0, -3.0, 1e4, -1e4])))
    width_lo, width_hi = draw(decades(-6, 3))
    widths = with_zeros(gen, log_uniform(gen, (R, B), width_lo, width_hi), draw(st.sampled_from([0, 0.4])))
    bins = torch.cat([torch.full((R, 1), start, dtype=torch.float64), start + torch.cumsum(widths, 1)], 1)
    mode = draw(st.sampled_from(["spread", "all_zero", "one_hot", "equal", "some_zero"]))
    scale = 10.0 ** draw(st.integers(-30, 30))
    if mode == "spread":
        spread = draw(st.integers(0, max_spread))
        weights = scale * log_uniform(gen, (R, B), -spread / 2, spread / 2)
    elif mode == "all_zero":
        weights = torch.zeros(R, B, dtype=torch.float64)
    elif mode == "one_hot":
        weights = torch.zeros(R, B, dtype=torch.float64)
        weights[torch.arange(R), torch.randint(B, (R,), generator=gen)] = scale
    elif mode == "equal":
        weights = torch.full((R, B), scale, dtype=torch.float64)
    else:
        weights = with_zeros(gen, scale * log_uniform(gen, (R, B), 0, 1), 0.5)
    u_mode = draw(st.sampled_from(["deterministic", "stratified", "per_ray", "shared"]))
    return bins.float(), weights.float(), N, u_mode, gen


def pdf_positions(u_mode, R, N, gen):
    """kwargs of sample_pdf for the case's positions; explicit ones include the endpoints 0 and 1."""
    if u_mode == "deterministic":
        return {"deterministic": True}
    if u_mode == "stratified":
        return {"generator": gen}
    shape = (N,) if u_mode == "shared" else (R, N)
    u = torch.rand(shape, generator=gen)
    if N >= 2:
        u[..., 0], u[..., -1] = 0.0, 1.0
    return {"u": torch.sort(u, dim=-1).values}


def explicit_u(kwargs, R, N, gen):
    """The positions the kernel used, for the reference (stratified draws are replayed from a
    generator in the same state)."""
    if "u" in kwargs:
        return kwargs["u"]
    strata = torch.arange(N, dtype=torch.float32)
    if "deterministic" in kwargs:
        return (strata + 0.5) / N
    return (strata + torch.rand(R, N, generator=gen)) / N


def sample_tolerance(bins: torch.Tensor) -> torch.Tensor:
    """(R, 1): the kernels carry the CDF, u W and t in float64, so a float32 sample is the float64
    one up to the rounding of b_k + t (b_{k+1} - b_k) and of the output, a few ulps of the ray's
    largest edge."""
    return 4 * F32_EPS * bins.double().abs().amax(dim=1, keepdim=True)


def assert_valid_samples(samples: torch.Tensor, bins: torch.Tensor) -> None:
    assert torch.isfinite(samples).all()
    if samples.numel():
        assert (samples[:, 1:] >= samples[:, :-1]).all()
        assert (samples >= bins[:, :1]).all() and (samples <= bins[:, -1:]).all()


@PROFILE
@given(case=pdf_cases())
def test_sample_pdf_sorted_in_range_and_matches_float64(case):
    bins, weights, N, u_mode, gen = case
    R = bins.shape[0]
    replay = torch.Generator().manual_seed(gen.initial_seed())
    kwargs = pdf_positions(u_mode, R, N, gen)
    if u_mode == "stratified":
        replay.set_state(gen.get_state())
    samples = sample_pdf(bins, weights, N, backend="kernel", **kwargs)
    assert samples.shape == (R, N) and samples.dtype == torch.float32
    assert_valid_samples(samples, bins)
    u = explicit_u(kwargs, R, N, replay)
    truth = sample_pdf_reference(bins.double(), weights.double(), u.double())
    assert ((samples.double() - truth).abs() <= sample_tolerance(bins)).all()


@PROFILE
@given(case=pdf_cases(max_spread=4), upstream_seed=seeds)
def test_sample_pdf_gradients_finite_and_match_float64(case, upstream_seed):
    """Gradients with respect to the weights scale like (bin width) / (bin weight): exact, but
    beyond float32 when a sample lands in a bin 1e-35 heavy, so a ray's non-zero weights here
    span <= 4 decades (around 1e-30..1e30) to keep the true gradient representable.

    The float64 kernel must match float64 autograd through the reference closely. In float32 the
    weight gradients are ill-conditioned: d s / d w_k = width_k (u - t) / w_k cancels when a sample
    sits near u W's own bin position, and the scale invariance sum_j w_j ds/dw_j = 0 makes heavy and
    light bins' terms cancel; the error grows like eps * W / w_min, so the float32 tolerance does.
    """
    bins, weights, N, u_mode, gen = case
    R = bins.shape[0]
    u = explicit_u(pdf_positions(u_mode, R, N, gen), R, N, gen)  # the same float32 positions for all
    upstream = torch.randn(
        (R, N), generator=torch.Generator().manual_seed(upstream_seed), dtype=torch.float64
    )
    leaves64 = bins.double().requires_grad_(), weights.double().requires_grad_()
    truths = torch.autograd.grad(sample_pdf_reference(*leaves64, u.double()), leaves64, upstream)
    floors = pdf_gradient_floors(bins, weights, upstream)
    positive = weights[weights > 0].double()
    conditioning = float(weights.double().sum(1).max() / positive.min()) if positive.numel() else 1.0
    for dtype, rel in ((torch.float64, 1e-9), (torch.float32, 1e-4 * max(conditioning, 1.0))):
        leaves = bins.to(dtype).requires_grad_(), weights.to(dtype).requires_grad_()
        samples = sample_pdf(*leaves, N, u=u.to(dtype), backend="kernel")
        grads = torch.autograd.grad(samples, leaves, upstream.to(dtype))
        for grad, truth, floor in zip(grads, truths, floors, strict=True):
            assert torch.isfinite(grad).all()
            torch.testing.assert_close(
                grad.double(), truth, atol=rel * relative_to_max(truth) + floor, rtol=0
            )


def pdf_gradient_floors(bins, weights, upstream) -> tuple[float, float]:
    """Rounding noise of the float64 truth where the true gradient is 0 (e.g. a ray of one bin):
    ~1e-16 of the gradients' natural units, |upstream| for the edges (d sample / d edge is in
    [0, 1]) and |upstream| |edge| / weight for the weights."""
    if not upstream.numel():
        return 0.0, 0.0
    up = float(upstream.abs().max())
    positive = weights[weights > 0]
    lightest = float(positive.min()) if positive.numel() else 1.0
    return 1e-12 * up, 1e-12 * up * float(bins.abs().max()) / lightest


@PROFILE
@given(case=pdf_cases())
def test_hierarchical_samples_merge_coarse_and_fine(case):
    """The coarse depths are the case's bins (sorted, duplicated) and its weights padded to S."""
    z, weights, N, u_mode, gen = case
    R, S = z.shape
    if S < 3:
        return
    weights_coarse = torch.cat([weights, weights[:, :1]], dim=1)  # (R, S)
    replay = torch.Generator().manual_seed(gen.initial_seed())
    kwargs = pdf_positions(u_mode, R, N, gen)
    if u_mode == "stratified":
        replay.set_state(gen.get_state())
    merged = hierarchical_samples(z, weights_coarse, N, backend="kernel", **kwargs)
    assert merged.shape == (R, S + N)
    assert_valid_samples(merged, z)
    truth = hierarchical_samples_reference(
        z.double(), weights_coarse.double(), explicit_u(kwargs, R, N, replay).double()
    )
    assert ((merged.double() - truth).abs() <= sample_tolerance(z)).all()
    # Every coarse depth is kept: the merge is a sorted union, not a resampling.
    for ray in range(R):
        kept = torch.isin(z[ray], merged[ray])
        assert kept.all()


@PROFILE
@given(case=pdf_cases(), bad=st.sampled_from([NAN, INF]), where=st.sampled_from(["weights", "bins"]))
def test_sample_pdf_non_finite_rays_do_not_touch_their_neighbours(case, bad, where):
    bins, weights, N, _, gen = case
    R = bins.shape[0]
    if R < 2:
        return
    bins, weights = bins.clone(), weights.clone()
    (weights if where == "weights" else bins)[0, -1] = bad
    u = torch.sort(torch.rand(R, N, generator=gen), dim=-1).values
    full = sample_pdf(bins, weights, N, u=u, backend="kernel", check_values=False)
    alone = sample_pdf(bins[1:], weights[1:], N, u=u[1:], backend="kernel", check_values=False)
    assert torch.equal(full[1:], alone)
    merged = (
        hierarchical_samples(
            bins, torch.cat([weights, weights[:, :1]], 1), N, u=u, backend="kernel", check_values=False
        )
        if bins.shape[1] >= 3
        else None
    )
    if merged is not None:
        merged_alone = hierarchical_samples(
            bins[1:],
            torch.cat([weights, weights[:, :1]], 1)[1:],
            N,
            u=u[1:],
            backend="kernel",
            check_values=False,
        )
        assert torch.equal(merged[1:], merged_alone)


@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_sample_pdf_nan_weight_propagates(backend):
    """A NaN weight makes its ray's samples, and the gradients of all its weights and edges, NaN;
    the other ray is untouched. hierarchical_samples puts such a ray's NaN fine depths after its
    coarse ones (as torch.sort puts NaN last)."""
    bins = torch.tensor([[0.0, 1.0, 2.0], [0.0, 1.0, 2.0]], requires_grad=True)
    weights = torch.tensor([[NAN, 1.0], [1.0, 3.0]], requires_grad=True)
    samples = sample_pdf(bins, weights, 3, deterministic=True, backend=backend, check_values=False)
    assert torch.isnan(samples[0]).all()
    samples.sum().backward()
    assert torch.isnan(bins.grad[0]).all() and torch.isnan(weights.grad[0]).all()
    alone = [x[1:].detach().clone().requires_grad_() for x in (bins, weights)]
    samples_alone = sample_pdf(*alone, 3, deterministic=True, backend=backend)
    samples_alone.sum().backward()
    assert torch.equal(samples[1:], samples_alone)
    assert torch.equal(bins.grad[1:], alone[0].grad) and torch.equal(weights.grad[1:], alone[1].grad)
    z = torch.tensor([[0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0, 3.0]])
    weights_coarse = torch.tensor([[1.0, NAN, 1.0, 1.0], [1.0] * 4])
    merged = hierarchical_samples(z, weights_coarse, 2, deterministic=True, backend=backend)
    assert torch.equal(merged[0, :4], z[0]) and torch.isnan(merged[0, 4:]).all()
    assert torch.isfinite(merged[1]).all()


# ---------------------------------------------------------------------------------------------
# Packed (ragged) layouts: each ray of a packed batch gives what the dense op gives on it alone


def ray_counts(draw, num_rays: int, most: int) -> list[int]:
    """Rows kept per ray (0 included), for packing the first rows of each dense ray."""
    return draw(st.lists(st.integers(0, most), min_size=num_rays, max_size=num_rays))


def offsets_of(counts: list[int]) -> torch.Tensor:
    return torch.tensor([0, *itertools.accumulate(counts)], dtype=torch.int64)


def pack_rows(dense: torch.Tensor, counts: list[int]) -> torch.Tensor:
    """Rows ``dense[r, :counts[r]]`` of every ray, concatenated."""
    return (
        torch.cat([dense[r, :c] for r, c in enumerate(counts)])
        if counts
        else dense.reshape(0, *dense.shape[2:])
    )


@PROFILE
@given(case=composite_cases(), data=st.data())
def test_composite_packed_matches_composite_ray_by_ray(case, data):
    """Forward and gradients of every ray of the packed batch are those of the dense op on that ray
    alone (a ray with no sample: background colour, zero opacity and depth). Both share the per-ray
    scans, so up to float32 reassociation only."""
    sigmas, rgbs, t_starts, t_ends, background = case
    R, S = sigmas.shape
    counts = ray_counts(data.draw, R, S)
    leaves = [pack_rows(x, counts).requires_grad_() for x in (sigmas, rgbs, t_starts, t_ends)]
    color, depth, opacity, weights = composite_packed(
        *leaves, offsets_of(counts), background, backend="kernel"
    )
    assert all(torch.isfinite(x).all() for x in (color, depth, opacity, weights))
    (color.sum() + depth.sum() + opacity.sum() + weights.sum()).backward()
    start = 0
    for r, c in enumerate(counts):
        rows = slice(start, start + c)
        start += c
        ray_background = (
            None if background is None else (background if background.dim() == 1 else background[r])
        )
        if c == 0:
            expected = torch.zeros(rgbs.shape[-1]) if ray_background is None else ray_background
            assert torch.equal(color[r], expected) and depth[r] == 0 and opacity[r] == 0
            continue
        alone = [x[r : r + 1, :c].clone().requires_grad_() for x in (sigmas, rgbs, t_starts, t_ends)]
        dense = composite(*alone, None if ray_background is None else ray_background, backend="kernel")
        for packed_value, dense_value in zip(
            (color[r], depth[r], opacity[r], weights[rows]), dense, strict=True
        ):
            torch.testing.assert_close(
                packed_value, dense_value.reshape(packed_value.shape), rtol=1e-5, atol=1e-7
            )
        sum(x.sum() for x in dense).backward()
        for leaf, single in zip(leaves, alone, strict=True):
            scale = float(single.grad.abs().max())
            torch.testing.assert_close(leaf.grad[rows], single.grad[0], rtol=1e-5, atol=1e-6 * scale + 1e-30)


@PROFILE
@given(case=pdf_cases(), data=st.data())
def test_sample_pdf_packed_matches_sample_pdf_ray_by_ray(case, data):
    """A ray with no bin has one edge, and all its samples are that edge."""
    bins, weights, N, _, gen = case
    R, B = weights.shape
    counts = ray_counts(data.draw, R, B)
    packed_bins = torch.cat([bins[r, : c + 1] for r, c in enumerate(counts)]) if counts else bins.reshape(0)
    u = torch.sort(torch.rand(R, N, generator=gen), dim=-1).values
    samples = sample_pdf_packed(
        packed_bins, pack_rows(weights, counts), offsets_of(counts), N, u=u, backend="kernel"
    )
    assert samples.shape == (R, N) and torch.isfinite(samples).all()
    for r, c in enumerate(counts):
        if c == 0:
            assert (samples[r] == bins[r, 0]).all()
            continue
        alone = sample_pdf(
            bins[r : r + 1, : c + 1], weights[r : r + 1, :c], N, u=u[r : r + 1], backend="kernel"
        )
        torch.testing.assert_close(samples[r], alone[0], rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# positional_encoding


@st.composite
def encoding_cases(draw):
    batch = tuple(draw(st.lists(st.integers(0, 4), min_size=0, max_size=2)))
    D = draw(st.integers(1, 4))
    gen = torch.Generator().manual_seed(draw(seeds))
    magnitude = 10.0 ** draw(st.integers(-3, 4))
    x = ((torch.rand(*batch, D, generator=gen, dtype=torch.float64) * 2 - 1) * magnitude).float()
    return x, draw(st.integers(0, 16)), draw(st.booleans()), draw(st.sampled_from([math.pi, 1.0]))


def encoding_truth(x: torch.Tensor, num_freqs: int, include_input: bool, scale: float):
    """float64 encoding and derivative blocks with exact phases: 2^k x is exact in float64 for float32
    x, so for scale = pi it is reduced exactly modulo 2 and for scale = 1 it is the exact argument of
    float64 sin (whose own range reduction is accurate). Returns (encoding, d encoding / d x, |θ|)."""
    x64 = x.double()
    values, slopes, angles = (
        ([x64], [torch.ones_like(x64)], [torch.zeros_like(x64)]) if include_input else ([], [], [])
    )
    for k in range(num_freqs):
        y = x64 * 2.0**k
        if scale == math.pi:
            y = math.pi * (y - 2 * torch.round(y / 2))
        s, c = torch.sin(y), torch.cos(y)
        values += [s, c]
        slopes += [scale * 2.0**k * c, -scale * 2.0**k * s]
        angles += [(scale * 2.0**k * x64).abs()] * 2
    if not values:
        empty = x64.new_empty(*x.shape[:-1], 0)
        return empty, empty, empty
    return tuple(torch.cat(parts, dim=-1) for parts in (values, slopes, angles))


@PROFILE
@given(case=encoding_cases())
def test_positional_encoding_within_documented_bounds(case):
    """Kernel: within the documented half ulp (plus |θ| 2^-78 and the truth's own 1e-15). The
    reference rounds θ to float32 first: within |θ| 2^-23 + 2^-23, the loss of digits the
    kernel avoids (asserted as a bound, so a regression of either shows)."""
    x, num_freqs, include_input, scale = case
    encoded = positional_encoding(x, num_freqs, include_input, scale, backend="kernel")
    truth, _, angles = encoding_truth(x, num_freqs, include_input, scale)
    assert encoded.shape == truth.shape and torch.isfinite(encoded).all()
    error = (encoded.double() - truth).abs()
    assert (error <= 2.0**-25 * torch.clamp(truth.abs(), min=1.0) + angles * 2.0**-78 + 1e-15).all()
    reference = positional_encoding(x, num_freqs, include_input, scale, backend="torch")
    reference_error = (reference.double() - truth).abs()
    assert (reference_error <= (angles + 1) * 2.0**-23 + 2.0**-25 * truth.abs()).all()


@PROFILE
@given(case=encoding_cases(), upstream_seed=seeds)
def test_positional_encoding_gradient_matches_float64(case, upstream_seed):
    """d/dx of each block is scale 2^k cos or sin at the same exact phase: each term carries ~2 ulps
    of its magnitude scale 2^k, and the (include_input + 2F) terms add up in float32."""
    x, num_freqs, include_input, scale = case
    leaf = x.clone().requires_grad_()
    encoded = positional_encoding(leaf, num_freqs, include_input, scale, backend="kernel")
    upstream = torch.randn(encoded.shape, generator=torch.Generator().manual_seed(upstream_seed))
    (grad,) = torch.autograd.grad(encoded, leaf, upstream)
    assert torch.isfinite(grad).all()
    _, slopes, _ = encoding_truth(x, num_freqs, include_input, scale)
    amplitudes = torch.tensor(
        [1.0] * include_input + [scale * 2.0**k for k in range(num_freqs) for _ in "sc"], dtype=torch.float64
    )  # |d block / dx| <= amplitude
    blocks = len(amplitudes)
    per_block = (upstream.double() * slopes).unflatten(-1, (blocks, x.shape[-1]))
    truth = per_block.sum(dim=-2)
    magnitudes = upstream.double().abs().unflatten(-1, (blocks, x.shape[-1])) * amplitudes[:, None]
    bound = (blocks + 4) * F32_EPS * magnitudes.sum(dim=-2)  # float32 terms and their sum
    assert ((grad.double() - truth).abs() <= bound + 1e-30).all()


@PROFILE
@given(case=encoding_cases(), bad=st.sampled_from([NAN, INF, -INF]))
def test_positional_encoding_non_finite_rows_do_not_touch_their_neighbours(case, bad):
    x, num_freqs, include_input, scale = case
    if x.dim() < 2 or x.shape[0] < 2:
        return
    x = x.clone()
    x[0, ..., 0] = bad
    leaf, alone = x.clone().requires_grad_(), x[1:].clone().requires_grad_()
    full = positional_encoding(leaf, num_freqs, include_input, scale, backend="kernel")
    rest = positional_encoding(alone, num_freqs, include_input, scale, backend="kernel")
    assert torch.equal(full[1:], rest)
    full.sum().backward()
    rest.sum().backward()
    assert torch.equal(leaf.grad[1:], alone.grad)
    if math.isnan(bad) and num_freqs and full[0].numel():
        D = x.shape[-1]
        sincos = full[0].reshape(*full.shape[1:-1], -1, D)[..., int(include_input) :, 0]
        assert torch.isnan(sincos).all()


def test_positional_encoding_infinite_input_propagates_nan():
    x = torch.tensor([[INF, 0.5]], requires_grad=True)
    encoded = positional_encoding(x, 2, include_input=False, backend="kernel")
    assert torch.isnan(encoded[0, 0::2]).all()  # every sin/cos column of the infinite coordinate
    encoded.sum().backward()
    assert torch.isnan(x.grad[0, 0])
