"""benchmarks.time_to_quality: a curve longer than one call, stopped and resumed from --run-dir (at
an absolute or a relative stop); a run ending at its trainer's --steps, as `mixer-nerf train`; a run's
file started from the record's; benchmarks.plot_time_to_quality merging curves run side by side and
marking a finished run's final model."""

from __future__ import annotations

import json
import re
import sys

import pytest

from test_cli import TINY_DEMO

from benchmarks import time_to_quality
from benchmarks.harness import scene_tag
from mixer_nerf.data import ensure_procedural_scene
from mixer_nerf.train import TrainConfig
from mixer_nerf.train.trainer import TrainingClock


def run(monkeypatch, *argv: str) -> None:
    monkeypatch.setattr(sys, "argv", ["time_to_quality", *argv])
    time_to_quality.main()


def test_a_stopped_curve_resumes_from_its_run_dir(tmp_path, monkeypatch, capsys):
    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    overrides = [f"--model-override={k}={json.dumps(v)}" for k, v in TINY_DEMO["model_overrides"].items()]
    argv = ["--method", "ours", "--device", "cpu", "--backend", "torch", "--data", str(scene), "--label", "tiny",
            "--sampler", "hierarchical", "--batch-rays", "16", "--checkpoints", "0.5,3", "--out", str(tmp_path),
            "--run-dir", str(tmp_path / "run"), "--save-every", "0.3", *overrides]
    # The clock is read every 16 steps: 0.8 s to 3 s leaves room for 16 slow steps on a loaded CPU.
    run(monkeypatch, *argv, "--stop-after", "0.8")
    assert "stopped at" in capsys.readouterr().out
    (first,) = json.loads(next(tmp_path.glob("*_cpu.json")).read_text())
    assert len(first["curve"]) == 1
    state = json.loads((tmp_path / "run" / "ttq_state.json").read_text())
    assert state["curve"] == first["curve"]

    run(monkeypatch, *argv)
    assert "resumed at" in capsys.readouterr().out
    (record,) = json.loads(next(tmp_path.glob("*_cpu.json")).read_text())
    points = record["curve"]
    assert len(points) == 2 and points[0] == first["curve"][0]
    assert all(0 < point["train_psnr"] < 100 for point in points)  # 3 training views by default
    assert 0.5 <= points[0]["seconds"] < points[1]["seconds"] and points[1]["seconds"] >= 3
    assert points[1]["step"] > state["step"] >= points[0]["step"]


def test_a_stop_after_plus_s_counts_from_where_the_call_resumed(tmp_path, monkeypatch, capsys):
    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    overrides = [f"--model-override={k}={json.dumps(v)}" for k, v in TINY_DEMO["model_overrides"].items()]
    argv = ["--method", "ours", "--device", "cpu", "--backend", "torch", "--data", str(scene), "--label", "tiny",
            "--sampler", "hierarchical", "--batch-rays", "16", "--checkpoints", "0.5,30", "--train-views", "0",
            "--out", str(tmp_path), "--run-dir", str(tmp_path / "run"), *overrides]
    stopped_at = []
    for stop in ("0.8", "+1.0"):
        run(monkeypatch, *argv, "--stop-after", stop)
        out = capsys.readouterr().out
        stopped_at.append(float(re.search(r"stopped at ([0-9.]+) s of training", out)[1]))
    assert stopped_at[0] >= 0.8 and stopped_at[1] >= stopped_at[0] + 1.0
    for bad in ("soon", "+0", "-5"):
        with pytest.raises(SystemExit):
            run(monkeypatch, *argv, "--stop-after", bad)
    assert "expected" in capsys.readouterr().err


