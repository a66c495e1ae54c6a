"""Trainer, checkpoints, resume, non-finite guard, logs and camera paths, at tiny sizes on CPU.

Everything runs with ``backend="torch"`` (the reference ops) so these tests do not depend on the
kernels building, on a 16x16 procedural scene rendered into a per-session cache.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from mixer_nerf.train import (
    CheckpointError,
    NonFiniteError,
    OutputError,
    TrainConfig,
    Trainer,
    load_checkpoint,
    load_trained,
    save_checkpoint,
)
from mixer_nerf.render.skipping import march_samples, march_samples_fixed, render_rays_proposal, shade_samples
from mixer_nerf.ops.ray_marching import padding_rays
from mixer_nerf.render.skipping.marching import with_padding_rays
from mixer_nerf.train.checkpoint import capture_rng_state, restore_rng_state
from mixer_nerf.train.config import (
    DEFAULT_STEPS,
    FORWARD_FACING_PROPOSAL_STEPS,
)
from mixer_nerf.train.fields import model_config
from mixer_nerf.train.sampling import recipe_notes, resolve_sampler
from mixer_nerf.train import trainer as trainer_module
from mixer_nerf.render.skipping import SampleBudget
from mixer_nerf.train import fixed_batch
from mixer_nerf.train.fixed_batch import FixedBatch, FixedBatches, FixedCapacity
from mixer_nerf.train.guard import NonFiniteGuard
from mixer_nerf.train.logbook import CsvLog, plot_curves
from mixer_nerf.train.loss_spikes import LossSpikeWatch
from dispatch_count import dispatched_ops

TINY_MODEL = {
    "depth": 2,
    "width": 16,
    "skips": (),
    "view_width": 8,
    "pos_freqs": 2,
    "dir_freqs": 1,
    "mlca_channels": 3,
    "se_reduction": 4,
}


@pytest.fixture(scope="session", autouse=True)
def scene_cache(tmp_path_factory):
    """The procedural scene is rendered once per session into a private cache."""
    old = os.environ.get("MIXER_NERF_CACHE")
    os.environ["MIXER_NERF_CACHE"] = str(tmp_path_factory.mktemp("cache"))
    yield
    if old is None:
        del os.environ["MIXER_NERF_CACHE"]
    else:
        os.environ["MIXER_NERF_CACHE"] = old


def tiny_config(out, **overrides) -> TrainConfig:
    values = dict(
        procedural_resolution=16,
        procedural_views=4,
        model_overrides=TINY_MODEL,
        steps=6,
        batch_rays=32,
        num_coarse=6,
        num_fine=6,
        val_every=3,
        val_images=1,
        ckpt_every=3,
        log_every=1,
        backend="torch",
        device="cpu",
        progress=False,
        out=str(out),
        sampler="hierarchical",
        grid_resolution=8,
        grid_warmup=2,
        grid_every=2,
        target_samples=256,
    )
    values.update(overrides)
    return TrainConfig(**values)


def quiet(_: str) -> None:
    pass


def params_of(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in trainer.fields.state_dict().items()}


# -- configuration ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("steps", 0),
        ("batch_rays", -1),
        ("preset", "E"),
        ("precision", "fp8"),
        ("backend", "cuda"),
        ("lr", 0.0),
        ("adam_eps", 0.0),
        ("adam_eps", math.inf),
        ("grad_clip", 0.0),
        ("grad_clip", -1.0),
        ("grad_clip", math.inf),
        ("grad_clip", math.nan),
        ("time_budget", -1.0),
        ("lr_warmup", -1),
        ("lr_hold", 1.0),
        ("device", "tpu"),
        ("num_fine", -1),
        ("empty_space_weight", -1e-3),
        ("empty_space_points", 0),
        ("proposal_update_every", 0),
        ("proposal_jitter", "per_bin"),
        ("proposal_residual", "far"),
        ("proposal_intervals", "mid"),
        ("proposal_weight_padding", -1e-4),
        ("distortion_weight", -1e-3),
        ("distortion_weight", math.nan),
        ("distortion_weight", math.inf),
        ("occlusion_weight", -1e-3),
        ("occlusion_weight", math.nan),
        ("occlusion_fraction", 0.0),
        ("occlusion_fraction", 1.0),
        ("density_noise", -0.5),
        ("density_noise", math.nan),
        ("frequency_anneal", -0.1),
        ("frequency_anneal", 1.5),
        ("frequency_anneal", math.nan),
        ("mlca_weight_decay", -0.1),
        ("mlca_weight_decay", math.nan),
        ("mlca_weight_decay", math.inf),
    ],
)
def test_config_rejects_bad_values_naming_them(field, value):
    with pytest.raises(ValueError, match=field):
        TrainConfig(**{field: value})


def test_config_round_trips_and_resolves_for_the_machine():
    cfg = TrainConfig(steps=7, model_overrides={"width": 32})
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown training settings"):
        TrainConfig.from_dict({**cfg.to_dict(), "bogus": 1})
    cpu = cfg.resolved(cuda_available=False)
    assert (cpu.device, cpu.precision, cpu.bf16_density_passes, cpu.val_images) == ("cpu", "fp32", False, 1)
    gpu = cfg.resolved(cuda_available=True)
    assert (gpu.device, gpu.precision, gpu.bf16_density_passes, gpu.val_images) == ("cuda", None, True, 3)
    assert not TrainConfig(bf16_density_passes=False).resolved(cuda_available=True).bf16_density_passes
    assert TrainConfig(val_images=5).resolved(cuda_available=False).val_images == 5
    with pytest.raises(ValueError, match="val_images must be positive"):
        TrainConfig(val_images=0)
    with pytest.raises(ValueError, match="cuda"):
        TrainConfig(device="cuda").resolved(cuda_available=False)


# -- checkpoints ------------------------------------------------------------------------------------


def minimal_state(step=1):
    return {"step": step, "train_config": {}, "model_config": {}, "scene": {}, "model": {"w": torch.randn(3)}}


def test_checkpoint_round_trip(tmp_path):
    path = tmp_path / "c.pt"
    state = minimal_state(5)
    save_checkpoint(path, state)
    loaded = load_checkpoint(path)
    assert loaded["step"] == 5 and torch.equal(loaded["model"]["w"], state["model"]["w"])
    assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]  # no temporary file left behind


def test_failed_checkpoint_write_keeps_the_previous_one(tmp_path, monkeypatch):
    path = tmp_path / "c.pt"
    save_checkpoint(path, minimal_state(1))
    before = path.read_bytes()

    def dies_mid_write(obj, f, *args, **kwargs):
        f.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", dies_mid_write)
    with pytest.raises(OutputError, match="c.pt: could not be written .disk full.; the previous file is kept"):
        save_checkpoint(path, minimal_state(2))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "foreign", "missing"])
def test_bad_checkpoint_error_names_the_file(tmp_path, damage):
    path = tmp_path / "c.pt"
    save_checkpoint(path, minimal_state())
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(os.urandom(len(data)))
    elif damage == "empty":
        path.write_bytes(b"")
    elif damage == "foreign":
        torch.save({"weights": torch.ones(2)}, path)
    else:
        path.unlink()
    with pytest.raises(CheckpointError, match=str(path)):
        load_checkpoint(path)


def test_rng_state_round_trip():
    import random

    g = torch.Generator().manual_seed(1)
    state = capture_rng_state(g)
    first = (torch.rand(3), np.random.rand(3), random.random(), torch.rand(3, generator=g))
    restore_rng_state(state, g)
    again = (torch.rand(3), np.random.rand(3), random.random(), torch.rand(3, generator=g))
    assert torch.equal(first[0], again[0]) and np.array_equal(first[1], again[1])
    assert first[2] == again[2] and torch.equal(first[3], again[3])


# -- training, resume, output folder --------------------------------------------------------------


@pytest.mark.parametrize("sampler", ["hierarchical", "occupancy", "proposal"])
def test_resume_after_a_kill_is_bit_exact(tmp_path, monkeypatch, sampler):
    """2N steps straight == N steps, a kill at step N+2 (losing at most ckpt_every steps), resume."""
    straight = Trainer(tiny_config(tmp_path / "a", sampler=sampler), log=quiet)
    straight.fit()

    cfg = tiny_config(tmp_path / "b", sampler=sampler)
    killed = Trainer(cfg, log=quiet)
    real_step = Trainer.train_step

    def killed_at_step_5(self):
        if self.step == 4:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", killed_at_step_5)
    with pytest.raises(KeyboardInterrupt):
        killed.fit()
    monkeypatch.setattr(Trainer, "train_step", real_step)
    assert load_checkpoint(cfg.out + "/checkpoint.pt")["step"] == 3  # lost only the steps since
    assert max(int(r["step"]) for r in CsvLog(tmp_path / "b" / "train_log.csv").rows()) == 4

    resumed = Trainer(cfg, resume=True, log=quiet)  # the same command again, with --resume
    assert resumed.step == 3 and resumed.cfg.steps == cfg.steps
    assert [int(r["step"]) for r in resumed.train_log.rows()] == [
        1,
        2,
        3,
    ]  # rows after the checkpoint dropped
    resumed.fit()
    a, b = params_of(straight), params_of(resumed)
    assert a.keys() == b.keys()
    for name in a:
        assert torch.equal(a[name], b[name]), name
    sa, sb = straight.optimizer.state_dict()["state"], resumed.optimizer.state_dict()["state"]
    for k in sa:
        assert all(torch.equal(sa[k][n], sb[k][n]) for n in sa[k])
    assert resumed.train_log.rows()[-1]["loss"] == straight.train_log.rows()[-1]["loss"]


def test_run_writes_logs_plot_summary_and_a_loadable_checkpoint(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, sampler="auto"), log=quiet)
    assert trainer.cfg.sampler == "occupancy" and trainer.fields.fine is None  # procedural scene has a box
    summary = trainer.fit()
    assert summary["status"] == "finished" and summary["step"] == 6
    for name in (
        "checkpoint.pt",
        "config.json",
        "train_log.csv",
        "val_log.csv",
        "curves.png",
        "summary.json",
    ):
        assert (tmp_path / name).is_file(), name
    rows = trainer.train_log.rows()
    assert [int(r["step"]) for r in rows] == list(range(1, 7))
    assert all(math.isfinite(float(r["loss"])) and float(r["rays_per_s"]) > 0 for r in rows)
    assert all(float(r["grad_norm"]) > 0 for r in rows)
    assert [int(r["step"]) for r in trainer.val_log.rows()] == [3, 6]
    run = load_trained(tmp_path / "checkpoint.pt")
    assert run.step == 6
    rays_o, rays_d = trainer.val_scene.rays_for_image(0)
    torch.testing.assert_close(run.render(rays_o, rays_d).color, trainer.render_rgb(rays_o, rays_d))


def test_a_loss_spike_is_said_in_the_log(tmp_path):
    lines: list[str] = []
    trainer = Trainer(tiny_config(tmp_path), log=lines.append)
    trainer.spikes = LossSpikeWatch(window=1)
    trainer.spikes.observe(0, 1e-12)  # every real loss is a spike against this one
    trainer.fit()
    assert any(line.startswith("  note: loss spike at step 1: ") for line in lines), lines


class SpikeAt:
    """A loss-spike watch that says a spike at ``step`` and nowhere else."""

    def __init__(self, step: int) -> None:
        self.step = step

    def observe(self, step: int, loss: float) -> str | None:
        return f"loss spike at step {step}: made by the test" if step == self.step else None


GRAPHED_PROPOSAL_STEPS = dict(sampler="proposal", proposal_rounds=(12, 8), proposal_samples=6, device="cuda",
                              backend="auto", cuda_graphs=True)


@pytest.mark.parametrize("settings", [
    {},
    pytest.param(GRAPHED_PROPOSAL_STEPS, marks=[pytest.mark.cuda, pytest.mark.skipif(
        not torch.cuda.is_available(), reason="no CUDA GPU")]),
], ids=["cpu", "cuda graphed proposal steps"])
def test_a_loss_spike_takes_the_run_back_to_before_it_and_says_so(tmp_path, settings):
    """Parameters and Adam's state (the fused, capturable one on CUDA) come back bit for bit, in the
    memory a replayed graph reads; the run trains on."""
    lines: list[str] = []
    trainer = Trainer(tiny_config(tmp_path, steps=6, ckpt_every=6, val_every=6, **settings), log=lines.append)
    trainer.spikes = SpikeAt(4)
    kept, restored = {}, []
    keep, restore = trainer.rollback.keep, trainer.rollback.restore

    def keeping(step):
        keep(step)
        kept[step] = [t.detach().clone() for t in trainer.rollback._tensors()]

    def restoring():
        back = restore()
        restored.append((back, [t.detach().clone() for t in trainer.rollback._tensors()]))
        return back

    trainer.rollback.keep, trainer.rollback.restore = keeping, restoring
    memory = [t.data_ptr() for t in trainer.params]
    trainer.fit()
    assert [t.data_ptr() for t in trainer.params] == memory and all(torch.isfinite(p).all() for p in trainer.params)
    assert sorted(kept) == [1, 2, 3, 5, 6]  # every logged step but the spike's
    back, state = restored[0]
    assert back == 2 and all(torch.equal(a, b) for a, b in zip(state, kept[2]))  # parameters and Adam state
    assert "  note: loss spike at step 4: made by the test" in lines
    assert "  note: back to the fields and optimiser of step 2, on with new batches (rollback 1 of 3; " \
           "--spike-rollbacks)" in lines
    assert load_checkpoint(tmp_path / "checkpoint.pt")["progress"]["spike_rollbacks"] == 1
    assert json.loads((tmp_path / "summary.json").read_text())["spike_rollbacks"] == 1
    resumed = Trainer(tiny_config(tmp_path, steps=8, val_every=6, spike_rollbacks=1, **settings), resume=True,
                      log=quiet)
    assert (resumed.rollback.used, resumed.rollback.left) == (1, 0)  # the count goes on; the limit may change


def test_a_spike_with_no_rollback_left_or_none_kept_is_said(tmp_path):
    lines: list[str] = []
    trainer = Trainer(tiny_config(tmp_path, spike_rollbacks=0), log=lines.append)
    trainer.spikes = SpikeAt(3)
    trainer.rollback.keep = trainer.rollback.restore = None  # never called: nothing is kept or read back
    trainer.fit()
    assert "  note: loss spike at step 3: made by the test" in lines
    assert not any("rollback" in line or "go back" in line for line in lines), lines
    lines.clear()
    trainer = Trainer(tiny_config(tmp_path / "first", spike_rollbacks=2), log=lines.append)
    trainer.spikes = SpikeAt(1)
    trainer.fit()
    assert "  note: no state kept yet to go back to (one is kept at each logged step)" in lines


def test_rollbacks_change_nothing_in_a_run_without_spikes(tmp_path):
    params = []
    for limit in (0, 3):
        trainer = Trainer(tiny_config(tmp_path / str(limit), spike_rollbacks=limit), log=quiet)
        trainer.spikes = SpikeAt(-1)
        trainer.fit()
        params.append([p.detach() for p in trainer.params])
    assert all(torch.equal(a, b) for a, b in zip(*params))


def test_time_budget_stops_training(tmp_path):
    summary = Trainer(tiny_config(tmp_path, steps=10_000, time_budget=0.5), log=quiet).fit()
    assert summary["status"] == "time budget reached"
    assert 0 < summary["step"] < 10_000
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == summary["step"]


def test_a_first_use_kernel_build_is_not_training_time(tmp_path, monkeypatch):
    """The kernels load when the trainer is made: a 1 s build (failing here, so the reference path
    trains) leaves a 0.5 s budget its steps."""
    from mixer_nerf import _extension

    def slow_failing_build():
        time.sleep(1.0)
        raise _extension.ExtensionUnavailable("no compiler in this test")

    monkeypatch.setattr(_extension, "_state", {})
    monkeypatch.setattr(_extension, "_load", slow_failing_build)
    with pytest.warns(RuntimeWarning, match="no compiler in this test"):
        trainer = Trainer(tiny_config(tmp_path, steps=10_000, time_budget=0.5, backend="auto"), log=quiet)
    assert trainer.fit()["step"] > 1


def test_a_resume_that_does_not_retype_the_time_budget_keeps_the_checkpoints(tmp_path):
    """`train --out RUN --resume` alone continues the run it was: same budget, same schedule."""
    Trainer(tiny_config(tmp_path, steps=10_000, time_budget=600.0), log=quiet).save()
    resumed = Trainer(tiny_config(tmp_path, steps=10_000), resume=True, log=quiet)
    assert resumed.cfg.time_budget == 600.0
    resumed.lock.release()  # a run folder has one owner at a time
    extended = Trainer(tiny_config(tmp_path, steps=10_000, time_budget=900.0), resume=True, log=quiet)
    assert extended.cfg.time_budget == 900.0


def test_learning_rate_comes_from_the_samplers_recipe_unless_given():
    occupancy, hierarchical = TrainConfig().with_recipe("occupancy"), TrainConfig().with_recipe("hierarchical")
    assert (occupancy.lr, occupancy.lr_final, occupancy.lr_warmup) == (4e-3, pytest.approx(4e-4), 200)
    assert occupancy.lr_hold == 0.5
    assert (hierarchical.lr, hierarchical.lr_final, hierarchical.lr_warmup) == (5e-4, pytest.approx(5e-5), 0)
    assert hierarchical.lr_hold == 0.0  # NeRF's decay over the whole run
    assert TrainConfig(lr_hold=0.25).with_recipe("occupancy").lr_hold == 0.25
    given = TrainConfig(lr=1e-3, lr_warmup=7).with_recipe("hierarchical")
    assert (given.lr, given.lr_final, given.lr_warmup) == (1e-3, pytest.approx(1e-4), 7)
    assert TrainConfig(lr_final=2e-3).with_recipe("occupancy").lr_final == 2e-3
    assert TrainConfig(lr=1e-3).with_recipe("occupancy").lr_final == pytest.approx(1e-4)
    proposal = TrainConfig().with_recipe("proposal")
    assert (proposal.lr, proposal.lr_final, proposal.lr_warmup) == (2e-3, pytest.approx(2e-4), 200)


def test_cuda_precision_comes_from_the_samplers_recipe_unless_given():
    on_gpu = {sampler: TrainConfig().resolved(cuda_available=True).with_recipe(sampler).precision
              for sampler in ("occupancy", "proposal", "hierarchical")}
    assert on_gpu == {"occupancy": "bf16", "proposal": "tf32", "hierarchical": "tf32"}
    given = TrainConfig(precision="tf32").resolved(cuda_available=True)
    assert given.with_recipe("occupancy").precision == "tf32"
    assert TrainConfig().resolved(cuda_available=False).with_recipe("occupancy").precision == "fp32"


def test_adam_eps_comes_from_the_samplers_recipe_unless_given():
    assert TrainConfig().adam_eps is None
    eps = {sampler: TrainConfig().with_recipe(sampler).adam_eps for sampler in ("occupancy", "proposal", "hierarchical")}
    assert eps == {"occupancy": 1e-15, "proposal": 1e-8, "hierarchical": 1e-15}
    assert TrainConfig(adam_eps=1e-15).with_recipe("proposal").adam_eps == 1e-15
    assert TrainConfig(adam_eps=1e-6).with_recipe("occupancy").adam_eps == 1e-6


def test_auto_sampler_marches_bounded_scenes_and_proposes_for_forward_facing_and_unbounded_ones():
    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    auto = TrainConfig(sampler="auto")
    assert resolve_sampler(auto, box, ndc=False).sampler == "occupancy"
    assert resolve_sampler(auto, box, ndc=True).sampler == "proposal"  # LLFF in NDC
    assert resolve_sampler(auto, None, ndc=False).sampler == "proposal"  # unbounded
    assert not resolve_sampler(auto, None, ndc=False).fine_network
    assert resolve_sampler(TrainConfig(sampler="hierarchical"), box, ndc=True).fine_network
    eq7 = TrainConfig(sampler="auto", model_overrides={"mlca_concat_direction": True})
    assert resolve_sampler(eq7, box, ndc=False).sampler == "proposal"  # the grid needs a view-free density
    with pytest.raises(ValueError, match="view-dependent"):
        resolve_sampler(dataclasses.replace(eq7, sampler="occupancy"), box, ndc=False)
    assert resolve_sampler(TrainConfig(sampler="occupancy"), box, ndc=True).sampler == "occupancy"
    with pytest.raises(ValueError, match="needs a scene box"):
        resolve_sampler(TrainConfig(sampler="occupancy"), None, ndc=False)


def test_no_scene_gets_the_few_view_regularisers_unless_told():
    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    for preset in "ABCD":
        for bbox, ndc in ((box, False), (box, True), (None, False)):
            cfg = resolve_sampler(TrainConfig(preset=preset), bbox, ndc)
            assert (cfg.occlusion_weight, cfg.mlca_weight_decay) == (0.0, 0.0)
    typed = resolve_sampler(TrainConfig(occlusion_weight=0.05, mlca_weight_decay=3.0), box, ndc=True)
    assert (typed.occlusion_weight, typed.mlca_weight_decay) == (0.05, 3.0)
    assert resolve_sampler(TrainConfig(mlca_weight_decay=3.0), box, ndc=False).mlca_weight_decay == 3.0
    assert resolve_sampler(TrainConfig(lr=0.1), box, ndc=True).mlca_weight_decay == 0.0  # no decay: any lr
    with pytest.raises(ValueError, match="mlca_weight_decay 10 times lr 0.1 must be below 1"):
        resolve_sampler(TrainConfig(lr=0.1, mlca_weight_decay=10.0), box, ndc=True)


def test_forward_facing_proposal_runs_train_fewer_steps_unless_told_otherwise():
    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    steps = {(sampler, ndc): resolve_sampler(TrainConfig(sampler=sampler), box, ndc).steps
             for sampler in ("auto", "proposal", "hierarchical") for ndc in (False, True)}
    assert steps == {("auto", False): DEFAULT_STEPS, ("auto", True): FORWARD_FACING_PROPOSAL_STEPS,
                     ("proposal", False): DEFAULT_STEPS, ("proposal", True): FORWARD_FACING_PROPOSAL_STEPS,
                     ("hierarchical", False): DEFAULT_STEPS, ("hierarchical", True): DEFAULT_STEPS}
    assert resolve_sampler(TrainConfig(sampler="auto"), None, ndc=False).steps == DEFAULT_STEPS  # unbounded
    for typed in (7, 60_000):
        assert resolve_sampler(TrainConfig(steps=typed), box, ndc=True).steps == typed
    with pytest.raises(ValueError, match="steps must be positive, got 0"):
        TrainConfig(steps=0)


def test_forward_facing_scenes_get_no_direction_mlca_unless_asked():
    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    assert model_config("D", {}, box, "torch", ndc=False).mlca_directions  # Blender: 360 degrees of views
    assert model_config("D", {}, None, "torch", ndc=False).mlca_directions  # unbounded captures too
    assert not model_config("D", {}, box, "torch", ndc=True).mlca_directions  # LLFF in NDC
    assert model_config("D", {"mlca_directions": True}, box, "torch", ndc=True).mlca_directions


def test_distortion_weight_is_refused_for_samplers_other_than_proposal():
    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    for sampler in ("occupancy", "hierarchical"):
        with pytest.raises(ValueError, match=f"applies to the proposal sampler only.*{sampler}"):
            TrainConfig(sampler=sampler, distortion_weight=0.01)
    auto = TrainConfig(sampler="auto", distortion_weight=0.01)
    assert resolve_sampler(auto, box, ndc=True).distortion_weight == 0.01  # "auto" picks proposal in NDC
    with pytest.raises(ValueError, match="'auto' chose 'occupancy'"):  # only the scene decides "auto"
        resolve_sampler(auto, box, ndc=False)
    assert resolve_sampler(TrainConfig(sampler="occupancy"), box, ndc=False).distortion_weight == 0.0


def test_lr_warms_up_linearly_then_decays_exponentially(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, steps=100, lr=1e-3, lr_final=1e-4, lr_warmup=4, lr_hold=0.0), log=quiet)
    lr = lambda: trainer.optimizer.param_groups[0]["lr"]  # noqa: E731
    trainer.train_step()
    assert lr() == pytest.approx(1e-3 / 4)
    trainer.train_step()
    assert lr() == pytest.approx(1e-3 * 2 / 4 * 0.1 ** (1 / 100))
    for _ in range(3):
        trainer.train_step()
    assert lr() == pytest.approx(1e-3 * 0.1 ** (4 / 100))  # warm-up done


def test_lr_is_held_then_decays_by_steps_or_by_the_time_budget_whichever_is_further(tmp_path):
    cfg = tiny_config(tmp_path, steps=100, lr=1e-3, lr_final=1e-4, lr_warmup=0, lr_hold=0.5, time_budget=1000.0)
    trainer = Trainer(cfg, log=quiet)
    assert trainer.learning_rate() == 1e-3
    trainer.step = 75  # three quarters of the steps: half-way through the decay
    assert trainer.learning_rate() == pytest.approx(1e-3 * 0.1**0.5)
    trainer.step, trainer.clock.elapsed = 10, 900.0  # nine tenths of the budget
    assert trainer.learning_rate() == pytest.approx(1e-3 * 0.1**0.8)
    trainer.clock.elapsed = 5000.0
    assert trainer.learning_rate() == pytest.approx(1e-4)


def test_bf16_density_passes_decide_the_skipping_under_autocast(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, sampler="occupancy", bf16_density_passes=True), log=quiet)
    assert trainer.density_field.dtype == torch.bfloat16 and trainer.density_field.field is trainer.fields.coarse
    assert trainer.coarse_field.dtype is None  # the training pass keeps its precision
    for _ in range(4):  # past the grid's warm-up: refreshes and pre-passes in bf16
        losses = trainer.train_step()
    assert torch.isfinite(losses["loss"])
    assert trainer.marched_seen >= trainer.samples_seen > 0  # early termination only drops samples


@pytest.mark.parametrize("sampler", ["occupancy", "proposal", "hierarchical"])
def test_a_bf16_training_pass_updates_the_float32_master_weights(tmp_path, sampler):
    """--precision bf16: every step's MLP runs on bf16 copies, the optimiser on float32 weights that
    all move (the linear layers' gradients come back through the one multi-tensor cast)."""
    trainer = Trainer(tiny_config(tmp_path, sampler=sampler, precision="bf16"), log=quiet)
    before = {n: p.detach().clone() for n, p in trainer.fields.coarse.named_parameters()}
    for _ in range(3):
        losses = trainer.train_step()
    assert torch.isfinite(losses["loss"])
    for name, p in trainer.fields.coarse.named_parameters():
        assert p.dtype == torch.float32 and p.grad is not None and p.grad.dtype == torch.float32, name
        if ".weight" in name and "mixer" not in name and name != "head.weight":
            assert not torch.equal(p.detach(), before[name]), name  # (MLCA's mixing and head row 0 start at 0)


def test_empty_space_loss_lowers_density_only_in_cells_the_grid_marks_empty(tmp_path):
    """Past the grid's warm-up each batch carries random box points; the loss is their mean density
    in empty cells (times the box diagonal and the weight), and its gradient reaches the MLP."""
    trainer = Trainer(tiny_config(tmp_path, sampler="occupancy", empty_space_weight=0.5,
                                  empty_space_points=64), log=quiet)
    batch = trainer.batches.take(0)
    assert batch.empty_points is None  # warm-up: every cell occupied, nothing to push down
    trainer.batches.discard()
    for _ in range(trainer.cfg.grid_warmup + 1):
        trainer.train_step()
    grid = trainer.fields.grid
    grid.occupied = torch.arange(grid.num_cells).reshape(grid.resolution) % 2 == 0  # half the cells
    grid.update = lambda *args, **kwargs: False  # keep that grid through the refresh step
    trainer.batches.discard()
    step = trainer.step + trainer.step % 2  # the points come with the grid refreshes (every 2 here)
    assert trainer.batches.take(step + 1).empty_points is None
    batch = trainer.batches.take(step)
    cells = ((batch.empty_points - grid.aabb[0]) / (grid.aabb[1] - grid.aabb[0]) * grid.resolution[0]).long()
    flat = (cells[:, 0] * grid.resolution[1] + cells[:, 1]) * grid.resolution[2] + cells[:, 2]
    assert torch.equal(batch.empty_mask, flat % 2 == 1) and 0 < batch.empty_mask.sum() < 64
    losses = trainer._marched_losses(batch)
    sigma = trainer.fields.coarse.density(batch.empty_points)
    diagonal = float((grid.aabb[1] - grid.aabb[0]).norm())
    expected = 0.5 * diagonal * (sigma * batch.empty_mask).sum() / 64
    torch.testing.assert_close(losses["loss_empty"], expected)
    (grad,) = torch.autograd.grad(losses["loss_empty"], trainer.fields.coarse.head.weight)
    assert grad[0].abs().sum() > 0  # the density row learns from it


def test_a_discarded_prefetch_rewinds_the_rays_and_the_batch_size(tmp_path):
    """Checkpoints drop the batch prepared ahead: preparing it again draws the same rays."""
    trainer = Trainer(tiny_config(tmp_path, sampler="occupancy", grid_warmup=100), log=quiet)
    trainer.train_step()  # prefetches step 1's batch
    ahead = trainer.batches._next[1]
    rays_before = trainer.batches._next[2][1]
    trainer.batches.discard()
    assert trainer.sampler.batch_rays == rays_before
    again = trainer.batches.take(1)
    assert torch.equal(again.rays_o, ahead.rays_o) and torch.equal(again.samples.t_starts, ahead.samples.t_starts)


def test_a_step_counted_on_the_device_prefetches_the_batch_the_next_step_takes(tmp_path):
    """The graphed path's eager steps pass ``_learn`` a device step counter: the prefetch is still
    the next host step's, so the next take() uses it instead of preparing the batch again in line.
    A tensor step is refused by prefetch."""
    trainer = Trainer(tiny_config(tmp_path, sampler="occupancy", grid_warmup=100), log=quiet)
    prepared = []
    prepare = trainer.batches.prepare
    trainer.batches.prepare = lambda step: prepared.append(step) or prepare(step)
    counter = torch.tensor(0)  # as the trainer's: one tensor, counted up before each step's take()
    for _ in range(3):
        counter.add_(1)
        batch = trainer.batches.take(trainer.step)
        trainer._learn(trainer._marched_losses(batch), counter)
        trainer.step += 1
    assert prepared == [0, 1, 2, 3]
    with pytest.raises(TypeError, match="host's int"):
        trainer.batches.prefetch(torch.tensor(4))


class _OpaqueSlab(torch.nn.Module):
    """A density pre-pass that ends every ray soon after it enters x > 0."""

    def density(self, x: torch.Tensor) -> torch.Tensor:
        return 200.0 * (x[:, 0] > 0).float()


@pytest.mark.parametrize("backend", ["torch", "kernel"])
@pytest.mark.parametrize("room", ["spare", "cut"])
def test_fixed_marching_keeps_and_teaches_what_eager_marching_does(tmp_path, backend, room):
    """march_samples_fixed against march_samples on the same rays and random state, with a trained
    field and a pruned grid: the same samples (cut at the capacity), the counts on the device; in
    a batch padded to the capacity (a padding ray, the cut rays weighted out) the loss and the
    gradients are those of the eager batch's intact rays."""
    trainer = Trainer(tiny_config(tmp_path, sampler="occupancy", backend=backend, grid_warmup=2), log=quiet)
    for _ in range(4):  # past the warm-up: pruned cells and early termination leave rays ragged
        trainer.train_step()
    occupancy, generator, scene = trainer.occupancy, trainer.sampler.generator, trainer.train_scene
    rays_o, rays_d, target = trainer.sampler.sample(64)
    state = generator.get_state()
    options, slab = occupancy.marching, _OpaqueSlab()  # the young field drops nothing yet: the slab does
    eager = march_samples(rays_o, rays_d, occupancy.grid, scene.near, scene.far, options, density_field=slab,
                          generator=generator, backend=backend)
    generator.set_state(state)
    marched, kept = eager.num_marched, eager.samples.t_starts.shape[0]
    assert 0 < kept < marched
    rows = (marched + 50, kept + 20) if room == "spare" else (marched, kept // 2)
    fixed = march_samples_fixed(rays_o, rays_d, occupancy.grid, scene.near, scene.far, options, *rows,
                                density_field=slab, generator=generator, backend=backend)
    assert fixed.marched.total.tolist() == [marched] and fixed.samples.total.tolist() == [kept]
    first = min(kept, rows[1])
    for name in ("t_starts", "t_ends", "ray_indices"):
        assert getattr(fixed.samples.samples, name).shape == (rows[1],)
        assert torch.equal(getattr(fixed.samples.samples, name)[:first], getattr(eager.samples, name)[:first])
    intact = fixed.intact()
    assert bool(intact.all()) == (room == "spare") and intact.any()

    def loss_and_grads(loss):
        trainer.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        return [loss.detach()] + [p.grad.clone() for p in trainer.params]

    def shade(rays_o, rays_d, samples):
        return shade_samples(trainer.coarse_field, rays_o, rays_d, samples, trainer.background, backend)[0]

    plain = loss_and_grads(F.mse_loss(shade(rays_o, rays_d, eager.samples)[intact], target[intact]))
    weight = intact.float()
    pad = padding_rays(rows[1])
    batch = FixedBatch(*with_padding_rays(rays_o, rays_d, pad), torch.cat([target, target.new_zeros(pad, 3)]),
                       fixed.samples.with_padding_rays(), torch.cat([weight, weight.new_zeros(pad)]), None, None)
    padded = loss_and_grads(batch.mse(shade(batch.rays_o, batch.rays_d, batch.samples)))
    for name, a, b in zip(["loss", *trainer.param_names], plain, padded, strict=True):
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-7, msg=name)


def test_fixed_batches_use_num_rays_and_adapt_it_on_the_device(tmp_path):
    """Only the first num_rays rays get samples and count; the next batch's num_rays comes from
    this one's counts (the sample target, the marched buffer), and the counters add up."""
    trainer = Trainer(tiny_config(tmp_path, sampler="occupancy", grid_warmup=2), log=quiet)
    for _ in range(4):
        trainer.train_step()
    eager = trainer.batches.take(trainer.step)
    scene, target = trainer.train_scene, 3000
    trainer.occupancy.budget = SampleBudget(target)
    capacity = FixedCapacity.for_batch(eager, trainer.occupancy.budget)
    assert capacity.rays >= 2 * eager.rays_o.shape[0] and capacity.kept >= target
    batches = FixedBatches(trainer.sampler, trainer.occupancy, capacity, 3, scene.near, scene.far, 16, "torch")
    seen, kept_per_draw = torch.zeros(3, dtype=torch.int64), []
    for draw in range(8):
        num_rays = int(batches.num_rays)
        b = batches.draw(trainer.density_field, empty_space=draw == 0)
        R = capacity.rays
        P = padding_rays(capacity.kept)
        assert b.rays_o.shape == (R + P, 3) and b.samples.offsets.shape == (R + P + 1,)
        assert b.samples.t_starts.shape == (capacity.kept,) and int(b.samples.offsets[-1]) == capacity.kept
        per_ray = b.samples.offsets.diff()
        assert not per_ray[num_rays:R].any() and not b.ray_weight[num_rays:].any()
        assert b.ray_weight[:num_rays].sum() > 0
        kept = int(b.samples.offsets[R])
        kept_per_draw.append(kept)
        seen += torch.tensor([num_rays, kept, 0])
        assert (b.empty_points is None) == (draw != 0)
        want = min(math.floor(num_rays * target / max(kept, 1)), R)
        assert int(batches.num_rays) <= max(want, 1)
    assert batches.seen[:2].tolist() == seen[:2].tolist() and batches.seen[2] >= batches.seen[1]
    assert 0.5 * target <= sum(kept_per_draw[-4:]) / 4 and max(kept_per_draw) <= capacity.kept  # near the target
    trainer.occupancy.budget, trainer.sampler.batch_rays = None, 24  # no budget: the configured rays
    batches = FixedBatches(trainer.sampler, trainer.occupancy, FixedCapacity(64, 10**5, 10**4), 3, scene.near,
                           scene.far, 0, "torch")
    for _ in range(2):
        batches.draw(trainer.density_field, empty_space=False)
        assert int(batches.num_rays) == 24  # as the eager path draws them


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_cuda_batches_prepared_on_the_side_stream_train_as_those_prepared_in_line(tmp_path):
    """On CUDA the next batch is prepared on a side stream while the backward pass runs; the same
    run preparing every batch on the main stream must end with the same weights."""
    runs = []
    for side_stream in (True, False):
        trainer = Trainer(tiny_config(tmp_path / str(side_stream), sampler="occupancy", device="cuda",
                                      backend="auto", bf16_density_passes=True), log=quiet)
        if not side_stream:
            trainer.batches._stream = trainer.batches._weights_ready = None
        for _ in range(8):  # past the warm-up: grid refreshes, early termination, empty-space loss
            assert torch.isfinite(trainer.train_step()["loss"])
        runs.append((params_of(trainer), trainer.samples_seen, trainer.marched_seen))
    assert runs[0][1:] == runs[1][1:]
    for name, value in runs[0][0].items():
        torch.testing.assert_close(value, runs[1][0][name], rtol=1e-4, atol=1e-6, msg=name)


class _EagerGraphs:
    """GraphedSteps' interface, each step run eagerly: the replayed path's bookkeeping on a CPU."""

    def __init__(self, body, params, generator):
        self.body, self.captured = body, ()

    def __call__(self, kind):
        self.captured = tuple(dict.fromkeys((*self.captured, kind)))
        return self.body(kind)


def test_fixed_batches_grow_where_the_last_batch_wanted_more(tmp_path):
    """Rays grow when the target asked for more than the buffers hold, marched rows when they
    limited the batch; a batch that fits changes nothing."""
    trainer = Trainer(tiny_config(tmp_path, sampler="occupancy", grid_warmup=2), log=quiet)
    for _ in range(4):
        trainer.train_step()
    scene = trainer.train_scene
    for capacity, target in ((FixedCapacity(4, 10**5, 10**4), 5000), (FixedCapacity(256, 256, 10**4), 5000),
                             (FixedCapacity(256, 10**5, 10**4), 50)):
        trainer.occupancy.budget = SampleBudget(target, max_rays=1000)
        batches = FixedBatches(trainer.sampler, trainer.occupancy, capacity, 4, scene.near, scene.far, 0, "torch")
        for _ in range(3):
            batches.draw(trainer.density_field, empty_space=False)
        for_target, for_buffer = batches.wanted.tolist()
        assert batches.grow() == (capacity != batches.capacity)
        grown = batches.capacity
        assert grown.kept == capacity.kept and grown.rays >= capacity.rays and grown.marched >= capacity.marched
        assert (grown.rays > capacity.rays) == (for_target > 0.95 * capacity.rays)
        assert (grown.marched > capacity.marched) == (for_buffer < min(for_target, grown.rays))
        assert grown.rays <= 1000
    assert grown == capacity  # the last one fits


@pytest.mark.parametrize("preset", ["A", "D"])
def test_the_fixed_capacity_path_trains_and_checkpoints(tmp_path, monkeypatch, preset):
    """The bookkeeping of ``--cuda-graphs`` on the occupancy path with graphs stood in by eager
    calls: eager steps until twice the grid's warm-up, then fixed-capacity steps (refreshes a kind
    of their own), buffers grown, the counters the device kept, and a checkpoint that resumes
    eagerly from the batch size the device reached."""
    monkeypatch.setattr(trainer_module, "_why_not_graphable", lambda *_: None)
    monkeypatch.setattr(trainer_module, "GraphedSteps", _EagerGraphs)
    monkeypatch.setattr(trainer_module, "CAPACITY_CHECK_EVERY", 1)
    monkeypatch.setattr(fixed_batch, "RAY_ROOM", 1.0)  # too few rays for the target: the path grows them
    monkeypatch.setattr(fixed_batch, "ALIGN", 1)
    cfg = tiny_config(tmp_path, sampler="occupancy", empty_space_weight=0.5, empty_space_points=64,
                      target_samples=2048, cuda_graphs=True, grid_every=4, steps=20, preset=preset)
    said = []
    trainer = Trainer(cfg, log=said.append)
    for group in trainer.optimizer.param_groups:
        group["capturable"] = False  # Adam captures on GPUs only
    for step in range(12):
        assert torch.isfinite(trainer.train_step()["loss"])
        assert (trainer.fixed is None) == (step < 2 * cfg.grid_warmup)
    assert set(trainer.graphs.captured) <= {"fixed", "refresh"}
    sizes = [line for line in said if "batches of up to" in line]
    assert len(sizes) >= 2 and sizes[0].startswith(f"  step {2 * cfg.grid_warmup}:")  # the switch, then growth
    rays, samples = trainer.rays_seen, trainer.samples_seen
    assert not trainer.fixed.seen.any() and 0 < rays < samples <= trainer.marched_seen
    trainer.train_step()
    assert trainer.rays_seen > rays
    num_rays = int(trainer.fixed.num_rays)
    trainer.save()
    assert load_checkpoint(tmp_path / "checkpoint.pt")["progress"]["batch_rays"] == num_rays
    trainer._release_folder()  # as fit() does when it returns
    resumed = Trainer(cfg, resume=True, log=quiet)
    assert resumed.sampler.batch_rays == num_rays and resumed.rays_seen == trainer.rays_seen
    for group in resumed.optimizer.param_groups:
        group["capturable"] = False
    resumed.train_step()
    assert resumed.fixed is not None  # past the switch: the first step measures the capacities


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_cuda_fixed_capacity_steps_replay_without_a_sync(tmp_path, monkeypatch):
    """On a GPU the fixed-capacity steps (plain and grid refreshes) replay their graphs with no host
    sync at all (capacity checks excepted), grow their buffers into new graphs, and train: finite
    losses that fall as the eager run's do."""
    monkeypatch.setattr(trainer_module, "CAPACITY_CHECK_EVERY", 5)
    monkeypatch.setattr(fixed_batch, "RAY_ROOM", 1.0)
    monkeypatch.setattr(fixed_batch, "ALIGN", 1)
    losses, said = {}, []
    for graphs in (True, False):
        trainer = Trainer(tiny_config(tmp_path / str(graphs), sampler="occupancy", device="cuda", backend="auto",
                                      precision="fp32", bf16_density_passes=True, empty_space_weight=0.5,
                                      empty_space_points=64, cuda_graphs=graphs, grid_every=4), log=said.append)
        losses[graphs], replayed = [], set()
        for _ in range(60):
            kind = "refresh" if trainer.occupancy.is_refresh_step(trainer.step) else "fixed"
            replay = graphs and trainer.graphs is not None and kind in trainer.graphs.captured and trainer.step % 5
            if replay:
                replayed.add(kind)
            torch.cuda.set_sync_debug_mode("error" if replay else 0)
            try:
                losses[graphs].append(trainer.train_step()["mse"].clone())
            finally:
                torch.cuda.set_sync_debug_mode(0)
        if graphs:
            assert replayed == {"fixed", "refresh"} and trainer.rays_seen > 0
            assert len([line for line in said if "batches of up to" in line]) >= 2  # grown, captured again
    for run in losses.values():
        assert all(torch.isfinite(v) for v in run)
    late = {graphs: float(torch.stack(run[-10:]).mean()) for graphs, run in losses.items()}
    early = float(torch.stack(losses[True][:4]).mean())
    assert late[True] < early and late[True] < 2 * late[False], (early, late)


def _profile_tool():
    """tools/profile_train_step.py as a module (tools/ is no package)."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "tools" / "profile_train_step.py"
    spec = importlib.util.spec_from_file_location("profile_train_step", path)
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    return tool


def test_the_step_profile_names_where_each_kernel_was_launched():
    """profile_train_step's launch table: a forward op by its innermost mixer_nerf frame, a backward
    op by its autograd node, counted in kernels; host-only ops and device events left out."""
    from types import SimpleNamespace

    from torch.autograd import DeviceType

    def event(name, parent=None, kernels=0, device=DeviceType.CPU):
        return SimpleNamespace(name=name, cpu_parent=parent, kernels=[object()] * kernels, device_type=device)

    step = event("tools/profile_train_step.py(180): step")
    learn = event("mixer_nerf/train/trainer.py(383): _learn", step)
    shade = event("mixer_nerf/render/volume.py(58): shade_samples", learn)
    inner = event("torch/nn/functional.py(12): pad", shade)
    node = event("autograd::engine::evaluate_function: MmBackward0", event("run_backward", learn))
    events = [event("aten::fill_", inner, kernels=2), event("aten::fill_", inner, kernels=1),
              event("aten::mm", node, kernels=2), event("aten::empty", shade),
              event("aten::add", step, kernels=1),
              event("void kernel<float>", kernels=1, device=DeviceType.CUDA)]
    assert _profile_tool().launches_by_site(events) == {
        "render/volume.py(58): shade_samples  aten::fill_": 3, "backward: MmBackward0  aten::mm": 2,
        "(no mixer_nerf frame)  aten::add": 1}


def test_the_step_profile_sums_the_gpu_busy_time_and_idle_gaps():
    """profile_train_step's idle table: the gaps where no kernel runs on any stream (a kernel inside
    another's span leaves none), by the kernel that ended last and the one after, per step."""
    from types import SimpleNamespace

    from torch.autograd import DeviceType

    def kernel(name, start, end, device=DeviceType.CUDA):
        span = SimpleNamespace(start=start, end=end)
        return SimpleNamespace(name=name, time_range=span, device_type=device)

    gemm, mask = "void ns::gemm<float, 4>(float*)", "void ns::mask<float>(float*)"
    events = [kernel(gemm, 0, 10), kernel("inner(int)", 2, 5), kernel(mask, 11, 20),
              kernel("aten::mm", 0, 100, DeviceType.CPU), kernel(gemm, 80, 90), kernel(mask, 91, 95)]
    tool = _profile_tool()
    assert tool.active_time_us(events) == 10 + 9 + 10 + 4  # the union of the kernels' spans
    table = tool.idle_gaps(events, steps=2)
    assert table.startswith("GPU idle between kernels: 0.031 ms per step")  # (1 + 60 + 1) us / 2 steps
    assert "< 2 us 1.0 gaps 0.001 ms, 2-10 us 0.0 gaps 0.000 ms, 10-50 us 0.0 gaps 0.000 ms, " \
        ">= 50 us 0.5 gaps 0.030 ms" in table
    rows = [line.split() for line in table.splitlines()[2:]]
    assert rows[0] == ["mask", "->", "gemm", "0.030"] and rows[1] == ["gemm", "->", "mask", "0.001"], table


def test_the_step_profile_splits_a_steps_stream_time_by_events():
    """profile_train_step's event timeline: a step's span on the stream (first launch to last) and
    the stream's idle between steps, the medians over the steps (one step that captures a graph
    again does not move them), each step between its two events."""
    # steps of 5 ms but the third (a recapture: 60 ms), 0.5, 2 and 1 ms apart
    clock = iter([0.0, 5.0, 5.5, 10.5, 12.5, 72.5, 73.5, 78.5])
    calls = []

    class Event:
        def record(self):
            self.t = next(clock)

        def elapsed_time(self, other):
            return other.t - self.t

        def synchronize(self):
            calls.append("sync")

    span, between = _profile_tool().step_timeline_ms(lambda: calls.append("step"), 4, event=Event)
    assert (span, between) == (5.0, 1.0)
    assert calls == ["step"] * 4 + ["sync"]


def test_the_step_profile_times_the_batch_preparation(tmp_path):
    """tools/profile_train_step.py's host time in the occupancy path's batch preparation: a part of
    the step's time, measured on real steps, the trainer's prefetch left as it was."""
    import re

    tool = _profile_tool()
    trainer = Trainer(tiny_config(tmp_path, sampler="occupancy"), log=quiet)
    trainer.train_step()
    line = tool.preparation_time(trainer, 3)
    spent, total = (float(v) for v in re.findall(r"([0-9.]+) ms", line))
    assert 0 < spent <= total, line
    assert trainer.step == 4 and "prefetch" not in vars(trainer.batches)
    assert tool.preparation_time(Trainer(tiny_config(tmp_path / "h"), log=quiet), 1) == ""


def test_the_step_profile_times_the_median_window():
    """profile_train_step's wall time per step: the median of its windows, so one window with a rare
    slow step (a graph recaptured) does not set it; each window synchronised before and after."""
    tool = _profile_tool()
    calls, syncs = [], []

    def step():
        calls.append(None)
        time.sleep(0.05 if len(calls) == 2 else 0.002)  # the first window's second step is slow

    ms = tool.median_step_ms(step, lambda: syncs.append(len(calls)), steps=4)
    assert len(calls) == 12 and syncs == [0, 4, 4, 8, 8, 12]
    assert 2 <= ms < 10


def test_cuda_graphs_are_refused_on_a_cpu_before_training(tmp_path):
    with pytest.raises(ValueError, match="--cuda-graphs: it needs a CUDA device"):
        Trainer(tiny_config(tmp_path, sampler="proposal", cuda_graphs=True), log=quiet)


@pytest.mark.parametrize("sampler, several, images, reason", [
    ("hierarchical", False, "cuda", "only the proposal and occupancy samplers' steps can keep their shapes"),
    ("proposal", True, "cuda", "not with several processes"),
    ("proposal", False, "cpu", "the training images do not fit on the GPU")])
def test_cuda_graphs_refusals_name_their_reason(sampler, several, images, reason):
    """--cuda-graphs where a step cannot be replayed is refused, saying why; left unset it is off there."""
    from mixer_nerf.train.trainer import replays_steps

    cfg = TrainConfig(sampler=sampler, cuda_graphs=True)
    with pytest.raises(ValueError, match=reason):
        replays_steps(cfg, torch.device("cuda"), several, torch.device(images))
    unset = dataclasses.replace(cfg, cuda_graphs=None)
    graphs, why = replays_steps(unset, torch.device("cuda"), several, torch.device(images))
    assert graphs is False and reason in why


@pytest.mark.parametrize("sampler", ["proposal", "occupancy"])
def test_cuda_graphs_are_on_by_default_where_a_step_can_be_replayed(sampler):
    from mixer_nerf.train.trainer import replays_steps

    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    assert replays_steps(TrainConfig(sampler=sampler), cuda, False, cuda) == (True, None)
    assert replays_steps(TrainConfig(sampler=sampler, cuda_graphs=False), cuda, False, cuda) == (False, None)
    assert replays_steps(TrainConfig(sampler=sampler), cpu, False, cpu) == (False, "it needs a CUDA device")


def test_a_resumed_run_decides_cuda_graphs_anew(tmp_path):
    """The checkpoint records what the run did (graphs on or off); a resume decides again for its own
    machine and processes, unless told."""
    from mixer_nerf.train.trainer import resume_config

    saved = TrainConfig(sampler="proposal", cuda_graphs=True)
    assert resume_config(saved, TrainConfig(out=str(tmp_path)), "ckpt", 0).cuda_graphs is None
    told = TrainConfig(out=str(tmp_path), cuda_graphs=False)
    assert resume_config(saved, told, "ckpt", 0).cuda_graphs is False


def test_a_cpu_run_records_that_it_replayed_no_graphs(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, sampler="proposal", steps=1), log=quiet)
    assert trainer.cfg.cuda_graphs is False and trainer.graphs is None
    assert json.loads((tmp_path / "config.json").read_text())["train"]["cuda_graphs"] is False


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
@pytest.mark.parametrize("options", [{}, {"frequency_anneal": 1.0, "mlca_weight_decay": 50.0, "density_noise": 1.0}],
                         ids=["defaults", "window, decay and density noise"])
