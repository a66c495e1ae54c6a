"""Tests of composite (volume rendering): CPU/CUDA kernels against the float64 reference."""

from __future__ import annotations

import pytest
import torch

from mixer_nerf import _extension
from mixer_nerf.ops.composite import composite, composite_packed
from mixer_nerf.ops.composite_reference import composite_reference
from cuda_poison import poison_allocator

needs_kernels = pytest.mark.skipif(not _extension.available(), reason="mixer_nerf kernels not built")
cuda = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")]

# Float32 kernels against the float64 truth, errors measured relative to each tensor's largest
# magnitude. Transmittance is exp(-E) with E a float32 sum of S positive terms: relative error of E
# <= S * 2^-24 worst case (6e-6 at S=100), hence T, weights, and the weighted sums of up to S terms
# are off by ~E * that; 1e-4 leaves margin for S ~ 1000 at E ~ 10 while catching any wrong term.
F32_REL = 1e-4
F64_REL = 1e-12  # float64 kernel vs float64 reference: same sums in another order
HALF_REL = {torch.float16: 4e-3, torch.bfloat16: 3e-2}  # storage rounding of inputs/outputs only


def make_inputs(R, S, C, gen, background="none", dtype=torch.float64, device="cpu", sigma_scale=3.0):
    """Random rays: sorted contiguous intervals from t=1, a third of the densities zero."""
    sigmas = torch.rand(R, S, generator=gen, dtype=torch.float64) * sigma_scale
    sigmas = sigmas * (torch.rand(R, S, generator=gen, dtype=torch.float64) > 0.3)
    deltas = 0.01 + 0.3 * torch.rand(R, S, generator=gen, dtype=torch.float64)
    edges = 1 + torch.cat([torch.zeros(R, 1, dtype=torch.float64), deltas.cumsum(1)], dim=1)
    rgbs = torch.rand(R, S, C, generator=gen, dtype=torch.float64)
    bg = {"none": None, "shared": (C,), "per_ray": (R, C)}[background]
    bg = None if bg is None else torch.rand(*bg, generator=gen, dtype=torch.float64)
    tensors = [sigmas, rgbs, edges[:, :-1].contiguous(), edges[:, 1:].contiguous(), bg]
    return [None if t is None else t.to(device=device, dtype=dtype) for t in tensors]


def with_grad(inputs):
    return [None if t is None else t.detach().clone().requires_grad_() for t in inputs]


def run(inputs, upstream, fn=composite, **kwargs):
    """Outputs and gradients of sum(output * upstream) w.r.t. every input (None where absent);
    ``fn(sigmas, rgbs, t_starts, t_ends, background, **kwargs)`` is composite or a packed one."""
    inputs = with_grad(inputs)
    out = fn(*inputs, **kwargs)
    present = [t for t in inputs if t is not None]
    loss = sum((o * u).sum() for o, u in zip(out, upstream, strict=False) if u is not None)
    grads = iter(torch.autograd.grad(loss, present, allow_unused=True, materialize_grads=True))
    return list(out), [None if t is None else next(grads) for t in inputs]


def truth(inputs, upstream, fn=composite):
    """The float64 reference on CPU."""
    inputs64 = [None if t is None else t.detach().to("cpu", torch.float64) for t in inputs]
    upstream64 = [None if u is None else u.to("cpu", torch.float64) for u in upstream]
    return run(inputs64, upstream64, fn, backend="torch")


def random_upstream(inputs, gen, which=(True, True, True, True), num_rays=None):
    """Upstream gradients of color, depth, opacity, weights; ``num_rays`` for packed inputs."""
    sigmas, rgbs = inputs[0], inputs[1]
    R = rgbs.shape[0] if num_rays is None else num_rays
    shapes = [(R, rgbs.shape[-1]), (R,), (R,), tuple(sigmas.shape)]
    return [
        torch.randn(*s, generator=gen, dtype=torch.float64).to(sigmas.device, sigmas.dtype) if use else None
        for s, use in zip(shapes, which, strict=False)
    ]


def assert_close(got, want, rel, what=""):
    """max |got - want| <= rel * max |want| (per tensor), and got finite; truths below the
    smallest normal number of got's dtype (e.g. a 1e-69 gradient in float32) count as 0."""
    for i, (g, w) in enumerate(zip(got, want, strict=False)):
        if w is None:
            assert g is None or not g.abs().any(), f"{what}[{i}]: expected no gradient"
            continue
        tiny = torch.finfo(g.dtype).tiny
        g, w = g.detach().to("cpu", torch.float64), w.detach().to("cpu", torch.float64)
        assert g.shape == w.shape, f"{what}[{i}]: shape {tuple(g.shape)} != {tuple(w.shape)}"
        assert torch.isfinite(g).all(), f"{what}[{i}]: non-finite values"
        if w.numel():
            err, scale = (g - w).abs().max().item(), w.abs().max().item()
            assert err <= rel * scale + tiny, f"{what}[{i}]: max err {err:.3e} vs scale {scale:.3e}"


SHAPES = [
    (1, 1, 1),
    (1, 7, 3),
    (6, 1, 3),
    (0, 5, 3),
    (4, 0, 3),
    (13, 64, 3),
    (5, 33, 1),
    (3, 40, 4),
    (2, 9, 7),
    (2, 8300, 3),  # a ray longer than the CPU kernel's scan group (8192 samples)
    (150, 61, 3),  # groups that end between rays
]
BACKGROUNDS = ["none", "shared", "per_ray"]


# ---------------------------------------------------------------------------------------------
# CPU kernel


