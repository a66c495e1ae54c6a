"""Value checks folded into the composite kernels (their ``invalid`` output) and reported later
without a host synchronisation on a GPU (mixer_nerf.ops.deferred_checks)."""

from __future__ import annotations

import types

import pytest
import torch

from mixer_nerf import _extension
from mixer_nerf.ops import (
    check_pending,
    composite,
    composite_packed,
    deferred_checks,
    hierarchical_samples,
    ray_scale,
    sample_pdf,
    sample_pdf_packed,
    segment_mean,
)
from mixer_nerf.ops.composite import INVALID_INPUT

NEGATIVE_SIGMA, REVERSED_INTERVAL, BAD_OFFSETS = 1, 2, 4

devices = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA GPU")])]


@pytest.fixture(autouse=True)
def _kernels_and_a_clean_queue():
    if not _extension.available():
        pytest.skip("compiled kernels unavailable")
    composite(torch.ones(1, 1), torch.ones(1, 1, 3), torch.zeros(1, 1), torch.ones(1, 1))  # loads the ops
    deferred_checks._discard_pending()
    yield
    deferred_checks._discard_pending()


def _rays(device, rays=37, samples=19):
    gen = torch.Generator().manual_seed(torch.seed() % 2**31)
    sigmas = 3 * torch.rand(rays, samples, generator=gen)
    rgbs = torch.rand(rays, samples, 3, generator=gen)
    t = (2 + 4 * torch.rand(rays, samples + 1, generator=gen)).sort(dim=-1).values
    return [x.to(device) for x in (sigmas, rgbs, t[:, :-1].contiguous(), t[:, 1:].contiguous())]


def _packed(device, rays=23, most=9):
    gen = torch.Generator().manual_seed(torch.seed() % 2**31)
    counts = torch.randint(0, most + 1, (rays,), generator=gen)
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])
    n = int(offsets[-1])
    t = 2 + 4 * torch.rand(n, generator=gen)
    return [x.to(device) for x in (3 * torch.rand(n, generator=gen), torch.rand(n, 3, generator=gen), t,
                                    t + torch.rand(n, generator=gen), offsets)]


def _invalid_dense(sigmas, rgbs, t_starts, t_ends):
    return int(torch.ops.mixer_nerf.composite_fwd(sigmas, rgbs, t_starts, t_ends, None)[-1])


def _invalid_packed(sigmas, rgbs, t_starts, t_ends, offsets):
    return int(torch.ops.mixer_nerf.composite_packed_fwd(sigmas, rgbs, t_starts, t_ends, None, offsets)[-1])


@pytest.mark.parametrize("device", devices)
def test_the_kernels_flag_each_kind_of_bad_value(device):
    sigmas, rgbs, t_starts, t_ends = _rays(device)
    assert _invalid_dense(sigmas, rgbs, t_starts, t_ends) == 0
    bad = sigmas.clone()
    bad[5, 7] = -1e-6
    assert _invalid_dense(bad, rgbs, t_starts, t_ends) == NEGATIVE_SIGMA
    swapped = t_starts.clone()
    swapped[36, 18] = t_ends[36, 18] + 1e-3
    assert _invalid_dense(sigmas, rgbs, swapped, t_ends) == REVERSED_INTERVAL
    assert _invalid_dense(bad, rgbs, swapped, t_ends) == NEGATIVE_SIGMA | REVERSED_INTERVAL

    sigmas, rgbs, t_starts, t_ends, offsets = _packed(device)
    n = sigmas.shape[0]
    assert _invalid_packed(sigmas, rgbs, t_starts, t_ends, offsets) == 0
    assert _invalid_packed(-sigmas, rgbs, t_starts, t_ends, offsets) == NEGATIVE_SIGMA
    assert _invalid_packed(sigmas, rgbs, t_ends, t_starts, offsets) == REVERSED_INTERVAL
    for broken in (offsets + 1, offsets.clamp(max=n - 1), offsets.flip(0)):
        if broken[-1] != n or broken[0] != 0 or bool((broken[1:] < broken[:-1]).any()):
            assert _invalid_packed(sigmas, rgbs, t_starts, t_ends, broken) & BAD_OFFSETS


