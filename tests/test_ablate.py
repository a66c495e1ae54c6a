"""`mixer-nerf ablate`: presets x seeds on the built-in scene with a 2-layer model and a few steps,
in-process with ``--backend torch`` (no kernels needed)."""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

import pytest
from test_cli import TINY_DEMO

from mixer_nerf import cli, lpips_alex, metrics
from mixer_nerf.ablation import AblationError, AblationPlan, parse_model_overrides, parse_presets, parse_seeds, runner
from mixer_nerf.train import TrainConfig, Trainer
from mixer_nerf.train import trainer as trainer_module

# test_cli's tiny demo, at 32x32 (LPIPS needs 31x31 images or more) and without a steps default.
TINY_SCENE = {**{k: v for k, v in TINY_DEMO.items() if k != "steps"}, "procedural_resolution": 32,
              "sampler": "hierarchical"}
FLAGS = ["--backend", "torch", "--device", "cpu", "--no-progress", "--max-images", "1"]
# CI installs LPIPS's weights (.ci/run) and these tests then score LPIPS; a machine without them runs
# them with --no-lpips, as ablate refuses to start there otherwise.
LPIPS_FLAGS = [] if metrics.lpips_available() else ["--no-lpips"]


def shrink(mp: pytest.MonkeyPatch, basetemp) -> None:
    mp.setenv("MIXER_NERF_CACHE", str(basetemp / "cache"))
    mp.setattr(cli, "DEMO_SETTINGS", TINY_SCENE)
    mp.setattr(trainer_module, "plot_curves", lambda *_: None)  # each run's own plot: tested in test_train


@pytest.fixture(autouse=True)
def tiny_scene(tmp_path_factory, monkeypatch):
    shrink(monkeypatch, tmp_path_factory.getbasetemp())


def ablate(out, *extra: str) -> int:
    return cli.main(["ablate", "--out", str(out), "--steps", "4", *FLAGS, *LPIPS_FLAGS, *extra])


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """One ablation of presets A and D over seeds 0 and 1, shared by the tests that read it."""
    out = tmp_path_factory.mktemp("ablate") / "AD"
    mp = pytest.MonkeyPatch()
    shrink(mp, tmp_path_factory.getbasetemp())
    try:
        assert ablate(out, "--presets", "AD", "--seeds", "0,1") == 0
    finally:
        mp.undo()
    return out


def test_table_lists_every_preset_and_seed_with_finite_scores(finished):
    table = json.loads((finished / "table.json").read_text())
    assert [(r["preset"], r["seed"]) for r in table["runs"]] == [("A", 0), ("A", 1), ("D", 0), ("D", 1)]
    for run in table["runs"]:
        assert run["status"] == "finished" and run["steps"] == 4
        assert math.isfinite(run["psnr"]) and math.isfinite(run["ssim"])
        assert run["params"] > 0 and run["steps_per_s"] > 0
        assert run["lpips"] is None and table["notes"] or math.isfinite(run["lpips"])
    a, d = table["presets"]
    assert (a["preset"], d["preset"], a["seeds"]) == ("A", "D", 2)
    assert a["psnr_change_vs_A"] == 0 and d["psnr_change_vs_A"] == pytest.approx(d["psnr_mean"] - a["psnr_mean"])
    assert a["psnr_spread"] >= 0 and d["params"] > a["params"]  # MLCA and SE add weights
    assert table["target_psnr"] <= min(max(p for _, _, p in c) for c in table["curves"].values())
    assert all(r["seconds_to_target"] is not None for r in table["runs"])


def test_table_files_agree(finished):
    md = (finished / "ablation.md").read_text()
    assert "| A | NeRF |" in md and "| D | Mixer-NeRF |" in md and "model overrides: " in md
    with (finished / "table.csv").open() as f:
        assert [r["preset"] for r in csv.DictReader(f)] == ["A", "D"]
    with (finished / "runs.csv").open() as f:
        assert len(list(csv.DictReader(f))) == 4
    assert (finished / "curves.png").stat().st_size > 0
    assert (finished / "A_seed1" / "eval" / "metrics.json").is_file()


def test_a_time_budget_alone_is_tabulated_with_the_trainers_default_steps(finished):
    from mixer_nerf.ablation.table import markdown

    table = json.loads((finished / "table.json").read_text())
    md = markdown({**table, "budget": {"steps": None, "time_budget_s": 240.0}})
    assert "the trainer's default steps (20000 with the proposal sampler on forward-facing scenes, else 50000) " \
           "or 240 s of training" in md


