"""Counts the ops a block dispatches below autograd (``aten.mm``, ``mixer_nerf.mlca_fwd``, ...): on
a GPU each is a kernel launch or host work, and the counts are deterministic, unlike timings."""

from __future__ import annotations

import collections
from collections.abc import Iterator
from contextlib import contextmanager

from torch.utils._python_dispatch import TorchDispatchMode


class _Count(TorchDispatchMode):
    def __init__(self, counts: collections.Counter) -> None:
        super().__init__()
        self.counts = counts

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.counts[str(func.overloadpacket)] += 1
        return func(*args, **(kwargs or {}))


@contextmanager
def dispatched_ops() -> Iterator[collections.Counter]:
    """``with dispatched_ops() as ops: ...`` fills ``ops`` with ``{op name: calls}``, backward included."""
    counts: collections.Counter = collections.Counter()
    with _Count(counts):
        yield counts
