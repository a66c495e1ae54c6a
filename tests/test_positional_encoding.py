"""Tests of positional_encoding: CPU/CUDA kernels against a float64 truth and the reference path.

The truth is computed in float64 with an exact phase: for scale == math.pi, 2^k x is reduced
exactly modulo 2 before sin(pi r); otherwise scale 2^k x is formed as an unevaluated double-double
sum (exact for inputs of <= 24 bits), so the truth is good to ~1e-16 even where |θ| is 1e9.
Kernel tolerances are the error bound documented in positional_encoding's docstring.
"""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
import torch

from mixer_nerf import _extension
from mixer_nerf.ops.positional_encoding import MAX_FREQS, positional_encoding
from mixer_nerf.ops.positional_encoding_reference import positional_encoding_reference

needs_kernels = pytest.mark.skipif(not _extension.available(), reason="mixer_nerf kernels not built")
on_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")

SCALES = (math.pi, 1.0, 0.7)
HALF_ULP = {
    torch.float32: 2.0**-25,
    torch.float16: 2.0**-12,
    torch.bfloat16: 2.0**-9,
    torch.float64: 2.0**-54,
}


def uniform(shape, magnitude, gen, dtype=torch.float32, device="cpu"):
    x = (torch.rand(shape, generator=gen, dtype=torch.float64) * 2 - 1) * magnitude
    return x.to(dtype).to(device)


def exact_angle_sincos(y: torch.Tensor, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """sin/cos(scale * y) in float64 with the phase kept exact for y of <= 24 significant bits."""
    if scale == math.pi:
        r = y - 2 * torch.round(y / 2)  # exact: y mod 2
        return torch.sin(math.pi * r), torch.cos(math.pi * r)
    t = scale * 134217729.0  # Veltkamp split: scale = s_hi + s_lo, 26 + 27 bits
    s_hi = t - (t - scale)
    p1, p2 = s_hi * y, (scale - s_hi) * y  # both exact for 24-bit y
    a1 = p1 + p2
    a2 = (p1 - a1) + p2  # exact: a1 + a2 == scale * y
    s, c = torch.sin(a1), torch.cos(a1)
    return s + a2 * c, c - a2 * s


def truth(x, num_freqs, include_input=True, scale=math.pi):
    """Float64 encoding of x (its values taken exactly) and the angles |θ| of each column."""
    x64 = x.detach().double().cpu()
    parts, angles = ([x64], [torch.zeros_like(x64)]) if include_input else ([], [])
    for k in range(num_freqs):
        y = x64 * 2.0**k
        s, c = exact_angle_sincos(y, scale)
        parts += [s, c]
        angles += [(scale * y).abs()] * 2
    if not parts:
        return x64.new_empty(*x64.shape[:-1], 0), x64.new_empty(*x64.shape[:-1], 0)
    return torch.cat(parts, -1), torch.cat(angles, -1)


def bound(angles: torch.Tensor, dtype: torch.dtype, scale: float) -> torch.Tensor:
    """The documented kernel error bound per element (plus the output dtype's rounding)."""
    if dtype == torch.float64:
        return 5e-16 + (0.0 if scale == math.pi else 2.0**-53) * angles
    return HALF_ULP[dtype] + 2.0**-25 + 7e-12 + 2.0**-78 * angles


def assert_within_bound(out, x, num_freqs, include_input, scale):
    want, angles = truth(x, num_freqs, include_input, scale)
    err = (out.detach().double().cpu() - want).abs()
    # For float64 x (53 bits) and scale != pi the truth's own phase rounds too, by ~|θ| 2^-53.
    truth_err = 2.0**-53 * angles if (x.dtype == torch.float64 and scale != math.pi) else 0.0
    excess = err - bound(angles, out.dtype, scale) - truth_err
    assert out.shape == want.shape
    assert bool((excess <= 0).all()), (
        f"max error {err.max().item():.3e}, max excess {excess.max().item():.3e}"
    )
    return err


# ---------------------------------------------------------------------------------------- CPU


@needs_kernels
@pytest.mark.parametrize("shape", [(1, 3), (37, 3), (0, 3), (2, 5, 3), (9, 1), (3,), (4, 7)])
@pytest.mark.parametrize("num_freqs", [0, 1, 6])
@pytest.mark.parametrize("include_input", [True, False])
def test_forward_matches_truth_and_reference(shape, num_freqs, include_input, gen):
    x = uniform(shape, 2.0, gen)
    for scale in (math.pi, 1.0):
        out = positional_encoding(x, num_freqs, include_input, scale, backend="kernel")
        assert_within_bound(out, x, num_freqs, include_input, scale)
        ref = positional_encoding_reference(x, num_freqs, include_input, scale)
        # The reference rounds θ = scale 2^k x (|θ| < 2 pi 32 here) to float32, ~|θ| 2^-24 ≈ 1.2e-5
        # of phase, plus its own ~1 ulp sin/cos.
        torch.testing.assert_close(out, ref, rtol=0, atol=2e-5)


@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float64, torch.float16, torch.bfloat16])
def test_other_dtypes_within_bound(dtype, gen):
    x = uniform((513, 3), 3.0, gen, dtype)
    for scale in SCALES:
        out = positional_encoding(x, 8, True, scale, backend="kernel")
        assert out.dtype == dtype
        assert_within_bound(out, x, 8, True, scale)


