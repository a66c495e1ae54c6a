"""Host time of a default call of composite (forward, and forward + autograd.grad) and of
hierarchical_samples on tiny CUDA inputs: microseconds a call, the least of 40 rounds of 100 calls
(a host's noise only ever adds time, so the minimum compares two trees best). For an A/B of a
Python-side change, run it in the tree and in $BASELINE_TREE (tools/gpu_build.sh), alternately:

    python tools/profile_host_time.py
    (cd $BASELINE_TREE && PYTHONPATH=$BASELINE_PYTHONPATH python tools/profile_host_time.py)
"""

import time

import torch

from mixer_nerf.ops import composite, hierarchical_samples

device = torch.device("cuda")
gen = torch.Generator().manual_seed(0)


def rand(*shape):
    return torch.rand(*shape, generator=gen).to(device)


sigmas, rgbs = rand(4, 8).requires_grad_(), rand(4, 8, 3).requires_grad_()
t_starts = rand(4, 8).cumsum(-1)
t_ends, background = t_starts + 0.1, rand(3)
z_coarse, weights_coarse = rand(4, 8).cumsum(-1), rand(4, 8)


def composite_step():
    color = composite(sigmas, rgbs, t_starts, t_ends, background).color
    torch.autograd.grad(color.sum(), (sigmas, rgbs))


cases = {
    "composite fwd": lambda: composite(sigmas, rgbs, t_starts, t_ends, background),
    "composite fwd+bwd": composite_step,
    "hierarchical": lambda: hierarchical_samples(z_coarse, weights_coarse, 8),
}
best = dict.fromkeys(cases, float("inf"))
for call in cases.values():
    for _ in range(200):
        call()
for _ in range(40):
    for name, call in cases.items():
        torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(100):
            call()
        torch.cuda.synchronize()
        best[name] = min(best[name], (time.perf_counter() - start) / 100 * 1e6)
print(" | ".join(f"{name} {us:.1f}" for name, us in best.items()))
