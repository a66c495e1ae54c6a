"""Reading pickles of numpy arrays in plain containers without running any pickled code.

``pickle.load`` calls whatever callable a file names. This reader resolves the three names a
pickled numpy array uses (``_reconstruct``, ``ndarray``, ``dtype``) to inert placeholders that only
record their arguments, refuses every other name, and then builds each array itself from the
recorded raw bytes with ``numpy.frombuffer``: numpy's own unpickling code never sees the file.
Dicts with string keys, lists, tuples, strings, numbers, booleans and None pass through as they are.
"""

from __future__ import annotations

import math
import pickle
from typing import Any, BinaryIO

import numpy as np

_NDARRAY = object()  # stands for ``numpy.ndarray``, only ever passed back to ``_reconstruct``
_PLAIN = (str, int, float, bool, type(None))


class _PendingDtype:
    """What ``numpy.dtype(spec, align, copy)`` plus its ``__setstate__`` recorded."""

    def __init__(self, spec: object, *flags: object) -> None:
        self.spec, self.flags, self.state = spec, flags, None

    def __setstate__(self, state: object) -> None:
        self.state = state

    def build(self) -> np.dtype:
        if not isinstance(self.spec, str) or not isinstance(self.state, tuple) or len(self.state) < 5:
            raise pickle.UnpicklingError(f"unsupported dtype record {self.spec!r}, {self.state!r}")
        byteorder, subarray_names_fields = self.state[1], self.state[2:5]
        if byteorder not in ("<", ">", "|", "=") or any(v is not None for v in subarray_names_fields):
            raise pickle.UnpicklingError(f"only plain numeric dtypes are allowed, got state {self.state!r}")
        dtype = np.dtype(self.spec)
        if dtype.kind not in "biuf":
            raise pickle.UnpicklingError(f"only numeric dtypes are allowed, got {self.spec!r}")
        return dtype.newbyteorder(byteorder) if byteorder in "<>" else dtype


class _PendingArray:
    """What ``numpy.core.multiarray._reconstruct`` plus the array's ``__setstate__`` recorded."""

    def __init__(self) -> None:
        self.state: object = None

    def __setstate__(self, state: object) -> None:
        self.state = state

    def build(self) -> np.ndarray:
        state = self.state
        if not (isinstance(state, tuple) and len(state) == 5 and isinstance(state[2], _PendingDtype)):
            raise pickle.UnpicklingError("malformed numpy array record")
        _, shape, pending_dtype, fortran_order, raw = state
        if not (isinstance(shape, tuple) and all(type(n) is int and n >= 0 for n in shape)):
            raise pickle.UnpicklingError(f"malformed array shape {shape!r}")
        dtype = pending_dtype.build()
        if not isinstance(raw, bytes) or len(raw) != math.prod(shape) * dtype.itemsize:
            raise pickle.UnpicklingError(f"array data does not match shape {shape} and dtype {dtype}")
        flat = np.frombuffer(raw, dtype=dtype)
        return flat.reshape(shape, order="F" if fortran_order else "C").copy(order="K")


class _Reconstruct:
    """Stands for ``numpy.core.multiarray._reconstruct``; slots only, so a pickle cannot set
    attributes on it."""

    __slots__ = ()

    def __call__(self, subtype: object, shape: object, typecode: object) -> _PendingArray:
        if subtype is not _NDARRAY:
            raise pickle.UnpicklingError("only plain numpy.ndarray instances are allowed")
        return _PendingArray()


_RECONSTRUCT = _Reconstruct()
_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"): _RECONSTRUCT,
    ("numpy._core.multiarray", "_reconstruct"): _RECONSTRUCT,  # the numpy >= 2 module name
    ("numpy", "ndarray"): _NDARRAY,
    ("numpy", "dtype"): _PendingDtype,
}


class _NumpyOnlyUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"refusing to load {module}.{name}: only numpy arrays in plain containers are allowed"
            ) from None

    def persistent_load(self, pid: object) -> Any:
        raise pickle.UnpicklingError("refusing a persistent reference: only numpy arrays are allowed")


def load(file: BinaryIO) -> Any:
    """Unpickle ``file`` (opened in binary mode), allowing only numpy arrays of numeric dtypes in
    dicts with string keys, lists and tuples; raises ``pickle.UnpicklingError`` for anything else."""
    return _materialize(_NumpyOnlyUnpickler(file).load())


def _materialize(value: object) -> Any:
    if isinstance(value, _PendingArray):
        return value.build()
    if type(value) is dict:
        if not all(isinstance(k, str) for k in value):
            raise pickle.UnpicklingError("only string dict keys are allowed")
        return {k: _materialize(v) for k, v in value.items()}
    if type(value) in (list, tuple):
        return type(value)(_materialize(v) for v in value)
    if type(value) in _PLAIN:
        return value
    raise pickle.UnpicklingError(f"unexpected {type(value).__name__} in a numpy-only pickle")
