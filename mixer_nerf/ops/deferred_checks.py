"""Value checks that cost a GPU no host synchronisation, and next to no host time.

On the CPU an op checks its input values before its kernel runs. On a GPU that would wait for the
device at every call, so a kernel that reads the values anyway ORs what it finds wrong into a
one-element int32 ``invalid`` output, and :func:`watch` reports it later. A CUDA graph being
captured is not watched: its replays have no host to report to.

A copy to the host and a CUDA event per call cost every checked call host time, so :func:`watch`
only appends the flag (kept alive by reference, no copy) to the open batch of the current CUDA
stream. The next checking call on that stream flushes the batch once it holds :data:`BATCH`
checks or its first check is older than :data:`FLUSH_SECONDS`: on the stream, one ``torch.cat``
of its flags, one copy into a pinned host buffer (a pool of :data:`MAX_IN_FLIGHT`, allocated
once) and one CUDA event. Each flush then polls the events (:func:`raise_ready`) and raises a
ValueError naming the op and the argument for the first bad check, in the order the checks were
made, whose batch has landed; later bad checks already read are raised by the next checking
calls. So an error comes at the first flush after its batch has landed (within :data:`BATCH`
checking calls on a stream, or at the first one :data:`FLUSH_SECONDS` after that stream's batch
opened), or at :func:`check_pending`, which flushes every open batch and waits (renderers call it
once an image is done; call it yourself before trusting results). A stream that gets no more
checks keeps its open batch until :func:`check_pending`.

The flushed batches are queued per CUDA stream: events recorded on one stream complete in order,
so :func:`raise_ready` queries only the oldest batch of each stream, O(streams) queries a poll
however many batches are in flight.
"""

from __future__ import annotations

import heapq
import itertools
import time
from collections import deque
from dataclasses import dataclass, field

import torch

BATCH = 64
"""Checks of one stream read back together (one copy and one event per batch)."""
FLUSH_SECONDS = 0.05
"""Age of a batch's first check past which the next checking call flushes it."""
MAX_IN_FLIGHT = 8
"""Flushed batches (pinned buffers) in flight before a flush waits for the oldest."""

StreamKey = tuple  # (stream id, device index, device type), as torch._C._cuda_getCurrentStream gives it


@dataclass
class _Batch:
    stream: StreamKey
    started: float  # time.perf_counter() at its first check
    flags: list[torch.Tensor] = field(default_factory=list)  # (1,) int32 on the device, until flushed
    checks: list[tuple[int, str, dict[int, str]]] = field(default_factory=list)  # (order, op, messages)
    done: torch.cuda.Event | None = None  # recorded behind the copy of its flags, once flushed
    slot: int | None = None  # its buffer of _BUFFERS, once flushed; given back once read


class HostSlots:
    """``capacity`` buffers of ``width`` int32 in one host tensor (pinned where CUDA is), allocated
    once: a pinned allocation per flush would go through the host allocator, which may call
    cudaHostAlloc while an earlier buffer still waits for its event."""

    def __init__(self, capacity: int, width: int, pin: bool):
        self.buffer = torch.zeros(capacity, width, dtype=torch.int32, pin_memory=pin)
        self.free = list(range(capacity - 1, -1, -1))

    def take(self) -> tuple[int, torch.Tensor]:
        slot = self.free.pop()
        return slot, self.buffer[slot]

    def give(self, slot: int) -> None:
        self.free.append(slot)


_made = itertools.count()
_open: dict[StreamKey, _Batch] = {}  # stream -> its batch not yet flushed
_queues: dict[StreamKey, deque[_Batch]] = {}  # stream -> flushed batches not landed yet, oldest first
_ready: list[tuple[int, int, str, dict[int, str]]] = []  # heap of (order, found, op, messages), unraised
_BUFFERS: HostSlots | None = None  # made at the first flush


def watch(invalid: torch.Tensor, op: str, messages: dict[int, str]) -> None:
    """Report ``invalid``'s bits (each a key of ``messages``) as a ValueError once they reach the
    host. Raises first what earlier calls found and was read."""
    on_device = invalid.is_cuda
    if on_device and torch.cuda.is_current_stream_capturing():
        return  # a capture forbids event queries, and its replays would not report anyway
    _raise_read()  # empties _ready (or raises)
    if on_device:
        _watch_on_device(invalid, op, messages)
    else:
        found = int(invalid.max()) if invalid.numel() else 0
        heapq.heappush(_ready, (next(_made), found, op, messages))  # a CPU flag is read at once


def in_kernel(kernel: bool, like: torch.Tensor) -> bool:
    """Whether an op whose kernel checks its values should leave them to it: on a GPU, when the
    kernel runs (``kernel``, decided once by the op; the CPU and the reference path check before it)."""
    return kernel and like.device.type == "cuda"


