"""``relu(x W^T + b)`` and ``x W^T + b``, the MLP's layers, with hand-written passes around cuBLAS.

Forward: one GEMM whose epilogue adds the bias (and applies the ReLU: ``torch._addmm_activation``,
cuBLASLt on CUDA), instead of a GEMM, a bias pass and a ReLU pass. Backward: the ReLU mask applied
once to the upstream gradient ``g`` and the bias gradient (its column sums) taken in the same pass
(``mixer_nerf::relu_bias_bwd``, or ``bias_grad`` without the ReLU: csrc/bias_grad.cpp), then
``dx = g W`` and ``dW = g^T x``. Where the extension has no kernels for the device, the mask is
ATen's ReLU backward and the bias gradient the GEMV ``g^T 1`` (cuBLAS), not autograd's column
reduction (a slow kernel for an (N, out) gradient in bf16). Saves what the eager path saves (``x``,
and for the ReLU the output, whose sign is the mask). The references are in
:mod:`mixer_nerf.ops.linear_relu_reference`.
"""

from __future__ import annotations

import contextlib

import torch

from ._checks import check_backend, check_floating, check_same_device, check_same_dtype, check_shape
from ._dispatch import use_kernel
from ._kernel_op import declare_fake
from .linear_relu_reference import linear_reference, linear_relu_reference

declare_fake("bias_grad", lambda grad: grad.new_empty(grad.shape[1]))
declare_fake("relu_bias_bwd", lambda grad, out: (torch.empty_like(grad), grad.new_empty(grad.shape[1])))


def linear_relu(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor,
                backend: str = "auto") -> torch.Tensor:
    """``relu(x W^T + b)``: x ``(..., in)``, weight ``(out, in)``, bias ``(out,)`` -> ``(..., out)``.

    ``backend``: ``"auto"`` the fused passes on CUDA (the reference on a CPU), ``"kernel"`` the
    fused passes anywhere, ``"torch"`` the reference. Under autocast the fused passes run in
    autocast's dtype, as ``F.linear`` would (x, weight and bias cast to it; the output in it; the
    gradients flow back through the casts). Raises ValueError/TypeError naming the argument for
    bad shapes, dtypes or devices.
    """
    return _layer(x, weight, bias, backend, relu=True)


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """``x W^T + b`` with shapes, backends, autocast and errors as :func:`linear_relu`."""
    return _layer(x, weight, bias, backend, relu=False)


def _layer(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, backend: str,
           relu: bool) -> torch.Tensor:
    check_backend(backend)
    for name, t in (("x", x), ("weight", weight), ("bias", bias)):
        check_floating(name, t)
    if x.dim() == 0:
        raise ValueError("x must have shape (..., in), got a scalar")
    check_shape("weight", weight, (None, x.shape[-1]), " (out, in) with in = x.shape[-1]")
    check_shape("bias", bias, (weight.shape[0],), " (out,)")
    check_same_device(x=x, weight=weight, bias=bias)
    autocast = torch.is_autocast_enabled(x.device.type)
    if not autocast:
        check_same_dtype(x=x, weight=weight, bias=bias)
    if backend == "torch" or (backend == "auto" and not x.is_cuda):
        return (linear_relu_reference if relu else linear_reference)(x, weight, bias)
    if autocast:  # the fused GEMM in the reduced dtype: the eager path would add bias and ReLU passes
        dtype = torch.get_autocast_dtype(x.device.type)
        x, weight, bias = x.to(dtype), weight.to(dtype), bias.to(dtype)
    with torch.autocast(x.device.type, enabled=False) if autocast else contextlib.nullcontext():
        out = _Layer.apply(x.reshape(-1, x.shape[-1]), weight, bias, relu, use_kernel("auto", x.device))
    return out.reshape(*x.shape[:-1], weight.shape[0])


class _Layer(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, relu: bool,
                bias_kernels: bool) -> torch.Tensor:
        out = torch._addmm_activation(bias, x, weight.t()) if relu else torch.addmm(bias, x, weight.t())
        ctx.relu, ctx.bias_kernels = relu, bias_kernels
        ctx.save_for_backward(x, weight, out if relu else None)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, weight, out = ctx.saved_tensors
        g, grad_bias = _masked_and_bias_grad(ctx, grad.contiguous(), out)
        grad_x = g @ weight if ctx.needs_input_grad[0] else None
        grad_weight = g.t() @ x if ctx.needs_input_grad[1] else None
        return grad_x, grad_weight, grad_bias, None, None


def _masked_and_bias_grad(ctx, grad: torch.Tensor, out: torch.Tensor | None):
    """The upstream gradient with the ReLU's mask applied (no gradient where the output is 0, as for
    torch.relu) and the bias gradient (None where none is wanted)."""
    wants_bias = ctx.needs_input_grad[2]
    # one pass, mask and column sums together; not under create_graph (our kernels have no backward)
    if wants_bias and ctx.bias_kernels and not torch.is_grad_enabled():
        if ctx.relu:
            return torch.ops.mixer_nerf.relu_bias_bwd(grad, out)
        return grad, torch.ops.mixer_nerf.bias_grad(grad)
    g = torch.ops.aten.threshold_backward(grad, out, 0) if ctx.relu else grad
    return g, (torch.mv(g.t(), g.new_ones(g.shape[0])) if wants_bias else None)
