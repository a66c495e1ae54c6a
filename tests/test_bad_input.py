"""Bad input everywhere: every public entry point fed wrong types, shapes, dtypes, devices and
values, broken scene folders and checkpoints, and the CLI pointed at missing or truncated files.

Each must fail with a clear error that names the argument or the file (never a crash deep inside a
kernel or an opaque torch message), and nothing on disk may be lost or overwritten. Device mixing is
tested with the ``meta`` device, which exists on every machine, and with CUDA where a GPU is there.
The per-op test files check their own argument validation in depth; this file sweeps every entry
point with one table and covers what lies between them (renderer, model, loaders, trainer, CLI).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from mixer_nerf import _extension
from mixer_nerf.cli import main as cli_main
from mixer_nerf.data import DatasetError, MissingFileError, load_scene
from mixer_nerf.data.blender import write_blender_split
from mixer_nerf.data.procedural import orbit_poses
from mixer_nerf.model import MixerNeRF, preset_config
from mixer_nerf.ops import (
    composite,
    composite_packed,
    hierarchical_samples,
    positional_encoding,
    ray_marching,
    ray_scale,
    sample_pdf,
    sample_pdf_packed,
    segment_mean,
)
from mixer_nerf.ops._checks import check_alike, check_shape
from mixer_nerf.render import render_image, render_rays
from mixer_nerf.train import CheckpointError, OutputError, TrainConfig, Trainer, load_checkpoint, load_trained

BACKENDS = ["torch"] + (["kernel"] if _extension.available() else [])
HAS_CUDA = torch.cuda.is_available()
META = torch.device("meta")


# ---------------------------------------------------------------------------------------------
# The ops: one table of (call with one thing wrong, error, regex the message must match)


def composite_args(**changes):
    R, S, C = 3, 4, 3
    args = {
        "sigmas": torch.rand(R, S),
        "rgbs": torch.rand(R, S, C),
        "t_starts": torch.arange(S, dtype=torch.float32).expand(R, S).contiguous(),
        "t_ends": torch.arange(1, S + 1, dtype=torch.float32).expand(R, S).contiguous(),
        "background": None,
    }
    return {**args, **changes}


def pdf_args(**changes):
    return {"bins": torch.linspace(0, 1, 6).expand(3, 6).contiguous(), "weights": torch.rand(3, 5), **changes}


def coarse_args(**changes):
    z = torch.linspace(2, 6, 8).expand(3, 8).contiguous()
    return {"z_coarse": z, "weights_coarse": torch.rand(3, 8), **changes}


def marching_args(**changes):
    grid = (torch.full((1,), 255, dtype=torch.uint8), torch.tensor([[-1.0] * 3, [1.0] * 3]), 2)
    rays_o = torch.tensor([[0.0, 0.0, -3.0]] * 2)
    rays_d = torch.tensor([[0.0, 0.0, 1.0]] * 2)
    return {
        "rays_o": rays_o,
        "rays_d": rays_d,
        "near": 0.0,
        "far": 10.0,
        "grid": grid,
        "step_size": 0.1,
        **changes,
    }


OFFSETS = torch.tensor([0, 2, 2, 5])  # 3 rays of 2, 0 and 3 rows


def packed_args(**changes):
    """composite_packed's inputs for OFFSETS."""
    args = {
        "sigmas": torch.rand(5),
        "rgbs": torch.rand(5, 3),
        "t_starts": torch.tensor([0.0, 1, 0, 1, 2]),
        "t_ends": torch.tensor([1.0, 2, 1, 2, 3]),
        "offsets": OFFSETS,
    }
    return {**args, **changes}


def packed_pdf_args(**changes):
    """sample_pdf_packed's inputs for OFFSETS: each ray has one more edge than bins."""
    return {
        "bins": torch.tensor([0.0, 1, 2, 5, 0, 1, 2, 3]),
        "weights": torch.rand(5),
        "offsets": OFFSETS,
        **changes,
    }


