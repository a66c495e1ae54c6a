"""How long the host takes to enqueue a composite forward + backward step, at the benchmark's size and
on tiny inputs, beside PyTorch's own floor (``torch.sin`` and ``autograd.grad``) at the same sizes:
whether a call's host time grows with its inputs. Each row times 10 steps queued without a
synchronisation (the host's enqueue time) and until the GPU is done, per step, over 20 rounds
(least / median, us). (No per-op split: torch.profiler's own overhead inflates a step's short ops
several times over; ``benchmarks/results/ops/host_overhead.md``.)

    python tools/profile_enqueue.py
"""

import statistics
import time

import torch

from benchmarks import cases_composite
from mixer_nerf.ops.composite_reference import composite_reference

device = torch.device("cuda")
SIZES = {"tiny 4x8": (4, 8), "bench 65536x192": (65536, 192)}


def composite_steps(R: int, S: int) -> dict:
    """The bench_ops training case's own step functions (inputs, casts and upstream included)."""
    inputs = cases_composite.make_inputs(R, S, device)
    impls = cases_composite.implementations(device)
    impls = {name: impls[name] for name in ("ours, defaults", "kernel")}
    case = cases_composite.training_case("composite", f"{R}x{S}", inputs, impls, composite_reference)
    return {variant.name: variant.fn for variant in case.variants}


def floor_step(R: int, S: int):
    x = torch.rand(R, S, device=device).requires_grad_()
    upstream = torch.randn(R, S, device=device)
    return lambda: torch.autograd.grad(torch.sin(x), (x,), upstream)


def timed(step, calls: int = 10, rounds: int = 20) -> tuple[list[float], list[float]]:
    for _ in range(20):
        step()
    enqueue, done = [], []
    for _ in range(rounds):
        torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(calls):
            step()
        queued = time.perf_counter()
        torch.cuda.synchronize()
        end = time.perf_counter()
        enqueue.append((queued - start) / calls * 1e6)
        done.append((end - start) / calls * 1e6)
    return enqueue, done


print("| size | step | enqueue us (least / median) | until done us (least / median) |")
print("|---|---|---:|---:|")
for size, (R, S) in SIZES.items():
    steps = {**composite_steps(R, S), "torch.sin + grad (floor)": floor_step(R, S)}
    for name, step in steps.items():
        enqueue, done = timed(step)
        print(f"| {size} | {name} | {min(enqueue):.1f} / {statistics.median(enqueue):.1f} "
              f"| {min(done):.1f} / {statistics.median(done):.1f} |")