def test_table_gives_each_held_out_views_psnr_where_there_are_few(finished):
    from mixer_nerf.ablation.table import MAX_VIEW_COLUMNS, markdown

    table = json.loads((finished / "table.json").read_text())
    for run in table["runs"]:  # --max-images 1: the one view's PSNR is the run's
        assert list(run["view_psnr"].values()) == [pytest.approx(run["psnr"])]
    md = (finished / "ablation.md").read_text()
    name = next(iter(table["runs"][0]["view_psnr"]))
    assert f"PSNR per held-out view:\n\n| Preset | Seed | {name} |" in md
    assert f"| D | 1 | {table['runs'][3]['psnr']:.2f} |" in md
    many = {f"v{i}.png": 20.0 for i in range(MAX_VIEW_COLUMNS + 1)}
    assert "per held-out view" not in markdown({**table, "runs": [{**r, "view_psnr": many} for r in table["runs"]]})
    other = [{**r, "view_psnr": {"other.png": 20.0}} if r["seed"] else r for r in table["runs"]]
    assert "per held-out view" not in markdown({**table, "runs": other})  # the runs scored different views


def test_table_names_the_steps_where_a_runs_colour_loss_spiked(finished, tmp_path):
    table = json.loads((finished / "table.json").read_text())
    assert all(run["loss_spikes"] == [] for run in table["runs"])  # 4 logged losses: too few to judge
    copy = tmp_path / "AD"
    shutil.copytree(finished, copy)
    mse = [0.002] * 12 + [0.009, 0.008, 0.002] + [0.002] * 5 + [0.01]
    loss = [v + (0.05 if i == 5 else 0.0) for i, v in enumerate(mse)]  # a regulariser at step 600: no spike
    rows = "".join(f"{100 * (i + 1)},{l},{-10 * math.log10(v)}\n" for i, (l, v) in enumerate(zip(loss, mse)))
    (copy / "A_seed0" / "train_log.csv").write_text("step,loss,psnr\n" + rows)
    assert cli.main(["ablate", "--report", "--out", str(copy)]) == 0
    spikes = [run["loss_spikes"] for run in json.loads((copy / "table.json").read_text())["runs"]]
    assert spikes == [[1300, 2100], [], [], []]
    assert "| 1,300, 2,100 |" in (copy / "ablation.md").read_text()
    with (copy / "runs.csv").open() as f:
        assert next(csv.DictReader(f))["loss_spikes"] == "1300 2100"


def test_second_invocation_skips_finished_runs(finished, capsys):
    before = (finished / "D_seed0" / "checkpoint.pt").stat().st_mtime_ns
    assert ablate(finished, "--presets", "AD", "--seeds", "0,1", "--resume") == 0
    assert capsys.readouterr().out.count("done earlier, skipped") == 4
    assert (finished / "D_seed0" / "checkpoint.pt").stat().st_mtime_ns == before


def test_interrupted_run_resumes(tmp_path, capsys, monkeypatch):
    out = tmp_path / "ablation"
    save = Trainer.save

    def save_then_interrupt(trainer):
        save(trainer)
        raise KeyboardInterrupt  # as a kill right after the step-2 checkpoint

    monkeypatch.setattr(Trainer, "save", save_then_interrupt)
    assert ablate(out, "--presets", "B", "--seeds", "3") == 130
    monkeypatch.setattr(Trainer, "save", save)
    capsys.readouterr()
    assert ablate(out, "--presets", "B", "--seeds", "3", "--resume") == 0
    assert "resuming at step 2" in capsys.readouterr().out
    record = json.loads((out / "B_seed3" / "ablation_run.json").read_text())
    assert record["steps"] == 4 and record["status"] == "finished"