R3 = torch.rand(3, 4)
OP_CASES = {
    # composite
    "composite sigmas list": (
        lambda b: composite(**composite_args(sigmas=[[1.0]]), backend=b),
        TypeError,
        "sigmas",
    ),
    "composite sigmas numpy": (
        lambda b: composite(**composite_args(sigmas=np.ones((3, 4), np.float32)), backend=b),
        TypeError,
        "sigmas",
    ),
    "composite int rgbs": (
        lambda b: composite(**composite_args(rgbs=torch.ones(3, 4, 3, dtype=torch.int32)), backend=b),
        TypeError,
        "rgbs",
    ),
    "composite 1-d sigmas": (
        lambda b: composite(**composite_args(sigmas=torch.rand(12)), backend=b),
        ValueError,
        "sigmas",
    ),
    "composite short t_ends": (
        lambda b: composite(**composite_args(t_ends=torch.rand(3, 3)), backend=b),
        ValueError,
        "t_ends",
    ),
    "composite float64 t_starts": (
        lambda b: composite(**composite_args(t_starts=R3.double()), backend=b),
        TypeError,
        "t_starts is torch.float64",
    ),
    "composite meta rgbs": (
        lambda b: composite(**composite_args(rgbs=torch.rand(3, 4, 3, device=META)), backend=b),
        ValueError,
        "rgbs on meta",
    ),
    "composite negative density": (
        lambda b: composite(**composite_args(sigmas=-torch.rand(3, 4)), backend=b),
        ValueError,
        "sigmas must be non-negative",
    ),
    "composite reversed interval": (
        lambda b: composite(**composite_args(t_ends=torch.zeros(3, 4) - 1), backend=b),
        ValueError,
        "t_ends must be >= t_starts",
    ),
    "composite background (R+1, C)": (
        lambda b: composite(**composite_args(background=torch.rand(4, 3)), backend=b),
        ValueError,
        "background",
    ),
    "composite background on meta": (
        lambda b: composite(**composite_args(background=torch.rand(3, device=META)), backend=b),
        ValueError,
        "background on meta",
    ),
    "composite bad backend": (lambda b: composite(**composite_args(), backend="cuda"), ValueError, "backend"),
    # composite_packed
    "composite_packed int32 offsets": (
        lambda b: composite_packed(**packed_args(offsets=OFFSETS.int()), backend=b),
        TypeError,
        "offsets must be an int64",
    ),
    "composite_packed offsets short of N": (
        lambda b: composite_packed(**packed_args(offsets=torch.tensor([0, 2, 4])), backend=b),
        ValueError,
        "offsets must start at 0 and end at 5",
    ),
    "composite_packed decreasing offsets": (
        lambda b: composite_packed(**packed_args(offsets=torch.tensor([0, 3, 2, 5])), backend=b),
        ValueError,
        "offsets must be non-decreasing",
    ),
    "composite_packed (N, 1) sigmas": (
        lambda b: composite_packed(**packed_args(sigmas=torch.rand(5, 1)), backend=b),
        ValueError,
        "sigmas",
    ),
    "composite_packed negative density": (
        lambda b: composite_packed(**packed_args(sigmas=-torch.rand(5)), backend=b),
        ValueError,
        "sigmas must be non-negative",
    ),
    "composite_packed offsets on meta": (
        lambda b: composite_packed(**packed_args(offsets=OFFSETS.to(META)), backend=b),
        ValueError,
        "offsets on meta",
    ),
    "composite_packed background (R+1, C)": (
        lambda b: composite_packed(**packed_args(background=torch.rand(4, 3)), backend=b),
        ValueError,
        "background",
    ),
    # sample_pdf_packed
    "sample_pdf_packed unsorted ray": (
        lambda b: sample_pdf_packed(
            **packed_pdf_args(bins=torch.tensor([0.0, 2, 1, 5, 0, 1, 2, 3])), num_samples=4, backend=b
        ),
        ValueError,
        "bins must be sorted",
    ),
    "sample_pdf_packed one edge short": (
        lambda b: sample_pdf_packed(
            **packed_pdf_args(bins=torch.tensor([0.0, 1, 2, 5, 0, 1, 2])), num_samples=4, backend=b
        ),
        ValueError,
        "bins must have shape",
    ),
    "sample_pdf_packed float offsets": (
        lambda b: sample_pdf_packed(**packed_pdf_args(offsets=OFFSETS.float()), num_samples=4, backend=b),
        TypeError,
        "offsets",
    ),
    "sample_pdf_packed offsets past N": (
        lambda b: sample_pdf_packed(**packed_pdf_args(offsets=OFFSETS + 1), num_samples=4, backend=b),
        ValueError,
        "offsets must start at 0",
    ),
    "sample_pdf_packed negative weights": (
        lambda b: sample_pdf_packed(**packed_pdf_args(weights=-torch.rand(5)), num_samples=4, backend=b),
        ValueError,
        "weights must be non-negative",
    ),
    # sample_pdf
    "sample_pdf unsorted bins": (
        lambda b: sample_pdf(
            **pdf_args(bins=torch.rand(3, 6) + torch.tensor([0, 0, 0, 2.0, 1.0, 3.0])),
            num_samples=4,
            backend=b,
        ),
        ValueError,
        "bins must be sorted",
    ),
    "sample_pdf negative weights": (
        lambda b: sample_pdf(**pdf_args(weights=-torch.rand(3, 5)), num_samples=4, backend=b),
        ValueError,
        "weights must be non-negative",
    ),
    "sample_pdf weights (R, B+1)": (
        lambda b: sample_pdf(**pdf_args(weights=torch.rand(3, 6)), num_samples=4, backend=b),
        ValueError,
        "weights",
    ),
    "sample_pdf int bins": (
        lambda b: sample_pdf(**pdf_args(bins=torch.arange(6).expand(3, 6)), num_samples=4, backend=b),
        TypeError,
        "bins",
    ),
    "sample_pdf weights on meta": (
        lambda b: sample_pdf(**pdf_args(weights=torch.rand(3, 5, device=META)), num_samples=4, backend=b),
        ValueError,
        "weights on meta",
    ),
    "sample_pdf negative num_samples": (
        lambda b: sample_pdf(**pdf_args(), num_samples=-1, backend=b),
        ValueError,
        "num_samples",
    ),
    "sample_pdf float num_samples": (
        lambda b: sample_pdf(**pdf_args(), num_samples=4.0, backend=b),
        TypeError,
        "num_samples",
    ),
    "sample_pdf u above 1": (
        lambda b: sample_pdf(**pdf_args(), num_samples=2, u=torch.tensor([0.5, 1.5]), backend=b),
        ValueError,
        "u must lie in",
    ),
    "sample_pdf NaN u": (
        lambda b: sample_pdf(**pdf_args(), num_samples=2, u=torch.tensor([0.5, float("nan")]), backend=b),
        ValueError,
        "u must lie in",
    ),
    "sample_pdf unsorted u": (
        lambda b: sample_pdf(**pdf_args(), num_samples=2, u=torch.tensor([0.6, 0.5]), backend=b),
        ValueError,
        "u must be sorted",
    ),
    "sample_pdf u on meta": (
        lambda b: sample_pdf(**pdf_args(), num_samples=2, u=torch.rand(2, device=META), backend=b),
        ValueError,
        "u on meta",
    ),
    "sample_pdf NaN weight_padding": (
        lambda b: sample_pdf(**pdf_args(), num_samples=2, weight_padding=float("nan"), backend=b),
        ValueError,
        "weight_padding",
    ),
    # hierarchical_samples
    "hierarchical 2 coarse samples": (
        lambda b: hierarchical_samples(
            **coarse_args(z_coarse=torch.rand(3, 2), weights_coarse=torch.rand(3, 2)), num_fine=4, backend=b
        ),
        ValueError,
        "z_coarse",
    ),
    "hierarchical unsorted z": (
        lambda b: hierarchical_samples(
            **coarse_args(z_coarse=torch.linspace(6, 2, 8).expand(3, 8)), num_fine=4, backend=b
        ),
        ValueError,
        "z_coarse must be sorted",
    ),
    "hierarchical negative weights": (
        lambda b: hierarchical_samples(
            **coarse_args(weights_coarse=-torch.rand(3, 8)), num_fine=4, backend=b
        ),
        ValueError,
        "weights_coarse must be non-negative",
    ),
    "hierarchical half weights": (
        lambda b: hierarchical_samples(
            **coarse_args(weights_coarse=torch.rand(3, 8).half()), num_fine=4, backend=b
        ),
        TypeError,
        "weights_coarse is torch.float16",
    ),
    "hierarchical num_fine True": (
        lambda b: hierarchical_samples(**coarse_args(), num_fine=True, backend=b),
        TypeError,
        "num_fine",
    ),
    # positional_encoding
    "encoding int x": (
        lambda b: positional_encoding(torch.ones(4, 3, dtype=torch.int64), 4, backend=b),
        TypeError,
        "x must",
    ),
    "encoding 0-d x": (lambda b: positional_encoding(torch.tensor(1.0), 4, backend=b), ValueError, "x must"),
    "encoding D = 0": (lambda b: positional_encoding(torch.ones(4, 0), 4, backend=b), ValueError, "x must"),
    "encoding 65 octaves": (
        lambda b: positional_encoding(torch.ones(4, 3), 65, backend=b),
        ValueError,
        "num_freqs",
    ),
    "encoding negative octaves": (
        lambda b: positional_encoding(torch.ones(4, 3), -1, backend=b),
        ValueError,
        "num_freqs",
    ),
    "encoding float octaves": (
        lambda b: positional_encoding(torch.ones(4, 3), 2.0, backend=b),
        TypeError,
        "num_freqs",
    ),
    "encoding infinite scale": (
        lambda b: positional_encoding(torch.ones(4, 3), 2, scale=float("inf"), backend=b),
        ValueError,
        "scale",
    ),
    "encoding include_input str": (
        lambda b: positional_encoding(torch.ones(4, 3), 2, include_input="yes", backend=b),
        TypeError,
        "include_input",
    ),
    # segment_mean, ray_scale: rows (5, 3) of the rays of OFFSETS
    "segment_mean int values": (
        lambda b: segment_mean(torch.ones(5, 3, dtype=torch.int64), OFFSETS, backend=b),
        TypeError,
        "values must",
    ),
    "segment_mean rows beyond offsets": (
        lambda b: segment_mean(torch.rand(6, 3), OFFSETS, backend=b),
        ValueError,
        "offsets must start at 0 and end at 6",
    ),
    "ray_scale float64 scale": (
        lambda b: ray_scale(torch.rand(5, 3), torch.rand(3, 3).double(), OFFSETS, backend=b),
        TypeError,
        "scale is torch.float64",
    ),
    "ray_scale scale (R+1, C)": (
        lambda b: ray_scale(torch.rand(5, 3), torch.rand(4, 3), OFFSETS, backend=b),
        ValueError,
        "scale must have shape",
    ),
    "ray_scale scale on meta": (
        lambda b: ray_scale(torch.rand(5, 3), torch.rand(3, 3, device=META), OFFSETS, backend=b),
        ValueError,
        "scale on meta",
    ),
    # ray_marching
    "marching rays_o (R, 2)": (
        lambda b: ray_marching(**marching_args(rays_o=torch.zeros(2, 2)), backend=b),
        ValueError,
        "rays_o",
    ),
    "marching rays_d (R+1, 3)": (
        lambda b: ray_marching(**marching_args(rays_d=torch.ones(3, 3)), backend=b),
        ValueError,
        "rays_d",
    ),
    "marching int rays_d": (
        lambda b: ray_marching(**marching_args(rays_d=torch.ones(2, 3, dtype=torch.int32)), backend=b),
        TypeError,
        "rays_d",
    ),
    "marching rays_d on meta": (
        lambda b: ray_marching(**marching_args(rays_d=torch.ones(2, 3, device=META)), backend=b),
        ValueError,
        "rays_d on meta",
    ),
    "marching zero step": (
        lambda b: ray_marching(**marching_args(step_size=0.0), backend=b),
        ValueError,
        "step_size",
    ),
}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", OP_CASES)
def test_ops_reject_bad_input_naming_the_argument(case, backend):
    call, error, message = OP_CASES[case]
    with pytest.raises(error, match=message):
        call(backend)


