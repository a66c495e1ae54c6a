"""Fault injection: runs killed (kill -9) at seeded random steps and in the middle of a checkpoint
write, two runs into one folder, a full disk, a GPU checkpoint resumed on a CPU, a moved run folder
and a moved scene; and the option, field and memory checks that keep a run from going silently wrong.

Each case ends with the last good checkpoint intact and, for what a user can fix, one line on
stderr. Killed runs are real subprocesses (``python -c DRIVER``) of the tiny demo of test_cli;
their resumed result must equal an uninterrupted run's bit for bit.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mixer_nerf import cli
from mixer_nerf.data import ensure_procedural_scene
from mixer_nerf.data.images import downscale, read_image, write_png
from mixer_nerf.metrics import psnr
from mixer_nerf.render import render_rays
from mixer_nerf.render.image_renderer import RENDER_SAMPLES
from mixer_nerf.render.skipping import OccupancyGrid
from mixer_nerf.train import OutputError, TrainConfig, Trainer, load_checkpoint, memory
from mixer_nerf.train.output import atomic_path, prepare_run_folder, remove_stale_temporaries
from mixer_nerf.train.restore import load_trained
from mixer_nerf.train.sampling import RenderGrid, image_renderer, measures_render_grid
from mixer_nerf.video import write_video
from test_cli import TINY_DEMO, TINY_FLAGS

STEPS = 6  # the demo's 4 would leave too few points to kill at
DEMO = {**TINY_DEMO, "steps": STEPS}

# Runs cli.main(argv) with the tiny demo settings, dying (SIGKILL) where argv[1:3] says:
# "step K" before step K+1, "write K" halfway through the K-th checkpoint write, "hold K" stops
# before step K+1 until killed (the run keeps its lock), "none" runs to the end.
DRIVER = """
import ast, os, signal, sys, time
import torch
from mixer_nerf import cli
from mixer_nerf.train.trainer import Trainer
cli.DEMO_SETTINGS, cli.DEMO_VIDEO_FRAMES = ast.literal_eval(os.environ["FAULTS_DEMO"]), 2
kind, at = sys.argv[1], int(sys.argv[2])
step, save, writes = Trainer.train_step, torch.save, []
def faulty_step(self):
    if self.step == at and kind in ("step", "hold"):
        if kind == "hold":
            time.sleep(600)
        os.kill(os.getpid(), signal.SIGKILL)
    return step(self)
def faulty_save(obj, f, *args, **kwargs):
    writes.append(1)
    if kind == "write" and len(writes) == at:
        f.write(b"half a checkpoint")
        f.flush()
        os.kill(os.getpid(), signal.SIGKILL)
    return save(obj, f, *args, **kwargs)