def test_gpus_trains_each_share_in_its_own_process_then_one_table(blender_scene, tmp_path, monkeypatch):
    """--gpus: one worker process per GPU (here on the CPU: the device is what --device says),
    each its share of the runs into one folder, then the caller writes the table of all."""
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    out = tmp_path / "shared"
    tiny = ["--data", str(blender_scene), "--sampler", "hierarchical", "--batch-rays", "32", "--num-coarse", "6",
            "--num-fine", "6", "--val-every", "2", "--ckpt-every", "2",
            *(f"--model-override={k}={json.dumps(v)}" for k, v in TINY_DEMO["model_overrides"].items())]
    assert cli.main(["ablate", "--out", str(out), "--steps", "3", "--seeds", "0,1", "--presets", "AD",
                     "--gpus", "0,1", *FLAGS, *LPIPS_FLAGS, *tiny]) == 0
    table = json.loads((out / "table.json").read_text())
    assert [(r["preset"], r["seed"], r["steps"]) for r in table["runs"]] == [
        ("A", 0, 3), ("A", 1, 3), ("D", 0, 3), ("D", 1, 3)]
    logs = [(out / f"worker_gpu{gpu}.log").read_text() for gpu in (0, 1)]
    assert "preset A, seed 0" in logs[0] and "preset D, seed 0" in logs[0] and "seed 1" not in logs[0]
    assert "preset A, seed 1" in logs[1] and "preset D, seed 1" in logs[1] and "seed 0" not in logs[1]
    assert not list(out.glob(".*.tmp*"))


def test_resumed_gpu_workers_share_only_the_runs_not_done(tmp_path, monkeypatch):
    """A resumed --gpus ablation spreads the runs left over every GPU, not its full plan (where
    the GPUs whose runs were done would idle while another trains two)."""
    from mixer_nerf.ablation import workers
    from mixer_nerf.ablation.runner import RUN_RECORD

    plan = AblationPlan(base=TrainConfig(steps=1), presets=("A", "B", "C", "D"), seeds=(0, 1), out=tmp_path)
    for run in plan.runs():
        if run[1] == 0:  # seed 0 done everywhere
            plan.run_folder(*run).mkdir(parents=True)
            (plan.run_folder(*run) / RUN_RECORD).write_text("{}")
    shares = {}

    class Worker:
        def __init__(self, command, env, **_):
            shares[env["CUDA_VISIBLE_DEVICES"]] = command[command.index("--runs") + 1]

        def wait(self):
            return 0

        poll = wait

    monkeypatch.setattr(workers.subprocess, "Popen", Worker)
    workers.train_on_gpus(plan, ["ablate"], (0, 1, 2, 3), log=lambda _: None)
    assert shares == {"0": "A:1", "1": "B:1", "2": "C:1", "3": "D:1"}


def test_a_failed_gpu_worker_is_one_line_naming_its_log(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "executable", "false")  # every worker exits 1 at once
    assert ablate(tmp_path / "failed", "--presets", "A", "--seeds", "0", "--gpus", "3") == 1
    assert f"the worker on GPU 3 failed (exit 1); see {tmp_path / 'failed' / 'worker_gpu3.log'}" in capsys.readouterr().err