def test_cuda_graphed_proposal_steps_train_as_the_eager_ones(tmp_path, options):
    """Replays draw the same rays and samples as eager steps (the generator's offsets advance alike),
    so the two runs agree step by step, through a checkpoint and a resume; a frequency window that
    moves every step reaches the replays through its device buffer, the mixing's decay reads
    the replayed step's learning rate, and the density noise comes from the registered generator."""
    settings = dict(sampler="proposal", proposal_rounds=(12, 8), proposal_samples=6, device="cuda",
                    backend="auto", steps=12, ckpt_every=6, val_every=100, log_every=3, **options)
    losses = {}
    for graphs in (False, True):
        out = tmp_path / str(graphs)
        Trainer(tiny_config(out, cuda_graphs=graphs, **{**settings, "steps": 6}), log=quiet).fit()
        trainer = Trainer(tiny_config(out, cuda_graphs=graphs, **settings), resume=True, log=quiet)
        losses[graphs] = [float(trainer.train_step()["loss"]) for _ in range(6)]
        if graphs:
            assert trainer.graphs.captured == (True,)  # every step updates the proposal networks this early
            assert all(p.grad is not None for p in trainer.params)
        losses[graphs].append(params_of(trainer))
    *eager, eager_params = losses[False]
    *graphed, graphed_params = losses[True]
    torch.testing.assert_close(graphed, eager, rtol=1e-4, atol=1e-6)
    for name, value in eager_params.items():
        torch.testing.assert_close(graphed_params[name], value, rtol=1e-4, atol=1e-6, msg=name)