@needs_kernels
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("background", BACKGROUNDS)
def test_cpu_kernel_matches_reference(gen, shape, background):
    inputs = make_inputs(*shape, gen, background)
    upstream = random_upstream(inputs, gen)
    want_out, want_grads = truth(inputs, upstream)
    for dtype, rel in ((torch.float64, F64_REL), (torch.float32, F32_REL)):
        cast = [None if t is None else t.to(dtype) for t in inputs]
        out, grads = run(cast, [u.to(dtype) for u in upstream], backend="kernel")
        assert all(o.dtype == dtype for o in out)
        assert_close(out, want_out, rel, f"{dtype} outputs")
        assert_close(grads, want_grads, rel, f"{dtype} grads")


@needs_kernels
@pytest.mark.parametrize("background", BACKGROUNDS)
def test_cpu_gradcheck(gen, background):
    inputs = with_grad(make_inputs(3, 5, 3, gen, background))
    present = [t for t in inputs if t is not None]

    def fn(*args):
        it = iter(args)
        args = [None if t is None else next(it) for t in inputs]
        return tuple(composite(*args, backend="kernel", check_values=False))  # sigmas +- eps < 0

    assert torch.autograd.gradcheck(fn, present)


@needs_kernels
@pytest.mark.parametrize(
    "which",
    [
        (True, False, False, False),
        (False, True, False, False),
        (False, False, True, False),
        (False, False, False, True),
    ],
)
def test_cpu_loss_on_one_output(gen, which):
    """Unused outputs reach the backward as None (no zero tensors); each alone must be right."""
    inputs = make_inputs(4, 11, 3, gen, "shared")
    upstream = random_upstream(inputs, gen, which)
    out, grads = run(inputs, upstream, backend="kernel")
    assert_close(grads, truth(inputs, upstream)[1], F64_REL, "grads")


@needs_kernels
def test_cpu_interval_grads_skipped_when_not_needed(gen):
    inputs = make_inputs(4, 9, 3, gen, "per_ray")
    upstream = random_upstream(inputs, gen)
    sigmas, rgbs, t_starts, t_ends, bg = with_grad(inputs)
    out = composite(sigmas, rgbs, t_starts.detach(), t_ends.detach(), bg, backend="kernel")
    loss = sum((o * u).sum() for o, u in zip(out, upstream, strict=True))
    grads = torch.autograd.grad(loss, [sigmas, rgbs, bg])
    want = truth(inputs, upstream)[1]
    assert_close(list(grads), [want[0], want[1], want[4]], F64_REL, "grads")


@needs_kernels
@pytest.mark.parametrize("background", ["shared", "per_ray"])
def test_cpu_background_grad_skipped_when_not_needed(gen, background):
    """A constant background (no grad) gets no gradient from the kernel, and the others are as with one."""
    inputs = make_inputs(4, 9, 3, gen, background)
    upstream = random_upstream(inputs, gen)
    sigmas, rgbs, t_starts, t_ends, _ = with_grad(inputs)
    out = composite(sigmas, rgbs, t_starts, t_ends, inputs[4], backend="kernel")
    loss = sum((o * u).sum() for o, u in zip(out, upstream, strict=True))
    grads = torch.autograd.grad(loss, [sigmas, rgbs, t_starts, t_ends])
    want = truth(inputs, upstream)[1]
    assert_close(list(grads), want[:4], F64_REL, "grads")
    chunk_transmittances = torch.ops.mixer_nerf.composite_fwd(*inputs)[4]
    raw = torch.ops.mixer_nerf.composite_bwd(*upstream, *inputs, chunk_transmittances, False, False)
    assert raw[4] is None


@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_cpu_half_precision(gen, dtype):
    inputs = [None if t is None else t.to(dtype) for t in make_inputs(7, 20, 3, gen, "shared")]
    upstream = [u.to(dtype) for u in random_upstream(inputs, gen)]
    out, grads = run(inputs, upstream, backend="kernel")
    assert all(o.dtype == dtype for o in out) and all(g.dtype == dtype for g in grads)
    want_out, want_grads = truth(inputs, upstream)  # the same rounded inputs, in float64
    assert_close(out, want_out, HALF_REL[dtype], "outputs")
    assert_close(grads, want_grads, HALF_REL[dtype], "grads")


@needs_kernels
def test_cpu_non_contiguous_inputs(gen):
    sigmas, rgbs, t_starts, t_ends, bg = make_inputs(6, 10, 3, gen, "shared")
    rgbs_nc = rgbs.transpose(0, 1).contiguous().transpose(0, 1)
    sigmas_nc = sigmas.t().contiguous().t()
    got = composite(sigmas_nc, rgbs_nc, t_starts, t_ends, bg, backend="kernel")
    assert_close(list(got), list(composite_reference(sigmas, rgbs, t_starts, t_ends, bg)), F64_REL)


# ---------------------------------------------------------------------------------------------
# Adversarial values


