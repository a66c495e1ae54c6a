"""Value checks that cost a GPU no host synchronisation.

On the CPU an op checks its input values before its kernel runs. On a GPU that would wait for the
device at every call, so a kernel that reads the values anyway ORs what it finds wrong into a
one-element int32 ``invalid`` output, and :func:`watch` copies it to pinned host memory behind a
CUDA event. The error is raised where the copy has landed without waiting: at the next call of a
checking op (:func:`raise_ready`), or at :func:`check_pending`, which waits (renderers call it once
an image is done; call it yourself before trusting results). A CUDA graph being captured is not
watched: its replays have no host to report to.

The checks in flight are queued per CUDA stream: events recorded on one stream complete in order,
so :func:`raise_ready` queries only the oldest check of each stream. The host usually runs ahead of
the GPU with many checks in flight, and an event query per check at every call would cost it
O(checks in flight) queries per op instead of O(streams).
"""

from __future__ import annotations

import heapq
import itertools
from collections import deque
from dataclasses import dataclass, field

import torch

MAX_PENDING = 256
"""Checks in flight before :func:`watch` waits for the oldest (bounds pinned memory and events)."""


@dataclass
class _Pending:
    bits: torch.Tensor  # (1,) int32 on the host: a slot of _SLOTS, filled by an asynchronous copy
    done: torch.cuda.Event | None  # None: ``bits`` is ready (a CPU flag)
    op: str
    messages: dict[int, str]  # bit -> what is wrong, naming the argument
    slot: int | None = None  # the slot of _SLOTS that ``bits`` views, given back once read
    order: int = field(default_factory=lambda: next(_made))  # when it was made: errors come in this order


class HostSlots:
    """``capacity`` int32 flags in one host buffer (pinned where CUDA is), allocated once: a
    pinned allocation per call would go through the host allocator, which may call cudaHostAlloc
    while the previous flag's buffer still waits for its event."""

    def __init__(self, capacity: int, pin: bool):
        self.buffer = torch.zeros(capacity, dtype=torch.int32, pin_memory=pin)
        self.free = list(range(capacity - 1, -1, -1))

    def take(self) -> tuple[int, torch.Tensor]:
        slot = self.free.pop()
        return slot, self.buffer[slot : slot + 1]

    def give(self, slot: int) -> None:
        self.free.append(slot)


_made = itertools.count()
_queues: dict[tuple[int, int], deque[_Pending]] = {}  # (device, stream id) -> not ready yet, oldest first
_ready: list[tuple[int, _Pending]] = []  # a heap by order: flags on the host, not yet read
_SLOTS: HostSlots | None = None  # made at the first GPU check


def watch(invalid: torch.Tensor, op: str, messages: dict[int, str]) -> None:
    """Report ``invalid``'s bits (each a key of ``messages``) as a ValueError once they reach the
    host. Raises first what earlier calls found (:func:`raise_ready`)."""
    if invalid.device.type == "cuda" and torch.cuda.is_current_stream_capturing():
        return  # a capture forbids event queries, and its replays would not report anyway
    raise_ready()  # empties _ready (or raises)
    if pending_count() >= MAX_PENDING:
        _wait(min((queue[0] for queue in _queues.values()), key=lambda p: p.order))  # the oldest
        raise_ready()
    if invalid.device.type == "cuda":
        global _SLOTS
        if _SLOTS is None:
            _SLOTS = HostSlots(MAX_PENDING, pin=True)
        slot, bits = _SLOTS.take()
        bits.copy_(invalid.reshape(1), non_blocking=True)  # on the current stream of invalid's device
        stream = torch.cuda.current_stream(invalid.device)
        done = torch.cuda.Event()
        done.record(stream)
        _enqueue((stream.device_index, stream.stream_id), _Pending(bits, done, op, messages, slot))
    else:
        pending = _Pending(invalid, None, op, messages)
        heapq.heappush(_ready, (pending.order, pending))  # a CPU flag is ready at once


def in_kernel(kernel: bool, like: torch.Tensor) -> bool:
    """Whether an op whose kernel checks its values should leave them to it: on a GPU, when the
    kernel runs (``kernel``, decided once by the op; the CPU and the reference path check before it)."""
    return kernel and like.device.type == "cuda"


def raise_ready() -> None:
    """Raise ValueError for the first bad check (in the order they were made) whose result is on the
    host; never waits. The checks behind it stay pending (the ready ones are raised by later calls).
    Queries one event per stream with checks in flight, plus one per check found ready."""
    for key, queue in list(_queues.items()):
        while queue and _is_ready(queue[0]):  # in order on a stream: the rest is not ready either
            pending = queue.popleft()
            heapq.heappush(_ready, (pending.order, pending))
        if not queue:
            del _queues[key]
    while _ready:
        _raise_if_bad(heapq.heappop(_ready)[1])


def check_pending() -> None:
    """Wait for every check in flight and raise ValueError for the first bad one."""
    for queue in _queues.values():
        for pending in queue:
            _wait(pending)
    raise_ready()


def pending_count() -> int:
    """How many checks are in flight or not yet read."""
    return len(_ready) + sum(len(queue) for queue in _queues.values())


def _enqueue(stream: tuple[int, int], pending: _Pending) -> None:
    """Queue a check behind the earlier ones of its stream ((device index, stream id))."""
    _queues.setdefault(stream, deque()).append(pending)


def _discard_pending() -> None:
    """Forget every check in flight, unread (tests start from an empty queue)."""
    for pending in [p for _, p in _ready] + [p for queue in _queues.values() for p in queue]:
        if pending.slot is not None:
            _wait(pending)
            _SLOTS.give(pending.slot)
    _ready.clear()
    _queues.clear()


def _is_ready(pending: _Pending) -> bool:
    return pending.done is None or pending.done.query()


def _wait(pending: _Pending) -> None:
    if pending.done is not None:
        pending.done.synchronize()


def _raise_if_bad(pending: _Pending) -> None:
    found = int(pending.bits.max()) if pending.bits.numel() else 0
    if pending.slot is not None:
        _SLOTS.give(pending.slot)
    if found:
        what = "; ".join(message for bit, message in pending.messages.items() if found & bit)
        raise ValueError(f"{pending.op}: {what} (found on the device by an earlier call: on a GPU the values "
                         f"are checked without waiting for it; mixer_nerf.ops.check_pending() waits)")
