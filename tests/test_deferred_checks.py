"""Value checks folded into the composite kernels (their ``invalid`` output) and reported later
without a host synchronisation on a GPU (mixer_nerf.ops.deferred_checks)."""

from __future__ import annotations

import pytest
import torch

from mixer_nerf import _extension
from mixer_nerf.ops import check_pending, composite, composite_packed, deferred_checks, hierarchical_samples
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


def test_host_slots_are_taken_and_given_back():
    slots = deferred_checks.HostSlots(3, pin=False)
    taken = [slots.take() for _ in range(3)]
    assert [slot for slot, _ in taken] == [0, 1, 2]
    taken[1][1].fill_(5)
    assert slots.buffer.tolist() == [0, 5, 0]
    slots.give(1)
    assert slots.take()[0] == 1


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_more_checks_than_slots_in_flight_wait_for_the_oldest_and_reuse_its_slot():
    sigmas, rgbs, t_starts, t_ends = _rays("cuda")
    for _ in range(3 * deferred_checks.MAX_PENDING):
        composite(sigmas, rgbs, t_starts, t_ends)
        assert deferred_checks.pending_count() <= deferred_checks.MAX_PENDING
    check_pending()
    assert not deferred_checks.pending_count()
    assert len(deferred_checks._SLOTS.free) == deferred_checks.MAX_PENDING


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

    def __init__(self, ready=False):
        self.ready, self.queries, self.waits = ready, 0, 0

    def query(self):
        self.queries += 1
        return self.ready

    def synchronize(self):
        self.waits += 1
        self.ready = True


def _fake_check(stream, op, found=0, ready=False):
    """Queue a check on a fake stream key, as watch does for a CUDA flag; returns its event."""
    done = _FakeEvent(ready)
    messages = {1: f"{op} is bad"}
    deferred_checks._enqueue(stream, deferred_checks._Pending(torch.tensor([found], dtype=torch.int32),
                                                              done, op, messages))
    return done


def test_raise_ready_queries_one_event_per_stream_however_many_are_pending():
    events = [_fake_check((0, 1), "a") for _ in range(100)] + [_fake_check((0, 2), "b") for _ in range(50)]
    for calls in (1, 2, 3):
        deferred_checks.raise_ready()
        assert sum(event.queries for event in events) == 2 * calls  # the heads of the two streams
    assert events[0].queries == events[100].queries == 3
    events[0].ready = events[1].ready = True  # the GPU has passed two checks of the first stream
    deferred_checks.raise_ready()
    assert deferred_checks.pending_count() == 148
    assert [events[i].queries for i in (0, 1, 2, 100)] == [4, 1, 1, 4]  # two ready, then a new head


def test_a_ready_bad_check_on_another_stream_is_raised_and_one_stream_keeps_its_order():
    slow = _fake_check((0, 1), "slow")
    _fake_check((0, 2), "other_stream", found=1, ready=True)
    with pytest.raises(ValueError, match="other_stream is bad"):
        deferred_checks.raise_ready()
    _fake_check((0, 1), "same_stream", found=1, ready=True)  # behind ``slow``, which is not ready
    deferred_checks.raise_ready()
    assert deferred_checks.pending_count() == 2
    slow.ready = True
    with pytest.raises(ValueError, match="same_stream is bad"):
        deferred_checks.raise_ready()
    assert not deferred_checks.pending_count()


def test_ready_bad_checks_are_raised_in_the_order_they_were_made_across_streams():
    events = [_fake_check((0, 1), "first", found=1), _fake_check((0, 2), "second", found=1),
              _fake_check((0, 1), "third", found=1), _fake_check((1, 1), "fourth", found=1, ready=True)]
    with pytest.raises(ValueError, match="fourth is bad"):  # the only one ready
        deferred_checks.raise_ready()
    with pytest.raises(ValueError, match="first is bad"):  # waits for all, raises the oldest bad one
        deferred_checks.check_pending()
    assert [event.waits for event in events[:3]] == [1, 1, 1]
    for name in ("second", "third"):  # read by check_pending, raised one a call
        with pytest.raises(ValueError, match=f"{name} is bad"):
            deferred_checks.raise_ready()
    assert not deferred_checks.pending_count()


def test_a_full_queue_waits_for_the_oldest_check_of_any_stream():
    oldest = _fake_check((0, 2), "oldest")
    others = [_fake_check((0, 1 + i % 2), "other") for i in range(deferred_checks.MAX_PENDING - 1)]
    deferred_checks.watch(torch.tensor([0], dtype=torch.int32), "composite", INVALID_INPUT)
    assert oldest.waits == 1 and not any(event.waits for event in others)
    assert deferred_checks.pending_count() == deferred_checks.MAX_PENDING
