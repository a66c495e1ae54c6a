"""What one training step's MLP costs: forward+backward of the Mixer-NeRF field per preset and
precision, on packed samples as the occupancy sampler feeds them.

    python -m benchmarks.bench_field [--samples 65536] [--rays 3000] [--profile D] [--compile] [--out DIR]

Writes ``<out>/field_<device>.md`` (default ``benchmarks/results/train_step/field_h100.md`` on an H100).

Each row times ``field(x, d, ray_indices, offsets)`` (SE's fused packed path, as in training)
then ``backward`` of a loss on sigma and rgb (median of CUDA-event timings). ``--profile P`` adds
a torch.profiler table of preset P's step (bf16), the ops sorted by their CUDA time, to find what
a preset adds over NeRF (A). ``--compile`` adds rows for the field under
``torch.compile(dynamic=True)`` (training feeds a different sample count each step), with the
first call's compile time.
"""

from __future__ import annotations

import argparse
import datetime
import json
import time
from pathlib import Path

import torch

from benchmarks.harness import RESULTS, device_tag, time_ms
from mixer_nerf.model import MixerNeRF, preset_config

PRECISIONS = {"bf16": torch.bfloat16, "tf32": None}


def packed_batch(samples: int, rays: int, device: torch.device, seed: int = 0):
    """Points in the unit box with sorted ray indices and their CSR offsets (every ray gets about
    samples/rays points)."""
    gen = torch.Generator(device=device).manual_seed(seed)
    x = torch.rand(samples, 3, generator=gen, device=device) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(samples, 3, generator=gen, device=device), dim=-1)
    ray_indices = torch.randint(rays, (samples,), generator=gen, device=device).sort().values
    offsets = torch.searchsorted(ray_indices, torch.arange(rays + 1, device=device))
    return x, d, ray_indices, offsets


def step_fn(field: MixerNeRF, batch, rays: int, dtype: torch.dtype | None):
    x, d, ray_indices, offsets = batch

    def step():
        with torch.autocast("cuda", dtype=dtype or torch.float32, enabled=dtype is not None):
            sigma, rgb = field(x, d, ray_indices=ray_indices, num_rays=rays, offsets=offsets)
        (sigma.float().mean() + rgb.float().mean()).backward()

    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=65536)
    parser.add_argument("--rays", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--profile", default="D", help="preset to profile ('' for none)")
    parser.add_argument("--presets", default="ABCD", help="presets to time (the first is the baseline)")
    parser.add_argument("--compile", action="store_true", help="also time torch.compile'd fields")
    parser.add_argument("--out", default=str(RESULTS / "train_step"))
    args = parser.parse_args()

    torch.backends.cuda.matmul.allow_tf32 = True
    device = torch.device("cuda")
    batch = packed_batch(args.samples, args.rays, device)
    rows = []
    for preset in args.presets:
        eager = MixerNeRF(preset_config(preset)).to(device)
        variants = {"eager": eager}
        if args.compile:
            variants["compiled"] = torch.compile(eager, dynamic=True)
        for mode, field in variants.items():
            for name, dtype in PRECISIONS.items():
                step = step_fn(field, batch, args.rays, dtype)
                start = time.perf_counter()
                step()
                torch.cuda.synchronize()
                first_s = time.perf_counter() - start
                ms = time_ms(step, device, args.repeats, warmup=5)
                rows.append({"preset": preset, "mode": mode, "precision": name, "ms": round(ms, 3),
                             "first_call_s": round(first_s, 1)})
                print(json.dumps(rows[-1]), flush=True)
    base = {(r["mode"], r["precision"]): r["ms"] for r in rows if r["preset"] == args.presets[0]}
    lines = [f"MLP forward+backward, {args.samples} packed samples over {args.rays} rays, "
             f"{torch.cuda.get_device_name()}, {datetime.date.today()}, torch {torch.__version__} "
             f"(python -m benchmarks.bench_field --samples {args.samples} --rays {args.rays}"
             f"{' --compile' if args.compile else ''})", "",
             f"| preset | mode | precision | ms | vs {args.presets[0]} | first call (s) |", "|---|---|---|---:|---:|---:|"]
    lines += [f"| {r['preset']} | {r['mode']} | {r['precision']} | {r['ms']:.3f} | "
              f"{r['ms'] / base[r['mode'], r['precision']]:.2f}x | {r['first_call_s']} |" for r in rows]
    if args.profile:
        field = MixerNeRF(preset_config(args.profile)).to(device)
        step = step_fn(field, batch, args.rays, torch.bfloat16)
        for _ in range(5):
            step()
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
            for _ in range(10):
                step()
            torch.cuda.synchronize()
        lines += ["", f"Preset {args.profile}, bf16, 10 steps:", "",
                  prof.key_averages().table(sort_by="cuda_time_total", row_limit=25)]
    text = "\n".join(lines)
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"field_{device_tag(device)}.md").write_text(text + "\n")


if __name__ == "__main__":
    main()