def test_existing_run_is_not_overwritten(tmp_path):
    Trainer(tiny_config(tmp_path, steps=1), log=quiet).fit()
    before = (tmp_path / "checkpoint.pt").read_bytes()
    with pytest.raises(OutputError, match="--resume"):
        Trainer(tiny_config(tmp_path, steps=1), log=quiet)
    assert (tmp_path / "checkpoint.pt").read_bytes() == before


def test_resume_from_a_corrupt_checkpoint_names_it_and_touches_nothing(tmp_path):
    Trainer(tiny_config(tmp_path, steps=1), log=quiet).fit()
    ckpt = tmp_path / "checkpoint.pt"
    ckpt.write_bytes(ckpt.read_bytes()[:200])
    snapshot = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(CheckpointError, match=str(ckpt)):
        Trainer(tiny_config(tmp_path), resume=True, log=quiet)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == snapshot


def test_unwritable_output_is_reported(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(OutputError, match="not writable"):
        Trainer(tiny_config(blocker / "run"), log=quiet)


def grad_norm(trainer: Trainer) -> float:
    """The global norm of the gradients the last step gave Adam (a step leaves them in place)."""
    grads = [p.grad for p in trainer.params if p.grad is not None]
    return float(torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads))))


def test_grad_clip_bounds_the_global_gradient_norm_without_host_reads(tmp_path):
    """The field's and the proposal networks' gradients together; clipping adds no ``.item()``."""
    runs = {}
    for clip in (None, 1e-3):
        trainer = Trainer(tiny_config(tmp_path / str(clip), sampler="proposal", proposal_rounds=(12, 8),
                                      proposal_samples=6, proposal_update_every=1, grad_clip=clip), log=quiet)
        with dispatched_ops() as ops:
            trainer.train_step()
        assert all(p.grad is not None for p in trainer.fields.proposal.parameters())
        runs[clip] = (grad_norm(trainer), ops["aten._local_scalar_dense"])
    assert runs[None][0] > 1e-2  # so 1e-3 clips
    assert 0 < runs[1e-3][0] <= 1e-3 * (1 + 1e-5)
    assert runs[1e-3][1] == runs[None][1]


