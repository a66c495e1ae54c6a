"""Side-by-side timing and error measurement for op benchmarks.

A :class:`Case` is one op at one size in one mode; its variants (our kernel, the eager reference,
the reference under ``torch.compile``, nerfacc, accuracy-trading variants) run in the same process
on the same inputs. Each is timed (median of CUDA-event timings on GPU, of ``perf_counter`` on CPU)
and compared with a float64 truth; achieved bandwidth is ``min_bytes / time``. On a GPU each is
timed twice: one call at a time, the GPU idle before each (what a call costs end to end, host work
included), and queued back to back with one synchronisation per batch (what a training loop sees
when its host keeps ahead of the GPU: the GPU's time, unless the host is the slower).
"""

from __future__ import annotations

import re
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

RESULTS = Path(__file__).resolve().parent / "results"
"""Where each benchmark writes its current result: ``RESULTS/<benchmark>/<device>.*``."""


@dataclass
class Variant:
    name: str
    fn: Callable[[], Any]  # runs the op once; returns the tensor(s) to compare with the truth


@dataclass
class Case:
    op: str
    mode: str  # "fwd" or "fwd+bwd"
    size: str
    variants: list[Variant]
    truth: Callable[[], Any] | None  # float64 result, same structure as each variant's; None: random draws
    min_bytes: int  # the fewest bytes the op must move (inputs read once, outputs written once)


@dataclass
class Result:
    op: str
    mode: str
    size: str
    variant: str
    ms: float | None
    gbps: float | None
    max_abs_err: float | None
    max_rel_err: float | None
    error: str | None = None
    queued_ms: float | None = None  # per call, queued back to back (GPU only; see queued_ms)
    speedups: dict[str, float] = field(default_factory=dict)  # other variant -> its ms / ours
    queued_speedups: dict[str, float] = field(default_factory=dict)  # the same, queued
    kernel_ms: float | None = None  # per call, the GPU's kernels and copies summed (see kernel_ms)
    kernel_speedups: dict[str, float] = field(default_factory=dict)  # the same, in kernel time


VENDOR_WORDS = {"nvidia", "geforce", "tesla", "quadro", "amd", "instinct", "radeon"}


def device_tag(device: torch.device | str) -> str:
    """Short device name for result file names: "cpu", or the GPU's model such as "h100" or
    "a100" (the first words of ``torch.cuda.get_device_name`` up to the one with a digit)."""
    device = torch.device(device)
    if device.type != "cuda":
        return device.type
    name = torch.cuda.get_device_name(device).lower()
    words = [w for w in re.split(r"[\s_-]+", name) if w not in VENDOR_WORDS]
    model = next((i for i, w in enumerate(words) if any(c.isdigit() for c in w)), len(words) - 1)
    return "".join(words[: model + 1]) or "cuda"


def scene_tag(data: str) -> str:
    """Short scene name for result file names: a scene folder's name up to its first "_" (lego for
    .data/lego_400)."""
    return Path(data).name.split("_")[0]


def _flatten(value: Any) -> list[torch.Tensor]:
    if isinstance(value, torch.Tensor):
        return [value]
    if value is None:
        return []
    return [t for item in value for t in _flatten(item)]


def errors(result: Any, truth: Any) -> tuple[float, float]:
    """Max absolute error and max error relative to the largest magnitude of each truth tensor.

    A relative error per element blows up where the truth is ~0, so each tensor's error is
    scaled by that tensor's max |truth|. Non-finite outputs give inf.
    """
    max_abs, max_rel = 0.0, 0.0
    for got, want in zip(_flatten(result), _flatten(truth), strict=True):
        got, want = got.detach().double().cpu(), want.detach().double().cpu()
        if not torch.isfinite(got).all():
            return float("inf"), float("inf")
        if got.numel() == 0:
            continue
        diff = (got - want).abs().max().item()
        scale = max(want.abs().max().item(), 1e-30)
        max_abs, max_rel = max(max_abs, diff), max(max_rel, diff / scale)
    return max_abs, max_rel


def _call_ms(fn: Callable[[], Any], device: torch.device) -> float:
    """Milliseconds of one call of ``fn``, the GPU idle before it."""
    if device.type != "cuda":
        t0 = time.perf_counter()
        fn()
        return (time.perf_counter() - t0) * 1e3
    torch.cuda.synchronize(device)
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    fn()
    end.record()
    end.synchronize()
    return start.elapsed_time(end)


def _batch_ms(fn: Callable[[], Any], device: torch.device, calls: int) -> float:
    """Milliseconds per call of ``calls`` calls of ``fn`` queued without synchronising (GPU)."""
    torch.cuda.synchronize(device)
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    for _ in range(calls):
        fn()
    end.record()
    end.synchronize()
    return start.elapsed_time(end) / calls