def test_watched_bits_raise_at_the_next_check_naming_the_argument():
    sigmas, rgbs, t_starts, t_ends = _rays("cpu")
    deferred_checks.watch(torch.tensor([0], dtype=torch.int32), "composite", INVALID_INPUT)
    check_pending()  # nothing found: nothing raised, nothing left
    assert not deferred_checks.pending_count()
    invalid = torch.ops.mixer_nerf.composite_fwd(-sigmas, rgbs, t_ends, t_starts, None)[-1]
    deferred_checks.watch(invalid, "composite", INVALID_INPUT)
    with pytest.raises(ValueError, match="composite: sigmas must be non-negative; t_ends must be >= t_starts"):
        deferred_checks.watch(torch.tensor([0], dtype=torch.int32), "composite", INVALID_INPUT)
    check_pending()  # reported once


def test_the_cpu_still_checks_before_the_kernel():
    sigmas, rgbs, t_starts, t_ends = _rays("cpu")
    with pytest.raises(ValueError, match="sigmas must be non-negative"):
        composite(-sigmas, rgbs, t_starts, t_ends, backend="kernel")
    sigmas, rgbs, t_starts, t_ends, offsets = _packed("cpu")
    with pytest.raises(ValueError, match="offsets must start at 0"):
        composite_packed(sigmas, rgbs, t_starts, t_ends, offsets + 1, backend="kernel")
    with pytest.raises(ValueError, match="no ray"):
        composite_packed(sigmas, rgbs, t_starts, t_ends, offsets[:1], backend="kernel")
    assert not deferred_checks.pending_count()


@pytest.mark.parametrize("device", devices)
def test_hierarchical_samples_flags_each_kind_of_bad_value(device):
    hierarchical_samples(torch.linspace(0, 1, 4).expand(1, 4), torch.ones(1, 4), 2)  # loads the op
    gen = torch.Generator().manual_seed(torch.seed() % 2**31)
    z = (2 + 4 * torch.rand(29, 33, generator=gen)).sort(dim=-1).values.to(device)
    w = torch.rand(29, 33, generator=gen).to(device)
    u = torch.rand(29, 17, generator=gen).sort(dim=-1).values.to(device)

    def invalid(z, w, u):
        return int(torch.ops.mixer_nerf.hierarchical_samples_fwd(z, w, u, 0.0)[1])

    assert invalid(z, w, u) == 0
    bad_w, bad_z, bad_u = w.clone(), z.clone(), u.clone()
    bad_w[28, 0] = -1.0  # the end weights are unused, but checked like the rest (as on the CPU path)
    bad_z[3, 31] = bad_z[3, 32] + 1
    assert invalid(z, bad_w, u) == 1 and invalid(bad_z, w, u) == 2
    bad_u[7, 16] = 1.5
    assert invalid(z, w, bad_u) == 4
    bad_u[7, 16], bad_u[7, 0] = 1.0, 0.9
    assert invalid(z, w, bad_u) == 8
    assert invalid(bad_z, bad_w, u.flip(-1)) == 1 | 2 | 8
    with pytest.raises(ValueError, match="z_coarse must be sorted"):  # the CPU checks first
        hierarchical_samples(bad_z.cpu(), w.cpu(), 17, u=u.cpu(), backend="kernel")


