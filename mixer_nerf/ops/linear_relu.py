"""``relu(x W^T + b)`` and ``x W^T + b``, the MLP's layers, with hand-written passes around cuBLAS.

Forward: one GEMM whose epilogue adds the bias (and applies the ReLU: ``torch._addmm_activation``,
cuBLASLt on CUDA), instead of a GEMM, a bias pass and a ReLU pass. Backward: the ReLU mask applied
once to the upstream gradient ``g`` (ATen's ReLU backward), then ``dx = g W``, ``dW = g^T x`` and
the bias gradient as the matrix-vector product ``g^T 1`` (cuBLAS), instead of autograd's column
reduction (a slow kernel for an (N, out) gradient in bf16). Saves what the eager path saves (``x``,
and for the ReLU the output, whose sign is the mask). The references are in
:mod:`mixer_nerf.ops.linear_relu_reference`.
"""

from __future__ import annotations

import contextlib

import torch

from ._checks import check_backend, check_floating, check_same_device, check_same_dtype, check_shape
from .linear_relu_reference import linear_reference, linear_relu_reference


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
        out = _Layer.apply(x.reshape(-1, x.shape[-1]), weight, bias, relu)
    return out.reshape(*x.shape[:-1], weight.shape[0])


class _Layer(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, relu: bool) -> torch.Tensor:
        out = torch._addmm_activation(bias, x, weight.t()) if relu else torch.addmm(bias, x, weight.t())
        ctx.relu = relu
        ctx.save_for_backward(x, weight, out if relu else None)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, weight, out = ctx.saved_tensors
        # relu's own backward, one vectorised pass (a comparison and a where with a scalar were two,
        # the second unvectorised): no gradient where the output is 0, as for torch.relu
        g = torch.ops.aten.threshold_backward(grad, out, 0) if ctx.relu else grad
        grad_x = g @ weight if ctx.needs_input_grad[0] else None
        grad_weight = g.t() @ x if ctx.needs_input_grad[1] else None
        grad_bias = torch.mv(g.t(), g.new_ones(g.shape[0])) if ctx.needs_input_grad[2] else None
        return grad_x, grad_weight, grad_bias, None
