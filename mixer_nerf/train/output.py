"""The run folder: what it holds, and refusing to clobber an earlier run in it."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path


class OutputError(RuntimeError):
    """The output folder cannot be used (not writable, or it holds a run and --resume was not given)."""


@dataclass(frozen=True)
class RunFiles:
    root: Path

    @property
    def checkpoint(self) -> Path:
        return self.root / "checkpoint.pt"

    @property
    def config(self) -> Path:
        return self.root / "config.json"

    @property
    def train_log(self) -> Path:
        return self.root / "train_log.csv"

    @property
    def val_log(self) -> Path:
        return self.root / "val_log.csv"

    @property
    def curves(self) -> Path:
        return self.root / "curves.png"

    @property
    def summary(self) -> Path:
        return self.root / "summary.json"


def prepare_run_folder(out: str | Path, resume: bool) -> RunFiles:
    """Create (if needed) and check the run folder before anything is written to it.

    Raises:
        OutputError: ``out`` cannot be created or written, or it already holds a checkpoint and
            ``resume`` is False (starting over would overwrite it), or ``resume`` is True and it
            holds none.
    """
    files = RunFiles(Path(out))
    if resume:
        if not files.checkpoint.is_file():
            raise OutputError(f"{files.checkpoint}: no checkpoint to resume from")
    elif files.checkpoint.exists():
        raise OutputError(
            f"{files.root}: already holds a run ({files.checkpoint.name}); pass --resume to "
            "continue it or choose another --out"
        )
    ensure_writable_folder(files.root)
    return files


def ensure_writable_folder(folder: Path) -> None:
    """mkdir -p ``folder`` and prove a file can be created in it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        raise OutputError(f"{folder}: output folder is not writable ({e.strerror or e})") from e