@needs_kernels
@pytest.mark.parametrize("magnitude, num_freqs", [(1e3, 10), (1e4, 16)])
@pytest.mark.parametrize("scale", SCALES)
def test_high_frequencies_keep_float32_accuracy(magnitude, num_freqs, scale, gen):
    """|θ| up to 1e4 2^15 pi ≈ 1e9: ours stays within half an ulp; the reference degrades."""
    x = uniform((4096, 3), magnitude, gen)
    out = positional_encoding(x, num_freqs, False, scale, backend="kernel")
    err = assert_within_bound(out, x, num_freqs, False, scale)
    want, _ = truth(x, num_freqs, False, scale)
    ref_err = (positional_encoding_reference(x, num_freqs, False, scale).double() - want).abs()
    assert err.max() <= ref_err.max()


@needs_kernels
def test_float64_high_frequencies(gen):
    x = uniform((1024, 3), 1e4, gen, torch.float64)
    for scale in SCALES:
        assert_within_bound(positional_encoding(x, 16, False, scale, backend="kernel"), x, 16, False, scale)


@needs_kernels
def test_extreme_inputs_stay_finite():
    """Huge finite inputs give finite outputs (no overflow to Inf/NaN); NaN propagates."""
    big32 = torch.tensor([[3.4e38, -3.4e38, 1e30], [2.0**24, -(2.0**23) - 1, 0.5]])
    big64 = torch.tensor([[1.7e308, -1e300, 1e200], [2.0**53, 2.0**53 + 2, -(2.0**60)]], dtype=torch.float64)
    for x in (big32, big64):
        for scale in (math.pi, 1.0, 1e3):
            out = positional_encoding(x, MAX_FREQS, True, scale, backend="kernel")
            assert bool(torch.isfinite(out).all())
    # sin(pi 2^k n) of integers n is exactly 0 at every octave.
    sines = positional_encoding(big32[1:, :2], 20, False, backend="kernel").view(1, 20, 2, 2)[:, :, 0]
    assert torch.equal(sines, torch.zeros_like(sines))
    nan = positional_encoding(torch.tensor([[float("nan"), 1.0]]), 3, False, backend="kernel")
    assert bool(nan[..., 0::2].isnan().all()) and bool(torch.isfinite(nan[..., 1::2]).all())


