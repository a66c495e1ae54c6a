"""The benchmark harness: errors against a truth, and none for variants that draw their own
random positions (a case without a truth)."""

from __future__ import annotations

import torch

from benchmarks.harness import Case, Variant, run_case


def test_a_case_without_a_truth_times_its_variants_and_reports_no_error():
    x = torch.rand(64)
    case = Case("op", "fwd", "64", [Variant("kernel", lambda: x * 2), Variant("torch", lambda: x + x)], None, 512)
    results = run_case(case, torch.device("cpu"), repeats=2, warmup=1)
    assert [r.variant for r in results] == ["kernel", "torch"]
    assert all(r.ms is not None and r.max_abs_err is None and r.error is None for r in results)
    assert "torch" in results[0].speedups


def test_a_case_with_a_truth_reports_each_variants_error():
    x = torch.rand(64)
    case = Case("op", "fwd", "64", [Variant("kernel", lambda: x.float() * 2)], lambda: x.double() * 2, 512)
    (result,) = run_case(case, torch.device("cpu"), repeats=2, warmup=1)
    assert result.max_abs_err is not None and result.max_abs_err < 1e-6


def test_speedups_are_our_kernels_and_our_default_calls_against_the_others():
    x = torch.rand(64)
    both = [Variant("kernel", lambda: x * 2), Variant("ours, defaults", lambda: x * 2), Variant("torch", lambda: x + x)]
    kernel, defaults, peer = run_case(Case("op", "fwd", "64", both, None, 512), torch.device("cpu"), 2, 1)
    assert set(kernel.speedups) == {"ours, defaults", "torch"} and set(defaults.speedups) == {"torch"}
    assert not peer.speedups and not kernel.queued_speedups  # nothing is queued on a CPU
    (defaults, _) = run_case(Case("op", "fwd", "64", both[1:], None, 512), torch.device("cpu"), 2, 1)
    assert set(defaults.speedups) == {"torch"}
