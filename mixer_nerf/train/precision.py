"""The precision a run's fields compute in: bf16 autocast around the MLP (float32 master weights,
their bf16 copies made together once a pass), TF32 matmuls."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import torch
from torch import nn


class _CastTogether(torch.autograd.Function):
    """``tensors`` (one dtype) in ``dtype`` by one multi-tensor copy, their gradients back by
    another: two kernels a pass, where autocast casts each weight alone, and its gradient back."""

    @staticmethod
    def forward(ctx, dtype: torch.dtype, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        ctx.set_materialize_grads(False)  # a weight the pass did not use keeps no gradient
        ctx.source_dtypes = [t.dtype for t in tensors]
        cast = [torch.empty_like(t, dtype=dtype) for t in tensors]
        torch._foreach_copy_(cast, list(tensors))
        return tuple(cast)

    @staticmethod
    def backward(ctx, *grads: torch.Tensor | None):
        given = [(g, dtype) for g, dtype in zip(grads, ctx.source_dtypes, strict=True) if g is not None]
        back = [torch.empty_like(g, dtype=dtype) for g, dtype in given]
        if back:
            torch._foreach_copy_(back, [g for g, _ in given])
        cast_back = iter(back)
        return None, *(None if g is None else next(cast_back) for g in grads)


class MixedPrecisionField(nn.Module):
    """Runs a field under bf16 autocast (``dtype``; None: as it is) and hands float32 back.

    Only the MLP runs in reduced precision: sampling and compositing kernels take float32, so the
    outputs are cast back before they reach them. The parameters stay float32 (the optimiser's);
    each pass runs on bf16 copies of the field's ``nn.Linear`` weights and biases, made together
    (:class:`_CastTogether`), which autocast then leaves alone. Other parameters (MLCA's, which its
    kernel takes in the encoding's float32) are the field's own.
    """

    packed_layout = ("ray_indices", "offsets", "ray_directions")

    def __init__(self, field: nn.Module, device_type: str, dtype: torch.dtype | None) -> None:
        super().__init__()
        self.field = field
        self.device_type = device_type
        self.dtype = dtype
        # (module, name) of each linear layer's weight and bias: read and swapped in place each
        # pass, where resolving dotted names and torch's reparametrisation cost ~0.5 ms of host time.
        self._linear_slots = [(m, p) for m in field.modules() if isinstance(m, nn.Linear)
                              for p in ("weight", "bias") if getattr(m, p) is not None]

    def _autocast(self):
        return torch.autocast(self.device_type, dtype=self.dtype or torch.float32, enabled=self.dtype is not None)

    def _run(self, fn, *args, **kwargs):
        """``fn`` (the field or one of its methods) on reduced copies of the linear layers' parameters."""
        if self.dtype is None or not self._linear_slots:
            return fn(*args, **kwargs)
        params = [m._parameters[p] for m, p in self._linear_slots]
        if params[0].dtype == self.dtype:
            return fn(*args, **kwargs)
        with _swapped(self._linear_slots, _CastTogether.apply(self.dtype, *params)):
            return fn(*args, **kwargs)

    def forward(
        self,
        x: torch.Tensor,
        d: torch.Tensor,
        ray_indices: torch.Tensor | None = None,
        num_rays: int | None = None,
        offsets: torch.Tensor | None = None,
        ray_directions: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The field's ``(sigma, rgb)`` in float32; packed-layout arguments as for
        :meth:`~mixer_nerf.model.MixerNeRF.forward`."""
        with self._autocast():
            sigma, rgb = self._run(self.field, x, d, ray_indices=ray_indices, num_rays=num_rays,
                                   offsets=offsets, ray_directions=ray_directions)
        return sigma.float(), rgb.float()

    def density(
        self,
        x: torch.Tensor,
        ray_indices: torch.Tensor | None = None,
        num_rays: int | None = None,
        offsets: torch.Tensor | None = None,
        ray_directions: torch.Tensor | None = None,
    ) -> torch.Tensor:
        with self._autocast():
            return self._run(self.field.density, x, ray_indices=ray_indices, num_rays=num_rays,
                             offsets=offsets, ray_directions=ray_directions).float()


@contextmanager
def _swapped(slots: Sequence[tuple[nn.Module, str]], tensors: Sequence[torch.Tensor]) -> Iterator[None]:
    """The modules' parameters ``slots`` replaced by ``tensors`` inside the block (what
    torch.func.functional_call does around a forward), restored after it, also on an error."""
    saved = [m._parameters[p] for m, p in slots]
    for (m, p), t in zip(slots, tensors, strict=True):
        m._parameters[p] = t
    try:
        yield
    finally:
        for (m, p), t in zip(slots, saved, strict=True):
            m._parameters[p] = t


def set_matmul_precision(precision: str) -> None:
    """TF32 tensor-core matmuls for "tf32" and "bf16" (outside autocast); exact float32 for "fp32"."""
    torch.backends.cuda.matmul.allow_tf32 = precision != "fp32"
    torch.backends.cudnn.allow_tf32 = precision != "fp32"