def test_a_clipped_run_trains_and_keeps_its_clip_in_config_json_and_on_resume(tmp_path):
    import json

    proposal = dict(sampler="proposal", proposal_rounds=(12, 8), proposal_samples=6)
    summary = Trainer(tiny_config(tmp_path, grad_clip=0.5, **proposal), log=quiet).fit()
    assert summary["status"] == "finished" and summary["step"] == 6
    saved = json.loads((tmp_path / "config.json").read_text())["train"]
    assert saved["grad_clip"] == 0.5 and TrainConfig.from_dict(saved).grad_clip == 0.5
    resumed = Trainer(tiny_config(tmp_path, steps=8, **proposal), resume=True, log=quiet)
    assert resumed.cfg.grad_clip == 0.5  # not retyped: the run continues clipped


def test_a_checkpoint_from_before_grad_clip_resumes_unclipped(tmp_path):
    Trainer(tiny_config(tmp_path), log=quiet).save()
    path = tmp_path / "checkpoint.pt"
    state = load_checkpoint(path)
    del state["train_config"]["grad_clip"]
    save_checkpoint(path, state)
    resumed = Trainer(tiny_config(tmp_path), resume=True, log=quiet)
    assert resumed.cfg.grad_clip is None and resumed.step == 0


# -- non-finite guard -------------------------------------------------------------------------------


