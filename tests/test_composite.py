"""Tests of composite (volume rendering): CPU/CUDA kernels against the float64 reference."""

from __future__ import annotations

import random

import pytest
import torch

from mixer_nerf import _extension
from mixer_nerf.ops.composite import composite
from mixer_nerf.ops.composite_reference import composite_reference

needs_kernels = pytest.mark.skipif(not _extension.available(), reason="mixer_nerf kernels not built")
cuda = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")]

# Float32 kernels against the float64 truth, errors measured relative to each tensor's largest
# magnitude. Transmittance is exp(-E) with E a float32 sum of S positive terms: relative error of E
# <= S * 2^-24 worst case (6e-6 at S=100), hence T, weights, and the weighted sums of up to S terms
# are off by ~E * that; 1e-4 leaves margin for S ~ 1000 at E ~ 10 while catching any wrong term.
F32_REL = 1e-4
F64_REL = 1e-12  # float64 kernel vs float64 reference: same sums in another order
HALF_REL = {torch.float16: 4e-3, torch.bfloat16: 3e-2}  # storage rounding of inputs/outputs only


@pytest.fixture
def gen():
    seed = random.getrandbits(32)
    print(f"seed={seed}")  # shown by pytest when a test fails
    return torch.Generator().manual_seed(seed)


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


def run(inputs, upstream, **kwargs):
    """Outputs and gradients of sum(output * upstream) w.r.t. every input (None where absent)."""
    inputs = with_grad(inputs)
    out = composite(*inputs, **kwargs)
    present = [t for t in inputs if t is not None]
    loss = sum((o * u).sum() for o, u in zip(out, upstream) if u is not None)
    grads = iter(torch.autograd.grad(loss, present, allow_unused=True, materialize_grads=True))
    return list(out), [None if t is None else next(grads) for t in inputs]


def truth(inputs, upstream):
    """The float64 reference on CPU."""
    inputs64 = [None if t is None else t.detach().to("cpu", torch.float64) for t in inputs]
    upstream64 = [None if u is None else u.to("cpu", torch.float64) for u in upstream]
    return run(inputs64, upstream64, backend="torch")


def random_upstream(inputs, gen, which=(True, True, True, True)):
    sigmas, rgbs = inputs[0], inputs[1]
    R, S, C = rgbs.shape
    shapes = [(R, C), (R,), (R,), (R, S)]
    return [
        torch.randn(*s, generator=gen, dtype=torch.float64).to(sigmas.device, sigmas.dtype) if use else None
        for s, use in zip(shapes, which)
    ]


def assert_close(got, want, rel, what=""):
    """max |got - want| <= rel * max |want| (per tensor), and got finite; truths below the
    smallest normal number of got's dtype (e.g. a 1e-69 gradient in float32) count as 0."""
    for i, (g, w) in enumerate(zip(got, want)):
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


SHAPES = [(1, 1, 1), (1, 7, 3), (6, 1, 3), (0, 5, 3), (4, 0, 3), (13, 64, 3), (5, 33, 1), (3, 40, 4), (2, 9, 7)]
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
@pytest.mark.parametrize("which", [(True, False, False, False), (False, True, False, False),
                                   (False, False, True, False), (False, False, False, True)])
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
    grads = torch.autograd.grad(sum((o * u).sum() for o, u in zip(out, upstream)), [sigmas, rgbs, bg])
    want = truth(inputs, upstream)[1]
    assert_close(list(grads), [want[0], want[1], want[4]], F64_REL, "grads")


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