def raise_ready() -> None:
    """Raise ValueError for the first bad check (in the order they were made) whose batch has
    landed on the host; never waits. The checks behind it stay pending (later calls raise them).
    Queries one event per stream with batches in flight, plus one per batch found landed."""
    _read_landed()
    _raise_read()


def check_pending() -> None:
    """Flush every open batch, wait for every batch in flight and raise ValueError for the first bad
    check."""
    for batch in list(_open.values()):
        _flush(batch)
    for queue in _queues.values():
        for batch in queue:
            batch.done.synchronize()
    raise_ready()


def pending_count() -> int:
    """How many checks are open, in flight or not yet read."""
    batches = list(_open.values()) + [batch for queue in _queues.values() for batch in queue]
    return len(_ready) + sum(len(batch.checks) for batch in batches)


def _current_stream(device_index: int) -> StreamKey:
    """The current stream of a device as a tuple: cheaper than torch.cuda.current_stream's object."""
    return torch._C._cuda_getCurrentStream(device_index)


def _copy_to_host(flags: list[torch.Tensor], stream: StreamKey, host: torch.Tensor) -> torch.cuda.Event:
    """Copy ``flags`` into ``host`` on ``stream`` without waiting; returns an event recorded behind."""
    cuda_stream = torch.cuda.Stream(stream_id=stream[0], device_index=stream[1], device_type=stream[2])
    with torch.cuda.stream(cuda_stream):  # the flags were made on it: no other stream's wait needed
        host[: len(flags)].copy_(torch.cat([flag.reshape(1) for flag in flags]), non_blocking=True)
        done = torch.cuda.Event()
        done.record(cuda_stream)
    return done


def _watch_on_device(invalid: torch.Tensor, op: str, messages: dict[int, str]) -> None:
    """Append a device flag to its stream's open batch; flush it once full or old, then poll."""
    stream = _current_stream(invalid.get_device())  # the stream the op's kernel wrote ``invalid`` on
    batch = _open.get(stream)
    if batch is None:
        batch = _open[stream] = _Batch(stream, time.perf_counter())
    batch.flags.append(invalid)
    batch.checks.append((next(_made), op, messages))
    if len(batch.checks) >= BATCH or time.perf_counter() - batch.started > FLUSH_SECONDS:
        _flush(batch)  # only the current stream's: another may be capturing a graph now
        raise_ready()


def _flush(batch: _Batch) -> None:
    """Start the copy of an open batch's flags to a host buffer and queue it behind its stream's."""
    global _BUFFERS
    if _BUFFERS is None:
        _BUFFERS = HostSlots(MAX_IN_FLIGHT, BATCH, pin=True)
    if not _BUFFERS.free:  # wait for the oldest batch in flight, which gives its buffer back
        min((queue[0] for queue in _queues.values()), key=lambda b: b.checks[0][0]).done.synchronize()
        _read_landed()
    batch.slot, host = _BUFFERS.take()
    batch.done = _copy_to_host(batch.flags, batch.stream, host)
    batch.flags = []  # the copy is queued on their stream: the allocator may reuse them behind it
    del _open[batch.stream]
    _queues.setdefault(batch.stream, deque()).append(batch)


def _read_landed() -> None:
    """Move the checks of every landed batch to _ready, giving its buffer back; never waits."""
    for stream, queue in list(_queues.items()):
        while queue and queue[0].done.query():  # in order on a stream: the rest has not landed either
            batch = queue.popleft()
            found = _BUFFERS.buffer[batch.slot, : len(batch.checks)].tolist()
            _BUFFERS.give(batch.slot)
            for (order, op, messages), bits in zip(batch.checks, found, strict=True):
                heapq.heappush(_ready, (order, bits, op, messages))
        if not queue:
            del _queues[stream]


def _raise_read() -> None:
    """Raise ValueError for the first bad check read (in the order made); the rest stay in _ready."""
    while _ready:
        _, found, op, messages = heapq.heappop(_ready)
        if found:
            what = "; ".join(message for bit, message in messages.items() if found & bit)
            raise ValueError(f"{op}: {what} (found on the device by an earlier call: on a GPU the values "
                             f"are checked without waiting for it; mixer_nerf.ops.check_pending() waits)")


def _discard_pending() -> None:
    """Forget every check open, in flight or unread (tests start from an empty queue)."""
    for queue in _queues.values():
        for batch in queue:
            batch.done.synchronize()  # its buffer is written until then
            _BUFFERS.give(batch.slot)
    _open.clear()
    _queues.clear()
    _ready.clear()
