"""Training on 2 CPU processes (gloo) under torchrun: ranks stay bit-identical, a killed run
resumes on 1 and on 2 processes, a failing rank stops the others; and one process is untouched.

Each torchrun launch costs seconds of process start-up, so there are four: an uninterrupted
run, the same run with a rank failing, its resume through ``train --devices 2``, and a run whose
rank 0 sees a loss spike.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mixer_nerf import cli
from mixer_nerf.data import ensure_procedural_scene
from mixer_nerf.ops.bitfield import unpack_bits
from mixer_nerf.render.skipping import CellShare, OccupancyGrid
from mixer_nerf.train import TrainConfig, Trainer, load_checkpoint
from mixer_nerf.train.distributed import join, rank_seed, restore_rank_sampler

WORKER = Path(__file__).with_name("distributed_worker.py")
LAUNCH_TIMEOUT = 240  # seconds; far above a healthy run, so only a hang reaches it
TINY = {
    "model_overrides": {"depth": 2, "width": 16, "skips": [], "view_width": 8, "pos_freqs": 2, "dir_freqs": 1,
                        "mlca_channels": 3, "se_reduction": 4},
    "steps": 6,
    "batch_rays": 32,
    "val_every": 6,
    "val_images": 1,
    "ckpt_every": 3,
    "log_every": 1,
    "backend": "torch",
    "device": "cpu",
    "progress": False,
    "sampler": "occupancy",  # gradients and the grid: refreshes at steps 0 (warm-up), 2, 4
    "grid_resolution": 8,
    "grid_warmup": 2,
    "grid_every": 2,
    "target_samples": 256,
    "time_budget": 1e6,  # never reached, but every step asks rank 0's clock
}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The procedural scene at 16x16 pixels (4 training views), as a Blender folder."""
    return ensure_procedural_scene(resolution=16, n_train=4, n_val=4, n_test=4,
                                   cache_dir=tmp_path_factory.mktemp("cache"))


def torchrun(scene: Path, out: Path, *flags: str, **settings) -> subprocess.CompletedProcess:
    """tests/distributed_worker.py on 2 processes training the TINY run (with ``settings``) in ``out``."""
    config = out.parent / f"{out.name}.json"
    config.write_text(json.dumps({**TINY, **settings, "data": str(scene), "out": str(out)}))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2",
               str(WORKER), str(config), *flags]
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=LAUNCH_TIMEOUT)


def fields_of(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, map_location="cpu", weights_only=True)["fields"]


