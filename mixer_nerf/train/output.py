"""The run folder: what it holds, one process owning it at a time, refusing to clobber an earlier
run in it, and writing every file atomically."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import socket
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

TEMPORARY = re.compile(r"^\..+\.(\d+)-[0-9a-f]{8}\.tmp")  # ".<name>.<pid>-<random>.tmp<suffix>"
LEGACY_TEMPORARY = ".checkpoint.pt.*.tmp"  # tempfile.mkstemp's names of earlier versions


class OutputError(RuntimeError):
    """The output folder cannot be used (not writable, in use by another run, or it holds a run
    and neither --resume nor --overwrite was given), or a file could not be written to it."""


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

    @property
    def lock(self) -> Path:
        return self.root / "run.lock"

    def run_files(self) -> list[Path]:
        """The files one run writes (what ``--overwrite`` removes)."""
        return [self.checkpoint, self.config, self.train_log, self.val_log, self.curves, self.summary]


class RunLock:
    """An exclusive ``flock`` on ``run.lock``, holding the owner's pid and host.

    The kernel drops the lock when its process dies, however it dies, so a crashed run never
    blocks the next one; the pid and host in the file only name the owner in the error."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd: int | None = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._fd)
            self._fd = None
            raise OutputError(
                f"{path.parent}: in use by another run ({_owner(path)}); wait for it to end or choose another --out"
            ) from None
        os.ftruncate(self._fd, 0)
        os.write(self._fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname()}).encode())

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock; the file stays for the next owner
            self._fd = None

    def __del__(self) -> None:
        self.release()


def prepare_run_folder(out: str | Path, resume: bool, overwrite: bool = False) -> tuple[RunFiles, RunLock]:
    """Create (if needed), lock and check the run folder before anything is written to it.

    Temporaries left by a killed writer are removed. With ``overwrite`` the files of an earlier
    run in the folder are removed first.

    Returns:
        The run's files and the lock, held until :meth:`RunLock.release` (or garbage collection).

    Raises:
        OutputError: ``out`` cannot be created or written; another process holds its lock; it
            holds a run (finished, or killed before its first checkpoint) and neither ``resume``
            nor ``overwrite`` is given; or ``resume`` is given and it holds no checkpoint.
    """
    if resume and overwrite:
        raise OutputError("--resume and --overwrite exclude each other")
    files = RunFiles(Path(out))
    ensure_writable_folder(files.root)
    lock = RunLock(files.lock)
    if overwrite:
        for path in files.run_files():
            path.unlink(missing_ok=True)
    if resume:
        if not files.checkpoint.is_file():
            raise OutputError(f"{files.checkpoint}: no checkpoint to resume from")
    elif files.checkpoint.exists():
        raise OutputError(
            f"{files.root}: already holds a run ({files.checkpoint.name}); pass --resume to "
            "continue it, --overwrite to start over, or choose another --out"
        )
    elif any(p.exists() for p in files.run_files()):
        raise OutputError(
            f"{files.root}: holds an unfinished run with no checkpoint (killed before its first?); "
            "pass --overwrite to start over or choose another --out"
        )
    return files, lock


def ensure_writable_folder(folder: Path) -> None:
    """mkdir -p ``folder``, prove a file can be created in it and remove the temporaries that
    killed writers left in it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        raise OutputError(f"{folder}: output folder is not writable ({e.strerror or e})") from e
    remove_stale_temporaries(folder)


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Delete the temporaries in ``folder`` whose writing process is gone; returns them."""
    stale = [p for p in folder.glob(".*.tmp*") if _is_stale(p)]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix, so writers that pick the format by
    extension work) to write, then fsync it and rename it over ``path``: a reader sees the old
    file or the new one, never a part. On any error the temporary is removed and ``path`` kept.

    Raises:
        OutputError: naming ``path``, when writing fails (disk full, permissions...).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{os.urandom(4).hex()}.tmp{path.suffix}")
    try:
        yield tmp
        with tmp.open("rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        raise OutputError(f"{path}: could not be written ({e.strerror or e}); the previous file is kept") from e
    finally:
        tmp.unlink(missing_ok=True)
    fsync_folder(path.parent)


def write_text_atomic(path: str | Path, text: str) -> None:
    """``Path.write_text`` through :func:`atomic_path`."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def fsync_folder(folder: Path) -> None:
    """Make a rename durable (POSIX); a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _is_stale(path: Path) -> bool:
    """A temporary of ours whose writer is not running (any legacy one: no process owns it now)."""
    match = TEMPORARY.match(path.name)
    if match is None:
        return path.match(LEGACY_TEMPORARY)
    try:
        os.kill(int(match[1]), 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


def _owner(lock: Path) -> str:
    try:
        owner = json.loads(lock.read_text())
        return f"pid {owner['pid']} on {owner['host']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "owner unknown"
