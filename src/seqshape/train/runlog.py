"""Training logs: ``RUN/log.csv`` (always) and TensorBoard events in ``RUN/tb`` (optional).

CSV columns: ``kind`` ("train": running means over the last ``log_every`` steps, or "val"),
``stage`` (1-3), ``step`` (within the stage), ``global_step``, ``wall_s`` (seconds since this
session started), ``lr``, ``loss`` (the stage objective), ``cd_m`` (Chamfer, m), ``pose_m2``
(pose loss, m^2), ``sigma_cd``, ``sigma_p`` and ``frames_per_s`` (training frames per second,
all processes). On resume, rows after the checkpoint's step are dropped so that the log
reads as one uninterrupted run.
"""

from __future__ import annotations

import csv
import io
import logging
import time
from pathlib import Path

from seqshape._io import atomic_write_text

log = logging.getLogger(__name__)

FIELDS = ("kind", "stage", "step", "global_step", "wall_s", "lr", "loss", "cd_m", "pose_m2",
          "sigma_cd", "sigma_p", "frames_per_s")


class RunLog:
    """Append-only CSV log plus optional TensorBoard writer of one run folder."""

    def __init__(self, out: Path, global_step: int, tensorboard: bool = True):
        out.mkdir(parents=True, exist_ok=True)
        self.path = out / "log.csv"
        self._truncate(global_step)
        self.fh = open(self.path, "a", newline="")  # noqa: SIM115 - closed in close()
        self.writer = csv.DictWriter(self.fh, FIELDS)
        self.tb = _tensorboard(out / "tb") if tensorboard else None
        self.t0 = self.t_last = time.monotonic()
        self._acc: dict[str, float] = {}

    def _truncate(self, global_step: int) -> None:
        rows = []
        if self.path.exists():
            with open(self.path, newline="") as fh:
                rows = [r for r in csv.DictReader(fh)
                        if r.get("global_step", "").isdigit()
                        and int(r["global_step"]) <= global_step]
        buf = io.StringIO()
        w = csv.DictWriter(buf, FIELDS)
        w.writeheader()
        w.writerows({k: r.get(k, "") for k in FIELDS} for r in rows)
        atomic_write_text(self.path, buf.getvalue())

    def _write(self, row: dict) -> None:
        row["wall_s"] = round(time.monotonic() - self.t0, 2)
        self.writer.writerow({k: _fmt(row.get(k, "")) for k in FIELDS})
        self.fh.flush()
        if self.tb is not None:
            for k in ("loss", "cd_m", "pose_m2", "lr", "sigma_cd", "sigma_p", "frames_per_s"):
                if isinstance(row.get(k), float):
                    self.tb.add_scalar(f"{row['kind']}/{k}", row[k], row["global_step"])

    def train_row(self, stage: int, step: int, global_step: int, values: dict[str, float],
                  sigmas: tuple[float, float], every: int) -> None:
        """Accumulate one step; write the running means every ``every`` steps."""
        for k in ("loss", "cd", "pose"):
            if k in values:
                self._acc[k] = self._acc.get(k, 0.0) + values[k]
        self._acc["n"] = self._acc.get("n", 0.0) + 1
        self._acc["frames"] = self._acc.get("frames", 0.0) + values["frames"]
        if step % every:
            return
        now, n = time.monotonic(), self._acc["n"]
        row = {"kind": "train", "stage": stage + 1, "step": step, "global_step": global_step,
               "lr": values["lr"], "loss": self._acc.get("loss", 0.0) / n,
               "sigma_cd": sigmas[0], "sigma_p": sigmas[1],
               "frames_per_s": self._acc["frames"] / max(now - self.t_last, 1e-9)}
        if "cd" in self._acc:
            row["cd_m"] = self._acc["cd"] / n
        if "pose" in self._acc:
            row["pose_m2"] = self._acc["pose"] / n
        self._write(row)
        self._acc, self.t_last = {}, now

    def val_row(self, stage: int, step: int, global_step: int, values: dict[str, float],
                sigmas: tuple[float, float]) -> None:
        self._write({"kind": "val", "stage": stage + 1, "step": step,
                     "global_step": global_step, "loss": values["val_loss"],
                     "cd_m": values["val_cd_m"], "pose_m2": values["val_pose_m2"],
                     "sigma_cd": sigmas[0], "sigma_p": sigmas[1]})
        log.info("stage %d step %d: val CD %.4f m, pose %.4f m^2", stage + 1, step,
                 values["val_cd_m"], values["val_pose_m2"])

    def flush(self) -> None:
        self.fh.flush()
        if self.tb is not None:
            self.tb.flush()

    def close(self) -> None:
        self.fh.close()
        if self.tb is not None:
            self.tb.close()


def _fmt(v):
    return f"{v:.6g}" if isinstance(v, float) else v


def _tensorboard(path: Path):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        log.info("tensorboard is not installed: logging to log.csv only")
        return None
    return SummaryWriter(str(path))
