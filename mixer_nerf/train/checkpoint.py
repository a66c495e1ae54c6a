"""Checkpoints: written atomically, read back with errors that name the file.

A checkpoint is one ``torch.save`` file holding plain containers of tensors and numbers only, so
it loads with ``weights_only=True``: no code is unpickled from it. Writing goes to a temporary file
in the same folder that is fsync'ed and then renamed over the target (:func:`~.output.atomic_path`);
a run killed at any moment leaves either the previous checkpoint or the new one, never a mixture,
and a failed write (disk full) keeps the previous one.
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .output import atomic_path

FORMAT = "mixer_nerf.checkpoint"
VERSION = 1
REQUIRED_KEYS = ("format", "version", "step", "train_config", "model_config", "scene", "model")


class CheckpointError(RuntimeError):
    """A checkpoint file is missing, truncated, corrupt or not one of ours."""


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Atomically write ``state`` (plus the format header) to ``path``.

    Raises:
        OutputError: naming ``path`` when it cannot be written; the previous checkpoint is kept.
    """
    with atomic_path(path) as tmp, tmp.open("wb") as f:
        torch.save({"format": FORMAT, "version": VERSION, **state}, f)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Raises:
        CheckpointError: naming ``path``, when it is absent, unreadable, truncated or not ours.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch raises RuntimeError, pickle/zip errors, EOFError... for bad files
        reason = str(e).strip().split(". ")[0]  # torch appends paragraphs of advice
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or corrupt?): {reason}") from e
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a mixer_nerf checkpoint")
    if state.get("version") != VERSION:
        raise CheckpointError(
            f"{path}: checkpoint version {state.get('version')} is not supported "
            f"(this mixer_nerf reads version {VERSION})"
        )
    missing = [k for k in REQUIRED_KEYS if k not in state]
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {missing}")
    return state


def capture_rng_state(sampler_generator: torch.Generator) -> dict[str, Any]:
    """Every random state a training step draws from: torch (CPU and each GPU), numpy, Python
    and the ray sampler's own generator."""
    np_kind, np_keys, np_pos, np_has_gauss, np_gauss = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": {
            "kind": np_kind,
            "keys": torch.from_numpy(np_keys.astype(np.int64)),
            "pos": int(np_pos),
            "has_gauss": int(np_has_gauss),
            "gauss": float(np_gauss),
        },
        "python": _to_lists(random.getstate()),
        "sampler": sampler_generator.get_state(),
    }


def restore_rng_state(state: dict[str, Any], sampler_generator: torch.Generator | None) -> None:
    """Inverse of :func:`capture_rng_state`; ``None`` leaves the sampler's generator as it is
    (its state is that of one device type)."""
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    n = state["numpy"]
    np.random.set_state(
        (n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["gauss"])
    )
    random.setstate(_to_tuples(state["python"]))
    if sampler_generator is not None:
        sampler_generator.set_state(state["sampler"])


def _to_lists(value: Any) -> Any:
    return [_to_lists(v) for v in value] if isinstance(value, tuple) else value


def _to_tuples(value: Any) -> Any:
    return tuple(_to_tuples(v) for v in value) if isinstance(value, list) else value