def adversarial_inputs(gen, C, dtype=torch.float32, device="cpu"):
    """Densities from {0, 1e-8, 1e8} and moderate, intervals from 1e-6 up to the 1e10-long last
    interval NeRF uses, so tau spans 0 .. 1e18 and T underflows mid-ray on some rays."""
    R, S = 64, 24
    choice = torch.randint(0, 4, (R, S), generator=gen)
    sigmas = torch.tensor([0.0, 1e-8, 1e8, 1.0], dtype=torch.float64)[choice]
    sigmas = torch.where(choice == 3, torch.rand(R, S, generator=gen, dtype=torch.float64) * 20, sigmas)
    deltas = 10 ** (torch.rand(R, S, generator=gen, dtype=torch.float64) * 5 - 6)  # 1e-6 .. 0.1
    deltas[:, -1] = 1e10
    deltas[R // 2 :, S // 2] = 1e10  # a 1e10-long interval mid-ray too
    edges = 2 + torch.cat([torch.zeros(R, 1, dtype=torch.float64), deltas.cumsum(1)], dim=1)
    rgbs = torch.rand(R, S, C, generator=gen, dtype=torch.float64)
    bg = torch.rand(C, generator=gen, dtype=torch.float64)
    # The float32 bounds must describe the same intervals as the float64 truth: round them first.
    tensors = [sigmas, rgbs, edges[:, :-1], edges[:, 1:], bg]
    return [t.to(dtype).contiguous().to(device) for t in tensors]


def assert_each_element_close(grads, want_grads):
    """Gradients span ~1e18 (1e10-long intervals): judge every element on its own scale, i.e.
    relative to the float64 truth, not only the largest one."""
    for got, want, name in zip(
        grads, want_grads, ["sigmas", "rgbs", "t_starts", "t_ends", "background"], strict=True
    ):
        assert torch.isfinite(got).all(), name
        err = (got.double().cpu() - want).abs()
        assert (err <= 1e-3 * want.abs() + 1e-6).all(), f"{name}: worst {err.max().item():.3e}"


@needs_kernels
@pytest.mark.parametrize("C", [1, 3])
def test_cpu_adversarial_values(gen, C):
    inputs = adversarial_inputs(gen, C)
    upstream = random_upstream(inputs, gen)
    want_out, want_grads = truth(inputs, upstream)
    out, grads = run(inputs, upstream, backend="kernel")
    assert_close(out, want_out, F32_REL, "outputs")
    assert_each_element_close(grads, want_grads)


def row_relative_errors(got, want):
    """|got - want| / max(|want|, half a float32 ulp of the row's largest |want|) (the error
    budget's metric: errors below the resolution of the row's largest entry are not magnified)."""
    got, want = got.double().cpu(), want.double().cpu()
    floor = want.abs().amax(dim=-1, keepdim=True) * torch.finfo(torch.float32).eps / 2
    return (got - want).abs() / torch.maximum(want.abs(), floor.clamp_min(torch.finfo(torch.float32).tiny))


KERNEL_DEVICES = ["cpu", pytest.param("cuda", marks=cuda)]


@needs_kernels
@pytest.mark.parametrize("device", KERNEL_DEVICES)
def test_float32_gradients_in_thin_media(gen, device):
    """Fog, optical thickness 1e-9..1e-4 per sample over S = 192 samples: dL/dtau_j =
    T_{j+1} (g_j - G_{j+1}) with g_j and G_{j+1} both O(1) and often close. G is built by S
    multiplications by exp(-tau) ~ 1; carried in float32 it held ~S ulps of the background term
    and the float32 gradients were off by up to ~1e-2 relative where g_j ~ G_{j+1}, ten times the
    reference path's error. The kernel must be at least as accurate as the reference on the same
    device (and, as it computes in double, within an ulp of the float64 truth)."""
    R, S = 128, 192
    u = torch.rand(R, S, generator=gen, dtype=torch.float64)
    sigmas = 10.0 ** (-8 + 5 * u)
    deltas = 4.0 / S * (0.5 + torch.rand(R, S, generator=gen, dtype=torch.float64))
    t_starts = 2.0 + deltas.cumsum(1) - deltas
    rgbs = torch.rand(R, S, 3, generator=gen, dtype=torch.float64)
    bg = torch.rand(3, generator=gen, dtype=torch.float64)
    inputs = [t.float().to(device) for t in (sigmas, rgbs, t_starts, t_starts + deltas, bg)]
    upstream = random_upstream(inputs, gen)  # float32: the truth takes the same values
    want = truth(inputs, upstream)[1]
    kernel = run(inputs, upstream, backend="kernel")[1]
    reference = run(inputs, upstream, backend="torch")[1]
    for k, name in ((0, "d sigmas"), (3, "d t_ends")):
        kernel_err = row_relative_errors(kernel[k], want[k]).max().item()
        reference_err = row_relative_errors(reference[k], want[k]).max().item()
        assert kernel_err <= reference_err, f"{name}: kernel {kernel_err:.2e} > reference {reference_err:.2e}"
        assert kernel_err <= torch.finfo(torch.float32).eps, f"{name}: kernel {kernel_err:.2e}"


@needs_kernels
@pytest.mark.parametrize("device", KERNEL_DEVICES)
@pytest.mark.parametrize("medium", ["typical", "thin"])
def test_float32_outputs_at_least_as_accurate_as_reference(gen, medium, device):
    """Forward outputs in float32 against the float64 truth. The optical depth E was a float32
    sequential sum, drifting by ~i ulps after i samples, and T = exp(-E) multiplied that by E;
    with tau, alpha and the color/depth sums also rounded at every step, float32 weights were off
    by up to ~1e2 ulps and colors, depths and opacities by 2-4 times the reference path's error
    (whose cumsum accumulates in double). Now computed in double and rounded once: every output
    must be at least as accurate as the reference's, in the worst element and in the median, and
    within an ulp of the truth."""
    R, S = 256, 192
    lo, hi = (-2, 2) if medium == "typical" else (-8, -3)  # densities 0.01..100, or fog
    sigmas = 10.0 ** (lo + (hi - lo) * torch.rand(R, S, generator=gen, dtype=torch.float64))
    deltas = 4.0 / S * (0.5 + torch.rand(R, S, generator=gen, dtype=torch.float64))
    t_starts = 2.0 + deltas.cumsum(1) - deltas
    rgbs = torch.rand(R, S, 3, generator=gen, dtype=torch.float64)
    bg = torch.rand(3, generator=gen, dtype=torch.float64)
    inputs = [t.float().to(device) for t in (sigmas, rgbs, t_starts, t_starts + deltas, bg)]
    want = composite(*[t.double() for t in inputs], backend="torch")
    kernel = composite(*inputs, backend="kernel")
    reference = composite(*inputs, backend="torch")
    for name in ("color", "depth", "opacity", "weights"):
        truth_ = getattr(want, name)
        if truth_.dim() == 1:  # depth, opacity: one value per ray, each its own row
            truth_ = truth_[:, None]
        kernel_err = row_relative_errors(getattr(kernel, name).reshape(truth_.shape), truth_)
        reference_err = row_relative_errors(getattr(reference, name).reshape(truth_.shape), truth_)
        for stat in ("max", "median"):
            k, r = getattr(kernel_err, stat)().item(), getattr(reference_err, stat)().item()
            assert k <= r, f"{name} {stat}: kernel {k:.2e} > reference {r:.2e}"
        assert kernel_err.max().item() <= torch.finfo(torch.float32).eps, f"{name}: {kernel_err.max().item():.2e}"


@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opacity_gradient_has_no_cancellation(dtype):
    """d opacity / d sigma_j = T_S * delta_j exactly. After an opaque surface T_S is ~e^-40:
    T_{j+1} - sum_{i>j} w_i (what naive formulas compute) would be rounding noise ~1e-7 instead of
    ~1e-18, times delta_j (up to 1e10); the kernel must get every element to full relative precision."""
    sigmas = torch.tensor([[0.5, 8.0, 0.3, 0.2, 1e-9], [0.0, 0.0, 1e8, 0.0, 0.0]], dtype=torch.float64)
    deltas = torch.tensor([[0.1, 5.0, 0.1, 0.1, 1e10], [0.1, 0.1, 1e10, 0.1, 1e10]], dtype=torch.float64)
    edges = torch.cat([torch.ones(2, 1, dtype=torch.float64), 1 + deltas.cumsum(1)], dim=1)
    t_starts, t_ends = edges[:, :-1].to(dtype), edges[:, 1:].to(dtype)
    sigmas = sigmas.to(dtype).requires_grad_()
    rgbs = torch.rand(2, 5, 3, dtype=dtype)
    opacity = composite(sigmas, rgbs, t_starts, t_ends, backend="kernel").opacity
    (grad,) = torch.autograd.grad(opacity.sum(), sigmas)
    tau = sigmas.detach().double() * (t_ends.double() - t_starts.double())
    want = torch.exp(-tau.sum(1, keepdim=True)) * (t_ends.double() - t_starts.double())
    assert torch.allclose(grad.double(), want, rtol=1e-5, atol=0), (grad, want)


@needs_kernels
def test_single_sample_ray_is_alpha():
    sigmas = torch.tensor([[0.0], [1e-8], [1.0], [1e8]], dtype=torch.float64)
    t_starts, t_ends = torch.zeros(4, 1, dtype=torch.float64), torch.full((4, 1), 2.0, dtype=torch.float64)
    out = composite(sigmas, torch.ones(4, 1, 1, dtype=torch.float64), t_starts, t_ends, backend="kernel")
    alpha = -torch.expm1(-2 * sigmas[:, 0])
    assert torch.allclose(out.opacity, alpha, rtol=1e-15, atol=0)
    assert torch.allclose(out.weights[:, 0], alpha, rtol=1e-15, atol=0)
    assert torch.allclose(out.depth, alpha, rtol=1e-15, atol=0)  # midpoint 1


# ---------------------------------------------------------------------------------------------
# Validation


def valid_inputs():
    return [torch.rand(3, 4), torch.rand(3, 4, 3), torch.zeros(3, 4), torch.ones(3, 4), torch.rand(3)]


@pytest.mark.parametrize(
    "index, bad, error, name",
    [
        (0, torch.rand(3, 4, 1), ValueError, "sigmas"),
        (1, torch.rand(3, 4), ValueError, "rgbs"),
        (0, torch.rand(3, 5), ValueError, "sigmas"),
        (2, torch.zeros(3, 5), ValueError, "t_starts"),
        (3, torch.ones(4, 4), ValueError, "t_ends"),
        (4, torch.rand(2), ValueError, "background"),
        (4, torch.rand(2, 3), ValueError, "background"),
        (4, torch.rand(3, 3, 1), ValueError, "background"),
        (1, torch.rand(3, 4, 0), ValueError, "rgbs"),
        (0, torch.ones(3, 4, dtype=torch.int64), TypeError, "sigmas"),
        (2, torch.zeros(3, 4, dtype=torch.int32), TypeError, "t_starts"),
        (1, torch.rand(3, 4, 3, dtype=torch.float64), TypeError, "rgbs"),
        (4, torch.rand(3, dtype=torch.float64), TypeError, "background"),
        (0, [[1.0]], TypeError, "sigmas"),
        (0, -torch.rand(3, 4) - 0.1, ValueError, "sigmas"),
        (3, -torch.ones(3, 4), ValueError, "t_ends"),
        (1, torch.rand(3, 4, 3, device="meta"), ValueError, "rgbs"),
    ],
)
@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_bad_inputs_raise(index, bad, error, name, backend):
    args = valid_inputs()
    args[index] = bad
    with pytest.raises(error, match=name):
        composite(*args, backend=backend)


def test_bad_backend_raises():
    with pytest.raises(ValueError, match="backend"):
        composite(*valid_inputs(), backend="cuda")


def test_check_values_false_skips_value_checks():
    args = valid_inputs()
    args[0] = -args[0]
    composite(*args, backend="torch", check_values=False)


# ---------------------------------------------------------------------------------------------
# Registered ops


def op_samples(gen, device="cpu"):
    """(fwd args, bwd args) for opcheck: every optional present and absent at least once (the
    kernels must be loaded: the backward's arguments include a forward output)."""
    samples = []
    for background, which, interval, background_grad in [
        ("none", (True,) * 4, True, False),
        ("shared", (True, False, True, False), False, True),
        ("per_ray", (False, True, False, True), True, False),
        ("per_ray", (True,) * 4, False, True),
    ]:
        inputs = make_inputs(3, 6, 3, gen, background, dtype=torch.float32, device=device)
        upstream = random_upstream(inputs, gen, which)
        chunk_transmittances = torch.ops.mixer_nerf.composite_fwd(*inputs)[4]
        samples.append((inputs, [*upstream, *inputs, chunk_transmittances, interval, background_grad]))
    return samples


def differentiable(fwd_args):
    """The op's arguments with sigmas, rgbs, t_starts, t_ends and background requiring grad."""
    return [*with_grad(fwd_args[:5]), *fwd_args[5:]]


@needs_kernels
def test_opcheck_cpu(gen):
    composite(*valid_inputs(), backend="kernel")  # registers the fake kernels
    for fwd_args, bwd_args in op_samples(gen):
        for args in (fwd_args, differentiable(fwd_args)):
            torch.library.opcheck(torch.ops.mixer_nerf.composite_fwd.default, args)
        torch.library.opcheck(torch.ops.mixer_nerf.composite_bwd.default, bwd_args)


@needs_kernels
def test_ops_take_any_strides(gen):
    """The registered ops make their inputs contiguous themselves, below autograd too (inference
    mode dispatches straight to the kernel)."""
    inputs = make_inputs(4, 6, 3, gen, "per_ray")
    strided = [t.transpose(0, -1).contiguous().transpose(0, -1) for t in inputs]
    assert not strided[0].is_contiguous()
    want = torch.ops.mixer_nerf.composite_fwd(*inputs)
    with torch.inference_mode():
        got = torch.ops.mixer_nerf.composite_fwd(*strided)
    for g, w in zip(got[:4], want[:4]):
        torch.testing.assert_close(g, w)
    upstream = [u.expand_as(u).t().contiguous().t() if u.dim() == 2 else u for u in random_upstream(inputs, gen)]
    grads = torch.ops.mixer_nerf.composite_bwd(*upstream, *strided, want[4], True, True)
    want_grads = torch.ops.mixer_nerf.composite_bwd(*[u.contiguous() for u in upstream], *inputs, want[4], True, True)
    for g, w in zip(grads, want_grads):
        torch.testing.assert_close(g, w)


# ---------------------------------------------------------------------------------------------
# CUDA kernel

on_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, on_cuda])])
@needs_kernels
def test_backward_rejects_transmittances_of_other_inputs(gen, device):
    """The backward reads the forward's chunk_transmittances: another size or dtype is an error."""
    composite(*[t.to(device) for t in valid_inputs()], backend="kernel")
    _, bwd_args = op_samples(gen, device)[0]
    saved = bwd_args[-3]  # then the two flags
    for wrong in (torch.zeros(saved.numel() + 1, dtype=saved.dtype, device=device), saved.float()):
        bwd_args[-3] = wrong
        with pytest.raises(RuntimeError, match="chunk_transmittances"):
            torch.ops.mixer_nerf.composite_bwd(*bwd_args)


