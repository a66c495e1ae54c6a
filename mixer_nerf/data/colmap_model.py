"""Reading a COLMAP sparse model: ``cameras``, ``images`` and ``points3D``, as ``.bin`` or ``.txt``.

The layouts are those of COLMAP's documentation ("Output format"), little-endian:

- ``cameras.bin``: uint64 count; per camera int32 id, int32 model id, uint64 width, uint64 height,
  then the model's float64 parameters. ``cameras.txt``: ``ID MODEL WIDTH HEIGHT PARAMS...``.
- ``images.bin``: uint64 count; per image int32 id, float64 qw qx qy qz, float64 tx ty tz, int32
  camera id, a NUL-terminated name, uint64 number of 2D points, then per point float64 x, y and
  int64 3D point id (-1: none). ``images.txt``: two lines per image, ``ID QW QX QY QZ TX TY TZ
  CAMERA_ID NAME`` then ``X Y POINT3D_ID`` triples (empty for an image without points).
- ``points3D.bin``: uint64 count; per point uint64 id, float64 x y z, uint8 r g b, float64 error,
  uint64 track length, then (int32 image id, int32 2D point index) per track element.
  ``points3D.txt``: ``ID X Y Z R G B ERROR TRACK...``.

(q, t) maps world to camera: x_cam = R(q) x_world + t, with COLMAP's camera axes (x right, y down,
looking down +z). Lines starting with ``#`` in the text files are comments.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import DatasetError, MissingFileError

CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4),
    13: ("DIVISION", 5),
    14: ("SIMPLE_FISHEYE", 3),
    15: ("FISHEYE", 4),
    16: ("EUCM", 6),
    17: ("EQUIRECTANGULAR", 2),
}
"""COLMAP's camera model ids: (name, number of parameters)."""

MODEL_PARAMS = dict(CAMERA_MODELS.values())
MODEL_FILES = ("cameras", "images", "points3D")


@dataclass(frozen=True)
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class ColmapImage:
    """One registered image: world-to-camera rotation ``qvec`` (w, x, y, z) and ``tvec``."""

    id: int
    qvec: tuple[float, float, float, float]
    tvec: tuple[float, float, float]
    camera_id: int
    name: str


@dataclass(frozen=True)
class ColmapModel:
    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]
    points: np.ndarray  # (P, 3) float64 world positions of the 3D points
    folder: Path


def model_suffix(folder: Path) -> str | None:
    """ ".bin" or ".txt" when ``folder`` holds that model's three files (binary preferred), else None."""
    for suffix in (".bin", ".txt"):
        if all((folder / (name + suffix)).is_file() for name in MODEL_FILES):
            return suffix
    return None


