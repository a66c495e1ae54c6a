"""Training logs: CSV tables (train steps, validations), a loss/PSNR plot and TensorBoard."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from .output import atomic_path


class CsvLog:
    """An append-only CSV table whose columns are fixed by the first row written (a resumed run
    keeps its table's columns: keys added by a later version are left out of it).

    On resume, :meth:`truncate_after` drops the rows a killed run logged after its last
    checkpoint, so the table matches the state training continues from.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def append(self, row: dict[str, Any]) -> None:
        new = not self.path.exists() or self.path.stat().st_size == 0
        with self.path.open("a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(self.fieldnames() or row), extrasaction="ignore")
            if new:
                writer.writeheader()
            writer.writerow(row)

    def rows(self) -> list[dict[str, str]]:
        if not self.path.exists():
            return []
        with self.path.open(newline="") as f:
            return list(csv.DictReader(f))

    def fieldnames(self) -> list[str] | None:
        if not self.path.exists() or self.path.stat().st_size == 0:
            return None
        with self.path.open(newline="") as f:
            return next(csv.reader(f), None)

    def truncate_after(self, step: int) -> None:
        rows, fields = self.rows(), self.fieldnames()
        if fields is None:
            return
        with atomic_path(self.path) as tmp, tmp.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fields)
            writer.writeheader()
            writer.writerows(r for r in rows if int(r["step"]) <= step)


def plot_curves(train_log: CsvLog, val_log: CsvLog, path: str | Path) -> Path | None:
    """Loss against step, and PSNR (train batches, validation views) against step and against
    training seconds, as a PNG; None if no rows."""
    train, val = train_log.rows(), val_log.rows()
    if not train:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [int(r["step"]) for r in train]
    fig, (ax_loss, ax_psnr, ax_time) = plt.subplots(1, 3, figsize=(15, 4))
    ax_loss.semilogy(steps, [float(r["loss"]) for r in train])
    ax_loss.set(xlabel="step", ylabel="loss (coarse + fine MSE)", title="training loss")
    for ax, x in ((ax_psnr, "step"), (ax_time, "seconds")):
        ax.plot([float(r[x]) for r in train], [float(r["psnr"]) for r in train], label="train batch (fine)")
        if val:
            ax.plot([float(r[x]) for r in val], [float(r["psnr"]) for r in val], "o-", label="validation")
        xlabel = "training seconds" if x == "seconds" else x
        ax.set(xlabel=xlabel, ylabel="PSNR (dB)", title=f"PSNR against {x}")
        ax.legend()
    for ax in (ax_loss, ax_psnr, ax_time):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return Path(path)


class TensorBoardLog:
    """Scalars and images for TensorBoard (``torch.utils.tensorboard``) in ``folder``.

    Raises:
        OutputError: the tensorboard package is missing or ``folder`` is not writable, before
            anything is trained.
    """

    def __init__(self, folder: str | Path) -> None:
        from .output import OutputError, ensure_writable_folder

        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError as e:
            raise OutputError(
                "--tensorboard needs the tensorboard package: pip install 'mixer_nerf[tensorboard]'"
            ) from e
        ensure_writable_folder(Path(folder))
        self.writer = SummaryWriter(str(folder))

    def scalars(self, step: int, values: dict[str, float]) -> None:
        for tag, value in values.items():
            self.writer.add_scalar(tag, value, step)

    def image(self, step: int, tag: str, image: Any) -> None:
        """``image``: (H, W, 3) float in [0, 1]."""
        self.writer.add_image(tag, image.clamp(0, 1).cpu(), step, dataformats="HWC")

    def close(self) -> None:
        self.writer.close()