def test_shared_checks_keep_their_messages_on_the_quick_path():
    a, b = torch.rand(2), torch.rand(2, 3)
    assert check_alike(a=a, gone=None, b=b) == (a.device, a.dtype)
    with pytest.raises(ValueError, match="a on cpu, b on meta"):  # the device is reported first
        check_alike(a=a, b=torch.rand(2, device=META, dtype=torch.float64))
    with pytest.raises(TypeError, match="a is torch.float32, gone is torch.float64"):
        check_alike(a=a, gone=a.double(), b=b)
    check_shape("b", b, (2, None))
    with pytest.raises(ValueError, match=r"b must have shape \(3, \*\), got \(2, 3\)"):
        check_shape("b", b, (3, None))


@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA GPU")
@pytest.mark.cuda
@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_ops_reject_cpu_cuda_mixes(backend):
    cuda = torch.device("cuda")
    with pytest.raises(ValueError, match="rgbs on cuda"):
        composite(**composite_args(rgbs=torch.rand(3, 4, 3, device=cuda)), backend=backend)
    with pytest.raises(ValueError, match="weights on cuda"):
        sample_pdf(**pdf_args(weights=torch.rand(3, 5, device=cuda)), num_samples=4, backend=backend)
    with pytest.raises(ValueError, match="weights_coarse on cuda"):
        hierarchical_samples(
            **coarse_args(weights_coarse=torch.rand(3, 8, device=cuda)), num_fine=4, backend=backend
        )
    with pytest.raises(ValueError, match="rays_d on cuda"):
        ray_marching(**marching_args(rays_d=torch.ones(2, 3, device=cuda)), backend=backend)
    with pytest.raises(ValueError, match="offsets on cpu"):
        segment_mean(torch.rand(5, 3, device=cuda), OFFSETS, backend=backend)
    with pytest.raises(ValueError, match="scale on cuda"):
        ray_scale(torch.rand(5, 3), torch.rand(3, 3, device=cuda), OFFSETS, backend=backend)
    field = ConstantField()
    with pytest.raises(ValueError, match="rays_d on cuda"):
        render_rays(field, torch.zeros(2, 3), torch.ones(2, 3, device=cuda), 2.0, 6.0, backend=backend)