def _pdf(device, rays=29, bins=13):
    """Dense bins (R, B+1), weights (R, B), and the same rays packed with 0 .. B bins each: bins
    (N + R), weights (N), offsets (R+1)."""
    gen = torch.Generator().manual_seed(torch.seed() % 2**31)
    edges = (2 + 4 * torch.rand(rays, bins + 1, generator=gen)).sort(dim=-1).values
    weights = torch.rand(rays, bins, generator=gen)
    counts = torch.randint(0, bins + 1, (rays,), generator=gen)
    slots = torch.arange(bins + 1)
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])
    packed = (edges[slots <= counts[:, None]], weights[slots[:-1] < counts[:, None]], offsets)
    return [x.to(device) for x in (edges, weights)], [x.to(device) for x in packed]


@pytest.mark.parametrize("device", devices)
def test_sample_pdf_flags_each_kind_of_bad_value(device):
    (edges, weights), (bins, packed_weights, offsets) = _pdf(device)

    ops = torch.ops.mixer_nerf

    def dense(edges, weights, num_samples=7):
        return int(ops.sample_pdf_stratified_fwd(edges, weights, num_samples, None, 0.0, False)[2])

    def packed(bins, weights, offsets, num_samples=7):
        out = ops.sample_pdf_packed_stratified_fwd(bins, weights, offsets, num_samples, None, 0.0, False)
        assert out[0].isfinite().all()  # whatever the offsets: clamped, in bounds
        return int(out[2])

    # (packed: a ray's first edge below the last of the ray before it is no error)
    assert dense(edges, weights) == 0 and packed(bins, packed_weights, offsets) == 0
    bad_w, bad_e = weights.clone(), edges.clone()
    bad_w[28, 12] = -1e-6
    bad_e[3, 5] = bad_e[3, 6] + 1
    assert dense(edges, bad_w) == 1 and dense(bad_e, weights) == 2
    assert dense(bad_e, bad_w, num_samples=0) == 1 | 2  # checked without samples too
    assert packed(bins, -packed_weights - 1, offsets) == 1
    assert packed(bins.flip(0), packed_weights, offsets) == 2  # every ray with 2 edges or more
    n = packed_weights.shape[0]
    for broken in (offsets + 1, offsets.clamp(max=n - 1), offsets.flip(0)):
        assert packed(bins, packed_weights, broken) & 16


def _segment_rows(device, rays=31, most=7, channels=5):
    """Packed rows (N, C), a per-ray scale (R, C) and offsets (R+1) with 0 .. most rows a ray."""
    gen = torch.Generator().manual_seed(torch.seed() % 2**31)
    counts = torch.randint(0, most + 1, (rays,), generator=gen)
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])
    rows = torch.randn(int(offsets[-1]), channels, generator=gen)
    return [x.to(device) for x in (rows, torch.rand(rays, channels, generator=gen), offsets)]


@pytest.mark.parametrize("device", devices)
def test_segment_ops_flag_bad_offsets(device):
    rows, scale, offsets = _segment_rows(device)
    ops = torch.ops.mixer_nerf

    def invalid(offsets):
        mean, mean_invalid = ops.segment_mean_fwd(rows, offsets)
        scaled, scale_invalid = ops.ray_scale_fwd(rows, scale, offsets)
        assert mean.isfinite().all() and scaled.isfinite().all()  # whatever the offsets: clamped, in bounds
        assert int(mean_invalid) == int(scale_invalid)
        return int(mean_invalid)

    assert invalid(offsets) == 0
    n = rows.shape[0]
    middle = offsets.clone()
    middle[15] = middle[16] + 1  # decreasing inside, first and last right
    for broken in (offsets + 1, offsets.clamp(max=n - 1), offsets.flip(0), middle, offsets - 1):
        assert invalid(broken) == BAD_OFFSETS


def test_the_cpu_checks_segment_ops_before_the_kernel():
    rows, scale, offsets = _segment_rows("cpu")
    with pytest.raises(ValueError, match="offsets must start at 0"):
        segment_mean(rows, offsets + 1, backend="kernel")
    decreasing = offsets.clone()
    decreasing[15] = decreasing[16] + 1
    with pytest.raises(ValueError, match="offsets must be non-decreasing"):
        ray_scale(rows, scale, decreasing, backend="kernel")
    assert not deferred_checks.pending_count()