@needs_kernels
@pytest.mark.parametrize("C", [1, 3])
def test_cpu_adversarial_values(gen, C):
    inputs = adversarial_inputs(gen, C)
    upstream = random_upstream(inputs, gen)
    want_out, want_grads = truth(inputs, upstream)
    out, grads = run(inputs, upstream, backend="kernel")
    assert_close(out, want_out, F32_REL, "outputs")
    # Gradients span ~1e18 (1e10-long intervals): judge every element on its own scale, i.e.
    # relative to the float64 truth, not only the largest one.
    for got, want, name in zip(grads, want_grads, ["sigmas", "rgbs", "t_starts", "t_ends", "background"]):
        assert torch.isfinite(got).all(), name
        err = (got.double() - want).abs()
        assert (err <= 1e-3 * want.abs() + 1e-6).all(), f"{name}: worst {err.max().item():.3e}"


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
    """(fwd args, bwd args) for opcheck: every optional present and absent at least once."""
    samples = []
    for background, which, interval in [("none", (True,) * 4, True), ("shared", (True, False, True, False), False),
                                        ("per_ray", (False, True, False, True), True)]:
        inputs = make_inputs(3, 6, 3, gen, background, dtype=torch.float32, device=device)
        upstream = random_upstream(inputs, gen, which)
        samples.append((inputs, [*upstream, *inputs, interval]))
    return samples


@needs_kernels
def test_opcheck_cpu(gen):
    composite(*valid_inputs(), backend="kernel")  # registers the fake kernels
    for fwd_args, bwd_args in op_samples(gen):
        torch.library.opcheck(torch.ops.mixer_nerf.composite_fwd.default, fwd_args)
        torch.library.opcheck(torch.ops.mixer_nerf.composite_bwd.default, bwd_args)


# ---------------------------------------------------------------------------------------------
# CUDA kernel

on_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")


def poison_allocator(shapes_and_dtypes, copies=2):
    """Leave NaN-filled blocks of exactly the sizes the op will allocate in CUDA's caching
    allocator: its torch.empty outputs then reuse NaN memory, so any element the kernel does not
    write stays NaN and fails the finiteness checks. The mechanism itself is asserted."""
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    blocks = [torch.full(shape, float("nan"), dtype=dtype, device="cuda")
              for shape, dtype in shapes_and_dtypes for _ in range(copies) if torch.Size(shape).numel()]
    if not blocks:
        return
    probe_shape, probe_dtype = blocks[0].shape, blocks[0].dtype
    del blocks
    probe = torch.empty(probe_shape, dtype=probe_dtype, device="cuda")
    assert torch.isnan(probe).all(), "poisoning did not reach the allocator"


def check_cuda(gen, inputs, rel=F32_REL):
    """CUDA kernel vs CPU kernel vs float64 reference, forward and every gradient, outputs poisoned."""
    upstream = random_upstream(inputs, gen)
    cpu_out, cpu_grads = run(inputs, upstream, backend="kernel")
    want_out, want_grads = truth(inputs, upstream)

    leaves = with_grad([None if t is None else t.cuda() for t in inputs])
    present = [t for t in leaves if t is not None]
    up_cuda = [u.cuda() for u in upstream]
    poison_allocator([(o.shape, o.dtype) for o in cpu_out] + [(t.shape, t.dtype) for t in present])
    out = composite(*leaves, backend="kernel", check_values=False)  # no value-check temporaries
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
    [(1, 1, 3), (1, 192, 3), (7, 31, 3), (5, 33, 1), (3, 64, 3), (9, 100, 4), (4, 45, 7), (2, 1000, 3),
     (0, 8, 3), (5, 0, 3), (70_000, 37, 3)],
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
    for got, want, name in zip(grads, want_grads, ["sigmas", "rgbs", "t_starts", "t_ends", "background"]):
        err = (got.double().cpu() - want).abs()
        assert (err <= 1e-3 * want.abs() + 1e-6).all(), f"{name}: worst {err.max().item():.3e}"


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_float64_gradcheck(gen):
    inputs = with_grad(make_inputs(3, 40, 3, gen, "per_ray", device="cuda"))
    assert torch.autograd.gradcheck(lambda *a: tuple(composite(*a, backend="kernel", check_values=False)), inputs)


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
        torch.library.opcheck(torch.ops.mixer_nerf.composite_fwd.default, fwd_args)
        torch.library.opcheck(torch.ops.mixer_nerf.composite_bwd.default, bwd_args)
