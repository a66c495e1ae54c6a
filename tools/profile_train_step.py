"""Where a training step's time goes: wall time per step against GPU busy time, and the kernels.

    python tools/profile_train_step.py [--data .data/lego_400] [--preset D] [--precision bf16|tf32|fp32]
        [--warmup 400] [--steps 30] [--[no-]bf16-density-passes] [--empty-space-weight W] [--cuda-graphs]
        [--out DIR]

Trains ``--warmup`` steps (past the occupancy grid's dense warm-up, so the batch has its steady
size), times three windows of ``--steps`` steps (the median window's ms per step: one may hold a
graph recapture), times ``--steps`` more by CUDA events (a step's span on the stream, the stream's
idle between steps), then profiles ``--steps`` steps with torch.profiler. Prints ms per step (wall),
the GPU's busy ms per step (sum of kernel times; and the time any kernel runs, overlapping streams
counted once, against the profiled wall time: the GPU idle), kernels per step, with the occupancy
sampler the host time per step spent preparing the next batch, the kernels sorted by CUDA time,
the GPU's idle gaps by size and by the kernels around them, the ops by the GPU time of the kernels
they launched and the kernels a step by the line that launched them (a replayed graph's step run
eagerly for these two); a wall time well above the busy time means the step waits on the host
(Python, launches, synchronisations) or, in a graph, on the gaps between its many kernels. The file
in ``--out`` also lists the Python functions by their own host time (cProfile, ``--steps`` more
steps) and the host ms per step when the GPU has nothing left to do: the step's host cost, then
every call of ``--steps`` more steps that makes the host wait for the GPU, by its line.
"""

from __future__ import annotations

import argparse
import collections
import functools
import statistics
import tempfile
import time
from pathlib import Path

import torch
from torch.autograd import DeviceType

from benchmarks.harness import RESULTS, device_tag, host_profile, scene_tag
from mixer_nerf.train import TrainConfig, Trainer


def _kernel_spans(events) -> list[tuple[float, float, str]]:
    """(start us, end us, short name) of each CUDA kernel and copy, by start."""
    return sorted((e.time_range.start, e.time_range.end, _short(e.name)) for e in events
                  if e.device_type == DeviceType.CUDA)


def _gaps(spans):
    """Each stretch in which no kernel or copy of ``spans`` runs, on any stream: (us, the kernel
    that ended last before it, the one that ends it)."""
    reached, last = None, None
    for begin, end, name in spans:
        if reached is not None and begin > reached:
            yield begin - reached, last, name
        if reached is None or end > reached:
            reached, last = end, name


def active_time_us(events) -> float:
    """Time some CUDA kernel runs, on any stream, in us: the union of the kernels' intervals (a
    sum of kernel times counts kernels of overlapping streams twice)."""
    spans = _kernel_spans(events)
    if not spans:
        return 0.0
    return max(end for _, end, _ in spans) - spans[0][0] - sum(gap for gap, _, _ in _gaps(spans))


def idle_gaps(events, steps: int, top: int = 15) -> str:
    """Where the GPU idles in profiled steps: the gaps in which no kernel or copy runs, summed per
    step by size and by the pair of kernels around them, the largest sums first."""
    buckets = {"< 2 us": (0, 2), "2-10 us": (2, 10), "10-50 us": (10, 50), ">= 50 us": (50, float("inf"))}
    by_size, count, by_pair = collections.Counter(), collections.Counter(), collections.Counter()
    for gap, before, after in _gaps(_kernel_spans(events)):
        size = next(label for label, (low, high) in buckets.items() if low <= gap < high)
        by_size[size] += gap
        count[size] += 1
        by_pair[f"{before} -> {after}"] += gap
    total = sum(by_size.values())
    sizes = ", ".join(f"{label} {count[label] / steps:.1f} gaps {by_size[label] / 1e3 / steps:.3f} ms"
                      for label in buckets)
    lines = [f"GPU idle between kernels: {total / 1e3 / steps:.3f} ms per step, by gap size: {sizes} "
             "(profiled steps: the profiler's tracing stretches a replayed graph's gaps)"]
    lines += [f"{'before -> after the gap':<100} {'ms/step':>8}"]
    lines += [f"{pair[:100]:<100} {gap / 1e3 / steps:>8.3f}" for pair, gap in by_pair.most_common(top)]
    return "\n".join(lines) + "\n"