@needs_kernels
def test_non_contiguous_input(gen):
    x = uniform((3, 40), 1.0, gen).t()  # (40, 3), not contiguous
    out = positional_encoding(x, 4, backend="kernel")
    torch.testing.assert_close(out, positional_encoding(x.contiguous(), 4, backend="kernel"), rtol=0, atol=0)


@needs_kernels
@pytest.mark.parametrize("include_input", [True, False])
@pytest.mark.parametrize("scale", [math.pi, 1.0])
def test_gradcheck_float64(include_input, scale, gen):
    x = uniform((6, 3), 1.5, gen, torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t: positional_encoding(t, 4, include_input, scale, backend="kernel"), (x,)
    )


def gradient_magnitude(grad, num_freqs, include_input, scale):
    """Sum over the terms of grad_x of their magnitudes: scale 2^k (|g_sin| + |g_cos|) (+ |g_x|)."""
    g = grad.detach().double().abs().cpu()
    blocks_per_row = int(include_input) + 2 * num_freqs
    blocks = g.reshape(*g.shape[:-1], blocks_per_row, g.shape[-1] // blocks_per_row)
    weights = [1.0] * int(include_input) + [abs(scale) * 2.0**k for k in range(num_freqs) for _ in (0, 1)]
    return (blocks * torch.tensor(weights, dtype=torch.float64)[:, None]).sum(-2)


def input_gradient(x, num_freqs, include_input, scale, backend, grad):
    xr = x.clone().requires_grad_()
    out = positional_encoding(xr, num_freqs, include_input, scale, backend=backend)
    (gx,) = torch.autograd.grad(out, xr, grad)
    return gx


@needs_kernels
@pytest.mark.parametrize("shape", [(1, 3), (300, 3), (0, 3), (5, 2, 1)])
@pytest.mark.parametrize("scale", [math.pi, 1.0])
def test_backward_matches_float64(shape, scale, gen):
    x = uniform(shape, 1.0, gen)
    num_freqs = 6
    g = torch.randn(*shape[:-1], shape[-1] * (1 + 2 * num_freqs), generator=gen)
    want = input_gradient(x.double(), num_freqs, True, scale, "torch", g.double())
    ours = input_gradient(x, num_freqs, True, scale, "kernel", g).double()
    # float32 sum of terms of magnitude <= M: a few float32 ulps of M.
    assert bool(((ours - want).abs() <= 4 * 2.0**-24 * gradient_magnitude(g, num_freqs, True, scale)).all())


@needs_kernels
def test_backward_without_input_gradient_block(gen):
    x = uniform((50, 3), 1.0, gen, torch.float64).requires_grad_()
    out = positional_encoding(x, 0, True, backend="kernel")
    (grad,) = torch.autograd.grad(out.sum(), x)
    assert torch.equal(grad, torch.ones_like(x))


@needs_kernels
def test_opcheck(gen):
    positional_encoding(torch.zeros(1, 3), 1, backend="kernel")  # loads the ops, registers fakes
    x = uniform((17, 3), 1.0, gen)
    for include_input in (True, False):
        args = (3, include_input, 1.0)
        out = torch.ops.mixer_nerf.positional_encoding_fwd(x, *args)
        torch.library.opcheck(torch.ops.mixer_nerf.positional_encoding_fwd, (x, *args))
        torch.library.opcheck(torch.ops.mixer_nerf.positional_encoding_bwd, (torch.randn_like(out), x, *args))


@pytest.mark.parametrize(
    "call, error, name",
    [
        (lambda: positional_encoding([1.0, 2.0], 2), TypeError, "x"),
        (lambda: positional_encoding(torch.ones(4, 3, dtype=torch.int32), 2), TypeError, "x"),
        (lambda: positional_encoding(torch.tensor(1.0), 2), ValueError, "x"),
        (lambda: positional_encoding(torch.ones(4, 0), 2), ValueError, "x"),
        (lambda: positional_encoding(torch.ones(4, 3), -1), ValueError, "num_freqs"),
        (lambda: positional_encoding(torch.ones(4, 3), MAX_FREQS + 1), ValueError, "num_freqs"),
        (lambda: positional_encoding(torch.ones(4, 3), 2.0), TypeError, "num_freqs"),
        (lambda: positional_encoding(torch.ones(4, 3), True), TypeError, "num_freqs"),
        (lambda: positional_encoding(torch.ones(4, 3), 2, include_input=1), TypeError, "include_input"),
        (lambda: positional_encoding(torch.ones(4, 3), 2, scale=float("nan")), ValueError, "scale"),
        (lambda: positional_encoding(torch.ones(4, 3), 2, scale=float("inf")), ValueError, "scale"),
        (lambda: positional_encoding(torch.ones(4, 3), 2, scale="pi"), TypeError, "scale"),
        (lambda: positional_encoding(torch.ones(4, 3), 2, backend="cuda"), ValueError, "backend"),
    ],
)
def test_bad_input(call, error, name):
    with pytest.raises(error, match=name):
        call()


@needs_kernels
def test_bwd_op_rejects_mismatched_grad():
    """The kernel's defensive shape check raises, naming the shapes. Run in a subprocess, so that a
    crash shows up as this test failing instead of ending the whole run: on the GPU machine (torch
    2.11+cu130, g++ 13.3) a TORCH_CHECK message that streams a shape killed the process with
    SIGSEGV (tools/diagnose_exception_crash.py); the kernels' MIXER_NERF_CHECK builds its own."""
    code = (
        "import torch\nfrom mixer_nerf import _extension\n_extension.load()\n"
        "try:\n"
        "    torch.ops.mixer_nerf.positional_encoding_bwd(torch.ones(4, 8), torch.ones(4, 3), 1, True, 1.0)\n"
        "except RuntimeError as exc:\n"
        "    print('raised' if 'grad_out must have shape [4, 9], got [4, 8]' in str(exc) else exc)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and "raised" in result.stdout, result.stderr[-2000:]


# --------------------------------------------------------------------------------------- CUDA


def poisoned_output(numel: int, dtype: torch.dtype, device) -> int:
    """Fill a cached CUDA block of exactly the output's size with NaN and free it: the caching
    allocator hands that same block to the next allocation of this size, so an output element the
    kernel does not write stays NaN. Returns the block's address to check that it was reused."""
    torch.cuda.empty_cache()  # drop other free blocks, so that the freed one is the best fit
    block = torch.full((numel,), float("nan"), dtype=dtype, device=device)
    ptr = block.data_ptr()
    del block
    return ptr


def cuda_forward_backward(x, num_freqs, include_input, scale, backend, grad):
    xr = x.clone().requires_grad_()
    out = positional_encoding(xr, num_freqs, include_input, scale, backend=backend)
    (gx,) = torch.autograd.grad(out, xr, grad)
    return out, gx


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize(
    "shape, num_freqs, include_input",
    [
        ((1, 3), 10, True),
        ((31, 3), 4, False),
        ((1000, 1), 16, True),
        ((257, 5), 0, True),
        ((0, 3), 3, True),
        ((3, 7, 3), 10, True),
        ((40, 200), 3, True),
        ((9, 3), MAX_FREQS, False),
        ((4, 2000), 8, True),
    ],
)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
def test_cuda_matches_cpu_and_truth(shape, num_freqs, include_input, dtype, gen):
    x = uniform(shape, 4.0, gen, dtype)
    grad = torch.randn(*shape[:-1], shape[-1] * (int(include_input) + 2 * num_freqs), generator=gen).to(dtype)
    xc, gc = x.cuda(), grad.cuda()
    for scale in (math.pi, 1.0):
        out_cpu, gx_cpu = cuda_forward_backward(x, num_freqs, include_input, scale, "kernel", grad)
        ptr = poisoned_output(out_cpu.numel(), dtype, xc.device)
        out = positional_encoding(xc, num_freqs, include_input, scale, backend="kernel")
        if out.numel():
            assert out.data_ptr() == ptr  # the NaN-filled block was reused: all of it was written
        assert bool(torch.isfinite(out).all())
        if num_freqs <= 16:
            assert_within_bound(out, x, num_freqs, include_input, scale)
        # Same double phase as the CPU kernel; the polynomials differ by FMA contraction only, so the
        # two agree to the output's rounding (float64 x: plus their shared phase rounding bound).
        _, angles = truth(x, num_freqs, include_input, scale)
        phase = 2.0**-52 * angles if dtype == torch.float64 else 0.0
        assert bool(
            ((out.cpu().double() - out_cpu.double()).abs() <= 2 * HALF_ULP[dtype] + 1e-15 + phase).all()
        )

        xr = xc.clone().requires_grad_()
        encoded = positional_encoding(xr, num_freqs, include_input, scale, backend="kernel")
        ptr = poisoned_output(x.numel(), dtype, xc.device)
        (gx,) = torch.autograd.grad(encoded, xr, gc)  # grad_x is the backward's first allocation
        if gx.numel():
            assert gx.data_ptr() == ptr
        magnitude = gradient_magnitude(grad, num_freqs, include_input, scale)
        if bool((magnitude < torch.finfo(dtype).max / 4).all()):  # half/bf16 gradients may overflow
            assert bool(torch.isfinite(gx).all())
            # Both accumulate the terms in float32 (float64) in the same order: differences come from
            # FMA contraction and the output rounding, a few ulps of the terms' magnitude.
            err = (gx.double().cpu() - gx_cpu.double()).abs()
            eps = 2 * (HALF_ULP[torch.float64 if dtype == torch.float64 else torch.float32])
            # (an ulp of the output is up to 4 HALF_ULP of its magnitude, at the bottom of a binade)
            assert bool((err <= 8 * eps * magnitude + 4 * HALF_ULP[dtype] * gx_cpu.double().abs()).all())
        if dtype == torch.float32 and num_freqs <= 4:
            _, gx_ref = cuda_forward_backward(xc, num_freqs, include_input, scale, "torch", gc)
            # The reference's phases are off by ~|θ| 2^-24 <= 1e-5 here, times scale 2^k <= 25.
            torch.testing.assert_close(gx, gx_ref, rtol=1e-4, atol=1e-3)


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize("magnitude, num_freqs", [(1e3, 10), (1e4, 16)])
def test_cuda_high_frequencies(magnitude, num_freqs, gen):
    x = uniform((100_003, 3), magnitude, gen)
    for scale in SCALES:
        out = positional_encoding(x.cuda(), num_freqs, False, scale, backend="kernel")
        assert_within_bound(out, x, num_freqs, False, scale)


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_output_beyond_32_bit_indexing(gen):
    """2^25 + 77 rows x 63 columns = 2.1e9 > 2^31 output elements, with a ragged last tile."""
    x = uniform((1 << 25 | 77, 3), 2.0, gen, device="cuda")
    out = positional_encoding(x, 10, backend="kernel")
    rows = torch.cat([torch.arange(0, 64), torch.arange(x.shape[0] - 64, x.shape[0])]).cuda()
    assert_within_bound(out[rows], x[rows], 10, True, math.pi)
    assert bool(torch.isfinite(out).all())
    del out
    g = torch.ones(x.shape[0], 63, device="cuda")
    xr = x.requires_grad_()
    (gx,) = torch.autograd.grad(positional_encoding(xr, 10, backend="kernel"), xr, g)
    _, gx_tail = cuda_forward_backward(x[rows].detach().cpu(), 10, True, math.pi, "kernel", g[rows].cpu())
    torch.testing.assert_close(gx[rows].cpu(), gx_tail, rtol=1e-5, atol=1e-2)