def test_guard_reports_first_bad_step_and_tensor():
    guard = NonFiniteGuard(["a.weight", "b.bias"], torch.device("cpu"))
    for step in (1, 2):
        guard.observe_losses(step, loss_coarse=torch.tensor(1.0), loss_fine=torch.tensor(1.0))
        guard.observe_grads(step, [torch.ones(2), torch.ones(1)])
    guard.observe_grads(2, [torch.ones(2), None])  # a parameter without a gradient is fine
    guard.raise_if_bad()
    guard.observe_losses(3, loss_coarse=torch.tensor(1.0), loss_fine=torch.tensor(math.inf))
    guard.observe_grads(3, [torch.ones(2), torch.tensor([math.nan])])
    guard.observe_losses(4, loss_coarse=torch.tensor(math.nan), loss_fine=torch.tensor(math.nan))
    with pytest.raises(NonFiniteError, match=r"step 3: loss_fine; gradient of b\.bias") as info:
        guard.raise_if_bad()
    assert info.value.step == 3


def test_guard_takes_the_step_from_a_device_counter_as_a_replayed_graph_gives_it():
    guard = NonFiniteGuard(["a.weight"], torch.device("cpu"))
    counter = torch.tensor(0)
    for loss in (1.0, 1.0, math.nan, math.nan):
        counter.add_(1)  # what a replay does: the step's number never passes through the host
        guard.observe_losses(counter, loss_coarse=torch.tensor(loss))
        guard.observe_grads(counter, [torch.tensor([loss])])
    with pytest.raises(NonFiniteError, match=r"step 3: loss_coarse; gradient of a\.weight"):
        guard.raise_if_bad()


