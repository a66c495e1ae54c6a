"""``mixer-nerf prepare``: a folder of photos or a video -> a COLMAP capture that training reads.

Camera poses come from COLMAP through ``pycolmap`` (``pip install 'mixer_nerf[prepare]'``), in
stages, each announced on the log:

1. frames: the photos of the folder (png/jpg, by name), or every ``every``-th frame of a video
   (decoded by imageio's ffmpeg plugin, saved as JPEG in ``OUT/colmap/frames/``);
2. SIFT features, with one shared camera (model ``camera_model``) when every image has one size;
3. matching: exhaustive for a folder of up to EXHAUSTIVE_MAX photos, sequential (neighbours in
   name order) for a video or a larger folder;
4. incremental mapping; the largest model is kept and must register at least MIN_REGISTERED of
   the images (and at least MIN_IMAGES);
5. undistortion into ``OUT/images/`` and a PINHOLE model in ``OUT/sparse/``, the layout
   :func:`mixer_nerf.data.load_colmap` reads. COLMAP's database and distorted model stay in
   ``OUT/colmap/``.
"""

from __future__ import annotations

import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import imageio.v3 as iio
from PIL import Image

from .data.images import IMAGE_SUFFIXES, list_images

MIN_IMAGES = 3
MIN_REGISTERED = 0.5  # fraction of the images the kept model must hold
EXHAUSTIVE_MAX = 200  # more photos than this are matched sequentially (exhaustive is quadratic)
MATCHERS = ("auto", "exhaustive", "sequential")
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
FRAME_QUALITY = 95  # JPEG quality of the frames taken from a video
STAGES = 5
DEFAULT_EVERY = 10
DEFAULT_CAMERA_MODEL = "RADIAL"  # k1, k2: phone lenses' barrel distortion, one focal length


class PrepareError(ValueError):
    """A problem with the input the user can fix (printed as one line by the command line)."""


