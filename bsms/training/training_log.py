"""The training log of a run folder: ``metrics.csv`` always, TensorBoard event files on request.

``metrics.csv`` holds one row per log: step, the mean training loss since the last row, the
learning rate, training seconds so far, samples per second, and at validations the validation
RMSE (and, for rollout validation, its ratio to predicting no motion, ``valid_vs_rest``).

``train.tensorboard: true`` also writes the same numbers as TensorBoard scalars to
``<run>/tensorboard/`` (``train/loss``, ``train/lr``, ``train/samples_per_s``, ``valid/rmse``,
``valid/vs_rest``), for ``tensorboard --logdir runs``. It needs the optional ``tensorboard``
package (``pip install "bsms[tensorboard]"``). A resumed run drops the events after the step it
resumes from, as it drops those rows of ``metrics.csv``.
"""

from __future__ import annotations

import csv
from pathlib import Path

from bsms.config import ConfigError
from datagen.atomic import atomic_path

__all__ = ["METRICS_FIELDS", "TENSORBOARD_TAGS", "TrainingLog", "require_tensorboard"]

METRICS_FIELDS = ("step", "loss", "lr", "seconds", "samples_per_s", "valid_rmse", "valid_vs_rest")
# metrics.csv column -> TensorBoard tag
TENSORBOARD_TAGS = {"loss": "train/loss", "lr": "train/lr", "samples_per_s": "train/samples_per_s",
                    "valid_rmse": "valid/rmse", "valid_vs_rest": "valid/vs_rest"}


def require_tensorboard():
    """torch's TensorBoard ``SummaryWriter``; ConfigError naming the extra when tensorboard is missing."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        raise ConfigError("config key 'train.tensorboard' needs the tensorboard package, which is not installed: "
                          "pip install \"bsms[tensorboard]\" (or pip install tensorboard), or set "
                          "train.tensorboard=false") from None
    return SummaryWriter


class TrainingLog:
    """Where a run's training numbers go: ``metrics.csv`` in ``run_dir`` and, with
    ``tensorboard``, event files in ``run_dir/tensorboard``.

    ``resume_step``: None starts a new log (a fresh metrics.csv); a step resumes one, keeping
    the rows and events up to that step."""

    def __init__(self, run_dir, tensorboard: bool = False, resume_step: int | None = None):
        self.path = Path(run_dir) / "metrics.csv"
        self._rewrite([] if resume_step is None else self._rows_up_to(resume_step))
        self.writer = None
        if tensorboard:
            purge = None if resume_step is None else resume_step + 1  # events after the resumed step go
            self.writer = require_tensorboard()(log_dir=str(Path(run_dir) / "tensorboard"), purge_step=purge)

    def _rows_up_to(self, step: int) -> list[dict]:
        if not self.path.is_file():
            return []
        with open(self.path, newline="") as fh:
            return [r for r in csv.DictReader(fh) if int(r["step"]) <= step]

    def _rewrite(self, rows: list[dict]) -> None:
        with atomic_path(self.path) as tmp, open(tmp, "w", newline="") as fh:
            writer = csv.DictWriter(fh, METRICS_FIELDS, lineterminator="\n")
            writer.writeheader()
            writer.writerows(rows)

    def write(self, row: dict) -> None:
        """Append one row (METRICS_FIELDS as keys; "" for a number not measured at this step)."""
        with open(self.path, "a", newline="") as fh:
            csv.DictWriter(fh, METRICS_FIELDS, lineterminator="\n").writerow(row)
        if self.writer is not None:
            step = int(row["step"])
            for column, tag in TENSORBOARD_TAGS.items():
                if row.get(column, "") != "":
                    self.writer.add_scalar(tag, float(row[column]), step)
            if row.get("valid_rmse", "") != "":
                self.writer.flush()

    def flush(self) -> None:
        """Write what TensorBoard holds in memory to its event file."""
        if self.writer is not None:
            self.writer.flush()