def test_guard_dispatches_no_op_per_gradient():
    """One multi-tensor norm for all gradients: a model with more parameters costs no more ops."""
    counts = []
    for n in (2, 20):
        guard = NonFiniteGuard([f"p{i}" for i in range(n)], torch.device("cpu"))
        guard.observe_grads(1, [torch.ones(3)] * n)  # the first call also makes the guard's zero
        with dispatched_ops() as ops:
            guard.observe_grads(2, [torch.ones(3)] * n)
        counts.append(ops)
    assert counts[0] == counts[1], counts


def test_nan_stops_training_and_keeps_the_last_good_checkpoint(tmp_path, monkeypatch):
    trainer = Trainer(tiny_config(tmp_path, steps=10), log=quiet)
    real_step = Trainer.train_step

    def poisoned(self):
        if self.step == 4:  # the 5th step runs with a NaN weight
            with torch.no_grad():
                next(self.fields.coarse.parameters()).view(-1)[0] = math.nan
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", poisoned)
    with pytest.raises(NonFiniteError, match="step 5: loss_coarse") as info:
        trainer.fit()
    assert info.value.step == 5
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert state["step"] == 3
    assert all(torch.isfinite(v).all() for v in state["model"].values() if v.is_floating_point())
    import json

    assert json.loads((tmp_path / "summary.json").read_text())["status"].startswith("non-finite")


