"""Host time of one call of each differentiable op: tiny inputs, so the kernels take next to nothing
and what is timed is the wrapper's checks, the dispatch, autograd's bookkeeping and the backward's
hand-off (what a training step pays per op where it is not replayed as a CUDA graph).

    python -m benchmarks.host_overhead [--device cpu|cuda] [--calls 3000] [--out DIR]

Per op: the forward with a backward recorded, and forward + ``torch.autograd.grad`` (microseconds
a call, the median of 5 rounds of ``--calls`` calls each, one CPU thread; on CUDA the rounds end
with a synchronisation, and the kernels of such inputs run faster than the host enqueues them).
A ``torch.sin`` row gives the floor PyTorch itself sets on the same host. Writes ``<out>/host_overhead_<device>.json`` and a table ``<out>/host_overhead_<device>.md``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from benchmarks.harness import RESULTS, device_tag
from mixer_nerf.ops import (
    composite,
    composite_packed,
    mlca,
    positional_encoding,
    ray_scale,
    sample_pdf,
    sample_pdf_packed,
    segment_mean,
)


def cases(device: torch.device) -> dict[str, tuple[list[torch.Tensor], Callable]]:
    """name -> (leaves, fn(*leaves) -> a tensor to differentiate), the ops' default arguments."""
    gen = torch.Generator().manual_seed(0)

    def rand(*shape, low=0.0):
        return (low + torch.rand(*shape, generator=gen)).to(device)

    offsets = torch.tensor([0, 3, 3, 7], device=device)
    bins = rand(4, 6).cumsum(-1)
    packed_bins = torch.cat([rand(c + 1).cumsum(0) for c in (3, 0, 4)])
    starts = rand(4, 8).cumsum(-1)
    packed_starts = rand(7).cumsum(0)
    return {
        # PyTorch's own op for scale: what the autograd engine costs a step without any of ours.
        "torch.sin (PyTorch's own, for scale)": ([rand(16, 3)], torch.sin),
        "positional_encoding": ([rand(16, 3)], lambda x: positional_encoding(x, 10)),
        "mlca": ([rand(16, 12), rand(5, 3), rand(4, 4), rand(4), rand(5, 5), rand(5)], mlca),
        "segment_mean": ([rand(7, 8)], lambda v: segment_mean(v, offsets)),
        "ray_scale": ([rand(7, 8), rand(3, 8)], lambda f, s: ray_scale(f, s, offsets)),
        "sample_pdf (stratified)": ([bins, rand(4, 5, low=0.1)], lambda b, w: sample_pdf(b, w, 8)),
        "sample_pdf_packed (stratified)": (
            [packed_bins, rand(7, low=0.1)], lambda b, w: sample_pdf_packed(b, w, offsets, 8)),
        "composite": ([rand(4, 8), rand(4, 8, 3), starts, starts + 0.1, rand(3)],
                      lambda s, c, t0, t1, bg: composite(s, c, t0, t1, bg).color),
        "composite_packed": ([rand(7), rand(7, 3), packed_starts, packed_starts + 0.1, rand(3)],
                             lambda s, c, t0, t1, bg: composite_packed(s, c, t0, t1, offsets, bg).color),
    }


def time_calls(call: Callable[[], None], calls: int, device: torch.device) -> float:
    """Microseconds a call: the median of 5 rounds, after one of warm-up."""
    rounds = []
    for _ in range(6):
        start = time.perf_counter()
        for _ in range(calls):
            call()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        rounds.append((time.perf_counter() - start) / calls * 1e6)
    return statistics.median(rounds[1:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--calls", type=int, default=3000)
    parser.add_argument("--out", default=str(RESULTS / "ops"))
    parser.add_argument("--label", default="", help="a name for this build in the table (e.g. a commit)")
    args = parser.parse_args()
    device = torch.device(args.device)
    torch.set_num_threads(1)
    rows = []
    for name, (tensors, fn) in cases(device).items():
        leaves = [t.requires_grad_() for t in tensors]
        forward_us = time_calls(lambda: fn(*leaves), args.calls, device)
        step_us = time_calls(lambda: torch.autograd.grad(fn(*leaves).sum(), leaves, allow_unused=True),
                             args.calls, device)
        rows.append({"op": name, "forward_us": round(forward_us, 1), "forward_backward_us": round(step_us, 1)})
        print(f"{name:32s} forward {forward_us:7.1f} us   forward + backward {step_us:7.1f} us", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = device_tag(device)
    record = {"device": tag, "label": args.label, "torch": torch.__version__, "calls": args.calls, "rows": rows}
    (out / f"host_overhead_{tag}.json").write_text(json.dumps(record, indent=1) + "\n")
    lines = [f"# Host time a call ({tag}{', ' + args.label if args.label else ''}; us, median of 5 rounds "
             f"of {args.calls} calls)", "", "| op | forward | forward + backward |", "|---|---:|---:|"]
    lines += [f"| {r['op']} | {r['forward_us']} | {r['forward_backward_us']} |" for r in rows]
    (out / f"host_overhead_{tag}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
