"""NeRF positional encoding with high-frequency accuracy: ``positional_encoding``."""

from __future__ import annotations

import math
import numbers

import torch

from ._checks import check_floating
from ._dispatch import use_kernel
from ._kernel_op import KernelOp
from .positional_encoding_reference import positional_encoding_reference

MAX_FREQS = 64  # beyond this, scale * 2**k leaves the float32 range of the backward's factors


def positional_encoding(
    x: torch.Tensor,
    num_freqs: int,
    include_input: bool = True,
    scale: float = math.pi,
    backend: str = "auto",
) -> torch.Tensor:
    """Encode ``x`` as ``[x, sin(scale 2^0 x), cos(scale 2^0 x), ..., sin(scale 2^(F-1) x), cos(...)]``.

    Args:
        x: ``(..., D)`` floating tensor (float32/64, half, bfloat16; half/bf16 compute in float32).
        num_freqs: ``F``, number of octaves, ``0 <= F <= 64``.
        include_input: whether ``x`` itself leads each row.
        scale: base angular frequency; ``math.pi`` (default) gives ``sin(pi 2^k x)``, ``1`` the
            original NeRF code's embedding.
        backend: ``"auto"``, ``"kernel"`` or ``"torch"`` (see :mod:`mixer_nerf.ops`).

    Returns:
        ``(..., D * (include_input + 2 F))``, each sin/cos block ``D`` wide, dtype of ``x``.
        Differentiable in ``x`` (the kernel's backward recomputes sin/cos from ``x``).

    Accuracy of the kernels: with ``θ = scale 2^k x``, the phase ``θ / π`` is carried in float64
    as ``(c_hi + c_lo) 2^k x``, ``c_hi + c_lo = scale / π`` to ~2^-80 and ``c_hi`` of 29 bits, so
    ``c_hi 2^k x`` is exact for float32/half/bf16 ``x``; it is reduced exactly modulo quarter
    turns and sin/cos of the remainder are evaluated in float64 and rounded once. ``scale ==
    math.pi`` is read as π itself (exact phase). The error of every sin/cos is thus

        float32 (half/bf16: before their final rounding):  <= 2^-25 + 7e-12 + |θ| 2^-78
        float64:                                            <= 5e-16 + |θ| 2^-53 (0 for math.pi)

    i.e. half an ulp of float32 for any frequency a float32 input can need: the only rounding that
    grows with ``θ`` is that of ``c_lo`` (and, for float64 ``x``, the unavoidable rounding of the
    product ``c_hi 2^k x`` to 53 bits). The reference formulation rounds ``θ`` itself to float32
    and is off by up to ``|θ| 2^-24`` (0.1 already at ``|x| = 1e3`` with 10 octaves). A finite
    ``x`` with ``|scale x / π| >= 2^900`` encodes like 0 (sin 0, cos 1): no NaN/Inf from finite
    inputs. ``x = ±inf`` or NaN gives NaN in every sin/cos column of that coordinate and in its
    gradient, as ``torch.sin`` (the reference path) does.
    """
    check_floating("x", x)
    if x.dim() < 1 or x.shape[-1] == 0:
        raise ValueError(f"x must have shape (..., D) with D >= 1, got {tuple(x.shape)}")
    if isinstance(num_freqs, bool) or not isinstance(num_freqs, numbers.Integral):
        raise TypeError(f"num_freqs must be an int, got {type(num_freqs).__name__}")
    if not 0 <= num_freqs <= MAX_FREQS:
        raise ValueError(f"num_freqs must be in [0, {MAX_FREQS}], got {num_freqs}")
    if not isinstance(include_input, bool):
        raise TypeError(f"include_input must be a bool, got {type(include_input).__name__}")
    if isinstance(scale, bool) or not isinstance(scale, numbers.Real):
        raise TypeError(f"scale must be a real number, got {type(scale).__name__}")
    if not math.isfinite(scale):
        raise ValueError(f"scale must be finite, got {scale}")

    if not use_kernel(backend, x.device):
        return positional_encoding_reference(x, int(num_freqs), include_input, float(scale))
    return _POSITIONAL_ENCODING(x, int(num_freqs), include_input, float(scale))


def _positional_encoding_fwd_fake(x, num_freqs, include_input, scale):
    return x.new_empty(*x.shape[:-1], x.shape[-1] * (int(include_input) + 2 * num_freqs))


def _positional_encoding_bwd_fake(grad_out, x, num_freqs, include_input, scale):
    return torch.empty_like(x)


_POSITIONAL_ENCODING = KernelOp(
    "positional_encoding_fwd",
    _positional_encoding_fwd_fake,
    "positional_encoding_bwd",
    _positional_encoding_bwd_fake,
)
