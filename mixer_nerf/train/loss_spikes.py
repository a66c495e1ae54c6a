"""Loss-spike notes: a logged training loss far above the losses logged just before it.

The optimiser can recover from a spike on the training views while the field stays broken for
unseen ones (preset A on Fern at 600 s: docs/training.md), so the run says so when it happens,
not only at its evaluation. Only logged losses are read: the log step synchronises anyway.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Iterable


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