def check_cuda(gen, inputs, rel=F32_REL, fn=composite, num_rays=None):
    """CUDA kernel vs CPU kernel vs float64 reference, forward and every gradient, outputs poisoned."""
    upstream = random_upstream(inputs, gen, num_rays=num_rays)
    cpu_out, cpu_grads = run(inputs, upstream, fn, backend="kernel")
    want_out, want_grads = truth(inputs, upstream, fn)

    leaves = with_grad([None if t is None else t.cuda() for t in inputs])
    present = [t for t in leaves if t is not None]
    up_cuda = [u.cuda() for u in upstream]
    poison_allocator(list(cpu_out) + present)
    out = fn(*leaves, backend="kernel", check_values=False)  # no value-check temporaries
    grads = iter(torch.autograd.grad(out, present, up_cuda))
    grads = [None if t is None else next(grads) for t in leaves]
    for got, want, what in ((out, want_out, "outputs"), (grads, want_grads, "grads")):
        assert_close(got, want, rel, f"cuda {what} vs reference")
    assert_close(out, cpu_out, rel, "cuda vs cpu outputs")
    assert_close(grads, cpu_grads, rel, "cuda vs cpu grads")


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize(
    "R, S, C",
    [
        (1, 1, 3),
        (1, 192, 3),
        (7, 31, 3),
        (5, 33, 1),
        (3, 64, 3),
        (9, 100, 4),
        (4, 45, 7),
        (2, 1000, 3),
        (0, 8, 3),
        (5, 0, 3),
        (70_000, 37, 3),
    ],
)
@pytest.mark.parametrize("background", BACKGROUNDS)
def test_cuda_matches_cpu_and_reference(gen, R, S, C, background):
    check_cuda(gen, make_inputs(R, S, C, gen, background, dtype=torch.float32))


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize("C", [1, 3])
def test_cuda_adversarial_values(gen, C):
    inputs = adversarial_inputs(gen, C)
    upstream = random_upstream(inputs, gen)
    want_grads = truth(inputs, upstream)[1]
    out, grads = run([t.cuda() for t in inputs], [u.cuda() for u in upstream], backend="kernel")
    assert all(torch.isfinite(o).all() for o in out)
    assert_each_element_close(grads, want_grads)


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_float64_gradcheck(gen):
    inputs = with_grad(make_inputs(3, 40, 3, gen, "per_ray", device="cuda"))
    assert torch.autograd.gradcheck(
        lambda *a: tuple(composite(*a, backend="kernel", check_values=False)), inputs
    )


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_cuda_half_precision(gen, dtype):
    inputs = [t.to(dtype) for t in make_inputs(50, 70, 3, gen, "shared")]
    upstream = [u.to(dtype) for u in random_upstream(inputs, gen)]
    out, grads = run([t.cuda() for t in inputs], [u.cuda() for u in upstream], backend="kernel")
    want_out, want_grads = truth(inputs, upstream)
    assert_close(out, want_out, HALF_REL[dtype], "outputs")
    assert_close(grads, want_grads, HALF_REL[dtype], "grads")


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_opcheck_cuda(gen):
    composite(*[t.cuda() for t in valid_inputs()], backend="kernel")
    for fwd_args, bwd_args in op_samples(gen, device="cuda"):
        for args in (fwd_args, differentiable(fwd_args)):
            torch.library.opcheck(torch.ops.mixer_nerf.composite_fwd.default, args)
        torch.library.opcheck(torch.ops.mixer_nerf.composite_bwd.default, bwd_args)