# ---------------------------------------------------------------------------------------------
# The renderer


class ConstantField(nn.Module):
    """sigma = density everywhere (negative to break the contract), grey colour."""

    def __init__(self, density: float = 1.0) -> None:
        super().__init__()
        self.density = density

    def forward(self, x, d):
        return torch.full(x.shape[:-1], self.density, dtype=x.dtype), torch.full_like(x, 0.5)


RAYS_O = torch.zeros(4, 3)
RAYS_D = torch.tensor([[0.0, 0.0, 1.0]] * 4)
RENDER_CASES = {
    "rays_o list": ({"rays_o": [[0.0, 0.0, 0.0]] * 4}, TypeError, "rays_o"),
    "rays_o (R, 2)": ({"rays_o": torch.zeros(4, 2)}, ValueError, "rays_o"),
    "rays_d (R-1, 3)": ({"rays_d": torch.ones(3, 3)}, ValueError, "rays_d"),
    "int rays_d": ({"rays_d": torch.ones(4, 3, dtype=torch.int64)}, TypeError, "rays_d"),
    "float64 rays_d": ({"rays_d": RAYS_D.double()}, TypeError, "rays_d"),
    "rays_o on meta": ({"rays_o": torch.zeros(4, 3, device=META)}, ValueError, "rays_o on meta"),
    "near on meta": ({"near": torch.full((4,), 2.0, device=META)}, ValueError, "near on meta"),
    "background on meta": ({"background": torch.ones(3, device=META)}, ValueError, "background on meta"),
    "near > far": ({"near": 6.0, "far": 2.0}, ValueError, "near must be <= far"),
    "NaN near": ({"near": float("nan")}, TypeError, "near"),
    "near string": ({"near": "2"}, TypeError, "near"),
    "far (R+1,)": ({"far": torch.full((5,), 6.0)}, ValueError, "far"),
    "zero coarse samples": ({"num_coarse": 0}, ValueError, "num_coarse"),
    "2 coarse samples with a fine pass": ({"num_coarse": 2, "num_fine": 4}, ValueError, "num_coarse"),
    "negative fine samples": ({"num_fine": -1}, ValueError, "num_fine"),
    "background (4,)": ({"background": torch.ones(4)}, ValueError, "background"),
    "lindisp from 0": ({"near": 0.0, "lindisp": True}, ValueError, "lindisp"),
    "bad backend": ({"backend": "gpu"}, ValueError, "backend"),
}


