"""What the default value checks cost a composite training step on a GPU, and where it goes.

    python tools/profile_checks.py [--steps 20]

Runs the ``bench_ops`` composite forward+backward case (R=65536, S=192) with the checks off
(``check_values=False``) and on (the default: in-kernel checks, ``deferred_checks.watch``), taking
turns step by step: median GPU ms per step from CUDA events and the host time to enqueue a step
and, of it, the time spent in ``deferred_checks.watch``, in the composite call (and of that in the
registered op) and in ``torch.autograd.grad``; then a torch.profiler pass of each that lists the
CUDA runtime calls per step (a cudaHostAlloc or a synchronising call is a host wait the events
show as GPU idle) and the GPU kernels per step (busy time against the event-timed step: the rest
is the GPU waiting for the host), and a cProfile of the host's Python per variant (the autograd
engine's own thread, where backward nodes run, shows only as ``torch.autograd.grad``).
"""

from __future__ import annotations

import argparse
import functools
import importlib
import statistics
import time

import torch
from torch.profiler import ProfilerActivity, profile

from benchmarks.cases_composite import make_inputs
from benchmarks.harness import host_profile
from mixer_nerf.ops import check_pending, composite, deferred_checks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args()
    inputs = make_inputs(65536, 192, torch.device("cuda"))
    upstream = [torch.randn_like(inputs["sigmas"][:, :3]), torch.randn_like(inputs["sigmas"][:, 0]),
                torch.randn_like(inputs["sigmas"][:, 0])]

    def step(check_values: bool, split: list | None = None) -> None:
        leaves = [inputs["sigmas"].detach().requires_grad_(), inputs["rgbs"].detach().requires_grad_()]
        start = time.perf_counter()
        out = composite(*leaves, inputs["t_starts"], inputs["t_ends"], inputs["background"], check_values=check_values)
        called = time.perf_counter()
        torch.autograd.grad(out[:3], leaves, upstream)
        if split is not None:
            split.append((called - start, time.perf_counter() - called))

    def timed(fn, seconds: list):
        def call(*args, **kwargs):
            start = time.perf_counter()
            result = fn(*args, **kwargs)
            seconds.append(time.perf_counter() - start)
            return result
        return call

    # What of the composite call is the registered op (its C++ autograd, allocations and launch)
    # and what is deferred_checks.watch; the rest is the Python wrapper.
    composite_module = importlib.import_module("mixer_nerf.ops.composite")  # the function shadows it
    watch_seconds, op_seconds = [], []
    deferred_checks.watch = timed(deferred_checks.watch, watch_seconds)
    composite_module._COMPOSITE = timed(composite_module._COMPOSITE, op_seconds)
    variants = (False, True)
    for check_values in variants:
        for _ in range(5):
            step(check_values)
    check_pending()
    # The variants take turns step by step, so that a drift of the host's speed over the run (this
    # host's timings wander) weighs on both alike.
    times, host, split = ({v: [] for v in variants} for _ in range(3))
    for _ in range(args.steps):
        for check_values in variants:
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            step(check_values)
            end.record()
            end.synchronize()
            times[check_values].append(start.elapsed_time(end))
    torch.cuda.synchronize()
    watch_seconds.clear()
    op_seconds_of = {v: [] for v in variants}
    for _ in range(args.steps):
        for check_values in variants:
            start = time.perf_counter()
            op_seconds.clear()
            step(check_values, split[check_values])
            op_seconds_of[check_values] += op_seconds
            host[check_values].append(time.perf_counter() - start)
            torch.cuda.synchronize()
    watched = 1e3 * sum(watch_seconds) / args.steps
    for check_values in variants:
        forward_call, grad_call = (1e3 * statistics.median(part) for part in zip(*split[check_values]))
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for _ in range(args.steps):
                step(check_values)
            torch.cuda.synchronize()
        check_pending()
        averages = prof.key_averages()
        kernels = [e for e in averages if e.device_type == torch.autograd.DeviceType.CUDA and e.self_device_time_total > 0]
        busy = sum(e.self_device_time_total for e in kernels) / args.steps / 1e3
        print(f"\ncheck_values={check_values}: {statistics.median(times[check_values]):.3f} ms per step (median of {args.steps}), "
              f"GPU busy {busy:.3f} ms, host {1e3 * statistics.median(host[check_values]):.3f} ms to enqueue a step "
              f"({watched if check_values else 0.0:.3f} ms of it in deferred_checks.watch; medians: the composite call {forward_call:.3f} ms, "
              f"torch.autograd.grad {grad_call:.3f} ms; of the call, the registered op "
              f"{1e3 * statistics.median(op_seconds_of[check_values]):.3f} ms)")
        for e in sorted(kernels, key=lambda e: -e.self_device_time_total):
            print(f"  {e.key[:60]:<60} {e.count / args.steps:4.1f} per step  {e.self_device_time_total / args.steps:8.1f} us per step")
        calls = [e for e in averages if e.key.startswith("cuda")]
        for e in sorted(calls, key=lambda e: -e.cpu_time_total):
            print(f"  {e.key:<32} {e.count / args.steps:6.1f} per step  {e.cpu_time_total / args.steps:8.1f} us per step")
        host_text = host_profile(functools.partial(step, check_values), args.steps, top=15)
        check_pending()
        print("\n".join("  " + line for line in host_text.splitlines() if line.strip()))


if __name__ == "__main__":
    main()