# ---------------------------------------------------------------------------------------------
# Packed (ragged) rays: composite_packed


def pack(inputs, counts):
    """Padded (R, S) inputs -> packed (N,) inputs keeping the first counts[r] samples of ray r,
    and the offsets (R+1,)."""
    sigmas = inputs[0]
    keep = torch.arange(sigmas.shape[1], device=sigmas.device) < counts.to(sigmas.device)[:, None]
    packed = [t[keep].contiguous() for t in inputs[:4]]
    offsets = torch.nn.functional.pad(counts.cumsum(0), (1, 0)).to(sigmas.device)
    return [*packed, inputs[4]], offsets


def packed_fn(offsets):
    """composite_packed with the signature of composite (offsets follow the inputs' device)."""

    def fn(sigmas, rgbs, t_starts, t_ends, background, **kwargs):
        return composite_packed(
            sigmas, rgbs, t_starts, t_ends, offsets.to(sigmas.device), background, **kwargs
        )

    return fn


def make_packed(counts, C, gen, background="none", dtype=torch.float64, device="cpu", **kwargs):
    counts = torch.as_tensor(counts, dtype=torch.int64)
    width = int(counts.max()) if counts.numel() else 0
    return pack(make_inputs(counts.numel(), width, C, gen, background, dtype, device, **kwargs), counts)