def time_ms(fn: Callable[[], Any], device: torch.device, repeats: int, warmup: int) -> float:
    """Median milliseconds of ``fn`` after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    return statistics.median(_call_ms(fn, device) for _ in range(repeats))


def queued_ms(fn: Callable[[], Any], device: torch.device, calls: int, batches: int = 5) -> float | None:
    """Milliseconds per call of ``calls`` calls queued without synchronising, the median over
    ``batches`` such batches (a host hiccup spoils one batch, not the result; GPU only)."""
    if device.type != "cuda":
        return None
    return statistics.median(_batch_ms(fn, device, calls) for _ in range(batches))


def kernel_ms(fn: Callable[[], Any], device: torch.device, calls: int = 10) -> float | None:
    """Milliseconds per call of the GPU's own work: the durations of the kernels, copies and fills
    of ``calls`` calls summed (torch.profiler), no host time between them. Where the host cannot
    enqueue a call as fast as the GPU runs it, ``queued_ms`` measures the host; this does not (GPU
    only)."""
    if device.type != "cuda":
        return None
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    fn()
    torch.cuda.synchronize(device)
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(calls):
            fn()
        torch.cuda.synchronize(device)
    total_us = sum(e.device_time for e in prof.events() if e.device_type == DeviceType.CUDA)
    return total_us / 1e3 / calls


def host_profile(step: Callable[[], Any], steps: int, top: int) -> str:
    """Python functions by own host time over ``steps`` calls of ``step`` (cProfile, the ``top``
    first), after each of which the host waits for the GPU: the host's cost of a step with nothing
    to overlap it, also given in ms per step on the first line."""
    import cProfile
    import io
    import pstats

    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.enable()
    for _ in range(steps):
        step()
        torch.cuda.synchronize()
    profiler.disable()
    serial_ms = (time.perf_counter() - start) * 1e3 / steps
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(top)
    header = f"host profile (cProfile, a GPU sync after each step): {serial_ms:.2f} ms per step\n"
    return header + text.getvalue()


def copy_bandwidth_gbps(device: torch.device, nbytes: int = 1 << 30) -> float:
    """Device-to-device copy bandwidth, counting bytes read plus bytes written."""
    src = torch.empty(nbytes // 4, dtype=torch.float32, device=device).uniform_()
    dst = torch.empty_like(src)
    ms = time_ms(lambda: dst.copy_(src), device, repeats=20, warmup=3)
    return 2 * nbytes / (ms * 1e-3) / 1e9


def run_case(case: Case, device: torch.device, repeats: int, warmup: int, batches: int = 5) -> list[Result]:
    """Errors and times of each of ``case``'s variants. Times are taken in rounds, each round one
    sample of every variant in turn (``repeats`` one-at-a-time rounds, then ``batches`` rounds of
    ``repeats`` queued calls), so what drifts over a case (clocks, the allocator's cache) touches
    every variant alike instead of favouring the one timed first or last."""
    truth = case.truth() if case.truth is not None else None
    results = [Result(case.op, case.mode, case.size, v.name, None, None, None, None) for v in case.variants]
    samples: dict[int, list[float]] = {}
    queued: dict[int, list[float]] = {}

    def guarded(i: int, measure: Callable[[int], Any]) -> None:
        try:
            measure(i)
        except Exception as exc:  # a peer that fails to build or run is reported, not fatal
            results[i].error = f"{type(exc).__name__}: {str(exc).splitlines()[0][:160]}"
            results[i].ms = results[i].gbps = results[i].queued_ms = None
            samples.pop(i, None)

    def first_calls(i: int) -> None:
        out = case.variants[i].fn()
        if truth is not None:
            results[i].max_abs_err, results[i].max_rel_err = errors(out, truth)
        del out
        for _ in range(warmup):
            case.variants[i].fn()
        samples[i], queued[i] = [], []

    for i in range(len(case.variants)):
        guarded(i, first_calls)
    for _ in range(repeats):
        for i in list(samples):
            guarded(i, lambda i: samples[i].append(_call_ms(case.variants[i].fn, device)))
    for _ in range(batches if device.type == "cuda" else 0):
        for i in list(samples):
            guarded(i, lambda i: queued[i].append(_batch_ms(case.variants[i].fn, device, repeats)))
    for i in list(samples):
        result = results[i]
        result.ms = statistics.median(samples[i])
        result.gbps = case.min_bytes / (result.ms * 1e-3) / 1e9
        result.queued_ms = statistics.median(queued[i]) if queued[i] else None
        guarded(i, lambda i: setattr(results[i], "kernel_ms", kernel_ms(case.variants[i].fn, device)))
    if device.type == "cuda":
        torch.cuda.empty_cache()
    # speedups of our kernel against every other variant, and of our default call (what a user
    # runs) against the peers
    timed = [r for r in results if r.ms]
    for ours in (r for r in timed if r.variant in ("kernel", "ours, defaults")):
        for r in timed:
            if r is ours or r.variant == "kernel":
                continue
            ours.speedups[r.variant] = r.ms / ours.ms
            if r.queued_ms and ours.queued_ms:
                ours.queued_speedups[r.variant] = r.queued_ms / ours.queued_ms
            if r.kernel_ms and ours.kernel_ms:
                ours.kernel_speedups[r.variant] = r.kernel_ms / ours.kernel_ms
    return results