@pytest.mark.parametrize("mode", [[], ["--gpus", "0"], ["--runs", "A:0"]], ids=["plain", "gpus", "worker"])
def test_missing_lpips_weights_refuse_the_ablation_before_anything(tmp_path, capsys, monkeypatch, mode):
    """Without the AlexNet weights every mode stops at once, naming the install and --no-lpips:
    runs scored without LPIPS cannot be scored again once their checkpoints are gone."""
    from mixer_nerf.ablation import workers

    monkeypatch.setattr(lpips_alex, "weights_path", lambda: None)
    monkeypatch.setattr(workers.subprocess, "Popen", lambda *_, **__: pytest.fail("a worker was started"))
    out = tmp_path / "no_weights"
    assert cli.main(["ablate", "--out", str(out), "--steps", "4", *FLAGS, "--presets", "A", "--seeds", "0",
                     *mode]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("mixer-nerf: error: LPIPS unavailable: ")
    assert lpips_alex.INSTALL_COMMAND in err and "pass --no-lpips" in err
    assert not out.exists()


def test_each_run_frees_its_trainer_before_the_next(tmp_path, monkeypatch):
    """A finished run's trainer (reference cycles, CUDA graph pools on a GPU) is collected before
    its evaluation and the next run, not whenever Python's cycle collector next runs."""
    import gc
    import weakref

    trainers = []
    init = trainer_module.Trainer.__init__

    def recorded(self, *args, **kwargs):
        init(self, *args, **kwargs)
        trainers.append(weakref.ref(self))

    monkeypatch.setattr(trainer_module.Trainer, "__init__", recorded)
    monkeypatch.setattr(runner, "_scores", lambda *_, **__: {**runner._no_scores(),
                                                           "alive": [t() is not None for t in trainers]})
    gc.disable()
    try:
        assert ablate(tmp_path / "freed", "--presets", "A", "--seeds", "0,1", "--no-lpips") == 0
    finally:
        gc.enable()
    records = [json.loads((tmp_path / "freed" / f"A_seed{s}" / "ablation_run.json").read_text()) for s in (0, 1)]
    assert [r["alive"] for r in records] == [[False], [False, False]]


def test_no_lpips_trains_and_scores_without_it(tmp_path, capsys, monkeypatch):
    """--no-lpips: a worker without the weights trains and scores PSNR/SSIM; the table notes why
    LPIPS is missing; the setting is the ablation's own, so a resume cannot add LPIPS runs to it."""
    out = tmp_path / "no_lpips"
    monkeypatch.setattr(lpips_alex, "weights_path", lambda: None)
    run = ["ablate", "--out", str(out), "--steps", "4", *FLAGS, "--presets", "A", "--no-lpips"]
    assert cli.main([*run, "--seeds", "0", "--runs", "A:0"]) == 0  # as a --gpus worker
    record = json.loads((out / "A_seed0" / "ablation_run.json").read_text())
    assert record["lpips"] is None and math.isfinite(record["psnr"]) and record["status"] == "finished"
    assert record["notes"] == [lpips_alex.unavailable_reason()]
    assert json.loads((out / "ablation.json").read_text())["settings"]["lpips"] is False

    # With the weights installed, --no-lpips still scores without LPIPS.
    monkeypatch.setattr(metrics, "lpips_unavailable_reason", lambda net="alex": None)
    assert cli.main([*run, "--seeds", "0,1", "--resume"]) == 0
    table = json.loads((out / "table.json").read_text())
    assert [r["lpips"] for r in table["runs"]] == [None, None]
    assert table["notes"] == ["LPIPS skipped: not asked for", lpips_alex.unavailable_reason()]
    assert "Note: LPIPS unavailable" in (out / "ablation.md").read_text()
    capsys.readouterr()
    assert cli.main([*run[:-1], "--seeds", "0,1", "--resume"]) == 1
    assert "other settings (lpips)" in capsys.readouterr().err


def test_gpu_workers_get_no_lpips(tmp_path, monkeypatch):
    from mixer_nerf.ablation import workers

    commands = []

    class Worker:
        def __init__(self, command, **_):
            commands.append(command)

        def wait(self):
            return 1

        poll = wait

    monkeypatch.setattr(workers.subprocess, "Popen", Worker)
    assert cli.main(["ablate", "--out", str(tmp_path / "gpus"), "--steps", "4", *FLAGS, "--presets", "A",
                     "--seeds", "0", "--gpus", "0", "--no-lpips"]) == 1
    assert len(commands) == 1 and "--no-lpips" in commands[0] and "--gpus" not in commands[0]


def test_model_overrides_are_recorded(tmp_path):
    out = tmp_path / "per_point"
    assert ablate(out, "--presets", "D", "--seeds", "0", "--model-override", "se_per_point=true",
                  "--model-override", "mlca_concat_direction=true") == 0
    table = json.loads((out / "table.json").read_text())
    assert table["model_overrides"]["se_per_point"] is True
    assert table["model_overrides"]["mlca_concat_direction"] is True
    assert "se_per_point=true" in (out / "ablation.md").read_text()
    assert json.loads((out / "D_seed0" / "config.json").read_text())["model"]["se_per_point"] is True


def test_a_model_without_the_direction_mlca_is_noted_in_the_table(finished, tmp_path):
    assert "MLCA mixes PE(x) only" not in (finished / "ablation.md").read_text()
    out = tmp_path / "nodir"
    assert ablate(out, "--presets", "D", "--seeds", "0", "--model-override", "mlca_directions=false") == 0
    assert "Note: MLCA mixes PE(x) only" in (out / "ablation.md").read_text()


def test_the_regularisers_a_run_trained_with_are_noted_in_the_table(finished, tmp_path):
    assert "decayed toward the identity" not in (finished / "ablation.md").read_text()
    out = tmp_path / "decay"
    assert ablate(out, "--presets", "D", "--seeds", "0", "--mlca-weight-decay", "2") == 0
    assert "Note: MLCA's mixing decayed toward the identity, W = 2 " in (out / "ablation.md").read_text()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--presets", "AX"], "unknown preset(s) X"),
        (["--seeds", ""], "no seeds given"),
        (["--seeds", "0,one"], "seeds must be integers"),
        (["--model-override", "colour=1"], "unknown model setting 'colour'"),
        (["--model-override", "width"], "is not NAME=VALUE"),
        (["--model-override", "se_per_point=False"], "se_per_point takes a value like false"),
        (["--model-override", "width=wide"], "width takes a value like 256"),
    ],
)
def test_bad_arguments_give_one_line_errors(tmp_path, capsys, args, message):
    assert ablate(tmp_path / "bad", *args) == 1
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "bad").exists()


