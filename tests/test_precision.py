"""MixedPrecisionField: bf16 passes on float32 master weights, whose linear layers' bf16 copies are
made together; the same numbers as autocast casting each weight alone, with fewer casts."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode

from dispatch_count import dispatched_ops
from mixer_nerf.model import MixerNeRF, preset_config
from mixer_nerf.train.precision import MixedPrecisionField


def field(backend: str) -> MixerNeRF:
    torch.manual_seed(0)
    model = MixerNeRF(preset_config("D", backend=backend, width=64, view_width=32, depth=4, skips=(2,)))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.1)  # MLCA's mixing and the density row start at zero
    return model


def packed_rays(R: int = 6, S: int = 10):
    N = R * S
    x = torch.rand(N, 3) * 2 - 1
    offsets = torch.arange(0, N + 1, S)
    return x, torch.arange(R).repeat_interleave(S), R, offsets, F.normalize(torch.randn(R, 3), dim=-1)


def outputs_and_grads(runner: MixedPrecisionField, args) -> list[torch.Tensor]:
    runner.field.zero_grad()
    sigma, rgb = runner(args[0], None, *args[1:])
    (sigma.square().sum() + rgb.sum()).backward()
    density = runner.density(*args)
    return [sigma, rgb, density] + [p.grad.clone() for p in runner.field.parameters()]


@pytest.mark.parametrize("backend", ["torch", "kernel"])
def test_weights_cast_together_give_what_autocast_gives(backend):
    """Bit for bit: the copies round as autocast's casts do, the gradients come back as its do."""
    model, args = field(backend), packed_rays()
    together = MixedPrecisionField(model, "cpu", torch.bfloat16)
    one_by_one = MixedPrecisionField(model, "cpu", torch.bfloat16)
    one_by_one._linear_slots = []  # the field's own parameters: autocast casts each
    got, want = outputs_and_grads(together, args), outputs_and_grads(one_by_one, args)
    assert got[0].dtype == got[1].dtype == torch.float32
    for a, b in zip(got, want, strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)


def test_one_copy_each_way_and_no_cast_per_weight():
    model, args = field("kernel"), packed_rays()
    runner = MixedPrecisionField(model, "cpu", torch.bfloat16)
    weight_shapes = {tuple(p.shape) for p in model.parameters()} - {tuple(a.shape) for a in args[:1]}
    cast_shapes = []

    class Casts(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func.overloadpacket is torch.ops.aten._to_copy:
                cast_shapes.append(tuple(args[0].shape))
            return func(*args, **(kwargs or {}))

    with dispatched_ops() as ops, Casts():
        sigma, rgb = runner(args[0], None, *args[1:])
        (sigma.sum() + rgb.sum()).backward()
    assert ops["aten._foreach_copy_"] == 2, ops  # the copies, and the gradients back
    assert cast_shapes and not weight_shapes & set(cast_shapes), cast_shapes  # activations' casts only
    assert all(p.dtype == torch.float32 for p in model.parameters())


def test_a_layer_the_pass_does_not_use_gets_no_gradient():
    model, args = field("kernel"), packed_rays()
    model.zero_grad()
    MixedPrecisionField(model, "cpu", torch.bfloat16).density(*args).sum().backward()
    assert model.rgb.weight.grad is None and model.view_feature.weight.grad is None
    assert model.trunk[0].weight.grad is not None and model.trunk[0].weight.grad.dtype == torch.float32