def _short(kernel: str) -> str:
    """A kernel's name without its return type, template arguments and parameters."""
    name = kernel.removeprefix("void ")
    for mark in ("<", "("):
        name = name.split(mark)[0]
    return name.split("::")[-1] or kernel[:40]


def median_step_ms(step, synchronize, steps: int, windows: int = 3) -> float:
    """ms per step over ``windows`` windows of ``steps`` steps each, the median window's: one window
    may hold a rare event (a batch capacity that grows, and the graph recaptured for it) that the
    others do not."""
    times = []
    for _ in range(windows):
        synchronize()
        start = time.perf_counter()
        for _ in range(steps):
            step()
        synchronize()
        times.append((time.perf_counter() - start) * 1e3 / steps)
    return sorted(times)[windows // 2]


def step_timeline_ms(step, steps: int, event=None) -> tuple[float, float]:
    """(ms the stream takes from a step's first launch to its last, ms it idles between steps): the
    medians over ``steps`` steps, from CUDA events recorded around each step, without the profiler
    (its tracing stretches the gaps inside a replayed graph). Medians: one step of a window may
    check the batch capacity and capture a graph again. The first less the GPU's busy time is the
    idle inside a step; the second the GPU waiting for the host to launch the next step."""
    event = event or functools.partial(torch.cuda.Event, enable_timing=True)
    marks = [(event(), event()) for _ in range(steps)]
    for start, end in marks:
        start.record()
        step()
        end.record()
    marks[-1][1].synchronize()
    spans = [start.elapsed_time(end) for start, end in marks]
    between = [end.elapsed_time(start) for (_, end), (start, _) in zip(marks, marks[1:])]
    return statistics.median(spans), statistics.median(between) if between else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=".data/lego_400")
    parser.add_argument("--preset", default="D")
    parser.add_argument("--precision", default=None, help="default: the trainer's (the sampler's recipe)")
    parser.add_argument("--warmup", type=int, default=400)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--bf16-density-passes", action=argparse.BooleanOptionalAction, default=None,
                        help="default: the trainer's (on CUDA)")
    parser.add_argument("--empty-space-weight", type=float, default=None, help="default: the trainer's")
    parser.add_argument("--cuda-graphs", action=argparse.BooleanOptionalAction, default=None,
                        help="replay each step as a CUDA graph (default: the trainer's, on where a step can be)")
    parser.add_argument("--out", default=str(RESULTS / "train_step"),
                        help="write the tables to DIR/<device>_<scene>_<preset>_<precision>[_bf16pass][_graphs]_step<N>.txt "
                             "('' for none)")
    args = parser.parse_args()

    cfg = TrainConfig(data=args.data, preset=args.preset, precision=args.precision, device="cuda",
                      val_every=10**9, ckpt_every=10**9, log_every=10**9, progress=False,
                      bf16_density_passes=args.bf16_density_passes, out=tempfile.mkdtemp(prefix="profile_"),
                      cuda_graphs=args.cuda_graphs,
                      **({} if args.empty_space_weight is None else {"empty_space_weight": args.empty_space_weight}))
    trainer = Trainer(cfg, log=lambda _: None)
    trainer.fields.train()
    for _ in range(args.warmup):
        trainer.train_step()
    torch.cuda.synchronize()
    seen = trainer.rays_seen, trainer.samples_seen, trainer.marched_seen
    wall_ms = median_step_ms(trainer.train_step, torch.cuda.synchronize, args.steps)
    rays, shaded, marched = (now - before for now, before in
                             zip((trainer.rays_seen, trainer.samples_seen, trainer.marched_seen), seen))
    span_ms, between_ms = step_timeline_ms(trainer.train_step, args.steps)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
        start = time.perf_counter()
        for _ in range(args.steps):
            trainer.train_step()
        torch.cuda.synchronize()
        profiled_ms = (time.perf_counter() - start) * 1e3 / args.steps
    events = prof.key_averages()
    busy_ms = sum(e.self_device_time_total for e in events) / 1e3 / args.steps
    active_ms = active_time_us(prof.events()) / 1e3 / args.steps
    # every gap between two kernels of a step (a CUDA graph's too) idles the GPU for a moment
    launches = sum(e.device_type == DeviceType.CUDA for e in prof.events()) / args.steps
    precision = trainer.cfg.precision
    header = (f"preset {args.preset}, {precision}, {args.data}, {torch.cuda.get_device_name()}: "
              f"{wall_ms:.2f} ms per step (wall, unprofiled: the median of 3 windows of {args.steps} steps; "
              f"idle {100 * max(0.0, 1 - active_ms / wall_ms):.0f}% of it), "
              f"GPU busy {busy_ms:.2f} ms per step "
              f"(kernel times summed; {active_ms:.2f} ms with some kernel running on any stream, idle "
              f"{100 * max(0.0, 1 - active_ms / profiled_ms):.0f}% of the profiled {profiled_ms:.2f} ms; "
              f"{launches:.0f} kernels and copies a step), "
              f"a step spans {span_ms:.2f} ms of the stream (CUDA events, unprofiled: "
              f"{span_ms - active_ms:.2f} ms of it idle) and the stream idles {between_ms:.2f} ms "
              f"between steps, "
              f"batch {batch_rays(trainer)} rays, step {trainer.step}, per ray {marched / rays:.1f} "
              f"marched and {shaded / rays:.1f} shaded samples, bf16 density passes "
              f"{trainer.cfg.bf16_density_passes}")
    table = events.table(sort_by="self_cuda_time_total", row_limit=60, max_name_column_width=70)
    table += "\n" + idle_gaps(prof.events(), args.steps)
    passes = "_bf16pass" * trainer.cfg.bf16_density_passes
    # named by the step profiled, before the host profile's steps
    graphs = "_graphs" * trainer.cfg.cuda_graphs
    name = (f"{device_tag('cuda')}_{scene_tag(args.data)}_{args.preset}_{precision}{passes}{graphs}"
            f"_step{trainer.step}.txt")
    table += "\n" + _kernels_by_op(trainer, args.steps)
    host = host_profile(trainer.train_step, args.steps, top=35)
    syncs = _sync_sites(trainer, args.steps)
    preparation = preparation_time(trainer, args.steps)
    if preparation:
        header += "\n" + preparation
    # The file before the prints: a reader that closes the pipe early (`| grep -m1`) must not lose it.
    if args.out:
        path = Path(args.out) / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(header + "\n" + table + "\n" + host + "\n" + syncs + "\n")
    print(header)
    print(table)
    print(syncs)


