"""``train --config FILE`` and the train flags derived from TrainConfig's fields."""

from __future__ import annotations

import dataclasses
import json

import pytest

from mixer_nerf import cli
from mixer_nerf.cli_options import train_options
from mixer_nerf.data import ensure_procedural_scene
from mixer_nerf.train.config import TrainConfig
from mixer_nerf.train.config_file import ConfigFileError, read_config_file

TINY_FLAGS = ["--backend", "torch", "--device", "cpu", "--no-progress"]


def parse_train(*argv):
    return cli.train_config_from_args(cli.build_parser().parse_args(["train", *argv]))


def test_every_field_with_help_is_a_flag_and_reaches_the_config(capsys):
    with_help = {f.name for f in dataclasses.fields(TrainConfig) if "help" in f.metadata}
    assert {flag[2:].replace("-", "_") for flag in train_options()} == with_help
    with pytest.raises(SystemExit):
        cli.main(["train", "--help"])
    usage = capsys.readouterr().out
    for flag in train_options():
        assert flag in usage
    cfg = parse_train(
        "--data",
        "x",
        "--early-stop-eps",
        "0.001",
        "--grid-resolution",
        "32",
        "--no-bf16-density-passes",
        "--format",
        "blender",
    )
    assert (cfg.early_stop_eps, cfg.grid_resolution, cfg.bf16_density_passes, cfg.format) == (
        1e-3,
        32,
        False,
        "blender",
    )


def test_a_runs_config_json_is_read_back_and_flags_override_it(tmp_path):
    saved = TrainConfig(
        data="scenes/lego",
        steps=777,
        lr=3e-3,
        proposal_rounds=(64, 32),
        out="runs/old",
        model_overrides={"width": 32, "skips": [2]},
        device="cpu",
    )
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"train": saved.to_dict(), "model": {"width": 32}}))
    assert parse_train("--config", str(path)) == dataclasses.replace(saved, progress=True)
    cfg = parse_train("--config", str(path), "--steps", "5", "--out", "runs/new", "--data", "scenes/ship")
    assert (cfg.steps, cfg.out, cfg.data, cfg.lr) == (5, "runs/new", "scenes/ship", 3e-3)


@pytest.mark.parametrize(
    "setting, default", [("grad_clip", None), ("distortion_weight", 0.0), ("val_holdout", 0)]
)
def test_a_config_from_before_a_setting_existed_reads_with_its_default(tmp_path, setting, default):
    older = TrainConfig(data="scenes/fern", sampler="proposal", steps=30_000).to_dict()
    del older[setting]
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"train": older, "model": {}}))
    assert read_config_file(path)["steps"] == 30_000
    cfg = parse_train("--config", str(path))
    assert getattr(cfg, setting) == default and cfg.steps == 30_000
    assert getattr(TrainConfig.from_dict(older), setting) == default  # a checkpoint's train_config


def test_grad_clip_and_adam_eps_in_a_config_file_and_on_the_command_line(tmp_path):
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"train": TrainConfig(data="scenes/fern").to_dict(), "model": {}}))
    assert parse_train("--config", str(path), "--grad-clip", "1").grad_clip == 1.0
    null = tmp_path / "null.json"
    null.write_text('{"grad_clip": null, "adam_eps": 1e-8}')
    assert read_config_file(null) == {"grad_clip": None, "adam_eps": 1e-8}


def test_a_toml_table_of_some_settings_starts_from_the_defaults(tmp_path):
    path = tmp_path / "lego.toml"
    path.write_text('data = "scenes/lego"\npreset = "A"\nlr_hold = 0\nproposal_rounds = [32, 16]\n')
    cfg = parse_train("--config", str(path))
    assert (cfg.preset, cfg.lr_hold, cfg.proposal_rounds, cfg.steps) == ("A", 0.0, (32, 16), None)
    assert isinstance(cfg.lr_hold, float) and cfg.out == "runs/lego"
    no_data = tmp_path / "demo.toml"
    no_data.write_text("seed = 4\n")
    assert parse_train("--config", str(no_data)).batch_rays == cli.DEMO_SETTINGS["batch_rays"]


def test_train_reruns_from_a_toml_file(tmp_path, monkeypatch):
    monkeypatch.setenv("MIXER_NERF_CACHE", str(tmp_path / "cache"))
    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    path = tmp_path / "run.toml"
    path.write_text(
        f'data = "{scene}"\nsteps = 2\nbatch_rays = 16\nnum_coarse = 4\nnum_fine = 4\nval_every = 1\n'
        f'sampler = "hierarchical"\nout = "{tmp_path / "first"}"\n'
        "[model_overrides]\ndepth = 2\nwidth = 16\nskips = []\npos_freqs = 2\n"
    )
    assert cli.main(["train", "--config", str(path), *TINY_FLAGS]) == 0
    first = json.loads((tmp_path / "first" / "config.json").read_text())
    assert first["train"]["steps"] == 2 and first["model"]["width"] == 16
    argv = [
        "train",
        "--config",
        str(tmp_path / "first" / "config.json"),
        "--out",
        str(tmp_path / "again"),
        "--steps",
        "1",
        *TINY_FLAGS,
    ]
    assert cli.main(argv) == 0
    again = json.loads((tmp_path / "again" / "config.json").read_text())
    assert again["train"] == {**first["train"], "steps": 1, "out": str(tmp_path / "again")}


@pytest.mark.parametrize(
    "name, text, message",
    [
        ("a.json", '{"steps": 10, "colour": "red"}', "unknown training settings ['colour']"),
        ("a.json", '{"steps": "many"}', "steps must be int, got 'many'"),
        ("a.json", '{"steps": true}', "steps must be int, got True"),
        ("a.json", '{"steps": 10,', "not valid JSON"),
        ("a.json", "[1, 2]", "expected a table of settings, got list"),
        ("a.toml", "steps = ", "not valid TOML"),
        ("a.yaml", "steps: 3", "must be .json or .toml"),
        ("missing.json", None, "cannot read the config file"),
    ],
)
def test_bad_config_files_are_one_line_errors(tmp_path, capsys, name, text, message):
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    with pytest.raises(ConfigFileError, match="^" + str(path)):
        read_config_file(path)
    assert cli.main(["train", "--config", str(path), "--out", str(tmp_path / "o"), *TINY_FLAGS]) == 1
    err = capsys.readouterr().err
    assert message in err and str(path) in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
