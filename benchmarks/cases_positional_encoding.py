"""Benchmark cases for positional_encoding (NeRF's Fourier features of sample positions).

Sizes: 10 octaves of D=3 coordinates (63 output columns with the input), 1M points on CPU and
12.6M on CUDA (65536 rays x 192 samples), float32. Two input ranges: |x| <= 1 (normalised scene
coordinates) and |x| <= 100 (unnormalised ones), where the reference's float32 phase rounding
shows in its error column. Modes: fwd, and fwd+bwd (output and grad of x for a fixed upstream
gradient). The byte floor is x read and the (N, 63) encoding written; fwd+bwd adds the upstream
gradient read, x read again and grad_x written. nerfacc 0.5.3 has no positional encoding op.
"""

from __future__ import annotations

import math

import torch

from benchmarks.harness import Case, Variant
from mixer_nerf.ops.positional_encoding import positional_encoding
from mixer_nerf.ops.positional_encoding_reference import positional_encoding_reference

DIMS, FREQS = 3, 10
WIDTH = DIMS * (1 + 2 * FREQS)


def forward_and_grad(fn, x: torch.Tensor, grad: torch.Tensor):
    xr = x.detach().requires_grad_()
    out = fn(xr)
    (grad_x,) = torch.autograd.grad(out, xr, grad)
    return out, grad_x


def encoding_cases(points: int, magnitude: float, device: torch.device) -> list[Case]:
    gen = torch.Generator(device=device).manual_seed(0)
    x = (torch.rand(points, DIMS, generator=gen, device=device) * 2 - 1) * magnitude
    grad = torch.randn(points, WIDTH, generator=gen, device=device)
    impls = {
        "kernel": lambda t: positional_encoding(t, FREQS, True, math.pi, backend="kernel"),
        "torch": lambda t: positional_encoding_reference(t, FREQS, True, math.pi),
    }
    if device.type == "cuda":
        compiled = torch.compile(positional_encoding_reference)
        impls["torch.compile"] = lambda t: compiled(t, FREQS, True, math.pi)

    def truth_forward():
        return positional_encoding_reference(x.double(), FREQS, True, math.pi)

    def truth_both():
        return forward_and_grad(
            lambda t: positional_encoding_reference(t, FREQS, True, math.pi), x.double(), grad.double()
        )

    def no_grad(fn):
        def run():
            with torch.no_grad():
                return fn(x)

        return run

    item = x.element_size()
    fwd_bytes = points * (DIMS + WIDTH) * item
    size = f"N={points} D={DIMS} F={FREQS} |x|<={magnitude:g}"
    return [
        Case(
            "positional_encoding",
            "fwd",
            size,
            [Variant(n, no_grad(f)) for n, f in impls.items()],
            truth_forward,
            fwd_bytes,
        ),
        Case(
            "positional_encoding",
            "fwd+bwd",
            size,
            [Variant(n, lambda f=f: forward_and_grad(f, x, grad)) for n, f in impls.items()],
            truth_both,
            fwd_bytes + points * (WIDTH + 2 * DIMS) * item,
        ),
    ]


def cases(device: torch.device) -> list[Case]:
    points = 12_582_912 if device.type == "cuda" else 1 << 20  # 65536 x 192 on CUDA
    return [case for magnitude in (1.0, 100.0) for case in encoding_cases(points, magnitude, device)]
