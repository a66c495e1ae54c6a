"""The benchmark harness: errors against a truth, and none for variants that draw their own
random positions (a case without a truth); the GPU-only times and how the table gives them."""

from __future__ import annotations

import json
import time

import pytest
import torch

from benchmarks import host_overhead
from benchmarks.bench_ops import table
from benchmarks.harness import Case, Result, Variant, kernel_ms, run_case


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


def test_a_cpu_run_measures_no_gpu_only_times():
    x = torch.rand(64)
    case = Case("op", "fwd", "64", [Variant("kernel", lambda: x * 2)], None, 512)
    (result,) = run_case(case, torch.device("cpu"), repeats=2, warmup=1)
    assert result.queued_ms is None and result.kernel_ms is None


def test_the_table_gives_each_speedup_one_at_a_time_queued_and_in_kernel_time():
    ours = Result("op", "fwd", "64", "kernel", 1.0, 1.0, None, None, queued_ms=0.5, kernel_ms=0.25,
                  speedups={"torch": 3.0}, queued_speedups={"torch": 4.0}, kernel_speedups={"torch": 6.0})
    peer = Result("op", "fwd", "64", "torch", 3.0, 1.0, None, None, queued_ms=2.0, kernel_ms=1.5)
    rows = table([ours, peer], copy_gbps=100.0).splitlines()
    assert "ms kernels" in rows[0]
    assert "| 0.250 |" in rows[2] and rows[2].endswith("| 3.0x / 4.0x / 6.0x vs torch |")
    cpu = Result("op", "fwd", "64", "kernel", 1.0, 1.0, None, None, speedups={"torch": 3.0})
    assert table([cpu], None).splitlines()[2].endswith("| 3.0x vs torch |")


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_kernel_time_counts_the_gpus_work_not_the_hosts():
    x = torch.rand(1 << 20, device="cuda")
    assert kernel_ms(lambda: time.sleep(0.002), x.device) == 0  # host work alone: no GPU time
    assert kernel_ms(lambda: x * 2, x.device) > 0


def test_host_overhead_times_every_differentiable_op(tmp_path, monkeypatch):
    monkeypatch.setattr("sys.argv", ["host_overhead", "--calls", "2", "--out", str(tmp_path)])
    host_overhead.main()
    rows = json.loads((tmp_path / "host_overhead_cpu.json").read_text())["rows"]
    assert [r["op"] for r in rows] == list(host_overhead.cases(torch.device("cpu")))
    assert all(r["forward_us"] > 0 and r["forward_backward_us"] > 0 for r in rows)
    assert "| composite |" in (tmp_path / "host_overhead_cpu.md").read_text()


def test_variants_are_timed_in_rounds_not_one_after_another():
    calls = []
    variants = [Variant(name, lambda name=name: calls.append(name)) for name in ("kernel", "torch")]
    run_case(Case("op", "fwd", "1", variants, None, 8), torch.device("cpu"), repeats=3, warmup=0)
    assert calls == ["kernel", "torch"] + ["kernel", "torch"] * 3


def test_a_variant_that_fails_while_timed_is_reported_and_the_others_still_timed():
    count = {"n": 0}

    def flaky():
        count["n"] += 1
        if count["n"] > 2:
            raise RuntimeError("out of memory\nmore")

    variants = [Variant("kernel", lambda: None), Variant("peer", flaky)]
    kernel, peer = run_case(Case("op", "fwd", "1", variants, None, 8), torch.device("cpu"), repeats=4, warmup=0)
    assert kernel.ms is not None and kernel.error is None and "peer" not in kernel.speedups
    assert peer.ms is None and peer.error == "RuntimeError: out of memory"