def test_the_cpu_checks_sample_pdf_before_the_kernel():
    (edges, weights), (bins, packed_weights, offsets) = _pdf("cpu")
    with pytest.raises(ValueError, match="weights must be non-negative"):
        sample_pdf(edges, -weights, 8, backend="kernel")
    with pytest.raises(ValueError, match="bins must be sorted"):
        sample_pdf(edges.flip(-1), weights, 8, backend="kernel")
    with pytest.raises(ValueError, match="bins must be sorted"):
        sample_pdf_packed(bins.flip(0), packed_weights, offsets, 8, backend="kernel")
    with pytest.raises(ValueError, match="offsets must start at 0"):
        sample_pdf_packed(bins, packed_weights, offsets + 1, 8, backend="kernel")
    assert not deferred_checks.pending_count()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_sample_pdf_on_a_gpu_checks_without_a_sync_and_reports_later():
    (edges, weights), (bins, packed_weights, offsets) = _pdf("cuda", rays=4096, bins=63)
    sample_pdf(edges, weights, 128)  # warm-up: the op, pinned buffers, events
    check_pending()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        sample_pdf(edges, weights, 128)  # stratified, the default
        sample_pdf(edges, -weights, 128)  # returns: the GPU has not looked yet
    finally:
        torch.cuda.set_sync_debug_mode("default")
    with pytest.raises(ValueError, match="sample_pdf: weights must be non-negative"):
        check_pending()
    torch.cuda.set_sync_debug_mode("error")
    try:
        sample_pdf(edges.flip(-1), weights, 128)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    with pytest.raises(ValueError, match="sample_pdf: bins must be sorted"):
        check_pending()
    # The packed op syncs once, to size shared memory by its longest ray (documented), but checks
    # the values in its kernel all the same.
    sample_pdf_packed(bins, packed_weights, offsets + 1, 32)  # shifted rays: unsorted within, too
    with pytest.raises(ValueError, match="sample_pdf_packed: .*offsets must start at 0"):
        check_pending()
    sample_pdf_packed(bins, -packed_weights - 1, offsets, 32)
    with pytest.raises(ValueError, match="sample_pdf_packed: weights must be non-negative"):
        check_pending()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_on_a_gpu_the_checks_never_synchronise_and_a_bad_value_is_reported():
    sigmas, rgbs, t_starts, t_ends = _rays("cuda", rays=4096, samples=64)
    composite(sigmas, rgbs, t_starts, t_ends)  # warm-up: pinned buffers, events
    check_pending()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(3):
            composite(sigmas, rgbs, t_starts, t_ends)
        composite(-sigmas, rgbs, t_starts, t_ends)  # returns: the GPU has not looked yet
    finally:
        torch.cuda.set_sync_debug_mode("default")
    with pytest.raises(ValueError, match="composite: sigmas must be non-negative"):
        check_pending()
    packed = _packed("cuda")
    packed[-1] = packed[-1] + 1
    composite_packed(*packed[:4], packed[4])
    with pytest.raises(ValueError, match="composite_packed: offsets must start at 0"):
        check_pending()
    z = torch.linspace(2, 6, 64, device="cuda").expand(4096, 64).contiguous()
    weights = torch.rand(4096, 64, device="cuda")
    hierarchical_samples(z, weights, 128)
    check_pending()
    torch.cuda.set_sync_debug_mode("error")
    try:
        hierarchical_samples(z, weights, 128)  # stratified, the default
        hierarchical_samples(z.flip(-1), weights, 128)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    with pytest.raises(ValueError, match="hierarchical_samples: z_coarse must be sorted"):
        check_pending()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_segment_ops_on_a_gpu_check_offsets_without_a_sync_and_report_later():
    rows, scale, offsets = _segment_rows("cuda", rays=4096, most=31, channels=64)
    segment_mean(rows, offsets), ray_scale(rows, scale, offsets)  # warm-up: the ops, pinned buffers
    check_pending()
    torch.cuda.synchronize()
    shifted = offsets + 1
    torch.cuda.set_sync_debug_mode("error")
    try:
        segment_mean(rows, offsets)
        ray_scale(rows, scale, offsets)
        segment_mean(rows, shifted)  # returns: the GPU has not looked yet
    finally:
        torch.cuda.set_sync_debug_mode("default")
    with pytest.raises(ValueError, match="segment_mean: offsets must start at 0"):
        check_pending()
    ray_scale(rows, scale, shifted)
    with pytest.raises(ValueError, match="ray_scale: offsets must start at 0"):
        check_pending()
    segment_mean(rows, shifted, check_values=False)  # unchecked: nothing watched, nothing raised
    check_pending()


