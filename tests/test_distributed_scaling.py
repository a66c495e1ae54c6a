"""benchmarks.distributed_scaling on two synthetic run folders (a 1-process and a 2-process run)."""

from __future__ import annotations

import json
import sys

import pytest

from benchmarks import distributed_scaling


def _run_folder(root, name, processes, rays_per_s, psnrs):
    folder = root / name
    (folder / "eval_val").mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps({"step": 1000, "train_seconds": 20.0, "processes": processes}))
    rows = "\n".join(f"{100 * i},{2.0 * i},0.001,0.01,30,{rays_per_s},10" for i in range(1, 11))
    (folder / "train_log.csv").write_text("step,seconds,lr,loss,psnr,rays_per_s,samples_per_ray\n" + rows + "\n")
    (folder / "val_log.csv").write_text("step,seconds,psnr\n" + "".join(
        f"{500 * i},{10.0 * i},{p}\n" for i, p in enumerate(psnrs, 1)))
    (folder / "eval_val" / "metrics.json").write_text(json.dumps({"summary": {
        "split": "val", "images": 2, "mean_psnr": psnrs[-1], "mean_ssim": 0.9}}))


def test_scaling_table_plot_and_time_to_psnr(tmp_path, monkeypatch, capsys):
    pytest.importorskip("matplotlib")
    _run_folder(tmp_path, "toy_1gpu", 1, 1000.0, [20.0, 24.0])
    _run_folder(tmp_path, "toy_2gpu", 2, 900.0, [23.0, 25.0])
    out = tmp_path / "results" / "toy"
    monkeypatch.setattr(sys, "argv", ["distributed_scaling", "--runs", str(tmp_path), "--out", str(out),
                                      "--device", "test", "--targets", "toy=22,24.5,30", "toy_1gpu", "toy_2gpu"])
    distributed_scaling.main()
    record = json.loads(out.with_suffix(".json").read_text())
    one, two = record["scenes"]["toy"]
    assert one["samples_per_s"] == pytest.approx(10_000) and two["samples_per_s"] == pytest.approx(18_000)
    table = out.with_suffix(".md").read_text()
    assert "1.80x" in table and "22 dB: 20 s" in table and "22 dB: 10 s" in table and "30 dB: not reached" in table
    assert out.with_suffix(".png").stat().st_size > 0
