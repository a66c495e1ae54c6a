"""Tests of linear_relu and linear (a layer with its bias, and ReLU, fused into the GEMM; the ReLU
mask and the bias gradient in one pass, the ops bias_grad and relu_bias_bwd): the fused passes
against the references, forward and backward, on fresh random inputs and on the edge of the ReLU,
on the CPU (the same autograd Function) and, where there is one, a CUDA GPU."""

from __future__ import annotations

import importlib

import pytest
import torch

from mixer_nerf.ops import linear, linear_relu
from mixer_nerf.ops.linear_relu_reference import linear_reference, linear_relu_reference

LAYER_MODULE = importlib.import_module("mixer_nerf.ops.linear_relu")

on_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
# each op with its reference
OPS = pytest.mark.parametrize("op, reference",
                              [(linear_relu, linear_relu_reference), (linear, linear_reference)],
                              ids=["linear_relu", "linear"])


def layer(gen, shape, width_in, width_out, dtype, device="cpu"):
    def rand(*size):
        return torch.randn(size, generator=gen, dtype=torch.float64).to(device, dtype)

    return rand(*shape, width_in), rand(width_out, width_in) * width_in**-0.5, rand(width_out) * 0.1


def outputs_and_grads(fn, x, weight, bias, upstream):
    leaves = [t.detach().requires_grad_() for t in (x, weight, bias)]
    out = fn(*leaves)
    return out, *torch.autograd.grad(out, leaves, upstream)


@pytest.mark.parametrize("shape", [(1,), (37,), (4, 9), (2, 3, 5)])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
@OPS
def test_fused_matches_reference_forward_and_backward(gen, shape, dtype, tol, op, reference):
    x, weight, bias = layer(gen, shape, 24, 16, dtype)
    upstream = torch.randn(*shape, 16, generator=gen, dtype=torch.float64).to(dtype)
    fused = outputs_and_grads(lambda *a: op(*a, backend="kernel"), x, weight, bias, upstream)
    reference = outputs_and_grads(reference, x, weight, bias, upstream)
    for got, want in zip(fused, reference, strict=True):
        assert got.shape == want.shape and got.dtype == want.dtype
        torch.testing.assert_close(got, want, rtol=tol, atol=tol)


@OPS
def test_gradcheck(gen, op, reference):
    x, weight, bias = layer(gen, (6,), 5, 4, torch.float64)
    inputs = [t.requires_grad_() for t in (x, weight, bias)]
    assert torch.autograd.gradcheck(lambda *a: op(*a, backend="kernel"), inputs)


@OPS
def test_gradgradcheck(gen, op, reference):
    """A second derivative through the layer (create_graph) takes the differentiable ATen path."""
    x, weight, bias = layer(gen, (6,), 5, 4, torch.float64)
    inputs = [t.requires_grad_() for t in (x, weight, bias)]
    assert torch.autograd.gradgradcheck(lambda *a: op(*a, backend="kernel"), inputs)