@pytest.mark.parametrize("case", RENDER_CASES)
def test_render_rays_rejects_bad_input_naming_the_argument(case):
    changes, error, message = RENDER_CASES[case]
    kwargs = {
        "rays_o": RAYS_O,
        "rays_d": RAYS_D,
        "near": 2.0,
        "far": 6.0,
        "num_coarse": 8,
        "num_fine": 8,
        **changes,
    }
    with pytest.raises(error, match=message):
        render_rays(ConstantField(), **kwargs)


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        ({"chunk": 0}, ValueError, "chunk"),
        ({"rays_d": torch.ones(4, 4)}, ValueError, "rays_d"),
        ({"near": torch.full((5,), 2.0)}, ValueError, "near"),
    ],
)
def test_render_image_rejects_bad_input(kwargs, error, message):
    args = {"rays_o": RAYS_O, "rays_d": RAYS_D, "near": 2.0, "far": 6.0, **kwargs}
    with pytest.raises(error, match=message):
        render_image(ConstantField(), **args)


def test_render_rays_rejects_per_ray_near_beyond_far():
    with pytest.raises(ValueError, match="near"):
        render_rays(ConstantField(), RAYS_O, RAYS_D, torch.full((4,), 6.0), torch.full((4,), 2.0), 8, 0)


