"""The mixer-nerf command line: argument parsing, tiny end-to-end runs and bad input.

Runs are in-process (``cli.main(argv)``) with ``--backend torch`` so they do not depend on the
kernels building; the demo settings are shrunk to a 16x16 scene and a 2-layer model.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from mixer_nerf import cli
from mixer_nerf.data import ensure_procedural_scene

TINY_DEMO = {
    "procedural_resolution": 16,
    "procedural_views": 4,
    "model_overrides": {
        "depth": 2,
        "width": 16,
        "skips": (),
        "view_width": 8,
        "pos_freqs": 2,
        "dir_freqs": 1,
        "mlca_channels": 3,
        "se_reduction": 4,
    },
    "steps": 4,
    "batch_rays": 32,
    "num_coarse": 6,
    "num_fine": 6,
    "val_every": 2,
    "val_images": 1,
    "ckpt_every": 2,
    "log_every": 1,
    "grid_resolution": 8,
    "grid_warmup": 2,
    "target_samples": 256,
}
TINY_FLAGS = ["--backend", "torch", "--device", "cpu", "--no-progress"]


@pytest.fixture(autouse=True)
def tiny_demo(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("MIXER_NERF_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
    monkeypatch.setattr(cli, "DEMO_SETTINGS", TINY_DEMO)
    monkeypatch.setattr(cli, "DEMO_VIDEO_FRAMES", 3)


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """One tiny demo (train + eval + render) shared by the tests that read its outputs."""
    out = tmp_path_factory.mktemp("demo") / "run"
    mp = pytest.MonkeyPatch()
    mp.setenv("MIXER_NERF_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
    mp.setattr(cli, "DEMO_SETTINGS", TINY_DEMO)
    mp.setattr(cli, "DEMO_VIDEO_FRAMES", 3)
    try:
        assert cli.main(["demo", "--out", str(out), *TINY_FLAGS]) == 0
    finally:
        mp.undo()
    return out


# -- parsing ----------------------------------------------------------------------------------------


def parse_train(*argv):
    return cli.train_config_from_args(cli.build_parser().parse_args(["train", *argv]))


def test_no_data_uses_the_demo_settings_and_typed_flags_win():
    cfg = parse_train("--steps", "9", "--lr", "1e-3", "--precision", "tf32", "--seed", "3")
    assert cfg.data is None and cfg.batch_rays == TINY_DEMO["batch_rays"]
    assert (cfg.steps, cfg.lr, cfg.precision, cfg.seed) == (9, 1e-3, "tf32", 3)
    assert cfg.with_recipe("hierarchical").lr_final == 1e-4  # the typed lr decays by the recipe's 10x
    assert cfg.out == cli.DEMO_OUT
    assert parse_train("--lr", "1e-3", "--lr-final", "1e-3").lr_final == 1e-3  # a constant rate
    assert parse_train("--lr-warmup", "50").lr_warmup == 50
    assert parse_train("--lr-hold", "0.6").lr_hold == 0.6


def test_grad_clip_and_adam_eps_reach_the_config_of_train_and_ablate_and_default_to_the_recipe():
    cfg = parse_train("--grad-clip", "0.5", "--adam-eps", "1e-8")
    assert (cfg.grad_clip, cfg.adam_eps) == (0.5, 1e-8)
    assert (parse_train().grad_clip, parse_train().adam_eps) == (None, None)  # None: the sampler's recipe
    args = cli.build_parser().parse_args(["ablate", "--out", "x", "--grad-clip", "2", "--adam-eps", "1e-10"])
    assert (args.grad_clip, args.adam_eps) == (2.0, 1e-10)
    with pytest.raises(ValueError, match="grad_clip must be a positive, finite norm"):
        parse_train("--grad-clip", "0")


def test_spike_rollbacks_reach_the_config_of_train_and_ablate():
    assert parse_train().spike_rollbacks == 3
    assert parse_train("--spike-rollbacks", "0").spike_rollbacks == 0
    assert cli.build_parser().parse_args(["ablate", "--out", "x", "--spike-rollbacks", "1"]).spike_rollbacks == 1
    with pytest.raises(ValueError, match="spike_rollbacks must be an integer >= 0"):
        parse_train("--spike-rollbacks", "-1")


def test_data_uses_the_full_defaults():
    cfg = parse_train("--data", "scenes/lego", "--preset", "A", "--time-budget", "30", "--ckpt-every", "7")
    assert cfg.data == "scenes/lego" and cfg.steps is None and cfg.batch_rays == 4096
    assert (cfg.preset, cfg.time_budget, cfg.ckpt_every, cfg.out) == ("A", 30.0, 7, "runs/lego")
    assert cfg.val_holdout == 0
    assert parse_train("--data", "scenes/fern", "--val-holdout", "8").val_holdout == 8


@pytest.mark.parametrize(
    ("sampler", "expected"),
    [
        ("occupancy", "occupancy-grid sampling, ~262144 samples per step"),
        ("proposal", "4096 rays x 48 samples (proposal rounds 128 + 64)"),
        ("hierarchical", "4096 rays x (64 + 128) samples"),
    ],
)
def test_the_start_line_says_what_each_sampler_shades(sampler, expected):
    cfg = parse_train("--data", "scenes/lego", "--sampler", sampler, "--target-samples", "262144")
    assert cli.sampling_summary(cfg) == expected


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--steps", "many"],
        ["train", "--preset", "Z"],
        ["eval"],
        ["render", "--ckpt", "x", "--path", "zigzag"],
        ["bogus"],
    ],
)
def test_usage_errors_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 2


def test_distortion_weight_flag_reaches_the_config_and_is_refused_off_the_proposal_sampler(capsys, tmp_path):
    assert parse_train("--data", "scenes/fern", "--distortion-weight", "0.002").distortion_weight == 0.002
    assert parse_train("--data", "scenes/fern").distortion_weight == 0.0
    with pytest.raises(SystemExit):
        cli.main(["train", "--help"])
    usage = " ".join(capsys.readouterr().out.split())
    assert "--distortion-weight W proposal sampler:" in usage and "(default 0: off;" in usage
    # no --data: the demo's hierarchical sampler
    assert cli.main(["train", "--distortion-weight", "0.01", "--out", str(tmp_path), *TINY_FLAGS]) == 1
    err = capsys.readouterr().err
    assert "distortion_weight applies to the proposal sampler only" in err and "Traceback" not in err


def test_invalid_setting_is_one_line(capsys, tmp_path):
    assert cli.main(["train", "--steps", "0", "--out", str(tmp_path), *TINY_FLAGS]) == 1
    err = capsys.readouterr().err
    assert "steps must be positive" in err and "Traceback" not in err


# -- end to end -------------------------------------------------------------------------------------


def test_demo_writes_everything_it_reports(demo_run, capsys):
    for name in ("checkpoint.pt", "train_log.csv", "val_log.csv", "curves.png", "summary.json"):
        assert (demo_run / name).is_file(), name
    metrics = json.loads((demo_run / "eval_test" / "metrics.json").read_text())
    assert metrics["summary"]["images"] == 4 and metrics["summary"]["mean_psnr"] > 0
    assert len(list((demo_run / "eval_test" / "images").glob("*.png"))) == 4
    videos = list((demo_run / "video").glob("video.*"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0
    assert len(list((demo_run / "video" / "depth").glob("frame_*.png"))) == 3


def test_eval_and_render_commands(demo_run, tmp_path, capsys):
    ckpt = str(demo_run / "checkpoint.pt")
    assert (
        cli.main(
            ["eval", "--ckpt", ckpt, "--split", "val", "--out", str(tmp_path / "ev"), "--backend", "torch"]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "eval (val, 4 views)" in out and str(tmp_path / "ev") in out
    rows = (tmp_path / "ev" / "metrics.csv").read_text().splitlines()
    assert rows[0] == "index,name,psnr,ssim,lpips" and len(rows) == 5
    argv = ["eval", "--ckpt", ckpt, "--split", "val", "--out", str(tmp_path / "ev2"), "--backend", "torch"]
    assert cli.main([*argv, "--max-images", "2"]) == 0
    assert "eval (val, 2 views)" in capsys.readouterr().out
    assert len((tmp_path / "ev2" / "metrics.csv").read_text().splitlines()) == 3

    assert (
        cli.main(
            [
                "render",
                "--ckpt",
                ckpt,
                "--frames",
                "2",
                "--scale",
                "0.5",
                "--path",
                "turntable",
                "--out",
                str(tmp_path / "vid"),
                "--backend",
                "torch",
            ]
        )
        == 0
    )
    import imageio.v3 as iio

    video = next((tmp_path / "vid").glob("video.*"))
    frames = list(iio.imiter(video))
    assert len(frames) == 2 and frames[0].shape[:2] == (8, 8)


def test_train_with_data_then_resume(tmp_path, capsys):
    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    out = tmp_path / "run"
    argv = [
        "train",
        "--data",
        str(scene),
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
        "--ckpt-every",
        "1",
        "--sampler",
        "hierarchical",
        "--eval-views",
        "all",  # a CPU's default is one view
        "--out",
        str(out),
        *TINY_FLAGS,
    ]
    assert cli.main(argv) == 0
    assert json.loads((out / "eval_test" / "metrics.json").read_text())["summary"]["images"] == 2
    # A second run into the same folder refuses; --resume continues (here: already finished).
    before = (out / "checkpoint.pt").read_bytes()
    assert cli.main(argv) == 1
    assert "--resume" in capsys.readouterr().err
    assert (out / "checkpoint.pt").read_bytes() == before
    assert cli.main([*argv, "--resume"]) == 0


def test_train_frees_its_trainer_before_the_evaluation(tmp_path, monkeypatch):
    """The trainer (reference cycles, CUDA graph pools on a GPU) is collected before the run's
    evaluation, not whenever Python's cycle collector next runs."""
    import gc
    import weakref

    from mixer_nerf.train import Trainer

    trainers, alive = [], []
    init = Trainer.__init__

    def recorded(self, *args, **kwargs):
        init(self, *args, **kwargs)
        trainers.append(weakref.ref(self))

    monkeypatch.setattr(Trainer, "__init__", recorded)
    monkeypatch.setattr(cli, "_evaluate", lambda *_, **__: alive.append(trainers[0]() is not None))
    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    gc.disable()
    try:
        cli.main(["train", "--data", str(scene), "--steps", "1", "--batch-rays", "16", "--sampler", "proposal",
                  "--out", str(tmp_path / "run"), *TINY_FLAGS])
    finally:
        gc.enable()
    assert len(trainers) == 1 and alive == [False]