def test_budget_is_required(tmp_path, capsys):
    assert cli.main(["ablate", "--out", str(tmp_path / "x"), *FLAGS]) == 1
    assert "--steps N" in capsys.readouterr().err


def test_existing_ablation_needs_resume_and_the_same_settings(finished, capsys, tmp_path):
    assert ablate(finished, "--presets", "A") == 1
    assert "pass --resume" in capsys.readouterr().err
    assert ablate(finished, "--presets", "A", "--resume", "--lr", "1e-2") == 1
    assert "other settings (lr)" in capsys.readouterr().err
    # how often runs save and log changes no result: a report (or resume) may give other values
    copy = shutil.copytree(finished, tmp_path / "copy")  # a report rewrites the shared table
    assert ablate(copy, "--presets", "A", "--report", "--ckpt-every", "7", "--log-every", "3") == 0


def test_sigterm_stops_the_gpu_workers(tmp_path, monkeypatch):
    """A GPU call's `timeout` sends SIGTERM to the ablation: its workers must not outlive it."""
    from mixer_nerf.ablation.workers import train_on_gpus

    worker = tmp_path / "worker.sh"
    worker.write_text(f"#!/bin/sh\necho $$ >> {tmp_path / 'pids'}\nexec sleep 60\n")
    worker.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(worker))
    plan = AblationPlan(base=TrainConfig(steps=1), presets=("A", "D"), seeds=(0,), out=tmp_path)
    pid_file = tmp_path / "pids"

    def stop_once_both_run():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(pid_file.read_text().split() if pid_file.exists() else []) < 2:
            time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=stop_once_both_run, daemon=True).start()
    with pytest.raises(SystemExit):
        train_on_gpus(plan, ["ablate"], (0, 1), log=lambda _: None)
    pids = [int(p) for p in pid_file.read_text().split()]
    assert len(pids) == 2
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_worker_arguments():
    from mixer_nerf.ablation.workers import format_runs, parse_gpus, parse_runs

    plan = AblationPlan(base=TrainConfig(steps=1), presets=("A", "D"), seeds=(0, 1), out=Path("x"))
    assert parse_gpus("0,1") == (0, 1) and parse_gpus("2 2 3") == (2, 3)
    for bad in ("", "a", "-1"):
        with pytest.raises(AblationError, match="--gpus takes device indices"):
            parse_gpus(bad)
    runs = [("D", 1), ("A", 0)]
    assert parse_runs(format_runs(runs), plan) == runs
    for bad in ("B:0", "A:2", "A", "A:x"):
        with pytest.raises(AblationError, match="is not a run of this ablation"):
            parse_runs(bad, plan)
    assert cli._without_option(["ablate", "--gpus", "0,1", "--out", "o", "--gpus=2"], "--gpus") == ["ablate", "--out", "o"]


def test_parsers():
    assert parse_presets("a, d,A") == ("A", "D")
    assert parse_seeds("2 0,2") == (2, 0)
    assert parse_model_overrides(["skips=[4]", "density_activation=relu", "width=64", "pe_scale=3"]) == {
        "skips": [4], "density_activation": "relu", "width": 64, "pe_scale": 3}
    with pytest.raises(AblationError, match="no presets"):
        parse_presets(" ,")


def test_eq7_with_the_occupancy_sampler_is_refused(tmp_path, capsys):
    assert ablate(tmp_path / "eq7", "--presets", "D", "--seeds", "0", "--sampler", "occupancy",
                  "--model-override", "mlca_concat_direction=true") == 1
    assert "view-dependent: use 'proposal' or 'hierarchical'" in capsys.readouterr().err
    # Nothing was trained, so the corrected command needs no --resume.
    assert ablate(tmp_path / "eq7", "--presets", "D", "--seeds", "0", "--sampler", "hierarchical",
                  "--model-override", "mlca_concat_direction=true") == 0


