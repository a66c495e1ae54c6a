"""How the time of our composite training step depends on what runs between its calls (GPU).

    python tools/profile_neighbours.py

The ``bench_ops`` composite forward+backward case (R=65536, S=192): our two variants (checks off,
and the default) timed taking turns, first alone, then with one call of a peer (eager, nerfacc,
torch.compile) after each of theirs, then alone again; each one at a time (median of 30, the GPU
idle before each) and queued (median of 5 batches of 30); the host time to enqueue a step alone
before and after; a torch.profiler table of each variant's host ops per step; and last the case
through ``harness.run_case`` as ``bench_ops`` runs it. A step that is queued as fast as its kernels
run has a host that keeps ahead; one at a time shows what a cold host (caches filled by the
neighbour) adds.
"""

from __future__ import annotations

import statistics
import time

import torch
from torch.profiler import ProfilerActivity, profile

from benchmarks.cases_composite import implementations, make_inputs, training_case
from benchmarks.harness import _batch_ms, _call_ms, run_case
from mixer_nerf.ops.composite_reference import composite_reference

OURS = ["kernel", "ours, defaults"]


def main() -> None:
    device = torch.device("cuda")
    case = training_case("composite", "R=65536 S=192 C=3", make_inputs(65536, 192, device),
                         implementations(device), composite_reference)
    steps = {v.name: v.fn for v in case.variants}

    def turns(label: str, neighbour: str | None = None) -> None:
        for name in OURS + ([neighbour] if neighbour else []):
            for _ in range(5):
                steps[name]()
        one, queued = ({name: [] for name in OURS} for _ in range(2))
        for samples, measure in ((one, lambda f: _call_ms(f, device)), (queued, lambda f: _batch_ms(f, device, 30))):
            for _ in range(30 if samples is one else 5):
                for name in OURS:
                    samples[name].append(measure(steps[name]))
                    if neighbour:
                        steps[neighbour]()
        for name in OURS:
            print(f"{label:<30} {name:<16} one at a time {statistics.median(one[name]):.3f} ms  "
                  f"queued {statistics.median(queued[name]):.3f} ms", flush=True)

    def host_us(name: str) -> float:
        seconds = []
        for _ in range(50):
            torch.cuda.synchronize()
            start = time.perf_counter()
            steps[name]()
            seconds.append(time.perf_counter() - start)
        return 1e6 * statistics.median(seconds)

    turns("alone")
    print("host us to enqueue a step, alone:", {name: round(host_us(name)) for name in OURS})
    for neighbour in ("torch", "nerfacc", "torch.compile"):
        if neighbour in steps:
            turns(f"a {neighbour} step after each", neighbour)
    turns("alone again")
    print("host us to enqueue a step, after:", {name: round(host_us(name)) for name in OURS})
    for name in OURS:
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for _ in range(20):
                steps[name]()
            torch.cuda.synchronize()
        print(f"\n{name}: host ops per step (torch.profiler, 20 steps)")
        for e in sorted(prof.key_averages(), key=lambda e: -e.self_cpu_time_total)[:16]:
            print(f"  {e.key[:58]:<58} {e.count / 20:5.1f} per step, self {e.self_cpu_time_total / 20:7.1f} us, "
                  f"total {e.cpu_time_total / 20:7.1f} us")
    print("\nharness.run_case (as bench_ops, 30 repeats): ms one at a time / queued / kernels")
    for r in run_case(case, device, repeats=30, warmup=3):
        print(f"  {r.variant:<16} {r.ms:.3f} / {r.queued_ms:.3f} / {r.kernel_ms:.3f}")


if __name__ == "__main__":
    main()
