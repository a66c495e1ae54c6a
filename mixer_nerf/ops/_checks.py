"""Input validation shared by every op wrapper: clear errors naming the argument, raised before
any kernel runs (kernels keep only defensive TORCH_CHECKs)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from operator import attrgetter

import torch

BACKENDS = ("auto", "kernel", "torch")


def check_backend(backend: str) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


def check_tensor(name: str, value: object) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value


def check_floating(name: str, t: torch.Tensor) -> None:
    check_tensor(name, t)
    if not t.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got dtype {t.dtype}")


def check_ndim(name: str, t: torch.Tensor, ndim: int | Sequence[int]) -> None:
    allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
    if t.dim() not in allowed:
        want = " or ".join(str(n) for n in allowed)
        raise ValueError(f"{name} must have {want} dimensions, got shape {tuple(t.shape)}")


def check_shape(name: str, t: torch.Tensor, shape: Sequence[int | None], hint: str = "") -> None:
    """``shape`` entries of None match any size."""
    if t.shape == shape:  # the common case, decided without a loop
        return
    ok = t.dim() == len(shape) and all(s is None or s == n for s, n in zip(shape, t.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}{hint}, got {tuple(t.shape)}")


_DEVICE, _DTYPE, _DEVICE_AND_DTYPE = attrgetter("device"), attrgetter("dtype"), attrgetter("device", "dtype")


def _shared(tensors: dict[str, torch.Tensor | None], read: attrgetter):
    """What ``read`` gives for every tensor given (None skipped), or None where they differ (or none
    is given): one pass without the sets and dicts a message needs, as every call that passes takes."""
    shared = None
    for t in tensors.values():
        if t is None:
            continue
        value = read(t)
        if shared is None:
            shared = value
        elif value != shared:
            return None
    return shared


def check_same_device(**tensors: torch.Tensor | None) -> torch.device:
    device = _shared(tensors, _DEVICE)
    if device is not None:
        return device
    present = {k: v for k, v in tensors.items() if v is not None}
    devices = {v.device for v in present.values()}
    if len(devices) > 1:
        listing = ", ".join(f"{k} on {v.device}" for k, v in present.items())
        raise ValueError(f"all tensors must be on one device, got {listing}")
    return next(iter(devices))


def check_same_dtype(**tensors: torch.Tensor | None) -> torch.dtype:
    dtype = _shared(tensors, _DTYPE)
    if dtype is not None:
        return dtype
    present = {k: v for k, v in tensors.items() if v is not None}
    dtypes = {v.dtype for v in present.values()}
    if len(dtypes) > 1:
        listing = ", ".join(f"{k} is {v.dtype}" for k, v in present.items())
        raise TypeError(f"all tensors must have one dtype, got {listing}")
    return next(iter(dtypes))


def check_alike(**tensors: torch.Tensor | None) -> tuple[torch.device, torch.dtype]:
    """check_same_device and check_same_dtype (in that order, with their messages) in one pass where
    the tensors pass, as nearly every call's do."""
    shared = _shared(tensors, _DEVICE_AND_DTYPE)
    return shared if shared is not None else (check_same_device(**tensors), check_same_dtype(**tensors))


# The messages of the value checks, shared with the kernels' deferred reports (deferred_checks).
def sorted_message(name: str) -> str:
    return f"{name} must be sorted (non-decreasing) along its last dimension"


def nonnegative_message(name: str) -> str:
    return f"{name} must be non-negative"


def in_range_message(name: str, low: float, high: float) -> str:
    return f"{name} must lie in [{low}, {high}]"


# Value checks reduce with one min: on CPUs a comparison's bool tensor and its any() cost about ten
# times more. The exact comparison decides only where the min cannot (a NaN, a -0 difference).


def has_negative(t: torch.Tensor) -> bool:
    """Whether an entry of t is < 0 (a NaN entry is not)."""
    if not t.numel():
        return False
    low = float(t.detach().amin())
    return low < 0 or (math.isnan(low) and bool((t < 0).any()))


def has_descent(low: torch.Tensor, high: torch.Tensor) -> bool:
    """Whether an entry of ``high`` is below the same entry of ``low`` (a pair with a NaN is not).

    For floats the sign of ``high - low`` says so (rounding never flips it). Equal neighbours give
    +0; a -0 (a negative gap flushed to zero under flush-to-zero, or -0 - +0) or a NaN is settled by
    the comparison itself."""
    if not high.numel():
        return False
    if not high.is_floating_point():
        return bool((high < low).any())
    gaps = high.detach() - low.detach()
    gap = float(gaps.amin())
    if gap < 0:
        return True
    if gap > 0 or (gap == 0 and float(torch.copysign(gaps.new_ones(()), gaps).amin()) > 0):
        return False
    return bool((high < low).any())


def check_sorted(name: str, t: torch.Tensor) -> None:
    """Non-decreasing along the last dimension (NaN entries are not judged here)."""
    if t.shape[-1] > 1 and has_descent(t[..., :-1], t[..., 1:]):
        raise ValueError(sorted_message(name))


def check_nonnegative(name: str, t: torch.Tensor) -> None:
    if has_negative(t):
        raise ValueError(nonnegative_message(name))


def check_in_range(name: str, t: torch.Tensor, low: float, high: float) -> None:
    """Every entry in [low, high] (NaN fails: the min and max of a tensor with a NaN are NaN)."""
    if not t.numel():
        return
    smallest, largest = torch.stack(torch.aminmax(t.detach())).tolist()
    if not (smallest >= low and largest <= high):
        raise ValueError(in_range_message(name, low, high))


def check_int(name: str, value: object, minimum: int = 0) -> int:
    """A Python integer >= minimum (bool is rejected)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return value


def check_offsets(name: str, offsets: torch.Tensor, num_items: int, check_values: bool = True) -> int:
    """CSR offsets (R+1,) int64 over ``num_items`` rows: returns R. With ``check_values``, also
    offsets[0] == 0, offsets[-1] == num_items and non-decreasing (on a GPU: a host sync)."""
    check_tensor(name, offsets)
    if offsets.dtype != torch.int64:
        raise TypeError(f"{name} must be an int64 tensor, got dtype {offsets.dtype}")
    if offsets.dim() != 1 or offsets.numel() < 1:
        raise ValueError(f"{name} must have shape (R+1,) with R >= 0, got {tuple(offsets.shape)}")
    if offsets.numel() == 1 and num_items != 0:  # no ray to own the rows, whatever the values
        raise ValueError(f"{name} has no ray (shape (1,)) but there are {num_items} rows")
    if check_values:
        first, last = offsets[[0, -1]].tolist()
        if first != 0 or last != num_items:
            raise ValueError(
                f"{name} must start at 0 and end at {num_items} (the number of rows), got {first} .. {last}"
            )
        if bool((offsets[1:] < offsets[:-1]).any()):
            raise ValueError(f"{name} must be non-decreasing")
    return offsets.numel() - 1