def report(out, *extra: str) -> int:
    return cli.main(["ablate", "--out", str(out), "--steps", "4", *FLAGS, *LPIPS_FLAGS, "--presets", "AD",
                     "--seeds", "0,1", "--report", *extra])


def test_report_tabulates_finished_and_unfinished_runs_without_training(finished, tmp_path, capsys):
    out = tmp_path / "copy"
    shutil.copytree(finished, out)
    (out / "D_seed1" / "ablation_run.json").unlink()  # as a run cut by a GPU call's limit
    before = (out / "D_seed1" / "checkpoint.pt").stat().st_mtime_ns
    assert report(out) == 0
    printed = capsys.readouterr().out
    assert "training" not in printed and "over 1 of 2 run(s)" in printed  # D seed 1 has no score
    assert (out / "D_seed1" / "checkpoint.pt").stat().st_mtime_ns == before
    assert not (out / "D_seed1" / "ablation_run.json").exists()
    table = json.loads((out / "table.json").read_text())
    runs = {(r["preset"], r["seed"]): r for r in table["runs"]}
    unfinished = runs[("D", 1)]
    assert unfinished["status"].startswith("unfinished") and unfinished["psnr"] is None
    assert unfinished["steps"] == 4 and unfinished["params"] == runs[("D", 0)]["params"]
    d = next(row for row in table["presets"] if row["preset"] == "D")
    assert d["psnr_mean"] == pytest.approx(runs[("D", 0)]["psnr"]) and d["psnr_spread"] is None
    assert all(Path(r["run"]).parent == out for r in table["runs"])  # curves read from the copy
    assert "| D | 1 | unfinished" in (out / "ablation.md").read_text()


def test_report_needs_only_the_folder(finished, tmp_path, capsys):
    """The settings, presets and seeds are the saved plan's; typed ones narrow or are checked."""
    out = shutil.copytree(finished, tmp_path / "copy")
    before = json.loads((out / "table.json").read_text())
    assert cli.main(["ablate", "--out", str(out), "--report"]) == 0
    after = json.loads((out / "table.json").read_text())
    assert [r["psnr"] for r in after["runs"]] == [r["psnr"] for r in before["runs"]]
    assert [row["preset"] for row in after["presets"]] == ["A", "D"] and "over 2 of 2 run(s)" in capsys.readouterr().out
    assert cli.main(["ablate", "--out", str(out), "--report", "--presets", "D", "--seeds", "1"]) == 0
    assert [(r["preset"], r["seed"]) for r in json.loads((out / "table.json").read_text())["runs"]] == [("D", 1)]
    assert cli.main(["ablate", "--out", str(out), "--report", "--lr", "0.5"]) == 1
    assert "other settings (lr)" in capsys.readouterr().err


def test_a_plan_from_before_a_setting_existed_matches_its_default(finished, tmp_path, capsys):
    out = shutil.copytree(finished, tmp_path / "copy")
    plan = json.loads((out / "ablation.json").read_text())
    del plan["settings"]["spike_rollbacks"]
    (out / "ablation.json").write_text(json.dumps(plan))
    assert report(out) == 0
    assert report(out, "--spike-rollbacks", "0") == 1
    assert "other settings (spike_rollbacks)" in capsys.readouterr().err


def test_report_leaves_out_runs_not_started(finished, tmp_path, capsys):
    out = tmp_path / "copy"
    shutil.copytree(finished, out)
    shutil.rmtree(out / "A_seed0")
    shutil.rmtree(out / "A_seed1")
    assert report(out) == 0
    assert "preset A, seed 0: not started, left out" in capsys.readouterr().out
    table = json.loads((out / "table.json").read_text())
    assert [row["preset"] for row in table["presets"]] == ["D"]
    assert "preset A is not in this ablation" in " ".join(table["notes"])


def test_report_refuses_other_settings_and_an_empty_folder(finished, tmp_path, capsys):
    assert report(finished, "--lr", "1e-2") == 1
    assert "other settings (lr)" in capsys.readouterr().err
    assert report(tmp_path / "empty") == 1
    assert "no ablation to report (ablation.json missing)" in capsys.readouterr().err
    assert report(finished, "--gpus", "0") == 1
    assert "--report trains nothing" in capsys.readouterr().err