def random_counts(R, high, gen):
    return torch.randint(0, high + 1, (R,), generator=gen)


COUNTS = {
    "one ray, one sample": [1],
    "one ray": [9],
    "one empty ray": [0],
    "all empty": [0, 0, 0],
    "no rays": [],
    "ragged": [3, 0, 7, 1, 0, 12, 33],
    "many": "random",
    "a ray longer than a scan group": [3, 8300, 0, 5],
}


def counts_named(name, gen):
    return (
        random_counts(300, 60, gen)  # ~9,000 samples: several of the CPU kernel's scan groups
        if COUNTS[name] == "random"
        else torch.tensor(COUNTS[name], dtype=torch.int64)
    )


@needs_kernels
@pytest.mark.parametrize("counts", list(COUNTS))
@pytest.mark.parametrize("background", BACKGROUNDS)
def test_packed_cpu_kernel_matches_reference(gen, counts, background):
    counts = counts_named(counts, gen)
    inputs, offsets = make_packed(counts, 3, gen, background)
    fn = packed_fn(offsets)
    upstream = random_upstream(inputs, gen, num_rays=counts.numel())
    want_out, want_grads = truth(inputs, upstream, fn)
    for dtype, rel in ((torch.float64, F64_REL), (torch.float32, F32_REL)):
        cast = [None if t is None else t.to(dtype) for t in inputs]
        out, grads = run(cast, [u.to(dtype) for u in upstream], fn, backend="kernel")
        assert all(o.dtype == dtype for o in out)
        assert_close(out, want_out, rel, f"{dtype} outputs")
        assert_close(grads, want_grads, rel, f"{dtype} grads")


@needs_kernels
@pytest.mark.parametrize("packed", [False, True], ids=["dense", "packed"])
def test_cpu_kernel_results_do_not_depend_on_the_thread_count(gen, packed):
    """Threads split the rays, and so the CPU kernel's scan groups, differently: bit-identical."""
    if packed:
        counts = random_counts(300, 60, gen)
        inputs, offsets = make_packed(counts, 3, gen, "per_ray", dtype=torch.float32)
        fn, upstream = packed_fn(offsets), random_upstream(inputs, gen, num_rays=counts.numel())
    else:
        inputs = make_inputs(300, 50, 3, gen, "per_ray", dtype=torch.float32)
        fn, upstream = composite, random_upstream(inputs, gen)
    threads = torch.get_num_threads()
    try:
        runs = []
        for n in (1, 2):
            torch.set_num_threads(n)
            runs.append(run(inputs, upstream, fn, backend="kernel"))
    finally:
        torch.set_num_threads(threads)
    for got, want in zip(*(out + grads for out, grads in runs), strict=True):
        assert (got is None and want is None) or torch.equal(got, want)


@needs_kernels
@pytest.mark.parametrize("background", BACKGROUNDS)
def test_packed_cpu_gradcheck(gen, background):
    inputs, offsets = make_packed([2, 0, 5, 1], 3, gen, background)
    inputs = with_grad(inputs)
    present = [t for t in inputs if t is not None]

    def fn(*args):
        it = iter(args)
        args = [None if t is None else next(it) for t in inputs]
        return tuple(packed_fn(offsets)(*args, backend="kernel", check_values=False))  # sigmas +- eps < 0

    assert torch.autograd.gradcheck(fn, present)


