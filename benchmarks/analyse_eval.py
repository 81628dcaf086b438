"""Break an evaluation's per-frame errors down by the number of detections so far, and split
the rotation error into 180-degree flips and the rest (docs/results.md, Table I notes).

Input: the ``per_frame.csv`` that ``seqshape evaluate`` writes (no timing; not part of
``make bench``).

Run: ``python benchmarks/analyse_eval.py EVAL/per_frame.csv``
"""

from __future__ import annotations

import argparse
import csv

import numpy as np
from _bench import print_table

BINS = (1, 2, 3, 6, 11, 21, 41, 81)  # detections so far: [1], [2], [3-5], ..., [81+]
ROWS = (("CD", "cd_m"), ("shape CD at the true pose", "cd_true_pose_m"),
        ("translation", "trans_m"))


def read(path) -> dict[str, dict[str, np.ndarray]]:
    """``{method: {column: values}}`` from a per_frame.csv (empty cells become NaN)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    out: dict[str, dict[str, np.ndarray]] = {}
    for m in sorted({r["method"] for r in rows}):
        sel = [r for r in rows if r["method"] == m]
        out[m] = {k: np.array([float(r[k]) if r[k] else np.nan for r in sel])
                  for k in ("n_det", "cd_m", "cd_true_pose_m", "trans_m", "rot_rad")}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("per_frame", help="EVAL/per_frame.csv from seqshape evaluate")
    args = ap.parse_args()
    data = read(args.per_frame)
    edges = list(BINS) + [np.inf]
    labels = [f"{lo}" if hi - lo == 1 else (f"{lo}+" if hi == np.inf else f"{lo}-{hi - 1}")
              for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    first = next(iter(data.values()))["n_det"]
    rows = [["frames", *[str(int(((first >= lo) & (first < hi)).sum()))
                         for lo, hi in zip(edges[:-1], edges[1:], strict=True)]]]
    for name, col in ROWS:
        for m, rec in data.items():
            n = rec["n_det"]
            rows.append([f"{name} {m} (cm)", *[
                f"{100 * np.nanmean(rec[col][(n >= lo) & (n < hi)]):.1f}"
                for lo, hi in zip(edges[:-1], edges[1:], strict=True)]])
    print_table(["detections so far", *labels], rows)
    print()
    flips = []
    for m, rec in data.items():
        r = np.degrees(rec["rot_rad"][np.isfinite(rec["rot_rad"])])
        f = r > 150
        flips.append([m, f"{r.mean():.1f}", f"{100 * f.mean():.1f}", f"{r[f].sum() / len(r):.1f}",
                      f"{r[~f].mean():.1f}", f"{np.median(r):.1f}"])
    print_table(["method", "rotation mean (deg)", "flips > 150 deg (% frames)",
                 "flips' share of the mean (deg)", "mean without flips (deg)", "median (deg)"],
                flips)


if __name__ == "__main__":
    main()