def read_model(folder: str | Path) -> ColmapModel:
    """Read the model in ``folder``. Raises MissingFileError / DatasetError naming the file."""
    folder = Path(folder)
    suffix = model_suffix(folder)
    if suffix is None:
        raise MissingFileError(
            f"{folder}: no COLMAP model (expected cameras, images and points3D as .bin or .txt)"
        )
    readers = (
        (_cameras_bin, _images_bin, _points_bin)
        if suffix == ".bin"
        else (_cameras_txt, _images_txt, _points_txt)
    )
    parts = []
    for name, reader in zip(MODEL_FILES, readers, strict=True):
        path = folder / (name + suffix)
        try:
            parts.append(reader(path))
        except DatasetError:
            raise
        except (struct.error, ValueError, IndexError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{path}: malformed COLMAP file ({type(exc).__name__}: {exc})") from exc
    cameras, images, points = parts
    return ColmapModel({c.id: c for c in cameras}, images, points, folder)


def quaternion_to_matrix(qvec: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (w, x, y, z), normalised here, -> (..., 3, 3) rotation matrices."""
    w, x, y, z = np.moveaxis(qvec / np.linalg.norm(qvec, axis=-1, keepdims=True), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


# -- binary ---------------------------------------------------------------------------------------


class _Reader:
    """Sequential little-endian reads from a file's bytes (struct.error when they run out)."""

    def __init__(self, path: Path) -> None:
        self.data, self.pos = path.read_bytes(), 0

    def take(self, fmt: str) -> tuple:
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += struct.calcsize("<" + fmt)
        return values

    def skip(self, size: int) -> None:
        if self.pos + size > len(self.data):
            raise struct.error(f"file ends inside a record ({size} bytes to skip)")
        self.pos += size

    def name(self) -> str:
        end = self.data.index(b"\0", self.pos)
        name, self.pos = self.data[self.pos : end].decode("utf-8"), end + 1
        return name

    def done(self, path: Path) -> None:
        if self.pos != len(self.data):
            raise DatasetError(f"{path}: {len(self.data) - self.pos} unexpected bytes after the last record")


def _cameras_bin(path: Path) -> list[ColmapCamera]:
    reader = _Reader(path)
    cameras = []
    for _ in range(reader.take("Q")[0]):
        camera_id, model_id, width, height = reader.take("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise DatasetError(f"{path}: camera {camera_id} has unknown model id {model_id}")
        model, count = CAMERA_MODELS[model_id]
        cameras.append(ColmapCamera(camera_id, model, width, height, reader.take(f"{count}d")))
    reader.done(path)
    return cameras


def _images_bin(path: Path) -> list[ColmapImage]:
    reader = _Reader(path)
    images = []
    for _ in range(reader.take("Q")[0]):
        image_id, *pose, camera_id = reader.take("i7di")
        name = reader.name()
        reader.skip(24 * reader.take("Q")[0])  # 2D points (x, y, 3D point id): not needed
        images.append(ColmapImage(image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id, name))
    reader.done(path)
    return images


def _points_bin(path: Path) -> np.ndarray:
    reader = _Reader(path)
    count = reader.take("Q")[0]
    points = np.empty((count, 3))
    for k in range(count):
        _, x, y, z, _, _, _, _, track = reader.take("Q3d3BdQ")
        reader.skip(8 * track)  # (image id, 2D point index) pairs: not needed
        points[k] = x, y, z
    reader.done(path)
    return points


# -- text -----------------------------------------------------------------------------------------


def _data_lines(path: Path) -> list[str]:
    """Lines that are not comments, blank ones kept (an image without 2D points has one)."""
    return [line.strip() for line in path.read_text().splitlines() if not line.startswith("#")]


def _cameras_txt(path: Path) -> list[ColmapCamera]:
    cameras = []
    for line in filter(None, _data_lines(path)):
        camera_id, model, width, height, *params = line.split()
        if model not in MODEL_PARAMS:
            raise DatasetError(f"{path}: camera {camera_id} has unknown model {model!r}")
        if len(params) != MODEL_PARAMS[model]:
            raise DatasetError(
                f"{path}: camera {camera_id} ({model}) has {len(params)} parameters, "
                f"expected {MODEL_PARAMS[model]}"
            )
        cameras.append(
            ColmapCamera(int(camera_id), model, int(width), int(height), tuple(map(float, params)))
        )
    return cameras


def _images_txt(path: Path) -> list[ColmapImage]:
    lines, images, k = _data_lines(path), [], 0
    while k < len(lines):
        if not lines[k]:
            k += 1
            continue
        fields = lines[k].split(maxsplit=9)
        if len(fields) != 10:
            raise DatasetError(
                f"{path}: image line {lines[k]!r} needs ID, QW..QZ, TX..TZ, CAMERA_ID and NAME"
            )
        pose = tuple(map(float, fields[1:8]))
        images.append(ColmapImage(int(fields[0]), pose[:4], pose[4:], int(fields[8]), fields[9]))
        k += 2  # the next line lists the image's 2D points: not needed
    return images


def _points_txt(path: Path) -> np.ndarray:
    rows = [line.split()[1:4] for line in filter(None, _data_lines(path))]
    return np.array(rows, dtype=np.float64).reshape(-1, 3)
