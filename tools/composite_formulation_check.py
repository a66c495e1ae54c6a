"""Do the CUDA composite kernels' forms round to the same float32 results as the definitions?

Usage: PYTHONPATH=. python tools/composite_formulation_check.py [--rays 4096]   (from the repository root)

On the CPU, in float64, on the error budget's four distributions (benchmarks/error_budget.py):
T as a running product of exp(-tau) (the kernels' product scans) and the sigma gradient as the
suffix sum ``T_{j+1} g_j - sum_{k>j} w_k g_k - T_S G`` (the CUDA backward), rounded to float32,
against the float64 truth of the definitions; the CPU kernel's affine recurrence
``T_{j+1} (g_j - G_{j+1})`` beside it. Prints max / median relative errors per quantity, as the
error budget does (half a float32 ulp is 6.0e-08). A check of the formulas before a GPU run, not
of the kernels: the GPU's error budget is the judge.
"""

from __future__ import annotations

import argparse

import torch

from benchmarks.error_budget import (
    cast,
    composite_inputs,
    composite_truth,
    forward_and_grads,
    relative_errors,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=4096)
    args = parser.parse_args()
    R, S = args.rays, 192
    gen = torch.Generator().manual_seed(0)
    for dist in ("typical", "thin", "dense", "extreme"):
        inputs = composite_inputs(dist, R, S, gen, "cpu")
        upstream = [torch.randn(s, generator=gen, dtype=torch.float64) for s in ((R, 3), (R,), (R,), (R, S))]
        exact, cot = [cast(x, torch.float32) for x in inputs], [cast(g, torch.float32) for g in upstream]
        truth = forward_and_grads(composite_truth, exact, cot, [0, 3])
        sigmas, rgbs, t_starts, t_ends, background = exact
        grad_color, grad_depth, grad_opacity, grad_weights = cot
        tau = sigmas * (t_ends - t_starts)
        decay, alpha = torch.exp(-tau), -torch.expm1(-tau)
        T = torch.cat([torch.ones(R, 1, dtype=torch.float64), torch.cumprod(decay, 1)[:, :-1]], 1)
        t_after, w = T * decay, T * alpha
        T_S = T[:, -1] * decay[:, -1]
        color = (w[..., None] * rgbs).sum(1) + torch.exp(-tau.sum(1))[:, None] * background
        midpoints = 0.5 * (t_starts + t_ends)
        g = grad_depth[:, None] * midpoints + grad_weights + (grad_color[:, None] * rgbs).sum(-1)
        depth = (w * midpoints).sum(1)
        G_end = (grad_color * background).sum(-1) - grad_opacity
        suffix, affine = torch.empty_like(tau), torch.empty_like(tau)
        after, G = T_S * G_end, G_end.clone()
        for j in range(S - 1, -1, -1):
            suffix[:, j] = t_after[:, j] * g[:, j] - after
            after = after + w[:, j] * g[:, j]
            affine[:, j] = t_after[:, j] * (g[:, j] - G)
            G = alpha[:, j] * g[:, j] + decay[:, j] * G
        dt = t_ends - t_starts
        rows = {"color": (color, 0), "depth": (depth, 1), "weights": (w, 3),
                "d sigmas (suffix sum)": (suffix * dt, 4), "d sigmas (affine, CPU kernel)": (affine * dt, 4),
                "d t_ends (suffix sum)": (0.5 * grad_depth[:, None] * w + suffix * sigmas, 5)}
        for name, (value, k) in rows.items():
            e = relative_errors(value.float(), truth[k])
            print(f"{dist:8s} {name:30s} max {e.max():.2e}  median {e.median():.2e}")


if __name__ == "__main__":
    main()