def test_relu_edge_gets_no_gradient_like_torch_relu():
    """Pre-activations exactly 0 (a dead unit, zero inputs) pass no gradient, as torch.relu's
    backward; negative ones none either; only x's rows with positive outputs reach the weights."""
    x = torch.tensor([[0.0, 0.0], [1.0, -2.0]])
    weight = torch.tensor([[1.0, 1.0], [1.0, 0.0], [-1.0, 0.0]])
    bias = torch.zeros(3)
    upstream = torch.ones(2, 3)
    fused = outputs_and_grads(lambda *a: linear_relu(*a, backend="kernel"), x, weight, bias, upstream)
    reference = outputs_and_grads(linear_relu_reference, x, weight, bias, upstream)
    for got, want in zip(fused, reference, strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    assert fused[3].tolist() == [0.0, 1.0, 0.0]  # bias gradient: only the unit that fired


@OPS
def test_only_the_needed_gradients_are_computed(gen, op, reference):
    x, weight, bias = layer(gen, (8,), 6, 5, torch.float64)
    weight.requires_grad_()
    out = op(x, weight, bias, backend="kernel")
    (grad,) = torch.autograd.grad(out.sum(), [weight])
    torch.testing.assert_close(grad, torch.autograd.grad(reference(x, weight, bias).sum(), [weight])[0])


@OPS
def test_auto_on_the_cpu_is_the_reference(gen, op, reference):
    x, weight, bias = layer(gen, (10,), 8, 4, torch.float32)
    assert torch.equal(op(x, weight, bias), reference(x, weight, bias))


@OPS
def test_under_autocast_the_fused_passes_run_in_its_dtype(gen, op, reference):
    """The fused GEMM in bf16 where autocast would run F.linear in bf16: the output in bf16, the
    float32 leaves' gradients back through the casts, both as the eager path's within bf16's
    rounding (2^-8 relative; a unit that sits at the ReLU's edge may flip, so the loose atol)."""
    x, weight, bias = layer(gen, (64,), 48, 32, torch.float32)
    upstream = torch.randn(64, 32, generator=gen)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        fused = outputs_and_grads(lambda *a: op(*a, backend="kernel"), x, weight, bias, upstream)
        eager = outputs_and_grads(reference, x, weight, bias, upstream)
    assert fused[0].dtype == eager[0].dtype == torch.bfloat16
    for got, want in zip(fused, eager, strict=True):
        assert got.dtype == want.dtype
        scale = want.abs().max().item()
        torch.testing.assert_close(got.float(), want.float(), rtol=2**-6, atol=2**-6 * scale)
    assert [g.dtype for g in fused[1:]] == [torch.float32] * 3


def bias_grad_truth(grad, out=None):
    """(masked grad, its column sums) in float64, the mask as torch's threshold_backward (a NaN output
    passes)."""
    g = grad.double() if out is None else torch.ops.aten.threshold_backward(grad.double(), out.double(), 0)
    return g, g.sum(0)


@pytest.mark.parametrize("rows", [0, 1, 255, 1000])
@pytest.mark.parametrize("cols", [1, 3, 16, 300])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5),
                                        (torch.bfloat16, 2**-7), (torch.float16, 2**-9)])
def test_bias_kernels_match_float64_sums(gen, rows, cols, dtype, tol):
    grad = torch.randn(rows, cols, generator=gen, dtype=torch.float64).to(dtype)
    out = torch.randn(rows, cols, generator=gen, dtype=torch.float64).relu().to(dtype)
    if rows and cols > 1:
        out[0, 0], out[-1, 1] = 0, float("nan")  # the ReLU's edge: no gradient; NaN: passes, as torch's mask
    masked, sums = torch.ops.mixer_nerf.relu_bias_bwd(grad, out)
    plain = torch.ops.mixer_nerf.bias_grad(grad)
    want_masked, want_sums = bias_grad_truth(grad, out)
    assert masked.dtype == sums.dtype == plain.dtype == dtype and sums.shape == plain.shape == (cols,)
    assert torch.equal(masked, want_masked.to(dtype))  # a mask rounds nothing
    scale = grad.double().abs().sum(0).clamp_min(1)  # a sum's rounding grows with what it adds up
    assert ((sums.double() - want_sums).abs() <= tol * scale).all()
    assert ((plain.double() - bias_grad_truth(grad)[1]).abs() <= tol * scale).all()
    assert torch.equal(torch.ops.mixer_nerf.relu_bias_bwd(grad, out)[1], sums)  # deterministic