# -- logs -------------------------------------------------------------------------------------------


def test_csv_log_truncation_and_plot(tmp_path):
    log, val = CsvLog(tmp_path / "t.csv"), CsvLog(tmp_path / "v.csv")
    for step in range(1, 6):
        log.append({"step": step, "seconds": 0.5 * step, "loss": 1.0 / step, "psnr": 10.0 + step})
    val.append({"step": 3, "seconds": 1.5, "psnr": 12.0})
    log.truncate_after(3)
    assert [r["step"] for r in log.rows()] == ["1", "2", "3"]
    assert plot_curves(log, val, tmp_path / "p.png").stat().st_size > 0
    assert plot_curves(CsvLog(tmp_path / "none.csv"), val, tmp_path / "q.png") is None


# -- camera paths and videos ------------------------------------------------------------------------


def test_turntable_orbits_the_centre_looking_at_it():
    from mixer_nerf.data.procedural import orbit_poses
    from mixer_nerf.video import turntable_poses

    train = torch.from_numpy(orbit_poses(20, seed=0)).float()
    poses = turntable_poses(train, 12)
    eye = poses[:, :3, 3]
    radius = train[:, :3, 3].norm(dim=-1).mean()
    torch.testing.assert_close(eye.norm(dim=-1), radius.expand(12), rtol=1e-5, atol=1e-5)
    looking = -poses[:, :3, 2]  # cameras look down -z
    torch.testing.assert_close(looking, -eye / eye.norm(dim=-1, keepdim=True), rtol=1e-5, atol=1e-5)
    assert torch.allclose(eye[:, 2], eye[0, 2])  # constant elevation about world z (the mean up)
    rot = poses[:, :3, :3]
    torch.testing.assert_close(rot.transpose(1, 2) @ rot, torch.eye(3).expand(12, 3, 3), rtol=1e-5, atol=1e-5)


def test_spiral_looks_at_the_focus_point():
    from mixer_nerf.video import spiral_poses

    train = torch.eye(4).repeat(5, 1, 1)
    train[:, 0, 3] = torch.linspace(-0.2, 0.2, 5)
    train[:, 1, 3] = torch.linspace(0.1, -0.1, 5)
    poses = spiral_poses(train, 10, focus_depth=4.0)
    assert torch.isfinite(poses).all() and poses.shape == (10, 4, 4)
    to_focus = torch.tensor([0.0, 0.0, -4.0]) - poses[:, :3, 3]
    torch.testing.assert_close(-poses[:, :3, 2], to_focus / to_focus.norm(dim=-1, keepdim=True))


def test_write_video_reads_back():
    import tempfile

    import imageio.v3 as iio

    from mixer_nerf.video import write_video

    frames = [np.full((9, 13, 3), 40 * i, dtype=np.uint8) for i in range(4)]  # odd sizes on purpose
    with tempfile.TemporaryDirectory() as folder:
        path = write_video(f"{folder}/clip", frames, fps=5)
        assert path.suffix in (".mp4", ".gif") and path.stat().st_size > 0
        assert len(list(iio.imiter(path))) == 4


def test_proposal_networks_learn_only_at_their_update_steps(tmp_path):
    """``proposal_update_every``: a step that is not due trains the main field alone (the proposal
    networks get no gradient, so Adam leaves them); a due step trains both."""
    trainer = Trainer(tiny_config(tmp_path, sampler="proposal", proposal_rounds=(12, 8), proposal_samples=6,
                                  proposal_update_every=6), log=quiet)
    for step, due in ((1001, False), (1002, True)):
        trainer.step = step
        before = params_of(trainer)
        trainer.train_step()
        after = params_of(trainer)
        changed = {k for k in before if not torch.equal(before[k], after[k])}
        assert any(k.startswith("proposal.") for k in changed) == due, step
        assert any(not k.startswith("proposal.") for k in changed), step


def test_distortion_loss_trains_the_main_field_with_the_proposal_sampler(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, sampler="proposal", proposal_rounds=(12, 8), proposal_samples=6,
                                  distortion_weight=0.01, steps=3), log=quiet)
    seen = []
    observe = trainer.guard.observe_losses

    def record(step, **losses):
        seen.append({k: (v.detach().clone(), v.requires_grad) for k, v in losses.items()})
        observe(step, **losses)

    trainer.guard.observe_losses = record
    trainer.fit()
    assert len(seen) == 3
    for losses in seen:
        value, with_grad = losses["loss_distortion"]
        assert torch.isfinite(value) and value > 0 and with_grad
    fields = trainer.fields
    out, samples = render_rays_proposal(trainer.coarse_field, fields.proposal, *trainer.sampler.sample()[:2],
                                        trainer.train_scene.near, trainer.train_scene.far, backend="torch")
    assert out.weights.shape == (32, 6) and samples.edges.shape == (32, 7)  # matching (R, N), (R, N + 1)
    assert samples.edges.min() >= 0 and samples.edges.max() <= 1  # s, not t in [near, far] = [2, 6]
    assert json.loads((tmp_path / "config.json").read_text())["train"]["distortion_weight"] == 0.01


def test_occlusion_loss_joins_the_proposal_losses_and_is_refused_elsewhere(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, sampler="proposal", proposal_rounds=(12, 8), proposal_samples=6,
                                  occlusion_weight=0.1, occlusion_fraction=0.5), log=quiet)
    losses = trainer._proposal_losses(*trainer.sampler.sample(), update=True)
    assert losses["loss_occlusion"].requires_grad and 0 < float(losses["loss_occlusion"].detach()) <= 0.1
    for sampler in ("occupancy", "hierarchical"):
        with pytest.raises(ValueError, match="occlusion_weight applies to the proposal sampler only"):
            TrainConfig(sampler=sampler, occlusion_weight=0.1)


def test_proposal_runs_without_a_distortion_weight_have_no_distortion_loss(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, sampler="proposal", proposal_rounds=(12, 8), proposal_samples=6),
                      log=quiet)
    assert "loss_distortion" not in trainer._proposal_losses(*trainer.sampler.sample(), update=True)