@needs_kernels
@pytest.mark.parametrize("backend", ["kernel", "torch"])
@pytest.mark.parametrize("background", BACKGROUNDS)
def test_packed_equals_dense_when_every_ray_has_S_samples(gen, backend, background):
    """The same per-ray scans: the CPU kernel gives bit-identical results in both layouts."""
    R, S = 6, 13
    inputs = make_inputs(R, S, 3, gen, background)
    packed, offsets = pack(inputs, torch.full((R,), S))
    upstream = random_upstream(inputs, gen)
    dense_out, dense_grads = run(inputs, upstream, backend=backend)
    packed_up = [*upstream[:3], upstream[3].reshape(-1)]
    packed_out, packed_grads = run(packed, packed_up, packed_fn(offsets), backend=backend)
    packed_out[3] = packed_out[3].reshape(R, S)
    packed_grads[:4] = [g.reshape(R, S, *g.shape[1:]) for g in packed_grads[:4]]
    exact = backend == "kernel"
    for got, want in zip(packed_out + packed_grads, dense_out + dense_grads, strict=False):
        if want is None:
            continue
        assert torch.equal(got, want) if exact else torch.allclose(got, want, rtol=1e-13, atol=1e-15)


@needs_kernels
@pytest.mark.parametrize("backend", ["kernel", "torch"])
@pytest.mark.parametrize("background", BACKGROUNDS)
def test_packed_empty_rays_show_the_background(gen, backend, background):
    counts = torch.tensor([0, 4, 0, 0, 2, 0])
    inputs, offsets = make_packed(counts, 3, gen, background)
    out = packed_fn(offsets)(*inputs, backend=backend)
    empty = counts == 0
    bg = inputs[4]
    want_color = torch.zeros(6, 3, dtype=torch.float64) if bg is None else bg.expand(6, 3)
    assert torch.equal(out.color[empty], want_color[empty])
    assert not out.opacity[empty].any() and not out.depth[empty].any()


@needs_kernels
@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_packed_no_rays_no_samples(backend):
    empty = torch.zeros(0, dtype=torch.float64)
    out = composite_packed(
        empty,
        torch.zeros(0, 3, dtype=torch.float64),
        empty,
        empty,
        torch.zeros(1, dtype=torch.int64),
        torch.ones(3, dtype=torch.float64),
        backend=backend,
    )
    assert [tuple(o.shape) for o in out] == [(0, 3), (0,), (0,), (0,)]
    out = composite_packed(
        empty,
        torch.zeros(0, 3, dtype=torch.float64),
        empty,
        empty,
        torch.zeros(4, dtype=torch.int64),
        torch.ones(3, dtype=torch.float64),
        backend=backend,
    )
    assert torch.equal(out.color, torch.ones(3, 3, dtype=torch.float64)) and not out.opacity.any()


@needs_kernels
@pytest.mark.parametrize("C", [1, 3])
def test_packed_cpu_adversarial_values(gen, C):
    """The dense adversarial rays (tau from 0 to 1e18, transmittance underflowing mid-ray)
    truncated to ragged lengths: a 1e18 tau in one ray must not leak into the next one."""
    dense = adversarial_inputs(gen, C)
    counts = random_counts(dense[0].shape[0], dense[0].shape[1], gen)
    inputs, offsets = pack(dense, counts)
    fn = packed_fn(offsets)
    upstream = random_upstream(inputs, gen, num_rays=counts.numel())
    want_out, want_grads = truth(inputs, upstream, fn)
    out, grads = run(inputs, upstream, fn, backend="kernel")
    assert_close(out, want_out, F32_REL, "outputs")
    assert_each_element_close(grads, want_grads)


# Unchecked bad offsets of 2 rays over 5 samples, and the valid ones the kernels take them as:
# clamped into [0, N], the first ray from 0 and the last to N, so that every row is written.
BAD_OFFSETS = [([0, 100, 5], [0, 5, 5]), ([-7, 2, 5], [0, 2, 5]), ([0, 4, 2], [0, 4, 5]), ([3, 1, 0], [0, 1, 5])]