def test_host_slots_are_taken_and_given_back():
    slots = deferred_checks.HostSlots(3, 2, pin=False)
    taken = [slots.take() for _ in range(3)]
    assert [slot for slot, _ in taken] == [0, 1, 2]
    taken[1][1].fill_(5)
    assert slots.buffer.tolist() == [[0, 0], [5, 5], [0, 0]]
    slots.give(1)
    assert slots.take()[0] == 1


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_more_batches_than_buffers_in_flight_wait_for_the_oldest_and_reuse_its_buffer():
    sigmas, rgbs, t_starts, t_ends = _rays("cuda")
    composite(sigmas, rgbs, t_starts, t_ends)
    check_pending()
    torch.cuda._sleep(1_000_000_000)  # the GPU lags behind: the buffers run out and flushes wait
    for _ in range(3 * deferred_checks.MAX_IN_FLIGHT * deferred_checks.BATCH):
        composite(sigmas, rgbs, t_starts, t_ends)
        assert deferred_checks.pending_count() <= (deferred_checks.MAX_IN_FLIGHT + 1) * deferred_checks.BATCH
    check_pending()
    assert not deferred_checks.pending_count()
    assert len(deferred_checks._BUFFERS.free) == deferred_checks.MAX_IN_FLIGHT


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_a_captured_graph_is_not_watched():
    sigmas, rgbs, t_starts, t_ends = _rays("cuda")
    composite(sigmas, rgbs, t_starts, t_ends)
    check_pending()
    graph = torch.cuda.CUDAGraph()
    stream = torch.cuda.Stream()
    with torch.cuda.stream(stream), torch.cuda.graph(graph):
        out = composite(sigmas, rgbs, t_starts, t_ends)
    graph.replay()
    torch.cuda.synchronize()
    assert not deferred_checks.pending_count() and out.color.isfinite().all()


class _FakeEvent:
    """Stands for a torch.cuda.Event: counts its queries; ready once ``ready`` is set or waited for."""

    def __init__(self):
        self.ready, self.queries, self.waits = False, 0, 0

    def query(self):
        self.queries += 1
        return self.ready

    def synchronize(self):
        self.waits += 1
        self.ready = True


class _FakeCudaFlag(torch.Tensor):
    """A host flag that deferred_checks.watch takes for a device one."""

    is_cuda = True


