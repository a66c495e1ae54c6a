"""Non-finite guard: notices the first step whose loss or gradients are NaN/Inf.

Checking a CUDA value on the host forces a synchronisation, which would stall the GPU every step.
So the guard records, on the device, the first step at which each watched tensor went bad, and the
trainer only reads that back (``raise_if_bad``) every few steps and always before it writes a
checkpoint: a checkpoint is never written from a bad state, and the error names the exact step.
"""

from __future__ import annotations

import torch


class NonFiniteError(RuntimeError):
    """Training produced NaN/Inf; ``step`` is the first bad step (1-based, as logged)."""

    def __init__(self, message: str, step: int) -> None:
        super().__init__(message)
        self.step = step


class NonFiniteGuard:
    def __init__(self, param_names: list[str], device: torch.device) -> None:
        self.param_names = param_names
        self.device = device
        self._first_bad: dict[str, torch.Tensor] = {}
        self._zero: torch.Tensor | None = None

    def observe_losses(self, step: int | torch.Tensor, **losses: torch.Tensor) -> None:
        """Record ``step`` (a number, or a 0-d int64 tensor on the device: a replayed CUDA graph's
        step) for each named scalar that is not finite (and not already bad)."""
        for name, value in losses.items():
            self._record(name, step, ~torch.isfinite(value.detach()))

    @torch.no_grad()  # rather than a detach per gradient: one op per parameter less each step
    def observe_grads(self, step: int | torch.Tensor, grads: list[torch.Tensor | None]) -> None:
        """Record ``step`` per parameter (ordered as ``param_names``) whose gradient is not finite.
        A missing gradient counts as finite; nothing here copies from the host or synchronises."""
        if self._zero is None:
            self._zero = torch.zeros((), device=self.device)
        norms = torch._foreach_norm([self._zero if g is None else g for g in grads])
        self._record("gradients", step, ~torch.isfinite(torch.stack(norms)))

    def raise_if_bad(self) -> None:
        """Synchronise and raise :class:`NonFiniteError` describing the first bad step, if any."""
        found = {name: first.cpu() for name, first in self._first_bad.items()}
        bad_steps = [int(v[v >= 0].min()) for v in found.values() if (v >= 0).any()]
        if not bad_steps:
            return
        step = min(bad_steps)
        what = []
        for name, first in found.items():
            if name == "gradients":
                params = [self.param_names[i] for i in torch.nonzero(first == step).flatten().tolist()]
                if params:
                    shown = ", ".join(params[:3]) + (f" (+{len(params) - 3} more)" if len(params) > 3 else "")
                    what.append(f"gradient of {shown}")
            elif int(first) == step:
                what.append(name)
        raise NonFiniteError(f"non-finite value at step {step}: {'; '.join(what)}", step)

    def _record(self, name: str, step: int | torch.Tensor, bad: torch.Tensor) -> None:
        first = self._first_bad.get(name)
        if first is None:
            first = self._first_bad[name] = torch.full(bad.shape, -1, dtype=torch.int64, device=self.device)
        first.copy_(torch.where(bad & (first < 0), step, first))