def check_bad_offsets_act_as_clamped(device, gen):
    inputs, _ = make_packed([3, 2], 3, gen, "shared", device=device)
    for bad, taken_as in BAD_OFFSETS:
        upstream = random_upstream(inputs, gen, num_rays=2)
        got = run(inputs, upstream, packed_fn(torch.tensor(bad)), backend="kernel", check_values=False)
        want = run(inputs, upstream, packed_fn(torch.tensor(taken_as)), backend="kernel", check_values=False)
        for a, b in zip(got[0] + got[1], want[0] + want[1], strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    # Three rays, the middle one reversed: rows 1..3 lie on two rays and none is left unwritten.
    out, grads = run(inputs, random_upstream(inputs, gen, num_rays=3), packed_fn(torch.tensor([0, 4, 1, 5])),
                     backend="kernel", check_values=False)
    assert all(torch.isfinite(t).all() for t in out + grads)


@needs_kernels
def test_packed_unchecked_bad_offsets_stay_in_bounds(gen):
    """check_values=False skips the offsets' value checks; the kernels neither read nor write
    outside the arrays, nor leave an output row unwritten."""
    check_bad_offsets_act_as_clamped("cpu", gen)


def valid_packed():
    """sigmas, rgbs, t_starts, t_ends, offsets, background for 3 rays of 0, 4 and 2 samples."""
    return [
        torch.rand(6),
        torch.rand(6, 3),
        torch.zeros(6),
        torch.ones(6),
        torch.tensor([0, 0, 4, 6]),
        torch.rand(3),
    ]


@pytest.mark.parametrize(
    "index, bad, error, name",
    [
        (0, torch.rand(6, 1), ValueError, "sigmas"),
        (0, torch.rand(5), ValueError, "sigmas"),
        (1, torch.rand(6), ValueError, "rgbs"),
        (1, torch.rand(6, 0), ValueError, "rgbs"),
        (2, torch.zeros(5), ValueError, "t_starts"),
        (3, torch.ones(6, 1), ValueError, "t_ends"),
        (5, torch.rand(4, 3), ValueError, "background"),
        (5, torch.rand(2), ValueError, "background"),
        (4, torch.tensor([0, 0, 4, 6], dtype=torch.int32), TypeError, "offsets"),
        (4, torch.tensor([0.0, 0.0, 4.0, 6.0]), TypeError, "offsets"),
        (4, [0, 0, 4, 6], TypeError, "offsets"),
        (4, torch.tensor([[0, 0, 4, 6]]), ValueError, "offsets"),
        (4, torch.zeros(0, dtype=torch.int64), ValueError, "offsets"),
        (4, torch.tensor([0, 0, 4, 5]), ValueError, "offsets"),
        (4, torch.tensor([1, 1, 4, 6]), ValueError, "offsets"),
        (4, torch.tensor([0, 5, 4, 6]), ValueError, "offsets"),
        (4, torch.tensor([0, 0, 4, 6], device="meta"), ValueError, "offsets"),
        (0, torch.ones(6, dtype=torch.int64), TypeError, "sigmas"),
        (1, torch.rand(6, 3, dtype=torch.float64), TypeError, "rgbs"),
        (0, -torch.rand(6) - 0.1, ValueError, "sigmas"),
        (3, -torch.ones(6), ValueError, "t_ends"),
        (1, torch.rand(6, 3, device="meta"), ValueError, "rgbs"),
    ],
)
@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_packed_bad_inputs_raise(index, bad, error, name, backend):
    args = valid_packed()
    args[index] = bad
    with pytest.raises(error, match=name):
        composite_packed(*args, backend=backend)


def packed_op_samples(gen, device="cpu"):
    """(fwd args, bwd args) of the packed ops: every optional present and absent at least once."""
    samples = []
    for background, which, interval, background_grad in [
        ("none", (True,) * 4, True, False),
        ("shared", (True, False, True, False), False, True),
        ("per_ray", (False, True, False, True), True, False),
        ("shared", (True,) * 4, False, False),
    ]:
        inputs, offsets = make_packed([3, 0, 5, 1], 3, gen, background, dtype=torch.float32, device=device)
        upstream = random_upstream(inputs, gen, which, num_rays=4)
        chunk_transmittances = torch.ops.mixer_nerf.composite_packed_fwd(*inputs, offsets)[4]
        samples.append(([*inputs, offsets],
                        [*upstream, *inputs, offsets, chunk_transmittances, interval, background_grad]))
    return samples


@needs_kernels
def test_packed_opcheck_cpu(gen):
    composite_packed(*valid_packed(), backend="kernel")  # registers the fake kernels
    for fwd_args, bwd_args in packed_op_samples(gen):
        for args in (fwd_args, differentiable(fwd_args)):
            torch.library.opcheck(torch.ops.mixer_nerf.composite_packed_fwd.default, args)
        torch.library.opcheck(torch.ops.mixer_nerf.composite_packed_bwd.default, bwd_args)


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize(
    "R, max_count, C",
    [
        (1, 1, 3),
        (1, 300, 3),
        (7, 31, 3),
        (50, 33, 1),
        (30, 64, 4),
        (9, 100, 7),
        (5, 1000, 3),
        (0, 8, 3),
        (70_000, 64, 3),
    ],
)
@pytest.mark.parametrize("background", BACKGROUNDS)
def test_packed_cuda_matches_cpu_and_reference(gen, R, max_count, C, background):
    counts = random_counts(R, max_count, gen)
    if R:
        counts[0] = max_count  # the longest ray is there
    if R > 2:
        counts[1] = 0  # and an empty one
    inputs, offsets = make_packed(counts, C, gen, background, dtype=torch.float32)
    check_cuda(gen, inputs, fn=packed_fn(offsets), num_rays=R)


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize("C", [1, 3])
def test_packed_cuda_adversarial_values(gen, C):
    dense = adversarial_inputs(gen, C)
    counts = random_counts(dense[0].shape[0], dense[0].shape[1], gen)
    inputs, offsets = pack(dense, counts)
    fn = packed_fn(offsets)
    upstream = random_upstream(inputs, gen, num_rays=counts.numel())
    want_grads = truth(inputs, upstream, fn)[1]
    out, grads = run([t.cuda() for t in inputs], [u.cuda() for u in upstream], fn, backend="kernel")
    assert all(torch.isfinite(o).all() for o in out)
    assert_each_element_close(grads, want_grads)


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_packed_cuda_float64_gradcheck(gen):
    inputs, offsets = make_packed([40, 0, 3, 70], 3, gen, "per_ray", device="cuda")
    fn = packed_fn(offsets)
    assert torch.autograd.gradcheck(
        lambda *a: tuple(fn(*a, backend="kernel", check_values=False)), with_grad(inputs)
    )


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_packed_cuda_unchecked_bad_offsets_stay_in_bounds(gen):
    poison_allocator([torch.empty(5, 3, device="cuda"), torch.empty(5, device="cuda")])
    check_bad_offsets_act_as_clamped("cuda", gen)


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_packed_opcheck_cuda(gen):
    composite_packed(*[t.cuda() for t in valid_packed()], backend="kernel")
    for fwd_args, bwd_args in packed_op_samples(gen, device="cuda"):
        for args in (fwd_args, differentiable(fwd_args)):
            torch.library.opcheck(torch.ops.mixer_nerf.composite_packed_fwd.default, args)
        torch.library.opcheck(torch.ops.mixer_nerf.composite_packed_bwd.default, bwd_args)