def test_proposal_sampler_trains_its_networks_and_renders_from_the_checkpoint(tmp_path):
    # Per-sample jitter: in 6 steps on the tiny scene, the default per-ray offsets can leave the last
    # round's envelope above the untrained field's weights everywhere (a zero loss for its network).
    trainer = Trainer(tiny_config(tmp_path, sampler="proposal", proposal_rounds=(12, 8), proposal_samples=6,
                                  proposal_jitter="per_sample"), log=quiet)
    assert trainer.fields.fine is None and trainer.fields.grid is None
    before = params_of(trainer)
    assert any(k.startswith("proposal.") for k in before)
    trainer.fit()
    after = params_of(trainer)
    assert all(not torch.equal(before[k], after[k]) for k in before if k.startswith("proposal.") and "center" not in k)
    rows = trainer.train_log.rows()
    assert all(float(r["samples_per_ray"]) == 6 for r in rows)  # the main field's samples only
    run = load_trained(tmp_path / "checkpoint.pt")
    rays_o, rays_d = trainer.val_scene.rays_for_image(0)
    torch.testing.assert_close(run.render(rays_o, rays_d).color, trainer.render_rgb(rays_o, rays_d))


def test_proposal_residual_and_intervals_reach_the_sampler_and_train(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, sampler="proposal", proposal_rounds=(12, 8), proposal_samples=6,
                                  proposal_residual="last", proposal_intervals="between", steps=3), log=quiet)
    assert (trainer.fields.proposal.options.residual, trainer.fields.proposal.options.intervals) == ("last", "between")
    trainer.fit()
    assert all(math.isfinite(float(r["loss"])) for r in trainer.train_log.rows())


@pytest.mark.parametrize("sampler", ["hierarchical", "proposal"])
def test_density_noise_reaches_every_field_from_the_ray_sampler_and_spares_validation(tmp_path, sampler):
    trainer = Trainer(tiny_config(tmp_path, sampler=sampler, steps=4, density_noise=1.0), log=quiet)
    fields = trainer.fields.mlps()
    assert len(fields) == (2 if sampler == "hierarchical" else 1)
    assert all(f.density_noise == 1.0 and f.noise_generator is trainer.sampler.generator for f in fields)
    trainer.fit()
    assert all(math.isfinite(float(r["loss"])) for r in trainer.train_log.rows())
    assert trainer.validate() == trainer.validate()  # eval passes draw no noise


def test_frequency_anneal_opens_the_octaves_over_its_fraction_of_the_run(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, steps=8, frequency_anneal=0.5), log=quiet)
    fields = [f for f in (trainer.fields.coarse, trainer.fields.fine) if f is not None]
    octaves = trainer.model_cfg.pos_freqs
    windows = []
    for _ in range(6):
        trainer.train_step()
        windows.append([f.frequency_window for f in fields])
    # before step s the progress is s / 8: alpha = octaves * (s / 8) / 0.5, open from step 4 on
    assert windows[:4] == [[octaves * s / 4] * len(fields) for s in range(4)]
    assert windows[4:] == [[None] * len(fields)] * 2
    assert all(bool((f.octave_weights == 1).all()) for f in fields)


@pytest.mark.parametrize("sampler", ["hierarchical", "proposal"])
def test_mlca_weight_decay_scales_only_the_mixing_after_each_step(tmp_path, sampler):
    """Decoupled decay: the same step as without it, then MLCA's mixing matrices times 1 - lr * W."""
    decay = 100.0
    params, lrs = {}, {}
    for W in (0.0, decay):
        trainer = Trainer(tiny_config(tmp_path / str(W), sampler=sampler, lr_warmup=0, mlca_weight_decay=W),
                          log=quiet)
        lrs[W] = trainer.cfg.lr
        trainer.train_step()
        params[W] = params_of(trainer)
    mixing = [name for name in params[0.0] if name.endswith(("token_weight", "channel_weight"))]
    assert len(mixing) == 4 * (2 if sampler == "hierarchical" else 1)  # two mixers per MLP
    for name, value in params[0.0].items():
        want = value * (1 - lrs[decay] * decay) if name in mixing else value
        torch.testing.assert_close(params[decay][name], want, rtol=1e-6, atol=0, msg=name)
    assert all(params[0.0][name].abs().max() > 0 for name in mixing)  # the step moved them


def test_mlca_weight_decay_leaves_presets_without_mlca_alone_and_refuses_a_scale_below_zero(tmp_path):
    lines = []
    trainer = Trainer(tiny_config(tmp_path / "A", preset="A", mlca_weight_decay=10.0), log=lines.append)
    assert trainer.decayed == []
    assert any("--mlca-weight-decay does nothing in preset A" in line for line in lines)
    trainer.train_step()
    with pytest.raises(ValueError, match="mlca_weight_decay"):
        Trainer(tiny_config(tmp_path / "D", lr=1e-2, mlca_weight_decay=100.0), log=quiet)


def _as_default_llff(llff_scene: Path) -> Path:
    """The fixture's scene readable with the LLFF loader's default downscale (8)."""
    rows = np.load(llff_scene / "poses_bounds.npy")
    rows[:, [4, 9, 14]] *= 2  # full-resolution H, W, focal doubled: images_4/ reads as the default images_8/
    np.save(llff_scene / "poses_bounds.npy", rows)
    (llff_scene / "images_4").rename(llff_scene / "images_8")
    return llff_scene


def test_a_forward_facing_scene_trains_d_without_the_direction_mlca_and_says_so(llff_scene, tmp_path):
    lines = []
    trainer = Trainer(tiny_config(tmp_path, data=str(_as_default_llff(llff_scene)), steps=1), log=lines.append)
    assert trainer.train_scene.ndc and not trainer.model_cfg.mlca_directions
    assert isinstance(trainer.fields.coarse.direction_mixer, torch.nn.Identity)
    assert any("MLCA mixes PE(x) only" in line for line in lines)
    assert trainer.cfg.mlca_weight_decay == 0.0 and not any("--mlca-weight-decay" in line for line in lines)


def test_recipe_notes_name_the_regularisers_that_are_on():
    assert recipe_notes(TrainConfig()) == []
    notes = recipe_notes(TrainConfig(sampler="proposal", occlusion_weight=0.01, mlca_weight_decay=10.0))
    assert notes == ["occlusion loss 0.01 on the first 0.1 of each ray (--occlusion-weight)",
                     "MLCA's mixing decayed toward the identity, W = 10 (--mlca-weight-decay; presets C and D)"]


def test_val_holdout_trains_without_the_val_views_and_evaluates_on_them(llff_scene, tmp_path):
    from mixer_nerf.evaluate import evaluate

    _as_default_llff(llff_scene)
    trainer = Trainer(tiny_config(tmp_path, data=str(llff_scene), val_holdout=4, steps=3), log=quiet)
    names = lambda scene: [p.name for p in scene.image_paths]  # noqa: E731
    assert len(trainer.train_scene) == 6 and trainer.val_split == "val"
    assert not set(names(trainer.train_scene)) & {"img_001.png", "img_005.png", "img_000.png", "img_008.png"}
    trainer.fit()
    checkpoint = tmp_path / "checkpoint.pt"
    record = evaluate(checkpoint, split="val", out=tmp_path / "eval_val", lpips=False, log=quiet)
    assert [image["name"] for image in record["images"]] == ["img_001.png", "img_005.png"]
    record = evaluate(checkpoint, out=tmp_path / "eval_test", lpips=False, log=quiet)
    assert [image["name"] for image in record["images"]] == ["img_000.png", "img_008.png"]
    with pytest.raises(ValueError, match="val_holdout must be an integer >= 0"):
        tiny_config(tmp_path, val_holdout=-1)


def test_a_blender_val_holdout_trains_without_the_carved_views_and_reports_the_shipped_ones(tmp_path):
    """Lego's case: a scene with train and val views only. Validation uses every 4th training view,
    which training leaves out; the default eval scores the scene's own val views (tuned on by nothing)."""
    from capture_files import write_blender_scene
    from mixer_nerf.evaluate import evaluate

    root = write_blender_scene(tmp_path / "scene", train=9, val=2)
    trainer = Trainer(tiny_config(tmp_path / "run", data=str(root), val_holdout=4, steps=3), log=quiet)
    trained = {p.name for p in trainer.train_scene.image_paths}
    assert trainer.val_split == "val" and trained == {f"r_{k}.png" for k in (1, 2, 3, 5, 6, 7)}
    assert recipe_notes(trainer.cfg) == [
        "val views: 1 in 4 of the training views, left out of training (--val-holdout 4)"]
    trainer.fit()
    record = evaluate(tmp_path / "run" / "checkpoint.pt", lpips=False, log=quiet)
    assert record["summary"]["split"] == "test" and record["summary"]["images"] == 2  # the val folder's two
    record = evaluate(tmp_path / "run" / "checkpoint.pt", split="val", out=tmp_path / "carved", lpips=False,
                      log=quiet)
    assert [image["name"] for image in record["images"]] == ["r_0.png", "r_4.png", "r_8.png"]


def test_the_logged_gradient_norm_is_the_clipped_one(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, grad_clip=1e-4, steps=3), log=quiet)
    trainer.fit()
    assert all(0 < float(r["grad_norm"]) <= 1e-4 * (1 + 1e-5) for r in trainer.train_log.rows())


def test_a_log_from_an_earlier_version_keeps_its_columns(tmp_path):
    log = CsvLog(tmp_path / "train_log.csv")
    log.append({"step": 1, "loss": 0.5})
    log.append({"step": 2, "loss": 0.25, "grad_norm": 3.0})  # a column a later version added
    assert log.rows() == [{"step": "1", "loss": "0.5"}, {"step": "2", "loss": "0.25"}]
