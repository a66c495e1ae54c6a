"""What the default value checks cost a composite training step on a GPU, and where it goes.

    python tools/profile_checks.py [--steps 20]

Runs the ``bench_ops`` composite forward+backward case (R=65536, S=192) with the checks off
(``check_values=False``) and on (the default: in-kernel checks, ``deferred_checks.watch``), one
after another: median GPU ms per step from CUDA events, then a torch.profiler pass of each that
lists the CUDA runtime calls per step (a cudaHostAlloc or a synchronising call is a host wait
the events show as GPU idle).
"""

from __future__ import annotations

import argparse
import statistics

import torch
from torch.profiler import ProfilerActivity, profile

from benchmarks.cases_composite import make_inputs
from mixer_nerf.ops import check_pending, composite


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args()
    inputs = make_inputs(65536, 192, torch.device("cuda"))
    upstream = [torch.randn_like(inputs["sigmas"][:, :3]), torch.randn_like(inputs["sigmas"][:, 0]),
                torch.randn_like(inputs["sigmas"][:, 0])]

    def step(check_values: bool) -> None:
        leaves = [inputs["sigmas"].detach().requires_grad_(), inputs["rgbs"].detach().requires_grad_()]
        out = composite(*leaves, inputs["t_starts"], inputs["t_ends"], inputs["background"], check_values=check_values)
        torch.autograd.grad(out[:3], leaves, upstream)

    for check_values in (False, True):
        for _ in range(5):
            step(check_values)
        check_pending()
        times = []
        for _ in range(args.steps):
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            step(check_values)
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for _ in range(args.steps):
                step(check_values)
            torch.cuda.synchronize()
        check_pending()
        print(f"\ncheck_values={check_values}: {statistics.median(times):.3f} ms per step (median of {args.steps})")
        calls = [e for e in prof.key_averages() if e.key.startswith("cuda")]
        for e in sorted(calls, key=lambda e: -e.cpu_time_total):
            print(f"  {e.key:<32} {e.count / args.steps:6.1f} per step  {e.cpu_time_total / args.steps:8.1f} us per step")


if __name__ == "__main__":
    main()