def test_run_curve_ends_at_finished_with_one_point_for_every_checkpoint_left(monkeypatch):
    """``finished()`` True after step 37 (not a 16th): no step past it, one last point, all done."""
    import torch

    monkeypatch.setattr(time_to_quality, "validate", lambda render, split, views=None: 20.0)
    steps, points, saved = [], [], []

    def step_fn(step: int) -> dict:
        steps.append(step)
        return {"lr": 1.0}

    done = time_to_quality.run_curve(step_fn, None, None, [1e3, 2e3, 4e3], log=points.append,
                                     clock=TrainingClock(torch.device("cpu")), save=saved.append,
                                     train=(None, [0]), finished=lambda: len(steps) >= 37)
    assert steps == list(range(37)) and done == 3 and saved == [37]
    (point,) = points
    assert point["finished"] and point["step"] == 37 and point["seconds"] < 1e3
    assert (point["val_psnr"], point["train_psnr"], point["lr"]) == (20.0, 20.0, 1.0)


def test_run_curve_resumed_with_every_checkpoint_done_trains_no_step():
    import torch

    def step_fn(step: int) -> dict:
        raise AssertionError(f"step {step} trained")

    done = time_to_quality.run_curve(step_fn, None, None, [1e3, 2e3], log=print, start=(37, 2),
                                     clock=TrainingClock(torch.device("cpu")), finished=lambda: True)
    assert done == 2


def test_run_curve_resumed_warms_up_on_a_val_view_before_its_clock_starts(monkeypatch):
    """A resumed run trains no warm-up step (it would move the state): one val view rendered, clock
    stopped, then steps from where it stopped."""
    import torch

    clock, events = TrainingClock(torch.device("cpu")), []

    def validate(render, split, views=None):
        events.append(("render", views, clock.now()))
        return 20.0

    monkeypatch.setattr(time_to_quality, "validate", validate)

    def step_fn(step: int) -> dict:
        events.append(("step", step))
        return {}

    time_to_quality.run_curve(step_fn, None, None, [1e3, 2e3], log=print, start=(37, 1), clock=clock,
                              finished=lambda: len(events) >= 3)
    assert events[0] == ("render", [0], 0.0) and events[1:3] == [("step", 37), ("step", 38)]


def test_a_run_ends_at_its_trainers_steps_and_stays_finished_when_resumed(tmp_path, monkeypatch, capsys):
    """As `mixer-nerf train`: ours stops at --steps (here --nominal-steps) well before its checkpoints;
    the same command again resumes a finished run, which trains no further."""
    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    overrides = [f"--model-override={k}={json.dumps(v)}" for k, v in TINY_DEMO["model_overrides"].items()]
    argv = ["--method", "ours", "--device", "cpu", "--backend", "torch", "--data", str(scene), "--label", "tiny",
            "--sampler", "hierarchical", "--batch-rays", "16", "--checkpoints", "60,120", "--nominal-steps", "40",
            "--train-views", "0", "--out", str(tmp_path), "--run-dir", str(tmp_path / "run"), *overrides]
    run(monkeypatch, *argv)
    assert "stopped at" not in capsys.readouterr().out
    (record,) = json.loads(next(tmp_path.glob("*_cpu.json")).read_text())
    (point,) = record["curve"]
    state = json.loads((tmp_path / "run" / "ttq_state.json").read_text())
    assert point["finished"] and point["step"] == state["trainer_step"] == 40 and point["seconds"] < 60

    run(monkeypatch, *argv)
    assert "resumed at" in capsys.readouterr().out
    assert json.loads((tmp_path / "run" / "ttq_state.json").read_text()) == state
    assert json.loads(next(tmp_path.glob("*_cpu.json")).read_text()) == [record]


def test_a_run_starts_its_file_from_the_record_and_copies_no_other(tmp_path, monkeypatch):
    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    record, out = tmp_path / "record", tmp_path / "out"
    record.mkdir()
    name = f"{scene_tag(str(scene))}_cpu.json"
    (record / name).write_text(json.dumps([{"label": "older", "curve": []}, {"label": "tiny", "curve": []}]))
    (record / "other_cpu.json").write_text("[]")
    overrides = [f"--model-override={k}={json.dumps(v)}" for k, v in TINY_DEMO["model_overrides"].items()]
    run(monkeypatch, "--method", "ours", "--device", "cpu", "--backend", "torch", "--data", str(scene),
        "--label", "tiny", "--sampler", "hierarchical", "--batch-rays", "16", "--checkpoints", "0.2",
        "--train-views", "0", "--out", str(out), "--record-from", str(record), *overrides)
    assert sorted(p.name for p in out.iterdir()) == [name]
    runs = json.loads((out / name).read_text())
    assert [r["label"] for r in runs] == ["older", "tiny"] and len(runs[1]["curve"]) == 1
    assert json.loads((record / name).read_text())[1]["curve"] == []  # the record itself is left as it was