def test_render_rays_rejects_a_field_that_is_not_callable():
    with pytest.raises(TypeError, match="field"):
        render_rays(None, RAYS_O, RAYS_D, 2.0, 6.0)


def test_render_rays_checks_field_densities_unless_told_not_to():
    """A field breaking the sigma >= 0 contract is named (one reduction per pass); check_field=False
    skips that GPU sync and gets meaningless (negative) opacities instead."""
    with pytest.raises(ValueError, match="field ConstantField returned a negative density"):
        render_rays(ConstantField(density=-1.0), RAYS_O, RAYS_D, 2.0, 6.0, num_coarse=8, num_fine=0)
    out = render_rays(ConstantField(density=-1.0), RAYS_O, RAYS_D, 2.0, 6.0, num_coarse=8, num_fine=0,
                      check_field=False)
    assert (out.final.opacity < 0).all()


# ---------------------------------------------------------------------------------------------
# The model


@pytest.fixture(scope="module")
def model():
    return MixerNeRF(preset_config("D", width=32, depth=2, skips=(), view_width=16, pos_freqs=2, dir_freqs=1))


MODEL_CASES = {
    "x list": ([[0.0, 0.0, 0.0]], torch.zeros(1, 3), TypeError, "x must"),
    "x (R, S, 2)": (torch.zeros(2, 4, 2), torch.zeros(2, 1, 3), ValueError, "x must"),
    "d (R, S, 2)": (torch.zeros(2, 4, 3), torch.zeros(2, 4, 2), ValueError, "d must"),
    "int d": (torch.zeros(2, 4, 3), torch.zeros(2, 1, 3, dtype=torch.int64), TypeError, "d must"),
    "d on meta": (torch.zeros(2, 4, 3), torch.zeros(2, 1, 3, device=META), ValueError, "d on meta"),
}


@pytest.mark.parametrize("case", MODEL_CASES)
def test_model_forward_rejects_bad_input_naming_the_argument(model, case):
    x, d, error, message = MODEL_CASES[case]
    with pytest.raises(error, match=message):
        model(x, d)


def test_model_forward_names_x_when_its_dtype_differs_from_the_model(model):
    with pytest.raises(TypeError, match="x"):
        model(torch.zeros(2, 4, 3, dtype=torch.float64), torch.zeros(2, 1, 3, dtype=torch.float64))


def test_model_forward_names_x_when_its_device_differs_from_the_model(model):
    with pytest.raises(ValueError, match="x"):
        model(torch.zeros(2, 4, 3, device=META), torch.zeros(2, 1, 3, device=META))


# ---------------------------------------------------------------------------------------------
# Scenes on disk: load_scene on empty, truncated and corrupt datasets (test_data.py covers the
# loaders' JSON/pose breakages one by one; these are whole-scene and file-level corruptions)


def truncate(path: Path, fraction: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])


SCENE_BREAKAGES = {
    "missing folder": (lambda r: r.rename(r.with_name("gone")), MissingFileError, "scene folder not found"),
    "empty folder": (
        lambda r: [p.unlink() for p in r.rglob("*") if p.is_file()],
        DatasetError,
        "unknown scene format",
    ),
    "no frames": (
        lambda r: (r / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []})),
        DatasetError,
        r"transforms_train\.json.*empty",
    ),
    "truncated JSON": (
        lambda r: truncate(r / "transforms_train.json"),
        DatasetError,
        r"transforms_train\.json",
    ),
    "truncated PNG": (lambda r: truncate(r / "train" / "r_1.png"), DatasetError, r"r_1\.png"),
    "zero-byte PNG": (lambda r: (r / "train" / "r_0.png").write_bytes(b""), DatasetError, r"r_0\.png"),
    "folder instead of image": (
        lambda r: ((r / "train" / "r_2.png").unlink(), (r / "train" / "r_2.png").mkdir()),
        DatasetError,
        r"r_2\.png",
    ),
}


