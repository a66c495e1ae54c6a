"""``train --tensorboard``: what a run logs, and the refusals before any training."""

from __future__ import annotations

import sys

import pytest

from mixer_nerf import cli
from mixer_nerf.data import ensure_procedural_scene

pytest.importorskip("tensorboard")

FLAGS = [
    "--backend",
    "torch",
    "--device",
    "cpu",
    "--no-progress",
    "--sampler",
    "hierarchical",
    "--steps",
    "2",
    "--batch-rays",
    "16",
    "--num-coarse",
    "4",
    "--num-fine",
    "4",
    "--val-every",
    "1",
    "--log-every",
    "1",
]


@pytest.fixture
def scene(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("MIXER_NERF_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
    return str(ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2))


def test_tensorboard_holds_the_scalars_and_validation_renders(scene, tmp_path, monkeypatch):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    monkeypatch.setattr(cli, "_evaluate", lambda *a, **k: {"summary": {}, "out": "", "notes": []})
    monkeypatch.setattr(cli, "_report", lambda *a: None)
    out = tmp_path / "run"
    assert cli.main(["train", "--data", scene, "--out", str(out), "--tensorboard", *FLAGS]) == 0
    events = EventAccumulator(str(out / "tensorboard")).Reload()
    scalars = set(events.Tags()["scalars"])
    assert {
        "train/loss",
        "train/psnr",
        "train/lr",
        "train/samples_per_ray",
        "train/rays_per_s",
        "validation/psnr",
    } <= scalars
    assert [e.step for e in events.Scalars("validation/psnr")] == [1, 2]
    assert "validation/view_0" in events.Tags()["images"]
    assert (out / "curves.png").stat().st_size > 0


def test_an_unwritable_log_folder_is_refused_before_training(scene, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "tensorboard").write_text("a file where the log folder goes")
    assert cli.main(["train", "--data", scene, "--out", str(out), "--tensorboard", *FLAGS]) == 1
    err = capsys.readouterr().err
    assert str(out / "tensorboard") in err and "not writable" in err and len(err.strip().splitlines()) == 1
    assert not (out / "checkpoint.pt").exists()


def test_a_missing_tensorboard_package_is_named(scene, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)
    assert cli.main(["train", "--data", scene, "--out", str(tmp_path / "run"), "--tensorboard", *FLAGS]) == 1
    assert "pip install 'mixer_nerf[tensorboard]'" in capsys.readouterr().err
