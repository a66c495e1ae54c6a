"""Value checks that cost a GPU no host synchronisation.

On the CPU an op checks its input values before its kernel runs. On a GPU that would wait for the
device at every call, so a kernel that reads the values anyway ORs what it finds wrong into a
one-element int32 ``invalid`` output, and :func:`watch` copies it to pinned host memory behind a
CUDA event. The error is raised where the copy has landed without waiting: at the next call of a
checking op (:func:`raise_ready`), or at :func:`check_pending`, which waits (renderers call it once
an image is done; call it yourself before trusting results). A CUDA graph being captured is not
watched: its replays have no host to report to.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

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


_pending: deque[_Pending] = deque()
_SLOTS: HostSlots | None = None  # made at the first GPU check


def watch(invalid: torch.Tensor, op: str, messages: dict[int, str]) -> None:
    """Report ``invalid``'s bits (each a key of ``messages``) as a ValueError once they reach the
    host. Raises first what earlier calls found (:func:`raise_ready`)."""
    if invalid.device.type == "cuda" and torch.cuda.is_current_stream_capturing():
        return  # a capture forbids event queries, and its replays would not report anyway
    raise_ready()
    if len(_pending) >= MAX_PENDING:
        _wait(_pending[0])
        raise_ready()
    if invalid.device.type == "cuda":
        global _SLOTS
        if _SLOTS is None:
            _SLOTS = HostSlots(MAX_PENDING, pin=True)
        slot, bits = _SLOTS.take()
        bits.copy_(invalid.reshape(1), non_blocking=True)
        done = torch.cuda.Event()
        done.record()
        _pending.append(_Pending(bits, done, op, messages, slot))
    else:
        _pending.append(_Pending(invalid, None, op, messages))


def in_kernel(kernel: bool, like: torch.Tensor) -> bool:
    """Whether an op whose kernel checks its values should leave them to it: on a GPU, when the
    kernel runs (``kernel``, decided once by the op; the CPU and the reference path check before it)."""
    return kernel and like.device.type == "cuda"


def raise_ready() -> None:
    """Raise ValueError for the first bad check whose result is on the host; never waits. The
    checks behind it stay pending."""
    while _pending and _is_ready(_pending[0]):
        _raise_if_bad(_pending.popleft())
    for pending in [p for p in _pending if _is_ready(p)]:  # other streams finish out of order
        _pending.remove(pending)
        _raise_if_bad(pending)


def check_pending() -> None:
    """Wait for every check in flight and raise ValueError for the first bad one."""
    for pending in list(_pending):
        _wait(pending)
    raise_ready()


def _discard_pending() -> None:
    """Forget every check in flight, unread (tests start from an empty queue)."""
    for pending in _pending:
        if pending.slot is not None:
            _wait(pending)
            _SLOTS.give(pending.slot)
    _pending.clear()


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