class _FakeGpu:
    """Stands for the CUDA pieces of deferred_checks: the current stream (``stream``), the copy of a
    batch's flags with its event (each one counted), the capture test and the clock (``now``)."""

    def __init__(self, monkeypatch):
        self.monkeypatch, self.stream, self.now, self.capturing = monkeypatch, (1, 0, 1), 0.0, False
        self.copies, self.events, self.capture_tests = [], [], 0
        monkeypatch.setattr(deferred_checks, "_current_stream", lambda device_index: self.stream)
        monkeypatch.setattr(deferred_checks, "_copy_to_host", self._copy_to_host)
        monkeypatch.setattr(deferred_checks, "time", types.SimpleNamespace(perf_counter=lambda: self.now))
        monkeypatch.setattr(torch.cuda, "is_current_stream_capturing", self._is_capturing)
        self.configure(deferred_checks.BATCH, deferred_checks.MAX_IN_FLIGHT)

    def configure(self, batch, in_flight):
        self.monkeypatch.setattr(deferred_checks, "BATCH", batch)
        self.monkeypatch.setattr(deferred_checks, "MAX_IN_FLIGHT", in_flight)
        buffers = deferred_checks.HostSlots(in_flight, batch, pin=False)
        self.monkeypatch.setattr(deferred_checks, "_BUFFERS", buffers)

    def watch(self, op, found=0, stream=None, messages=None):
        """A checking op's call on ``stream`` (the current one if None) whose kernel found ``found``."""
        self.stream = stream or self.stream
        flag = torch.tensor([found], dtype=torch.int32).as_subclass(_FakeCudaFlag)
        deferred_checks.watch(flag, op, messages or {1: f"{op} is bad"})

    def _copy_to_host(self, flags, stream, host):
        host[: len(flags)] = torch.tensor([int(flag) for flag in flags])
        self.copies.append((stream, len(flags)))
        self.events.append(_FakeEvent())
        return self.events[-1]

    def _is_capturing(self):
        self.capture_tests += 1
        return self.capturing


@pytest.fixture
def gpu(monkeypatch):
    fake = _FakeGpu(monkeypatch)
    yield fake
    deferred_checks._discard_pending()  # while the fake buffers are still there


A, B = (1, 0, 1), (2, 0, 1)  # two streams of device 0


def test_a_watch_that_does_not_flush_copies_nothing_and_a_full_batch_flushes(gpu):
    batch = deferred_checks.BATCH
    for _ in range(batch - 1):
        gpu.watch("composite")
    assert not gpu.copies and not gpu.events  # no copy, no event, no event query
    assert gpu.capture_tests == batch - 1 and deferred_checks.pending_count() == batch - 1
    gpu.watch("composite")
    assert gpu.copies == [(A, batch)] and gpu.events[0].queries == 1  # one copy, one poll
    assert deferred_checks.pending_count() == batch and not deferred_checks._open
    gpu.events[0].ready = True
    deferred_checks.raise_ready()
    assert not deferred_checks.pending_count()
    assert len(deferred_checks._BUFFERS.free) == deferred_checks.MAX_IN_FLIGHT


def test_a_batch_flushes_once_its_first_check_is_older_than_flush_seconds(gpu):
    late = deferred_checks.FLUSH_SECONDS
    gpu.watch("b", stream=B)
    gpu.now = 0.4 * late
    gpu.watch("a", stream=A)
    gpu.now = 1.2 * late  # B's batch is old, but a call on A flushes only A's
    gpu.watch("a", stream=A)
    assert not gpu.copies
    gpu.now = 1.5 * late
    gpu.watch("a", stream=A)
    assert gpu.copies == [(A, 3)]
    gpu.watch("a", stream=A)  # a new batch
    gpu.watch("b", stream=B)
    assert gpu.copies == [(A, 3), (B, 2)] and deferred_checks.pending_count() == 6


def test_errors_come_in_the_order_of_the_calls_within_a_batch_and_across_streams(gpu):
    gpu.watch("composite", stream=A, messages=INVALID_INPUT)
    gpu.watch("composite", found=NEGATIVE_SIGMA, stream=A, messages=INVALID_INPUT)
    gpu.watch("composite_packed", found=BAD_OFFSETS, stream=B, messages=INVALID_INPUT)
    gpu.watch("composite", stream=A, messages=INVALID_INPUT)
    gpu.watch("composite", found=REVERSED_INTERVAL, stream=A, messages=INVALID_INPUT)
    with pytest.raises(ValueError, match="^composite: sigmas must be non-negative"):
        deferred_checks.check_pending()
    assert deferred_checks.pending_count() == 3  # read, raised by the next calls
    with pytest.raises(ValueError, match="^composite_packed: offsets must"):
        gpu.watch("composite", stream=A)
    with pytest.raises(ValueError, match="^composite: t_ends must be >= t_starts"):
        deferred_checks.raise_ready()
    deferred_checks.raise_ready()
    assert not deferred_checks.pending_count()  # the call that raised watched nothing: it raised first


