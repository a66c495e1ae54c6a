"""Benchmark cases for linear_relu (a trunk layer: GEMM, bias and ReLU, and their backward).

Size: 131072 samples (the occupancy recipe's samples per step) through a 256 -> 256 layer on
CUDA, 16384 on CPU, float32 with the trainer's TF32 matmuls. Variants: the fused passes (bias
and ReLU in cuBLASLt's epilogue, the bias gradient as a gemv), the eager reference (what
``nn.Linear`` + ``torch.relu`` run) and, on CUDA, the reference under torch.compile. Modes: fwd,
and fwd+bwd with the gradients of x, the weight and the bias. The byte floor is x read and the
output written; fwd+bwd adds the upstream gradient, x and the output (the mask) read and dx
written.
"""

from __future__ import annotations

import torch

from benchmarks.harness import Case, Variant
from mixer_nerf.ops.linear_relu import linear_relu
from mixer_nerf.ops.linear_relu_reference import linear_relu_reference

WIDTH = 256


def linear_relu_cases(samples: int, device: torch.device) -> list[Case]:
    gen = torch.Generator(device=device).manual_seed(0)
    x = torch.randn(samples, WIDTH, generator=gen, device=device)
    weight = torch.randn(WIDTH, WIDTH, generator=gen, device=device) * WIDTH**-0.5
    bias = torch.randn(WIDTH, generator=gen, device=device) * 0.1
    grad = torch.randn(samples, WIDTH, generator=gen, device=device)
    impls = {"kernel": lambda *a: linear_relu(*a, backend="kernel"), "torch": linear_relu_reference}
    if device.type == "cuda":
        impls["torch.compile"] = torch.compile(linear_relu_reference)

    def both(fn, *tensors):
        leaves = [t.detach().requires_grad_() for t in tensors]
        out = fn(*leaves)
        return out, *torch.autograd.grad(out, leaves, grad.to(out.dtype))

    def no_grad(fn):
        def run():
            with torch.no_grad():
                return fn(x, weight, bias)

        return run

    def truth_forward():
        return linear_relu_reference(x.double(), weight.double(), bias.double())

    def truth_both():
        # The ReLU's mask of the float32 forward: a pre-activation within rounding of 0 would
        # otherwise flip sign in float64 and count a whole gradient row as error.
        mask = linear_relu_reference(x, weight, bias) > 0
        x64, w64, b64, g64 = x.double(), weight.double(), bias.double(), grad.double() * mask
        return torch.relu(x64 @ w64.t() + b64), g64 @ w64, g64.t() @ x64, g64.sum(0)

    item = x.element_size()
    fwd_bytes = 2 * samples * WIDTH * item
    size = f"N={samples} {WIDTH}->{WIDTH}"
    return [
        Case("linear_relu", "fwd", size, [Variant(n, no_grad(f)) for n, f in impls.items()], truth_forward,
             fwd_bytes),
        Case("linear_relu", "fwd+bwd", size,
             [Variant(n, lambda f=f: both(f, x, weight, bias)) for n, f in impls.items()], truth_both,
             fwd_bytes + 4 * samples * WIDTH * item),
    ]


def cases(device: torch.device) -> list[Case]:
    return linear_relu_cases(131_072 if device.type == "cuda" else 16_384, device)