def batch_rays(trainer: Trainer) -> int:
    """The rays of the next batch (fixed-capacity batches keep that count on the device)."""
    return trainer.sampler.batch_rays if trainer.fixed is None else int(trainer.fixed.num_rays)


def preparation_time(trainer: Trainer, steps: int) -> str:
    """Host ms per step spent preparing the occupancy path's next batch (``MarchedBatches.prefetch``:
    marching, the density pre-pass and the filter, their reads of sample counts included, which wait
    for the GPU), against the whole step's, over ``steps`` more steps. Empty for other samplers and
    for fixed-capacity batches (drawn inside the step's graph)."""
    batches = trainer.batches
    if batches is None or trainer.fixed is not None:
        return ""
    spent = 0.0
    prefetch = batches.prefetch

    def timed(step: int) -> None:
        nonlocal spent
        start = time.perf_counter()
        prefetch(step)
        spent += time.perf_counter() - start

    sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
    batches.prefetch = timed
    try:
        sync()
        start = time.perf_counter()
        for _ in range(steps):
            trainer.train_step()
        sync()
        total = time.perf_counter() - start
    finally:
        del batches.prefetch  # the instance attribute: the method again
    return (f"host in the next batch's preparation: {spent * 1e3 / steps:.2f} ms of {total * 1e3 / steps:.2f} ms "
            f"per step ({100 * spent / total:.0f}%)")


