"""Benchmark cases for mlca (Mixer-NeRF's token + channel mixing of the positions' encoding).

Sizes: T=21 tokens (10 octaves) of D=3 values lifted to C=8 channels, float32, 262144 points on
CUDA (a training step of 1024 rays x 256 samples; 65536 points is a quarter of that) and 65536 on
CPU; weights random and non-zero (at init the mixing weights are zero). Variants: our kernel, the
eager reference (lift, einsum token mixing, linear channel mixing, GELUs) and, on CUDA, the
reference under torch.compile. Modes: fwd, and fwd+bwd for a fixed upstream gradient, with the
gradients of the five weights only (as in training, where the encoding of positions needs none).
The byte floor is encoded read and the (N, T*C) output written; fwd+bwd adds the upstream
gradient read and encoded read again (the kernel recomputes the intermediates).
"""

from __future__ import annotations

import torch

from benchmarks.harness import Case, Variant
from mixer_nerf.ops.mlca import mlca
from mixer_nerf.ops.mlca_reference import mlca_reference

TOKENS, CHANNELS, DIMS = 21, 8, 3


def weights(device: torch.device, gen: torch.Generator) -> list[torch.Tensor]:
    def rand(*shape, scale):
        return torch.randn(shape, generator=gen, device=device) * scale

    return [
        rand(CHANNELS, DIMS, scale=1.0),
        rand(TOKENS, TOKENS, scale=TOKENS**-0.5),
        rand(TOKENS, scale=0.5),
        rand(CHANNELS, CHANNELS, scale=CHANNELS**-0.5),
        rand(CHANNELS, scale=0.5),
    ]


def forward_and_grads(fn, encoded: torch.Tensor, params: list[torch.Tensor], grad: torch.Tensor):
    leaves = [p.detach().requires_grad_() for p in params]
    out = fn(encoded, *leaves)
    return out, *torch.autograd.grad(out, leaves, grad)


def mlca_cases(points: int, device: torch.device) -> list[Case]:
    gen = torch.Generator(device=device).manual_seed(0)
    encoded = torch.rand(points, TOKENS * DIMS, generator=gen, device=device) * 2 - 1
    params = weights(device, gen)
    grad = torch.randn(points, TOKENS * CHANNELS, generator=gen, device=device)
    impls = {
        "kernel": lambda *args: mlca(*args, backend="kernel"),
        "torch": mlca_reference,
    }
    if device.type == "cuda":
        impls["torch.compile"] = torch.compile(mlca_reference)

    def truth_forward():
        return mlca_reference(encoded.double(), *(p.double() for p in params))

    def truth_both():
        return forward_and_grads(mlca_reference, encoded.double(), [p.double() for p in params], grad.double())

    def no_grad(fn):
        def run():
            with torch.no_grad():
                return fn(encoded, *params)

        return run

    item = encoded.element_size()
    fwd_bytes = points * TOKENS * (DIMS + CHANNELS) * item
    size = f"N={points} T={TOKENS} C={CHANNELS} D={DIMS}"
    return [
        Case("mlca", "fwd", size, [Variant(n, no_grad(f)) for n, f in impls.items()], truth_forward, fwd_bytes),
        Case(
            "mlca",
            "fwd+bwd",
            size,
            [Variant(n, lambda f=f: forward_and_grads(f, encoded, params, grad)) for n, f in impls.items()],
            truth_both,
            fwd_bytes + points * TOKENS * (CHANNELS + DIMS) * item,
        ),
    ]


def cases(device: torch.device) -> list[Case]:
    return mlca_cases(262_144 if device.type == "cuda" else 65_536, device)