Trainer.train_step, torch.save = faulty_step, faulty_save
sys.exit(cli.main(sys.argv[3:]))
"""


@pytest.fixture(autouse=True)
def tiny_demo(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("MIXER_NERF_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
    monkeypatch.setattr(cli, "DEMO_SETTINGS", DEMO)
    monkeypatch.setattr(cli, "DEMO_VIDEO_FRAMES", 2)


def train_argv(out: Path, *extra: str) -> list[str]:
    return ["train", "--out", str(out), "--eval-views", "1", *TINY_FLAGS, *extra]


def driver(kind: str, at: int, argv: list[str]) -> subprocess.Popen:
    env = {**os.environ, "FAULTS_DEMO": repr(DEMO), "PYTHONPATH": str(Path(cli.__file__).parents[1])}
    return subprocess.Popen([sys.executable, "-c", DRIVER, kind, str(at), *argv], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("mixer-nerf: error: "), err
    return err


def weights(path: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path)["model"]


def assert_same_weights(a: Path, b: Path) -> None:
    wa, wb = weights(a), weights(b)
    assert wa.keys() == wb.keys()
    for name in wa:
        assert torch.equal(wa[name], wb[name]), name


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """An uninterrupted run of the tiny demo: what every interrupted one must end as."""
    out = tmp_path_factory.mktemp("reference") / "run"
    mp = pytest.MonkeyPatch()
    mp.setenv("MIXER_NERF_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
    mp.setattr(cli, "DEMO_SETTINGS", DEMO)
    mp.setattr(cli, "DEMO_VIDEO_FRAMES", 2)
    try:
        assert cli.main(train_argv(out)) == 0
    finally:
        mp.undo()
    return out / "checkpoint.pt"


# -- kill -9 --------------------------------------------------------------------------------------


# Before the first checkpoint, at a seeded random step after it, and halfway through the second write.
KILLS = [("step", 1), ("step", random.Random(26).randrange(2, STEPS)), ("write", 2)]


@pytest.mark.parametrize(("kind", "at"), KILLS, ids=[f"{k}{a}" for k, a in KILLS])
def test_a_killed_run_ends_as_an_uninterrupted_one(kind, at, reference, tmp_path, capsys):
    out = tmp_path / "run"
    proc = driver(kind, at, train_argv(out))
    assert proc.wait(timeout=120) == -signal.SIGKILL, proc.stderr.read()
    ckpt = out / "checkpoint.pt"
    if ckpt.exists():  # the last good one: intact whatever the kill interrupted
        assert load_checkpoint(ckpt)["step"] % DEMO["ckpt_every"] == 0
        # The same command again refuses in one line, and --resume finishes the run.
        assert cli.main(train_argv(out)) == 1
        assert "--resume" in one_line_error(capsys)
        assert cli.main(train_argv(out, "--resume")) == 0
    else:  # killed before its first checkpoint: logs only, which a fresh start must not extend
        assert cli.main(train_argv(out)) == 1
        assert "--overwrite" in one_line_error(capsys)
        assert cli.main(train_argv(out, "--overwrite")) == 0
    assert_same_weights(ckpt, reference)
    steps = [int(line.split(",")[0]) for line in (out / "train_log.csv").read_text().splitlines()[1:]]
    assert steps == list(range(1, STEPS + 1))
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]  # the torn write was cleaned up


def test_two_runs_into_one_folder(reference, tmp_path, capsys):
    """The second is refused while the first holds the folder; after the first is killed, its
    lock is stale and --resume takes over."""
    out = tmp_path / "run"
    first = driver("hold", 2, train_argv(out))
    try:
        deadline = time.monotonic() + 120
        while not (out / "checkpoint.pt").exists() and first.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert (out / "checkpoint.pt").exists(), first.stderr.read() if first.poll() is not None else "timeout"
        for extra in ((), ("--resume",), ("--overwrite",)):
            assert cli.main(train_argv(out, *extra)) == 1
            err = one_line_error(capsys)
            assert f"in use by another run (pid {first.pid} on {socket.gethostname()})" in err
        assert load_checkpoint(out / "checkpoint.pt")["step"] == 2  # the first run's files untouched
    finally:
        first.kill()
        first.wait()
    assert cli.main(train_argv(out, "--resume")) == 0
    assert_same_weights(out / "checkpoint.pt", reference)


# -- disk full, stale temporaries, atomic outputs -------------------------------------------------


def test_a_full_disk_keeps_the_last_checkpoint(reference, tmp_path, monkeypatch, capsys):
    out, save, writes = tmp_path / "run", torch.save, []

    def disk_full_on_the_second_write(obj, f, *args, **kwargs):
        writes.append(1)
        if len(writes) == 2:
            f.write(b"the first bytes")
            raise OSError(errno.ENOSPC, "No space left on device")
        return save(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", disk_full_on_the_second_write)
    assert cli.main(train_argv(out)) == 1
    assert "checkpoint.pt: could not be written (No space left on device)" in one_line_error(capsys)
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 2
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]
    monkeypatch.setattr(torch, "save", save)  # space freed
    assert cli.main(train_argv(out, "--resume")) == 0
    assert_same_weights(out / "checkpoint.pt", reference)


def test_a_full_disk_in_a_log_write_is_one_line(tmp_path, monkeypatch, capsys):
    from mixer_nerf.train.logbook import CsvLog

    def disk_full(self, row):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.path))

    monkeypatch.setattr(CsvLog, "append", disk_full)
    assert cli.main(train_argv(tmp_path / "run")) == 1
    assert "No space left on device" in one_line_error(capsys)


def test_stale_temporaries_are_removed_at_the_next_start(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    stale = [tmp_path / ".checkpoint.pt.k2j4_x.tmp",  # tempfile's names of earlier versions
             tmp_path / f".checkpoint.pt.{dead.stdout.strip()}-0123abcd.tmp.pt"]
    live = tmp_path / f".video.gif.{os.getpid()}-0123abcd.tmp.gif"  # a writer still at work
    mine = tmp_path / ".notes.tmp"  # not ours
    for path in (*stale, live, mine):
        path.write_bytes(b"partial")
    files, lock = prepare_run_folder(tmp_path, resume=False)
    lock.release()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, mine.name, "run.lock"])
    assert remove_stale_temporaries(tmp_path) == []


def test_atomic_outputs_keep_the_old_file_when_writing_fails(tmp_path):
    video = write_video(tmp_path / "video", [torch.zeros(4, 4, 3, dtype=torch.uint8).numpy()] * 2, fps=5)
    before = video.read_bytes()
    with pytest.raises(OutputError, match="could not be written"), atomic_path(video) as tmp:
        tmp.write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert video.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == [video.name]
    with pytest.raises(ValueError, match="fps must be a positive whole number"):
        write_video(tmp_path / "video", [torch.zeros(4, 4, 3, dtype=torch.uint8).numpy()], fps=-5)
    assert video.read_bytes() == before


# -- a checkpoint moved between machines, a moved run folder, a moved scene -------------------------


def as_if_trained_on_a_gpu(ckpt: Path, monkeypatch) -> None:
    """Rewrite ``ckpt`` as a CUDA run writes it: CUDA settings, storages tagged "cuda:0" (which
    torch.load without map_location cannot read on a machine without a GPU), a CUDA generator state."""
    state = load_checkpoint(ckpt)
    state["train_config"].update(device="cuda", precision="tf32", bf16_density_passes=True)
    state["rng"]["sampler"] = torch.zeros(16, dtype=torch.uint8)  # CUDA generators: seed and offset
    with monkeypatch.context() as m:
        m.setattr(torch.serialization, "location_tag", lambda storage: "cuda:0")
        torch.save(state, ckpt)
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):
            torch.load(ckpt, weights_only=True)


def test_a_gpu_checkpoint_is_evaluated_and_resumed_on_a_cpu(reference, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    shutil.copytree(reference.parent, out)
    as_if_trained_on_a_gpu(out / "checkpoint.pt", monkeypatch)
    assert cli.main(["eval", "--ckpt", str(out / "checkpoint.pt"), "--max-images", "1", "--backend", "torch"]) == 0
    if not torch.cuda.is_available():
        assert cli.main(["train", "--out", str(out), "--resume", "--backend", "torch", "--no-progress"]) == 1
        assert "pass --device cpu" in one_line_error(capsys)
    assert cli.main(train_argv(out, "--resume", "--steps", str(STEPS + 2), "--ckpt-every", "1", "--log-every", "1")) == 0
    printed = capsys.readouterr().out
    assert "moved from cuda to cpu" in printed and f"training {STEPS + 2} steps on cpu (fp32" in printed
    assert load_checkpoint(out / "checkpoint.pt")["step"] == STEPS + 2


def test_a_moved_run_folder_and_a_moved_scene(tmp_path, monkeypatch, capsys):
    scene = tmp_path / "scenes" / "mine"
    shutil.copytree(ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2), scene)
    monkeypatch.chdir(tmp_path)
    small = ["--steps", "2", "--batch-rays", "16", "--num-coarse", "4", "--num-fine", "4", "--sampler", "hierarchical"]
    assert cli.main(train_argv(Path("a"), "--data", "scenes/mine", *small)) == 0  # relative paths
    shutil.move(tmp_path / "a", tmp_path / "b")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    ckpt = str(tmp_path / "b" / "checkpoint.pt")
    assert cli.main(["eval", "--ckpt", ckpt, "--max-images", "1", "--backend", "torch"]) == 0
    assert cli.main(train_argv(tmp_path / "b", "--resume", "--steps", "3")) == 0
    # The scene moves too: its old place is named, --data finds it, another scene is refused.
    shutil.move(scene, tmp_path / "moved")
    assert cli.main(["eval", "--ckpt", ckpt, "--backend", "torch"]) == 1
    assert "pass --data where it is now" in one_line_error(capsys)
    assert cli.main(["eval", "--ckpt", ckpt, "--data", str(tmp_path / "moved"), "--max-images", "1",
                     "--backend", "torch"]) == 0
    capsys.readouterr()
    other = ensure_procedural_scene(resolution=16, n_train=5, n_val=2, n_test=2)
    assert cli.main(["eval", "--ckpt", ckpt, "--data", str(other), "--backend", "torch"]) == 1
    assert "not the scene" in one_line_error(capsys)
    assert cli.main(["render", "--ckpt", ckpt, "--frames", "1", "--backend", "torch"]) == 0  # needs no scene


# -- what --resume may change ---------------------------------------------------------------------


def test_resume_extends_steps_and_refuses_other_changes_by_name(reference, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(reference.parent, out)
    assert cli.main(train_argv(out, "--resume", "--lr", "0.5", "--num-fine", "3")) == 1
    err = one_line_error(capsys)
    assert "lr (checkpoint 0.004, given 0.5)" in err and "num_fine (checkpoint 6, given 3)" in err
    assert cli.main(train_argv(out, "--resume", "--steps", "2")) == 1
    assert "--steps 2 is short of the checkpoint's step 6" in one_line_error(capsys)
    assert cli.main(train_argv(out, "--resume", "--steps", str(STEPS + 2), "--ckpt-every", "1", "--log-every", "1")) == 0
    assert f"training {STEPS + 2} steps" in capsys.readouterr().out
    assert load_checkpoint(out / "checkpoint.pt")["step"] == STEPS + 2


# -- options checked before any work --------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--time-budget", "nan"], "time_budget must be a positive, finite number"),
        (["--batch-rays", "100000000", "--data", "DATA"], "--batch-rays 100000000 needs at least"),
        (["--grid-resolution", "5000", "--data", "DATA"], "--grid-resolution 5000 needs at least"),
        (["--render-samples", "0"], "render_samples must be positive"),
    ],
    ids=["nan-budget", "batch-rays", "grid-resolution", "render-samples"],
)
def test_train_options_out_of_range_are_one_line(argv, message, tmp_path, capsys, monkeypatch):
    # A device of 1 GiB: the tiny model's 1e8-ray batch is a lower bound of 26 GB, which a 139 GB
    # GPU would hold and then train (the suite hung there on an H200).
    monkeypatch.setattr(memory, "device_memory", lambda device: 2**30)
    scene = str(ensure_procedural_scene(resolution=16, n_train=4, n_val=2, n_test=2))
    argv = [scene if a == "DATA" else a for a in argv]
    assert cli.main(train_argv(tmp_path / "run", *argv)) == 1
    assert message in one_line_error(capsys)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--fps", "-5"], "fps must be a positive whole number"),
        (["--fps", "0"], "fps must be a positive whole number"),
        (["--scale", "10000"], "--scale 10000 with 1 frames needs at least"),
        (["--scale", "inf"], "scale must be positive and finite"),
        (["--render-samples", "-1"], "--render-samples must be positive"),
    ],
    ids=["fps-negative", "fps-zero", "scale-huge", "scale-inf", "render-samples"],
)
def test_render_options_out_of_range_keep_the_video(argv, message, reference, tmp_path, capsys):
    out = tmp_path / "video"
    out.mkdir()
    (out / "video.gif").write_bytes(b"a good video")
    render = ["render", "--ckpt", str(reference), "--frames", "1", "--out", str(out), "--backend", "torch"]
    assert cli.main([*render, *argv]) == 1
    assert message in one_line_error(capsys)
    assert (out / "video.gif").read_bytes() == b"a good video"


def test_train_eval_views(tmp_path, capsys):
    assert cli.main(train_argv(tmp_path / "none", "--steps", "2", "--eval-views", "none")) == 0
    assert "eval (" not in capsys.readouterr().out and not (tmp_path / "none" / "eval_test").exists()
    assert cli.main(train_argv(tmp_path / "one", "--steps", "2", "--eval-views", "1")) == 0
    assert "eval (test, 1 views)" in capsys.readouterr().out
    assert cli.main(train_argv(tmp_path / "all", "--steps", "2", "--eval-views", "all")) == 0
    assert "eval (test, " in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli.main(train_argv(tmp_path / "bad", "--eval-views", "0"))


def test_downscale_applies_to_llff_scenes(llff_scene, tmp_path):
    for path in sorted((llff_scene / "images_4").iterdir()):  # the loader's default factor, 8: 4x6 images
        write_png(llff_scene / "images_8" / path.name, downscale(read_image(path), 2))
    cfg = TrainConfig(data=str(llff_scene), downscale=2, steps=1, batch_rays=8, num_coarse=4, num_fine=0,
                      sampler="hierarchical", model_overrides=TINY_DEMO["model_overrides"], device="cpu",
                      backend="torch", progress=False, out=str(tmp_path / "run"))
    trainer = Trainer(cfg, log=lambda _: None)
    trainer.lock.release()
    assert (trainer.train_scene.H, trainer.train_scene.W) == (2, 3)


# -- memory: whole images rendered under a sample budget ------------------------------------------


def test_no_render_chunk_shades_more_than_the_budget(tmp_path):
    """An occupancy run whose grid is still dense (every cell occupied) is the worst case."""
    cfg = TrainConfig(procedural_resolution=16, procedural_views=4, model_overrides=TINY_DEMO["model_overrides"],
                      sampler="occupancy", grid_resolution=8, steps=1, device="cpu", backend="torch",
                      progress=False, render_samples=20_000, out=str(tmp_path / "run"))
    trainer = Trainer(cfg, log=lambda _: None)
    trainer.lock.release()
    renderer, shaded = trainer.renderer, []
    chunk = renderer.render_chunk

    def counted(rays_o, rays_d):
        out = chunk(rays_o, rays_d)
        shaded.append(out.num_marched)  # what the field saw, before early termination dropped some
        return out

    renderer.render_chunk = counted
    rays_o, rays_d = trainer.val_scene.rays_for_image(0)
    renderer(rays_o, rays_d)
    assert len(shaded) > 1 and max(shaded) <= 20_000
    assert renderer.chunk == 19  # a ray may cross the box diagonal in 1000 steps


def warmup_run(tmp_path: Path, steps: int) -> Trainer:
    """A tiny CPU occupancy run of ``steps`` steps whose grid is still in warm-up (every cell occupied)."""
    cfg = TrainConfig(procedural_resolution=16, procedural_views=4, model_overrides=TINY_DEMO["model_overrides"],
                      sampler="occupancy", grid_resolution=16, grid_warmup=1000, grid_every=1000, steps=steps,
                      target_samples=4096, val_every=steps, ckpt_every=steps, device="cpu", backend="torch",
                      progress=False, out=str(tmp_path / "run"))
    trainer = Trainer(cfg, log=lambda _: None)
    trainer.fit()
    return trainer


def test_a_cpu_render_in_warm_up_skips_what_the_field_holds_empty(tmp_path):
    """A run that ends in its grid's warm-up renders through a grid measured from its field: fewer
    samples than the dense training grid, no lower PSNR, and the same image from its checkpoint."""
    trainer = warmup_run(tmp_path, steps=60)
    dense = image_renderer(trainer.cfg, trainer.fields, trainer.val_scene.near, trainer.val_scene.far,
                           trainer.background, grid=trainer.fields.grid)  # a given grid is marched as is
    rays_o, rays_d = trainer.val_scene.rays_for_image(0)
    target = trainer.val_scene.image(0)
    (measured, shaded, _), (full, dense_shaded, _) = (r.render_counted(rays_o, rays_d) for r in (trainer.renderer, dense))
    assert trainer.fields.grid.occupied.all(), "training's grid is left in its warm-up"
    assert shaded < 0.9 * dense_shaded
    image = lambda out: out.color.reshape(target.shape).clamp(0, 1)  # noqa: E731
    assert psnr(image(measured), target) >= psnr(image(full), target) - 0.01
    run = load_trained(tmp_path / "run" / "checkpoint.pt")
    torch.testing.assert_close(run.render(rays_o, rays_d).color, measured.color)


def test_gpu_renders_and_defaults_are_unchanged():
    """The CPU-only bounds leave a GPU run as it was: its settings, its grid in warm-up, all views."""
    gpu = TrainConfig().resolved(cuda_available=True).with_recipe("occupancy")
    pinned = {"device": "cuda", "precision": "bf16", "bf16_density_passes": True, "grid_warmup": 256,
              "grid_every": 16, "grid_threshold": 0.01, "grid_resolution": 128, "target_samples": 131072,
              "render_samples": None, "step_size": None, "early_stop_eps": 1e-4, "val_images": 3, "chunk": 8192}
    assert {k: gpu.to_dict()[k] for k in pinned} == pinned
    assert RENDER_SAMPLES["cuda"] == 1 << 22
    cpu = dataclasses.replace(gpu, device="cpu")
    assert not measures_render_grid(gpu, 0) and measures_render_grid(cpu, 255) and not measures_render_grid(cpu, 256)
    grid = OccupancyGrid([-1, -1, -1, 1, 1, 1], 4)
    assert RenderGrid(gpu, grid, field=None, step=lambda: 0)() is grid
    assert cli.eval_views(None, "cuda") is None and cli.eval_views(None, "cuda:1") is None
    assert cli.eval_views(None, "cpu") == cli.EVAL_VIEWS_CPU and cli.eval_views(None, "cpu", builtin=True) is None
    assert cli.eval_views("all", "cpu") is None and cli.eval_views(3, "cpu") == 3


def test_a_cpu_scores_a_bounded_number_of_views_by_default(blender_scene, tmp_path, capsys):
    argv = ["train", "--data", str(blender_scene), "--steps", "2", "--sampler", "hierarchical", "--batch-rays", "16",
            "--num-coarse", "4", "--num-fine", "4", *TINY_FLAGS]  # preset D's full model: few samples keep it quick
    assert cli.main([*argv, "--out", str(tmp_path / "default")]) == 0
    out = capsys.readouterr().out
    assert f"eval (test, {cli.EVAL_VIEWS_CPU} views)" in out and "--eval-views all" in out
    assert cli.main([*argv, "--out", str(tmp_path / "all"), "--eval-views", "all"]) == 0
    assert "eval (test, 2 views)" in capsys.readouterr().out


class NegativeField(torch.nn.Module):
    def forward(self, x, d):
        return -torch.ones(x.shape[:-1]), torch.zeros_like(x)


class ColumnSigmaField(torch.nn.Module):
    def forward(self, x, d):
        return torch.ones(*x.shape[:-1], 1), torch.zeros_like(x)


@pytest.mark.parametrize(("field", "message"), [
    (NegativeField(), "field NegativeField returned a negative density"),
    (ColumnSigmaField(), r"field ColumnSigmaField returned sigma \(2, 4, 1\) and rgb \(2, 4, 3\) for \(2, 4\) samples"),
])
def test_render_rays_names_a_field_with_bad_output(field, message):
    rays_o, rays_d = torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0]] * 2)
    with pytest.raises(ValueError, match=message):
        render_rays(field, rays_o, rays_d, 1.0, 2.0, num_coarse=4, num_fine=0)
