"""Vertex positions from a PLY point cloud (nerfstudio's ``sparse_pc.ply``): ascii or binary, the
``vertex`` element first, scalar properties x, y, z among others."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import DatasetError, MissingFileError

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
ENCODINGS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def read_ply_points(path: str | Path) -> np.ndarray:
    """(P, 3) float64 vertex positions. Raises MissingFileError / DatasetError naming ``path``."""
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{path}: point cloud file not found")
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise DatasetError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header)")
    try:
        encoding, count, fields = _parse_header(data[:end].decode("ascii").splitlines()[1:])
    except (UnicodeDecodeError, ValueError, IndexError) as exc:
        raise DatasetError(f"{path}: malformed PLY header ({exc})") from exc
    if not {"x", "y", "z"} <= {name for name, _ in fields}:
        raise DatasetError(f"{path}: the vertex element has no x, y, z properties")
    body = data[end + len(b"end_header\n") :]
    order = ENCODINGS[encoding]
    try:
        if order is None:
            rows = np.loadtxt(body.decode("ascii").splitlines()[:count], ndmin=2).reshape(count, len(fields))
            table = {name: rows[:, k] for k, (name, _) in enumerate(fields)}
        else:
            table = np.frombuffer(body, dtype=np.dtype([(n, order + t) for n, t in fields]), count=count)
    except (ValueError, IndexError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: truncated or malformed vertex data ({exc})") from exc
    return np.stack([np.asarray(table[k], dtype=np.float64) for k in "xyz"], axis=-1)


def _parse_header(lines: list[str]) -> tuple[str, int, list[tuple[str, str]]]:
    """(encoding, vertex count, [(property name, numpy type)]) from the header lines after 'ply'."""
    encoding, count, fields, element = None, None, [], None
    for line in lines:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            if words[1] not in ENCODINGS:
                raise ValueError(f"unknown format {words[1]!r}")
            encoding = words[1]
        elif words[0] == "element":
            element = words[1]
            if element == "vertex":
                count = int(words[2])
            elif count is None:
                raise ValueError("the vertex element must come first")
        elif words[0] == "property" and element == "vertex":
            if words[1] == "list" or words[1] not in PLY_TYPES:
                raise ValueError(f"unsupported vertex property {line!r}")
            fields.append((words[2], PLY_TYPES[words[1]]))
    if encoding is None or count is None:
        raise ValueError("no format line or no vertex element")
    return encoding, count, fields
