"""Benchmark every op side by side: our kernels vs the eager reference vs torch.compile vs nerfacc.

    python -m benchmarks.bench_ops [--device cuda|cpu] [--ops composite,sample_pdf] [--out DIR]

Cases come from ``benchmarks/cases_<op>.py``. Writes ``<device>.md``, ``.json`` and ``.png`` (a
time-against-error plot) under ``--out`` (default ``benchmarks/results/ops``; device ``cpu``, ``h100``,
...) and prints the table.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import importlib
import json
import platform
import time
from pathlib import Path

import torch

from benchmarks.harness import RESULTS, Result, copy_bandwidth_gbps, device_tag, run_case

OPS = ("positional_encoding", "sample_pdf", "composite", "ray_marching", "mlca", "linear_relu")


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"{platform.processor() or platform.machine()} CPU, {torch.get_num_threads()} threads"


def fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def table(results: list[Result], copy_gbps: float | None) -> str:
    head = ("| op | mode | size | variant | ms | GB/s | % of copy | ms queued | ms kernels | max abs err "
            "| max rel err | kernel speedup (one at a time, queued, kernels) |")
    lines = [head, "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in results:
        pct = None if (r.gbps is None or not copy_gbps) else 100 * r.gbps / copy_gbps
        speed = ", ".join(
            f"{v:.1f}x" + "".join(f" / {other[k]:.1f}x" if k in other else " / -"
                                  for other in (r.queued_speedups, r.kernel_speedups) if other)
            + f" vs {k}" for k, v in r.speedups.items())
        ms = fmt(r.ms, ".3f") if r.error is None else f"failed: {r.error}"
        lines.append(
            f"| {r.op} | {r.mode} | {r.size} | {r.variant} | {ms} | {fmt(r.gbps, '.0f')} | {fmt(pct, '.0f')} "
            f"| {fmt(r.queued_ms, '.3f')} | {fmt(r.kernel_ms, '.3f')} | {fmt(r.max_abs_err, '.2e')} "
            f"| {fmt(r.max_rel_err, '.2e')} | {speed} |"
        )
    return "\n".join(lines)


def plot(results: list[Result], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted({(r.op, r.mode) for r in results})
    fig, axes = plt.subplots(1, len(groups), figsize=(4.5 * len(groups), 4), squeeze=False)
    for ax, (op, mode) in zip(axes[0], groups):
        for r in results:
            if (r.op, r.mode) == (op, mode) and r.ms and r.max_rel_err is not None:
                ax.scatter(r.ms, max(r.max_rel_err, 1e-17))
                ax.annotate(r.variant, (r.ms, max(r.max_rel_err, 1e-17)), fontsize=7)
        ax.set(xscale="log", yscale="log", xlabel="time (ms)", ylabel="max rel. error vs float64", title=f"{op} {mode}")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--ops", default=",".join(OPS))
    parser.add_argument("--out", default=str(RESULTS / "ops"))
    parser.add_argument("--repeats", type=int, default=None)
    args = parser.parse_args()
    device = torch.device(args.device)
    repeats = args.repeats or (50 if device.type == "cuda" else 5)
    copy_gbps = copy_bandwidth_gbps(device) if device.type == "cuda" else None

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results: list[Result] = []
    for op in args.ops.split(","):
        module = importlib.import_module(f"benchmarks.cases_{op}")
        for case in module.cases(device):
            start = time.perf_counter()
            results.extend(run_case(case, device, repeats=repeats, warmup=max(2, repeats // 10)))
            torch.manual_seed(0)
            # where a run's time goes (torch.compile's builds included): what splits a cut-off run into calls
            print(f"{case.op} {case.mode} {case.size}: {time.perf_counter() - start:.0f} s", flush=True)
            text = write_results(results, device, repeats, copy_gbps, out)  # a cut-off run keeps what it did
    print(text)


def write_results(results: list[Result], device: torch.device, repeats: int, copy_gbps: float | None, out: Path) -> str:
    """Write ``<device>.md``, ``.json`` and the time-against-error plot ``.png``; return the markdown."""
    stamp = datetime.date.today().isoformat()
    header = (f"# Op benchmarks on {device_name(device)}, {stamp}\n\ntorch {torch.__version__}; "
              f"median of {repeats} runs, each after a synchronisation (host work included); ms queued: "
              f"per call of {repeats} calls queued back to back and synchronised once, the median of 5 such "
              "batches (GPU only); each case's variants timed in turns, one sample of each in a round; ms kernels: the kernels and copies of 10 calls summed, per call (GPU only, "
              "no host time); errors against a float64 reference (rel: scaled by each output's max |truth|)"
              + (f"; device copy bandwidth {copy_gbps:.0f} GB/s (read + write)" if copy_gbps else "")
              + "\n\nCommand: `python -m benchmarks.bench_ops " + f"--device {device.type} --repeats {repeats}`\n\n")
    text = header + table(results, copy_gbps) + "\n"
    tag = device_tag(device)
    (out / f"{tag}.md").write_text(text)
    (out / f"{tag}.json").write_text(json.dumps({
        "device": device_name(device), "date": stamp, "torch": torch.__version__, "copy_gbps": copy_gbps,
        "results": [dataclasses.asdict(r) for r in results]}, indent=1))
    plot(results, out / f"{tag}.png")
    return text

if __name__ == "__main__":
    main()