@pytest.mark.parametrize("breakage", SCENE_BREAKAGES)
def test_load_scene_names_the_broken_file(blender_scene, breakage):
    breaker, error, message = SCENE_BREAKAGES[breakage]
    breaker(blender_scene)
    with pytest.raises(error, match=message):
        load_scene(blender_scene)


@pytest.mark.parametrize(
    "breakage, message",
    [
        (lambda r: truncate(r / "poses_bounds.npy"), r"poses_bounds\.npy"),
        (lambda r: [p.unlink() for p in (r / "images_4").iterdir()], r"images_4"),
        (lambda r: truncate(r / "images_4" / "img_004.png", 0.3), r"img_004\.png"),
    ],
    ids=["truncated poses", "no images", "truncated image"],
)
def test_load_scene_llff_names_the_broken_file(llff_scene, breakage, message):
    breakage(llff_scene)
    with pytest.raises(DatasetError, match=message):
        load_scene(llff_scene, factor=4)


def test_load_scene_rejects_unknown_format_and_split(blender_scene):
    with pytest.raises(ValueError, match="format"):
        load_scene(blender_scene, format="mesh")
    with pytest.raises(MissingFileError, match=r"transforms_nope\.json"):
        load_scene(blender_scene, split="nope")


# ---------------------------------------------------------------------------------------------
# Checkpoints and the trainer


def tiny_train_config(data: Path, out: Path, **changes) -> TrainConfig:
    settings = {
        "data": str(data),
        "out": str(out),
        "steps": 2,
        "batch_rays": 16,
        "num_coarse": 4,
        "num_fine": 4,
        "preset": "A",
        "model_overrides": {
            "depth": 2,
            "width": 16,
            "skips": (),
            "view_width": 8,
            "pos_freqs": 2,
            "dir_freqs": 1,
        },
        "val_every": 2,
        "val_images": 1,
        "ckpt_every": 2,
        "log_every": 1,
        "progress": False,
        "device": "cpu",
    }
    return TrainConfig(**{**settings, **changes})


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """(scene folder, run folder) of a 2-step training run on a tiny Blender scene (seconds)."""
    root = tmp_path_factory.mktemp("trained")
    scene = root / "scene"
    rng = np.random.default_rng(0)
    for seed, (split, n) in enumerate((("train", 3), ("test", 2))):
        write_blender_split(scene, split, rng.uniform(size=(n, 8, 8, 4)), orbit_poses(n, seed), 0.69)
    Trainer(tiny_train_config(scene, root / "run"), log=lambda _: None).fit()
    return scene, root / "run"


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def broken_copies(checkpoint: Path, folder: Path) -> dict[str, Path]:
    """Truncated, empty, garbage, foreign and wrong-version versions of a real checkpoint."""
    folder.mkdir(parents=True, exist_ok=True)
    data = checkpoint.read_bytes()
    state = torch.load(checkpoint, weights_only=True)
    files = {
        "truncated": data[: len(data) // 2],
        "one byte short": data[:-1],
        "empty": b"",
        "garbage": b"\x00not a checkpoint" * 10,
    }
    paths = {}
    for name, content in files.items():
        paths[name] = folder / f"{name.replace(' ', '_')}.pt"
        paths[name].write_bytes(content)
    for name, value in (("foreign", {"weights": torch.zeros(2)}), ("version 99", {**state, "version": 99})):
        paths[name] = folder / f"{name.replace(' ', '_')}.pt"
        torch.save(value, paths[name])
    return paths


BROKEN_MESSAGES = {
    "truncated": "not a readable checkpoint",
    "one byte short": "not a readable checkpoint",
    "empty": "not a readable checkpoint",
    "garbage": "not a readable checkpoint",
    "foreign": "not a mixer_nerf checkpoint",
    "version 99": "version 99 is not supported",
}


@pytest.mark.parametrize("kind", BROKEN_MESSAGES)
def test_broken_checkpoints_raise_checkpoint_error_naming_the_file(trained, tmp_path, kind):
    path = broken_copies(trained[1] / "checkpoint.pt", tmp_path)[kind]
    for load in (load_checkpoint, load_trained):
        with pytest.raises(CheckpointError, match=BROKEN_MESSAGES[kind]) as info:
            load(path)
        assert str(path) in str(info.value)


def test_checkpoint_with_mismatched_weights_names_the_file(trained, tmp_path):
    state = torch.load(trained[1] / "checkpoint.pt", weights_only=True)
    name = next(iter(state["model"]))
    state["model"][name] = torch.zeros(1)
    path = tmp_path / "mismatched.pt"
    torch.save(state, path)
    with pytest.raises(CheckpointError, match="weights do not match") as info:
        load_trained(path)
    assert str(path) in str(info.value)


def test_trainer_refuses_to_overwrite_or_resume_from_a_broken_run(trained, tmp_path):
    scene, run = trained
    before = digest(run / "checkpoint.pt")
    with pytest.raises(OutputError, match="already holds a run"):
        Trainer(tiny_train_config(scene, run))
    assert digest(run / "checkpoint.pt") == before
    broken = tmp_path / "broken_run"
    broken.mkdir()
    truncated = broken_copies(run / "checkpoint.pt", tmp_path / "copies")["truncated"]
    (broken / "checkpoint.pt").write_bytes(truncated.read_bytes())
    with pytest.raises(CheckpointError, match="checkpoint.pt: not a readable checkpoint"):
        Trainer(tiny_train_config(scene, broken), resume=True)
    assert digest(broken / "checkpoint.pt") == digest(truncated)  # kept for the user to inspect


def test_trainer_names_a_missing_or_empty_dataset(tmp_path):
    with pytest.raises(MissingFileError, match="scene folder not found"):
        Trainer(tiny_train_config(tmp_path / "nothing", tmp_path / "run1"))
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match="unknown scene format"):
        Trainer(tiny_train_config(empty, tmp_path / "run2"))