def test_trainer_flags_reach_our_trainers_config_and_clip_only_ours(tmp_path, monkeypatch, capsys):
    import mixer_nerf.train

    class Built(Exception):
        pass

    def trainer(cfg, **kwargs):
        raise Built(cfg)

    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    monkeypatch.setattr(mixer_nerf.train, "Trainer", trainer)
    argv = ["--device", "cpu", "--data", str(scene), "--out", str(tmp_path), "--grad-clip", "0.5",
            "--adam-eps", "1e-8", "--proposal-residual", "last", "--proposal-intervals", "between",
            "--frequency-anneal", "0.25", "--mlca-weight-decay", "2", "--proposal-loss-weight", "0.02",
            "--density-noise", "0.5"]
    with pytest.raises(Built) as built:
        run(monkeypatch, "--method", "ours", *argv)
    (cfg,) = built.value.args
    assert (cfg.grad_clip, cfg.adam_eps, cfg.proposal_residual, cfg.proposal_intervals, cfg.frequency_anneal,
            cfg.mlca_weight_decay, cfg.proposal_loss_weight, cfg.density_noise) == (
                0.5, 1e-8, "last", "between", 0.25, 2.0, 0.02, 0.5)
    # as `mixer-nerf train --time-budget` with its default --steps: whichever ends the schedule first
    assert cfg.time_budget == 240 and cfg.steps == TrainConfig().steps
    with pytest.raises(Built) as built:
        run(monkeypatch, "--method", "ours", *argv, "--nominal-steps", "7000")
    assert built.value.args[0].steps == 7000
    with pytest.raises(SystemExit):
        run(monkeypatch, "--method", "nerfacc-proposal", *argv)
    assert "--grad-clip needs --method ours" in capsys.readouterr().err


def fake_nerfacc(monkeypatch) -> dict:
    """The names of nerfacc 0.5.3 the nerfacc-proposal method calls, in plain PyTorch (even intervals,
    the volume-rendering sum), so its glue around our trainer runs where nerfacc is not installed."""
    import types

    import torch

    calls = {"updates": 0, "sampled": 0}

    class PropNetEstimator(torch.nn.Module):
        def __init__(self, optimizer):
            super().__init__()
            self.optimizer = optimizer

        def sampling(self, prop_sigma_fns, prop_samples, num_samples, n_rays, near_plane, far_plane,
                     sampling_type, stratified, requires_grad):
            t = near_plane + (far_plane - near_plane) * torch.linspace(0, 1, num_samples + 1).expand(n_rays, -1)
            for sigma_fn in prop_sigma_fns:
                assert sigma_fn(t[:, :-1], t[:, 1:]).shape == (n_rays, num_samples)
            calls["sampled"] += 1
            return t[:, :-1], t[:, 1:]

        def update_every_n_steps(self, trans, requires_grad, loss_scaler):
            calls["updates"] += requires_grad

    def rendering(t_starts, t_ends, rgb_sigma_fn, render_bkgd):
        rgb, sigma = rgb_sigma_fn(t_starts, t_ends, None)
        tau = sigma * (t_ends - t_starts)
        trans = torch.exp(-(torch.cumsum(tau, -1) - tau))
        weights = trans * -torch.expm1(-tau)
        opacity = weights.sum(-1, keepdim=True)
        color = (weights[..., None] * rgb).sum(-2) + (1 - opacity) * render_bkgd
        return color, opacity, None, {"trans": trans}

    prop_net = types.SimpleNamespace(get_proposal_requires_grad_fn=lambda: lambda step: step % 2 == 0)
    estimators = types.SimpleNamespace(prop_net=prop_net)
    module = types.SimpleNamespace(PropNetEstimator=PropNetEstimator, rendering=rendering, estimators=estimators)
    for name, value in (("nerfacc", module), ("nerfacc.estimators", estimators),
                        ("nerfacc.estimators.prop_net", prop_net)):
        monkeypatch.setitem(sys.modules, name, value)
    return calls