@OPS
def test_without_the_extension_the_layer_backward_takes_a_gemv(gen, op, reference, monkeypatch):
    """Where the extension has no kernels for a device the backward masks with ATen and sums with
    a GEMV: the same gradients."""
    monkeypatch.setattr(LAYER_MODULE, "use_kernel", lambda backend, device: False)
    x, weight, bias = layer(gen, (40,), 12, 8, torch.float64)
    upstream = torch.randn(40, 8, generator=gen, dtype=torch.float64)
    fused = outputs_and_grads(lambda *a: op(*a, backend="kernel"), x, weight, bias, upstream)
    for got, want in zip(fused, outputs_and_grads(reference, x, weight, bias, upstream), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_bias_kernels_opcheck(gen):
    linear_relu(*layer(gen, (3,), 4, 5, torch.float32), backend="kernel")  # registers the fake kernels
    grad = torch.randn(37, 5, generator=gen)
    out = torch.randn(37, 5, generator=gen).relu()
    torch.library.opcheck(torch.ops.mixer_nerf.bias_grad.default, (grad,))
    torch.library.opcheck(torch.ops.mixer_nerf.relu_bias_bwd.default, (grad, out))


def test_bias_kernels_refuse_what_they_cannot_read(gen):
    grad = torch.randn(6, 4, generator=gen)
    with pytest.raises(RuntimeError, match="contiguous"):
        torch.ops.mixer_nerf.bias_grad(grad.t())
    with pytest.raises(RuntimeError, match="floating"):
        torch.ops.mixer_nerf.bias_grad(grad.long())
    with pytest.raises(RuntimeError, match="like grad"):
        torch.ops.mixer_nerf.relu_bias_bwd(grad, grad[:3])


@pytest.mark.parametrize("args, error, match", [
    (lambda x, w, b: (x[..., :3], w, b), ValueError, "weight must have shape"),
    (lambda x, w, b: (x, w, b[:2]), ValueError, "bias must have shape"),
    (lambda x, w, b: (x.double(), w, b), TypeError, "one dtype"),
    (lambda x, w, b: (x.long(), w, b), TypeError, "x must be a floating-point"),
    (lambda x, w, b: (x[0, 0], w, b), ValueError, "scalar"),
    (lambda x, w, b: (x.to("meta"), w, b), ValueError, "one device"),
])
@OPS
def test_bad_input_is_refused_naming_the_argument(gen, args, error, match, op, reference):
    x, weight, bias = layer(gen, (4,), 6, 5, torch.float32)
    with pytest.raises(error, match=match):
        op(*args(x, weight, bias), backend="kernel")
    with pytest.raises(ValueError, match="backend"):
        op(x, weight, bias, backend="cuda")


@on_cuda
@pytest.mark.cuda
@pytest.mark.parametrize("tf32", [False, True])
@pytest.mark.parametrize("relu", [True, False])
def test_cuda_fused_matches_float64_with_its_own_mask(gen, tf32, relu, monkeypatch):
    """On the GPU the fused passes go through cuBLASLt's bias(+ReLU) epilogue and cuBLAS's gemv,
    with TF32 matmuls off and on (training's setting). Against float64 math on the ReLU mask of
    the fused output: another GEMM kernel rounds the pre-activations differently, and one that
    lands within rounding of 0 flips, moving a whole gradient row."""
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_tf32", tf32)
    x, weight, bias = layer(gen, (4096,), 256, 256, torch.float32, "cuda")
    upstream = torch.randn(4096, 256, generator=gen).cuda()
    op = linear_relu if relu else linear
    out, grad_x, grad_weight, grad_bias = outputs_and_grads(op, x, weight, bias, upstream)
    x64, w64 = x.double(), weight.double()
    g64 = upstream.double() * (out > 0) if relu else upstream.double()
    pre = x64 @ w64.t() + bias.double()
    truth = (torch.relu(pre) if relu else pre, g64 @ w64, g64.t() @ x64, g64.sum(0))
    tol = 2e-3 if tf32 else 1e-5  # of each tensor's largest magnitude
    for got, want in zip((out, grad_x, grad_weight, grad_bias), truth, strict=True):
        assert got.dtype == torch.float32 and torch.isfinite(got).all()
        assert (got.double() - want).abs().max() <= tol * want.abs().max()


@on_cuda
@pytest.mark.cuda
@pytest.mark.parametrize("rows, cols, offset", [(150_000, 256, 0), (4097, 301, 0), (3000, 64, 1), (1, 8, 0)])
@pytest.mark.parametrize("dtype, tol",
                         [(torch.float32, 1e-5), (torch.bfloat16, 2**-7), (torch.float64, 1e-12)])
def test_cuda_bias_kernels_match_float64_sums(gen, rows, cols, offset, dtype, tol):
    """Many bands (150,000 rows), channels that do not fill 16-byte columns (301) and tensors that
    start off 16-byte alignment (offset 1: the one-channel columns) against float64 sums, the mask
    bit for bit, and the same sums twice."""
    grad = torch.randn(rows * cols + offset, generator=gen, dtype=torch.float64).to(dtype).cuda()[offset:]
    out = torch.randn(rows * cols + offset, generator=gen, dtype=torch.float64).relu()
    out = out.to(dtype).cuda()[offset:]
    grad, out = grad.view(rows, cols), out.view(rows, cols)
    masked, sums = torch.ops.mixer_nerf.relu_bias_bwd(grad, out)
    want_masked, want_sums = bias_grad_truth(grad, out)
    assert torch.equal(masked, want_masked.to(dtype))
    scale = grad.double().abs().sum(0).clamp_min(1)
    assert ((sums.double() - want_sums).abs() <= tol * scale).all()
    plain = torch.ops.mixer_nerf.bias_grad(grad)
    assert ((plain.double() - bias_grad_truth(grad)[1]).abs() <= tol * scale).all()
    assert torch.equal(torch.ops.mixer_nerf.relu_bias_bwd(grad, out)[1], sums)
