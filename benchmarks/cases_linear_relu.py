"""Benchmark cases for linear_relu and linear (the MLP's layers: GEMM, bias (and ReLU), and their
backward).

Size: 131072 samples (the occupancy recipe's samples per step) through a 256 -> 256 layer on
CUDA, 16384 on CPU; float32 with the trainer's TF32 matmuls, and on CUDA bf16 too (what the
occupancy sampler trains in). Variants: the fused passes (bias and ReLU in cuBLASLt's epilogue,
the mask and the bias gradient in one pass of ours), the eager reference (what ``nn.Linear``
(+ ``torch.relu``) runs, its bias gradient a column sum) and, on CUDA, the reference under torch.compile. Modes: fwd, and
fwd+bwd with the gradients of x, the weight and the bias. The byte floor is x read and the output
written; fwd+bwd adds the upstream gradient and x read and dx written, and for the ReLU the output
(the mask) read.
"""

from __future__ import annotations

import torch

from benchmarks.harness import Case, Variant
from mixer_nerf.ops.linear_relu import linear, linear_relu
from mixer_nerf.ops.linear_relu_reference import linear_reference, linear_relu_reference

WIDTH = 256
LAYERS = {"linear_relu": (linear_relu, linear_relu_reference, True),
          "linear": (linear, linear_reference, False)}
"""op name: (fused op, reference, whether it applies a ReLU)"""


def layer_cases(name: str, samples: int, device: torch.device, dtype: torch.dtype) -> list[Case]:
    op, reference, relu = LAYERS[name]
    gen = torch.Generator(device=device).manual_seed(0)
    x = torch.randn(samples, WIDTH, generator=gen, device=device).to(dtype)
    weight = (torch.randn(WIDTH, WIDTH, generator=gen, device=device) * WIDTH**-0.5).to(dtype)
    bias = (torch.randn(WIDTH, generator=gen, device=device) * 0.1).to(dtype)
    grad = torch.randn(samples, WIDTH, generator=gen, device=device).to(dtype)
    impls = {"kernel": lambda *a: op(*a, backend="kernel"), "torch": reference}
    if device.type == "cuda":
        impls["torch.compile"] = torch.compile(reference)

    def both(fn, *tensors):
        leaves = [t.detach().requires_grad_() for t in tensors]
        out = fn(*leaves)
        return out, *torch.autograd.grad(out, leaves, grad)

    def no_grad(fn):
        def run():
            with torch.no_grad():
                return fn(x, weight, bias)

        return run

    def truth_forward():
        return reference(x.double(), weight.double(), bias.double())

    def truth_both():
        # The ReLU's mask of the forward in the op's dtype: a pre-activation within rounding of 0
        # would otherwise flip sign in float64 and count a whole gradient row as error.
        x64, w64, b64, g64 = x.double(), weight.double(), bias.double(), grad.double()
        if relu:
            g64 = g64 * (reference(x, weight, bias) > 0)
        return reference(x64, w64, b64), g64 @ w64, g64.t() @ x64, g64.sum(0)

    item = x.element_size()
    fwd_bytes = 2 * samples * WIDTH * item
    size = f"N={samples} {WIDTH}->{WIDTH} {str(dtype).removeprefix('torch.')}"
    return [
        Case(name, "fwd", size, [Variant(n, no_grad(f)) for n, f in impls.items()], truth_forward, fwd_bytes),
        Case(name, "fwd+bwd", size,
             [Variant(n, lambda f=f: both(f, x, weight, bias)) for n, f in impls.items()],
             truth_both, fwd_bytes + (4 if relu else 3) * samples * WIDTH * item),
    ]


def cases(device: torch.device) -> list[Case]:
    samples = 131_072 if device.type == "cuda" else 16_384
    dtypes = (torch.float32, torch.bfloat16) if device.type == "cuda" else (torch.float32,)
    return [case for dtype in dtypes for name in LAYERS for case in layer_cases(name, samples, device, dtype)]