# -- bad input --------------------------------------------------------------------------------------


def test_missing_data_path(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    assert cli.main(["train", "--data", str(missing), "--out", str(tmp_path / "o"), *TINY_FLAGS]) == 1
    err = capsys.readouterr().err
    assert str(missing) in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "checkpoint.pt").exists()


def test_empty_dataset(tmp_path, capsys):
    scene = tmp_path / "empty"
    scene.mkdir()
    (scene / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    assert cli.main(["train", "--data", str(scene), "--out", str(tmp_path / "o"), *TINY_FLAGS]) == 1
    err = capsys.readouterr().err
    assert "transforms_train.json" in err and "empty" in err


def test_unwritable_output(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert cli.main(["demo", "--out", str(blocker / "run"), *TINY_FLAGS]) == 1
    err = capsys.readouterr().err
    assert str(blocker / "run") in err and "not writable" in err


@pytest.mark.parametrize("command", ["eval", "render"])
def test_truncated_checkpoint(command, demo_run, tmp_path, capsys):
    bad = tmp_path / "checkpoint.pt"
    bad.write_bytes((demo_run / "checkpoint.pt").read_bytes()[:300])
    assert cli.main([command, "--ckpt", str(bad), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "truncated or corrupt" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_python_dash_m_entry_point():
    result = subprocess.run(
        [sys.executable, "-m", "mixer_nerf", "--help"],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": os.getcwd()},
    )
    assert result.returncode == 0 and "train" in result.stdout and "render" in result.stdout