def assert_identical(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for name in a:
        assert torch.equal(a[name], b[name]), name


@pytest.fixture(scope="module")
def uninterrupted(scene, tmp_path_factory):
    """6 steps on 2 ranks."""
    out = tmp_path_factory.mktemp("uninterrupted") / "run"
    result = torchrun(scene, out)
    assert result.returncode == 0, result.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def killed(scene, tmp_path_factory):
    """The same run with rank 1 failing before step 5: its last checkpoint is step 3's."""
    out = tmp_path_factory.mktemp("killed") / "run"
    return out, torchrun(scene, out, "--fail-rank", "1", "--fail-step", "5")


def test_ranks_stay_bit_identical(uninterrupted):
    rank0, rank1 = fields_of(uninterrupted / "rank0.pt"), fields_of(uninterrupted / "rank1.pt")
    assert_identical(rank0, rank1)
    occupied = unpack_bits(rank0["grid.bitfield"], rank0["grid.opacity"].numel()).float().mean()
    assert 0 < occupied < 1  # refreshed past warm-up: thresholded, not every cell


@pytest.mark.cuda
@pytest.mark.skipif(torch.cuda.device_count() < 2, reason="needs 2 CUDA GPUs")
def test_nccl_ranks_stay_bit_identical(scene, tmp_path):
    """The same on 2 GPUs: NCCL, the kernels, bf16 density passes."""
    result = torchrun(scene, tmp_path / "run", device="cuda", backend="auto")
    assert result.returncode == 0, result.stderr[-3000:]
    assert_identical(fields_of(tmp_path / "run" / "rank0.pt"), fields_of(tmp_path / "run" / "rank1.pt"))


def test_a_spike_rank_0_sees_rolls_every_rank_back_alike(scene, tmp_path):
    out = tmp_path / "run"
    result = torchrun(scene, out, "--spike-step", "4")
    assert result.returncode == 0, result.stderr[-3000:]
    ranks = [torch.load(out / f"rank{r}.pt", map_location="cpu", weights_only=True) for r in (0, 1)]
    assert [r["rollbacks"] for r in ranks] == [1, 1]
    assert_identical(ranks[0]["fields"], ranks[1]["fields"])


def test_gradients_are_averaged_over_ranks(uninterrupted):
    """Rank r's gradient r + 1 averages to 1.5; a gradient missing on one rank counts as zero."""
    for rank in (0, 1):
        probe = torch.load(uninterrupted / f"rank{rank}.pt", weights_only=True)["probe"]
        assert torch.equal(probe[0], torch.full((3,), 1.5)) and torch.equal(probe[1], torch.full((2,), 0.5))


def test_only_rank_0_writes(uninterrupted):
    names = {p.name for p in uninterrupted.iterdir()}
    assert {"checkpoint.pt", "train_log.csv", "summary.json"} <= names
    steps = [line.split(",")[0] for line in (uninterrupted / "train_log.csv").read_text().splitlines()[1:]]
    assert steps == [str(s) for s in range(1, 7)]  # one row per step: no rank 1 rows
    assert len(load_checkpoint(uninterrupted / "checkpoint.pt")["rank_samplers"]) == 2


def test_failing_rank_stops_the_others(killed):
    out, result = killed
    assert result.returncode != 0
    assert "injected failure on rank 1 at step 5" in result.stderr
    assert "another training process stopped" in result.stderr or "SIGTERM" in result.stderr  # rank 0
    assert not (out / "rank0.pt").exists()  # rank 0 did not carry on alone
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 3


def test_killed_run_resumes_on_2_processes_exactly(scene, killed, uninterrupted, tmp_path):
    """Through ``train --resume --devices 2``: the relaunch under torchrun, rank 0's report."""
    out = tmp_path / "run"
    shutil.copytree(killed[0], out)
    command = [sys.executable, "-m", "mixer_nerf", "train", "--data", str(scene), "--resume",
               "--devices", "2", "--out", str(out), "--device", "cpu", "--backend", "torch", "--no-progress"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=LAUNCH_TIMEOUT)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("checkpoint:") == 1  # one report, rank 0's
    resumed = load_checkpoint(out / "checkpoint.pt")
    assert resumed["step"] == 6
    assert_identical(resumed["model"], fields_of(uninterrupted / "rank0.pt"))


def test_killed_run_resumes_on_1_process(killed, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(killed[0], out)
    trainer = Trainer(TrainConfig(**{**TINY, "out": str(out)}), resume=True, log=lambda _: None)
    assert trainer.ranks is None and trainer.step == 3
    assert trainer.fit()["step"] == 6
    assert all(torch.isfinite(p).all() for p in trainer.params)


def test_one_process_without_torchrun_is_untouched(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert join("cpu") is None
    assert rank_seed(7, 0) == 7  # rank 0 draws what one process always drew
    assert len({rank_seed(7, r, s) for r in range(3) for s in (0, 9)}) == 6


def test_resume_gives_each_rank_its_saved_stream_or_a_fresh_one():
    saved = [torch.Generator().manual_seed(s).get_state() for s in (1, 2)]
    generator = torch.Generator()
    restore_rank_sampler(generator, saved, 1, seed=0, step=9)
    assert torch.equal(generator.get_state(), saved[1])
    restore_rank_sampler(generator, saved, 2, seed=0, step=9)  # the saving run had 2 ranks
    assert generator.initial_seed() == rank_seed(0, 2, 9)


def test_shared_refresh_equals_the_max_of_its_shares():
    """Two shares of a warm-up refresh together measure every cell once, as one process does."""
    density = lambda x: 10.0 * (x[:, 0] > 0)  # noqa: E731  (constant within each cell)
    whole = OccupancyGrid([-1, -1, -1, 1, 1, 1], 8)
    whole.update(0, density, generator=torch.Generator().manual_seed(0))
    parts = [OccupancyGrid([-1, -1, -1, 1, 1, 1], 8) for _ in range(2)]
    fresh = []
    for i, grid in enumerate(parts):
        grid.update(0, density, generator=torch.Generator().manual_seed(i),
                    share=CellShare(i, 2, lambda t: fresh.append(t)))
    merged = torch.maximum(*fresh)
    assert (merged >= 0).all() and ((fresh[0] >= 0) ^ (fresh[1] >= 0)).all()  # each cell once
    inside = whole.opacity.view(-1) > 0
    assert torch.equal(inside, merged > 0)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--devices", "0"], "--devices must be positive, got 0"),
        (["--devices", "2", "--device", "cuda"], "torch sees no CUDA GPU"),
    ],
)
def test_bad_devices_is_one_line(argv, message, tmp_path, capsys):
    if torch.cuda.is_available() and "cuda" in argv:
        pytest.skip("this machine has a GPU")
    assert cli.main(["train", "--out", str(tmp_path), "--no-progress", *argv]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err


def test_devices_must_match_torchrun(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "test")
    assert cli.main(["train", "--out", str(tmp_path), "--no-progress", "--devices", "3"]) == 1
    assert "leave --devices out there" in capsys.readouterr().err


def test_devices_reports_a_failed_rank_in_one_line(tmp_path, capsys, monkeypatch):
    """What ``train --devices 2`` prints when torchrun reports a failed rank (no launch here)."""
    import torch.distributed.run as torchrun_module
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError, ProcessFailure

    def failed_run(args):
        raise ChildFailedError("mixer_nerf", {1: ProcessFailure(1, 4242, 1, "<N/A>")})

    monkeypatch.delenv("WORLD_SIZE", raising=False)
    monkeypatch.delenv("TORCHELASTIC_RUN_ID", raising=False)
    monkeypatch.setattr(torchrun_module, "run", failed_run)
    argv = ["train", "--out", str(tmp_path), "--no-progress", "--device", "cpu", "--devices", "2"]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err == ("mixer-nerf: error: training process 1 of 2 failed (exit code 1); its error is printed "
                   "above and the others were stopped")