# ---------------------------------------------------------------------------------------------
# The command line: exit status 1, one line naming the file, nothing on disk lost


def run_cli(argv, capsys) -> tuple[int, str]:
    code = cli_main([str(a) for a in argv])
    return code, capsys.readouterr().err


def snapshot(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): digest(p) for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("command", ["eval", "render"])
@pytest.mark.parametrize("kind", ["truncated", "empty", "foreign"])
def test_cli_reports_a_broken_checkpoint(trained, tmp_path, capsys, command, kind):
    path = broken_copies(trained[1] / "checkpoint.pt", tmp_path / "copies")[kind]
    before = snapshot(tmp_path)
    extra = ["--frames", 2] if command == "render" else []
    code, err = run_cli(
        [command, "--ckpt", path, "--out", tmp_path / "out", "--device", "cpu", *extra], capsys
    )
    assert code == 1
    assert err.startswith("mixer-nerf: error:") and str(path) in err and len(err.strip().splitlines()) == 1
    assert snapshot(tmp_path) == before  # nothing written, nothing removed


def test_cli_reports_a_missing_checkpoint_and_data(trained, tmp_path, capsys):
    code, err = run_cli(["eval", "--ckpt", tmp_path / "none.pt", "--device", "cpu"], capsys)
    assert code == 1 and "none.pt: checkpoint not found" in err
    code, err = run_cli(
        ["eval", "--ckpt", trained[1] / "checkpoint.pt", "--data", tmp_path / "nodata", "--device", "cpu"],
        capsys,
    )
    assert code == 1 and "nodata: scene folder not found" in err
    code, err = run_cli(
        ["train", "--data", tmp_path / "nodata", "--out", tmp_path / "run", "--no-progress"], capsys
    )
    assert code == 1 and "nodata: scene folder not found" in err
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_cli_train_keeps_an_existing_run(trained, capsys):
    scene, run = trained
    before = snapshot(run)
    code, err = run_cli(
        ["train", "--data", scene, "--out", run, "--device", "cpu", "--steps", 1, "--no-progress"], capsys
    )
    assert code == 1 and "already holds a run" in err and "--resume" in err
    assert snapshot(run) == before


def test_cli_resume_without_a_checkpoint_and_bad_numbers(trained, tmp_path, capsys):
    scene, _ = trained
    code, err = run_cli(
        ["train", "--data", scene, "--out", tmp_path / "fresh", "--resume", "--no-progress"], capsys
    )
    assert code == 1 and "no checkpoint to resume from" in err
    code, err = run_cli(
        ["train", "--data", scene, "--out", tmp_path / "r", "--steps", -3, "--no-progress"], capsys
    )
    assert code == 1 and "steps must be positive" in err
    with pytest.raises(SystemExit) as info:  # argparse: usage errors exit with 2
        cli_main(["train", "--steps", "many"])
    assert info.value.code == 2
