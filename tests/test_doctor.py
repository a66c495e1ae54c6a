"""``mixer-nerf doctor``: the environment report, the kernel accuracy checks, and what it says
when the kernels are off or a kernel is wrong."""

from __future__ import annotations

import pytest
import torch

from mixer_nerf import _extension, cli, doctor


def test_doctor_reports_and_checks_every_op(capsys):
    assert cli.main(["doctor"]) == 0
    out = capsys.readouterr().out
    for line in ("python:", f"torch:      {torch.__version__}", "GPU:", "kernels:", "optional:"):
        assert line in out
    if not _extension.available():
        pytest.skip("no kernels here: the accuracy checks are skipped (tested below)")
    for op in doctor.CASES:
        assert f"  {op} " in out
    assert "all checks passed" in out


def test_it_names_the_training_precision_of_each_sampler(capsys):
    assert doctor.training_precision(cuda=False) == (
        "MLP in fp32 (occupancy, proposal, hierarchical) on cpu (--precision overrides)")
    assert doctor.training_precision(cuda=True) == (
        "MLP in bf16 (occupancy); tf32 (proposal, hierarchical) on cuda (--precision overrides)")
    assert cli.main(["doctor"]) == 0
    assert f"training:   {doctor.training_precision(torch.cuda.is_available())}" in capsys.readouterr().out


def test_without_kernels_it_names_the_fallback_and_why(monkeypatch, capsys):
    monkeypatch.setattr(_extension, "available", lambda: False)
    monkeypatch.setitem(
        _extension._state, "error", _extension.ExtensionUnavailable("kernels disabled by test")
    )
    assert cli.main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "none, PyTorch reference fallback: kernels disabled by test" in out
    assert "accuracy:   skipped, no kernels loaded" in out


def test_a_wrong_kernel_fails_the_check(monkeypatch, capsys):
    if not _extension.available():
        pytest.skip("no kernels to compare")
    good = doctor.CASES["segment_mean"]

    def off_by_a_bit(device, gen):
        op, inputs = good(device, gen)
        return (
            lambda v, o, backend: op(v, o, backend=backend) * (1.001 if backend == "kernel" else 1.0)
        ), inputs

    monkeypatch.setitem(doctor.CASES, "segment_mean", off_by_a_bit)
    assert cli.main(["doctor"]) == 1
    out = capsys.readouterr().out
    devices = 1 + torch.cuda.device_count()  # the CPU and every GPU are checked
    assert "segment_mean" in out and "MISMATCH" in out and f"{devices} check(s) FAILED" in out