def tiny_nerfacc_curve(monkeypatch, tmp_path, scene, *argv: str) -> dict:
    """The record of a one-checkpoint nerfacc-proposal curve of a tiny model on ``scene`` (CPU)."""
    overrides = [f"--model-override={k}={json.dumps(v)}" for k, v in TINY_DEMO["model_overrides"].items()]
    run(monkeypatch, "--method", "nerfacc-proposal", "--device", "cpu", "--backend", "torch", "--data", str(scene),
        "--label", "tiny", "--batch-rays", "16", "--proposal-samples", "8", "--checkpoints", "0.5",
        "--out", str(tmp_path), *argv, *overrides)
    (record,) = json.loads(next(tmp_path.glob("*_cpu.json")).read_text())
    return record


def test_the_nerfacc_proposal_method_trains_our_networks_on_its_schedule(tmp_path, monkeypatch):
    """The glue around nerfacc's estimator (learning rate from our schedule, its requires-grad
    schedule, validation renders) on a CPU, with nerfacc's names faked."""
    calls = fake_nerfacc(monkeypatch)
    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    (point,) = tiny_nerfacc_curve(monkeypatch, tmp_path, scene)["curve"]
    assert point["step"] > 0 and 0 < point["val_psnr"] < 100 and point["samples_per_ray"] == 8
    assert calls["sampled"] > point["step"] and 0 < calls["updates"] < point["step"] + 1


def test_the_nerfacc_proposal_method_ends_at_the_trainers_steps(tmp_path, monkeypatch):
    """Its step function counts the trainer's steps, so it stops where our trainer would."""
    fake_nerfacc(monkeypatch)
    scene = ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2)
    record = tiny_nerfacc_curve(monkeypatch, tmp_path, scene, "--nominal-steps", "24", "--checkpoints", "60")
    (point,) = record["curve"]
    assert point["finished"] and point["step"] == 24


def test_a_val_holdout_on_a_blender_scene_scores_training_views_the_curve_left_out(tmp_path, monkeypatch):
    """As the trainer does: every K-th training view is the val split (here 3 of 6), trained without."""
    fake_nerfacc(monkeypatch)
    scene = ensure_procedural_scene(resolution=16, n_train=6, n_val=2, n_test=2)
    record = tiny_nerfacc_curve(monkeypatch, tmp_path, scene, "--val-holdout", "2")
    assert record["val_views"] == 3 and record["curve"]


def test_plot_adds_runs_from_side_by_side_files_in_place_of_their_labels(tmp_path, monkeypatch):
    """Curves run side by side on several GPUs come back one file each; ``--add`` merges them into
    the record, a run of the same label replaced, then plots the merged file."""
    from benchmarks import plot_time_to_quality

    def record_of(label, psnr, **fit):
        return {"label": label, "method": "ours", "data": "d", "device": "cpu", "val_views": 1,
                "curve": [{"seconds": 30.0, "step": 10, "val_psnr": psnr, "samples_per_ray": 8.0, **fit}]}

    record, side = tmp_path / "record", tmp_path / "gpu1"
    record.mkdir(), side.mkdir()
    (record / "fern_cpu.json").write_text(json.dumps([record_of("a", 20.0), record_of("b", 21.0)]))
    (side / "fern_cpu.json").write_text(json.dumps([record_of("b", 22.0), record_of("c", 23.0, train_psnr=26.5)]))
    monkeypatch.setattr("sys.argv", ["plot", str(record), "--add", str(side / "fern_cpu.json")])
    plot_time_to_quality.main()
    merged = json.loads((record / "fern_cpu.json").read_text())
    assert [(r["label"], r["curve"][0]["val_psnr"]) for r in merged] == [("a", 20.0), ("b", 22.0), ("c", 23.0)]
    table = (record / "fern_cpu.md").read_text()
    assert (record / "fern_cpu.png").is_file() and "| c | 23.00 | 8.0 | 10 | 26.50 |" in table
    assert "| a | 20.00 | 8.0 | 10 |  |" in table  # a run without training views: an empty cell