def prepare(
    source: str | Path,
    out: str | Path,
    every: int = DEFAULT_EVERY,
    matcher: str = "auto",
    camera_model: str = DEFAULT_CAMERA_MODEL,
    verbose: bool = False,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Solve the camera poses of ``source`` (photo folder or video) into the new folder ``out``.

    Args:
        every: keep every ``every``-th frame of a video.
        matcher: "auto" (see the module docstring), "exhaustive" or "sequential".
        camera_model: COLMAP camera model solved for (one of CAMERA_MODELS; lens distortion is
            removed at stage 5).
        verbose: let COLMAP log its own progress (otherwise only its warnings).
        log: where stage lines go.

    Returns:
        Summary: "images", "registered", "matcher", "out" and "seconds" per stage.
    """
    source, out = Path(source), Path(out)
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if matcher not in MATCHERS:
        raise ValueError(f"matcher must be one of {MATCHERS}, got {matcher!r}")
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {CAMERA_MODELS}, got {camera_model!r}")
    pycolmap = _import_pycolmap()
    if not source.exists():
        raise FileNotFoundError(f"{source}: no such folder or video")
    if out.exists() and any(out.iterdir()):
        raise PrepareError(f"{out}: exists and is not empty; choose a new output folder")
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = level if verbose else max(level, int(pycolmap.logging.WARNING))
    try:
        summary = _solve(pycolmap, source, out, every, matcher, camera_model, log)
    except PrepareError:
        shutil.rmtree(out, ignore_errors=True)  # the input was at fault: leave OUT free for a retry
        raise
    finally:
        pycolmap.logging.minloglevel = level
    stages = ", ".join(f"{name} {seconds:.1f} s" for name, seconds in summary["seconds"].items())
    log(f"done ({stages}): train with  mixer-nerf train --data {out}")
    return summary


def _solve(pycolmap, source: Path, out: Path, every: int, matcher: str, camera_model: str,
           log: Callable[[str], None]) -> dict[str, Any]:  # fmt: skip
    """The five stages of :func:`prepare`."""
    work = out / "colmap"
    work.mkdir(parents=True, exist_ok=True)
    clock = _StageClock(log)
    clock.start("frames", f"reading {source}")
    image_dir, names, is_video = _frames(source, work / "frames", every)
    if len(names) < MIN_IMAGES:
        raise PrepareError(
            f"{source}: {len(names)} image(s); COLMAP needs at least {MIN_IMAGES} (a NeRF wants dozens)"
        )
    if matcher == "auto":
        matcher = "sequential" if is_video or len(names) > EXHAUSTIVE_MAX else "exhaustive"

    clock.start("features", f"extracting SIFT features from {len(names)} images ({camera_model} camera)")
    database = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    one_size = len({_image_size(image_dir / n) for n in names}) == 1
    mode = pycolmap.CameraMode.SINGLE if one_size else pycolmap.CameraMode.AUTO
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=mode, reader_options=reader)

    clock.start("matching", f"matching features ({matcher})")
    (pycolmap.match_exhaustive if matcher == "exhaustive" else pycolmap.match_sequential)(database)

    clock.start("mapping", "incremental mapping")
    models = pycolmap.incremental_mapping(database, image_dir, work / "sparse")
    best = max(models, key=lambda k: models[k].num_reg_images(), default=None)
    registered = 0 if best is None else models[best].num_reg_images()
    needed = max(MIN_IMAGES, math.ceil(MIN_REGISTERED * len(names)))
    if registered < needed:
        raise PrepareError(_registration_advice(registered, len(names), needed, matcher, is_video))
    log(f"  registered {registered} of {len(names)} images")

    clock.start("undistortion", f"undistorting into {out}")
    pycolmap.undistort_images(out, work / "sparse" / str(best), image_dir)
    _drop_stereo_files(out)
    seconds = clock.stop()
    return {
        "images": len(names),
        "registered": registered,
        "matcher": matcher,
        "out": str(out),
        "seconds": seconds,
    }


def extract_frames(video: Path, folder: Path, every: int) -> list[str]:
    """Save every ``every``-th frame of ``video`` as ``folder/frame_NNNNN.jpg``; their names."""
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    try:
        for k, frame in enumerate(iio.imiter(video, plugin="FFMPEG")):
            if k % every == 0:
                names.append(f"frame_{k:05d}.jpg")
                Image.fromarray(frame[..., :3]).save(folder / names[-1], quality=FRAME_QUALITY)
    except Exception as exc:  # imageio and ffmpeg raise many types for missing codecs or bad data
        first_line = (str(exc).splitlines() or [""])[0]
        raise PrepareError(
            f"{video}: cannot decode as a video ({type(exc).__name__}: {first_line}); it needs "
            "imageio-ffmpeg (pip install 'mixer_nerf[prepare]') and a format ffmpeg reads"
        ) from exc
    if not names:
        raise PrepareError(f"{video}: the video has no frames")
    return names


def _frames(source: Path, frames_dir: Path, every: int) -> tuple[Path, list[str], bool]:
    """(folder COLMAP reads, image names in it, whether they came from a video)."""
    if source.is_dir():
        return source, [p.name for p in list_images(source)], False
    if source.suffix.lower() in IMAGE_SUFFIXES:
        raise PrepareError(f"{source}: a single image; give a folder of photos or a video")
    return frames_dir, extract_frames(source, frames_dir, every), True


def _registration_advice(registered: int, total: int, needed: int, matcher: str, is_video: bool) -> str:
    tips = ["more overlap between neighbouring views", "sharp photos of a static, textured scene"]
    if matcher == "sequential":
        tips.append("--matcher exhaustive" if not is_video else "a smaller --every")
    return (
        f"COLMAP registered {registered} of {total} images in one model (needs {needed}); "
        f"try {', '.join(tips)}"
    )


def _image_size(path: Path) -> tuple[int, int]:
    with Image.open(path) as img:
        return img.size


def _drop_stereo_files(out: Path) -> None:
    """The undistorter also writes inputs for COLMAP's dense stereo, which nothing here uses."""
    shutil.rmtree(out / "stereo", ignore_errors=True)
    for script in out.glob("run-colmap-*.sh"):
        script.unlink()


def _import_pycolmap():
    try:
        import pycolmap
    except ImportError as exc:
        raise PrepareError("prepare needs pycolmap: pip install 'mixer_nerf[prepare]'") from exc
    return pycolmap


class _StageClock:
    """Announces the numbered stages and times them."""

    def __init__(self, log: Callable[[str], None]) -> None:
        self.log, self.seconds, self.current, self.began = log, {}, None, 0.0

    def start(self, name: str, message: str) -> None:
        self.stop()
        self.log(f"[{len(self.seconds) + 1}/{STAGES}] {message}")
        self.current, self.began = name, time.perf_counter()

    def stop(self) -> dict[str, float]:
        if self.current is not None:
            self.seconds[self.current] = round(time.perf_counter() - self.began, 2)
            self.current = None
        return self.seconds
