"""Fused MLCA (Mixer-NeRF's token + channel mixing of an encoding): ``mlca``."""

from __future__ import annotations

import torch

from ._checks import check_alike, check_floating, check_shape
from ._dispatch import use_kernel
from ._kernel_op import KernelOp
from .mlca_reference import mlca_reference

# Kernel limits: the CUDA kernel keeps a channel of all of a point's tokens in registers, and a
# tile of points, its intermediates and the weights in shared memory.
MAX_TOKENS = 32
MAX_CHANNELS = 32
MAX_TOKEN_DIM = 32


def mlca(
    encoded: torch.Tensor,
    lift: torch.Tensor,
    token_weight: torch.Tensor,
    token_bias: torch.Tensor,
    channel_weight: torch.Tensor,
    channel_bias: torch.Tensor,
    backend: str = "auto",
) -> torch.Tensor:
    """Token + channel mixing of ``T`` tokens of ``D`` values per point, lifted to ``C`` channels.

    Per point, with ``X = encoded.view(T, D)``::

        L[t, c] = sum_k lift[c, k] X[t, k]
        Y[t, c] = L[t, c] + GELU(sum_s token_weight[t, s] L[s, c] + token_bias[t])
        Z[t, c] = Y[t, c] + GELU(sum_e channel_weight[c, e] Y[t, e] + channel_bias[c])

    GELU is the exact (erf) form. The kernels fuse all of it, recompute the intermediates from
    ``encoded`` in the backward and accumulate in float32 (float64 for float64 tensors); the
    plain-PyTorch formulation is :func:`mixer_nerf.ops.mlca_reference.mlca_reference`.

    Args:
        encoded: ``(..., T * D)``, token-major (token ``t`` is columns ``t*D:(t+1)*D``).
        lift: ``(C, D)``. token_weight: ``(T, T)``. token_bias: ``(T,)``.
        channel_weight: ``(C, C)``. channel_bias: ``(C,)``.
        backend: ``"auto"``, ``"kernel"`` or ``"torch"`` (see :mod:`mixer_nerf.ops`).

    All tensors must share one floating dtype (float32/64, half, bfloat16; the latter two
    compute in float32) and one device; ``T <= 32``, ``C <= 32``, ``D <= 32``.

    Returns:
        ``(..., T * C)`` token-major, dtype of ``encoded``; differentiable in every input.
    """
    tensors = {
        "encoded": encoded,
        "lift": lift,
        "token_weight": token_weight,
        "token_bias": token_bias,
        "channel_weight": channel_weight,
        "channel_bias": channel_bias,
    }
    for name, t in tensors.items():
        check_floating(name, t)
    if lift.dim() != 2 or 0 in lift.shape:
        raise ValueError(f"lift must have shape (C, D) with C, D >= 1, got {tuple(lift.shape)}")
    if token_weight.dim() != 2 or token_weight.shape[0] != token_weight.shape[1] or token_weight.shape[0] == 0:
        raise ValueError(f"token_weight must have shape (T, T) with T >= 1, got {tuple(token_weight.shape)}")
    (channels, token_dim), num_tokens = lift.shape, token_weight.shape[0]
    if num_tokens > MAX_TOKENS:
        raise ValueError(f"token_weight: at most {MAX_TOKENS} tokens are supported, got {num_tokens}")
    if channels > MAX_CHANNELS or token_dim > MAX_TOKEN_DIM:
        raise ValueError(
            f"lift: at most {MAX_CHANNELS} channels of at most {MAX_TOKEN_DIM} values per token are "
            f"supported, got shape {tuple(lift.shape)}"
        )
    check_shape("token_bias", token_bias, (num_tokens,), " (T from token_weight)")
    check_shape("channel_weight", channel_weight, (channels, channels), " (C from lift)")
    check_shape("channel_bias", channel_bias, (channels,), " (C from lift)")
    if encoded.dim() < 1 or encoded.shape[-1] != num_tokens * token_dim:
        raise ValueError(
            f"encoded must have shape (..., T*D) = (..., {num_tokens}*{token_dim}) (T from token_weight, "
            f"D from lift), got {tuple(encoded.shape)}"
        )
    check_alike(**tensors)

    if not use_kernel(backend, encoded.device):
        return mlca_reference(encoded, lift, token_weight, token_bias, channel_weight, channel_bias)
    if encoded.dim() == 2:  # packed rows are the kernel's layout: no views to record and backpropagate
        return _MLCA(encoded, lift, token_weight, token_bias, channel_weight, channel_bias)
    flat = encoded.reshape(-1, num_tokens * token_dim)
    out = _MLCA(flat, lift, token_weight, token_bias, channel_weight, channel_bias)
    return out.view(*encoded.shape[:-1], num_tokens * channels)


def _mlca_fwd_fake(encoded, lift, token_weight, token_bias, channel_weight, channel_bias):
    return encoded.new_empty(encoded.shape[0], token_weight.shape[0] * lift.shape[0])


def _mlca_bwd_fake(grad_out, encoded, *weights_and_flag):
    *weights, input_grad = weights_and_flag
    return (torch.empty_like(encoded) if input_grad else None, *(torch.empty_like(t) for t in weights))


_MLCA = KernelOp("mlca_fwd", _mlca_fwd_fake, "mlca_bwd", _mlca_bwd_fake)