def test_check_pending_flushes_the_open_batches_and_waits_for_them(gpu):
    gpu.watch("a", stream=A)
    gpu.watch("b", found=1, stream=B)
    assert not gpu.copies and deferred_checks.pending_count() == 2
    with pytest.raises(ValueError, match="b is bad"):
        deferred_checks.check_pending()
    assert sorted(gpu.copies) == [(A, 1), (B, 1)] and [event.waits for event in gpu.events] == [1, 1]
    assert not deferred_checks.pending_count()


def test_a_captured_graph_is_not_watched_nor_raised_into(gpu):
    deferred_checks.watch(torch.tensor([1], dtype=torch.int32), "a", {1: "a is bad"})  # read at once
    gpu.capturing = True
    gpu.watch("b", found=1)
    assert gpu.capture_tests == 1 and deferred_checks.pending_count() == 1 and not deferred_checks._open
    gpu.capturing = False
    with pytest.raises(ValueError, match="a is bad"):
        gpu.watch("c")


def test_raise_ready_queries_one_event_per_stream_however_many_batches_are_in_flight(gpu):
    gpu.configure(batch=2, in_flight=64)
    for _ in range(40):
        gpu.watch("a", stream=A)
    for _ in range(20):
        gpu.watch("b", stream=B)
    a, b = gpu.events[:20], gpu.events[20:]
    for event in gpu.events:
        event.queries = 0
    for calls in (1, 2, 3):
        deferred_checks.raise_ready()
        assert sum(event.queries for event in gpu.events) == 2 * calls  # the heads of the two streams
    a[0].ready = a[1].ready = True  # the GPU has passed two batches of the first stream
    deferred_checks.raise_ready()
    assert deferred_checks.pending_count() == 56
    assert [a[0].queries, a[1].queries, a[2].queries, b[0].queries] == [4, 1, 1, 4]  # two landed, a new head


def test_a_landed_bad_batch_on_another_stream_is_raised_and_one_stream_keeps_its_order(gpu):
    gpu.configure(batch=1, in_flight=8)  # every call flushes
    gpu.watch("slow", stream=A)
    gpu.watch("other_stream", found=1, stream=B)
    slow, other = gpu.events
    other.ready = True
    with pytest.raises(ValueError, match="other_stream is bad"):
        deferred_checks.raise_ready()
    gpu.watch("same_stream", found=1, stream=A)  # behind ``slow``, which has not landed
    gpu.events[-1].ready = True
    deferred_checks.raise_ready()
    assert deferred_checks.pending_count() == 2
    slow.ready = True
    with pytest.raises(ValueError, match="same_stream is bad"):
        deferred_checks.raise_ready()
    assert not deferred_checks.pending_count()


def test_a_flush_without_a_free_buffer_waits_for_the_oldest_batch_of_any_stream(gpu):
    gpu.configure(batch=2, in_flight=3)
    for stream in (B, A, A):
        gpu.watch("x", stream=stream)
        gpu.watch("x", stream=stream)
    assert not deferred_checks._BUFFERS.free
    gpu.watch("x", stream=A)
    gpu.watch("x", stream=A)
    assert [event.waits for event in gpu.events] == [1, 0, 0, 0]  # B's, the oldest
    assert deferred_checks.pending_count() == 6 and not deferred_checks._BUFFERS.free