def test_plot_marks_the_checkpoints_after_a_run_finished_with_its_final_model(tmp_path):
    """A finished run's final PSNR fills the later time columns, marked †, with a footnote; a file
    without a finished run has neither."""
    from benchmarks import plot_time_to_quality

    def point(seconds, psnr, **more):
        return {"seconds": seconds, "step": int(seconds * 10), "val_psnr": psnr, "samples_per_ray": 8.0,
                **more}

    def record_of(label, *curve):
        return {"label": label, "method": "ours", "data": "d", "device": "cpu", "val_views": 1,
                "curve": list(curve)}

    unfinished = record_of("b", point(30.0, 21.0), point(60.0, 23.0), point(120.0, 25.0))
    (tmp_path / "fern_cpu.json").write_text(json.dumps(
        [record_of("a", point(30.0, 20.0), point(60.0, 22.0), point(95.4, 24.5, finished=True)), unfinished]))
    plot_time_to_quality.plot(tmp_path / "fern_cpu.json", targets_db=(24.0, 25.0))
    table = (tmp_path / "fern_cpu.md").read_text(encoding="utf-8")
    assert "| a | 20.00 | 22.00 | 24.50 | 24.50† | 8.0 | 954 |  | 95 s | not by 95 s |" in table
    assert "| b | 21.00 | 23.00 |  | 25.00 | 8.0 | 1200 |  | 120 s | 120 s |" in table
    footnote = "† finished (the trainer's --steps) before this checkpoint: its final model."
    assert table.endswith(f"\n\n{footnote}\n")

    (tmp_path / "fern_cpu.json").write_text(json.dumps([unfinished]))
    plot_time_to_quality.plot(tmp_path / "fern_cpu.json", targets_db=(24.0, 25.0))
    table = (tmp_path / "fern_cpu.md").read_text(encoding="utf-8")
    assert "| b | 21.00 | 23.00 | 25.00 | 8.0 | 1200 |  | 120 s | 120 s |" in table and "†" not in table


def test_plot_highlights_the_runs_its_pattern_matches_and_keeps_every_run_in_the_table(tmp_path):
    """``highlight``: matching runs in colour with a legend entry, the others grey and unlabelled;
    the table still lists all of them."""
    from benchmarks import plot_time_to_quality

    def record_of(label, psnr):
        return {"label": label, "method": "ours", "data": ".data/fern_8", "device": "cpu", "val_views": 1,
                "curve": [{"seconds": 30.0, "step": 10, "val_psnr": psnr, "samples_per_ray": 8.0},
                          {"seconds": 60.0, "step": 20, "val_psnr": psnr + 1, "samples_per_ray": 8.0}]}

    records = [record_of(f"run-{k}", 20.0 + k) for k in range(25)] + [record_of("new-seed1", 30.0)]
    fig = plot_time_to_quality.curve_figure(records, highlight="^new|run-2[34]$")
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["run-23", "run-24", "new-seed1"]
    assert ax.get_title() == "fern_8" and len(ax.lines) == 26
    colours = {line.get_label(): line.get_color() for line in ax.lines}
    assert len({colours[k] for k in ("run-23", "run-24", "new-seed1")}) == 3
    assert sum(line.get_color() == "0.8" for line in ax.lines) == 23
    plot_time_to_quality.plt.close(fig)
    (tmp_path / "fern_cpu.json").write_text(json.dumps(records))
    plot_time_to_quality.plot(tmp_path / "fern_cpu.json", targets_db=(24.0,), highlight="^new")
    assert (tmp_path / "fern_cpu.md").read_text().count("\n| run-") == 25