def _eager_step(trainer: Trainer):
    """A step whose kernels come from ops the profiler sees: a step replayed as a CUDA graph launches
    its kernels from no op, so its graph's body runs eagerly instead (the same kernels: the kind most
    steps replay, the occupancy path's plain step or the proposal path's without the networks' update)."""
    graphs = trainer.graphs
    if graphs is None or not graphs.captured:
        return trainer.train_step
    kind = next((k for k in ("fixed", False) if k in graphs.captured), graphs.captured[0])
    return lambda: graphs.body(kind)


def _kernels_by_op(trainer: Trainer, steps: int, top: int = 30) -> str:
    """The GPU time of `steps` more steps (run eagerly, :func:`_eager_step`) by the op that launched
    each kernel (its self GPU time), which names what the kernel table cannot (an unvectorised
    elementwise kernel: which op's?), then the kernels and copies a step by the line of mixer_nerf
    that launched them (each a gap in a replayed graph; backward kernels by their autograd node).
    Profiling the host's ops slows the steps, so this runs apart from the timed ones."""
    activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    step = _eager_step(trainer)
    with torch.profiler.profile(activities=activities, with_stack=True) as prof:
        for _ in range(steps):
            step()
        torch.cuda.synchronize()
    ops = [e for e in prof.key_averages() if e.device_type == DeviceType.CPU and e.self_device_time_total > 0]
    ops.sort(key=lambda e: e.self_device_time_total, reverse=True)
    title = "op (self GPU time: the kernels it launched itself)"
    rows = [f"{title:<60} {'calls/step':>10} {'GPU ms/step':>12}"]
    rows += [f"{e.key[:60]:<60} {e.count / steps:>10.1f} {e.self_device_time_total / 1e3 / steps:>12.3f}"
             for e in ops[:top]]
    rows += ["", f"{'launched from (kernels and copies a step)':<100} {'per step':>8}"]
    sites = launches_by_site(prof.events()).most_common(top)
    rows += [f"{site[:100]:<100} {count / steps:>8.1f}" for site, count in sites]
    return "\n".join(rows) + "\n"


def launches_by_site(events):
    """How many device kernels and copies each host op launched, keyed by the op's name after the
    innermost frame of mixer_nerf among its parents (``file(line): function``, as the profiler names
    Python frames); a backward op, which the autograd engine runs without its forward's frames, by
    its autograd node instead."""
    sites: collections.Counter[str] = collections.Counter()
    for e in events:
        if e.device_type != DeviceType.CPU or not e.kernels:
            continue
        sites[f"{_launch_site(e)}  {e.name}"] += len(e.kernels)
    return sites


def _launch_site(event) -> str:
    parent = event.cpu_parent
    while parent is not None:
        if parent.name.startswith(_BACKWARD_NODE):
            return "backward: " + parent.name[len(_BACKWARD_NODE):]
        if "mixer_nerf/" in parent.name:
            return parent.name.split("mixer_nerf/")[-1]
        parent = parent.cpu_parent
    return "(no mixer_nerf frame)"


_BACKWARD_NODE = "autograd::engine::evaluate_function: "


def _sync_sites(trainer: Trainer, steps: int) -> str:
    """Every call of ``steps`` steps that makes the host wait for the GPU (torch's sync debug
    mode), by the line of mixer_nerf that made it and its count per step."""
    import traceback
    import warnings

    sites: collections.Counter[str] = collections.Counter()

    def record(message, category, filename, lineno, file=None, line=None):
        frames = [f for f in traceback.extract_stack()[:-1] if "/mixer_nerf/" in f.filename]
        where = f"{frames[-1].filename.split('/mixer_nerf/')[-1]}:{frames[-1].lineno} {frames[-1].line}" if frames \
            else f"{filename}:{lineno}"
        sites[f"{where}  [{str(message).splitlines()[0][:60]}]"] += 1

    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings():  # restores showwarning on exit
            warnings.simplefilter("always")
            warnings.showwarning = record
            for _ in range(steps):
                trainer.train_step()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    lines = [f"{count / steps:6.2f} per step  {site}" for site, count in sites.most_common()]
    return "host waits (torch.cuda.set_sync_debug_mode), per step:\n" + ("\n".join(lines) or "  none")


if __name__ == "__main__":
    main()
