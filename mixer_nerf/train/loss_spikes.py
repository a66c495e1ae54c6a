"""Loss spikes: a logged training loss far above the losses logged just before it.

The optimiser can recover from a spike on the training views while the field stays broken for
unseen ones (preset A on Fern at 600 s: docs/training.md), so the run says so when it happens and
goes back to its state from before it. Only logged losses are read: the log step synchronises anyway.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Iterable, Sequence

import torch


class LossSpikeWatch:
    """Says a spike once, when a logged loss exceeds ``ratio`` x the median of the ``window`` losses
    logged before it; quiet again once a loss is back under that bound."""

    def __init__(self, ratio: float = 2.0, window: int = 10) -> None:
        if ratio <= 1 or window < 1:
            raise ValueError(f"need ratio > 1 and window >= 1, got ratio={ratio}, window={window}")
        self.ratio = ratio
        self._recent: deque[float] = deque(maxlen=window)
        self._in_spike = False

    def observe(self, step: int, loss: float) -> str | None:
        """The note for ``loss`` logged at ``step``, or None. A non-finite loss is the non-finite
        guard's to report: it is passed over."""
        if not math.isfinite(loss):
            return None
        note = None
        if len(self._recent) == self._recent.maxlen:
            median = statistics.median(self._recent)
            spiking = median > 0 and loss > self.ratio * median  # a zero median has no ratio to give
            if spiking and not self._in_spike:
                note = (f"loss spike at step {step}: {loss:.4g} is {loss / median:.1f}x the median of the "
                        f"{len(self._recent)} losses logged before; if validation PSNR falls and stays "
                        "down, see docs/training.md, 'Learning-rate schedule'")
            self._in_spike = spiking
        self._recent.append(loss)
        return note


def spike_steps(logged: Iterable[tuple[int, float]]) -> list[int]:
    """The steps a :class:`LossSpikeWatch` would say a spike at, over ``(step, loss)`` as logged."""
    watch = LossSpikeWatch()
    return [step for step, loss in logged if watch.observe(step, loss) is not None]


class SpikeRollback:
    """Takes a run back to before a loss spike: the trained tensors (parameters and the optimiser's
    state) are copied on their device at each of the last two logged steps without a spike, and a
    spike writes the older copy back in place (a CUDA graph's replay keeps reading the same memory).
    The older one, two log intervals before the spiking loss: the loss logged in between may
    already be climbing. At most ``limit`` times a run (0: never); the batches after a rollback are
    new ones, as the random stream goes on."""

    def __init__(self, params: Sequence[torch.Tensor], optimizer: torch.optim.Optimizer, limit: int) -> None:
        if limit < 0:
            raise ValueError(f"spike_rollbacks must be >= 0, got {limit}")
        self.params, self.optimizer, self.limit, self.used = list(params), optimizer, limit, 0
        self._copies: deque[tuple[int, list[torch.Tensor], list[torch.Tensor]]] = deque(maxlen=2)

    @property
    def left(self) -> int:
        return self.limit - self.used

    def _tensors(self) -> list[torch.Tensor]:
        state = (v for p in self.params for v in self.optimizer.state.get(p, {}).values())
        return [*self.params, *(v for v in state if isinstance(v, torch.Tensor))]

    @torch.no_grad()
    def keep(self, step: int) -> None:
        """Copy the trained tensors as they are after ``step``."""
        if not self.left:
            return
        tensors = self._tensors()
        leaving = self._copies[0] if len(self._copies) == self._copies.maxlen else None
        if leaving is not None and len(leaving[1]) == len(tensors) and all(a is b for a, b in zip(leaving[1], tensors)):
            buffers = leaving[2]  # the copy leaving the window lends its memory
            torch._foreach_copy_(buffers, tensors)
        else:
            buffers = [t.detach().clone() for t in tensors]
        self._copies.append((step, tensors, buffers))

    @torch.no_grad()
    def restore(self) -> int | None:
        """Write the older copy back and forget the newer one (it may hold the spike's start).
        Returns the step the copy was taken at, or None: no copy kept, or no rollback left."""
        if not self.left or not self._copies:
            return None
        oldest = self._copies[0]
        step, tensors, buffers = oldest
        torch._foreach_copy_(tensors, buffers)
        self._copies.clear()
        self._copies.append(oldest)
        self.used += 1
        return step
