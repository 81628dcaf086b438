"""Break an evaluation's per-frame errors down by the number of detections so far, split
the rotation error into 180-degree flips and the rest, and split the tracks into parked and
moving vehicles, also by range from the sensor, at their first frame and by track length
against the training window (docs/results.md, Table I notes); list the tracks that carry the
flips (docs/history/model.md, "What the remaining flips are"), and compare how far away and how densely
the tracks that reach 17 detections are seen at their first detection and from the 17th on
(docs/results.md, Round 13: the detections ratio on the realistic set); with the evaluation's
``metrics.json`` beside the CSV, the sequential model's gains over the baseline above the
floors in the first 10 detections, from the 11th and from the 17th (docs/results.md, issue
19's targets).

Parked: the vehicle's distance to the sensor does not change over its track (spread below
1 cm). With the generator's fixed sensor and no range noise such a track repeats one view, so
it holds a single sample of the estimator's error however many frames it has.

Input: the ``per_frame.csv`` that ``seqshape evaluate`` writes (no timing; not part of
``make bench``).

Run: ``python benchmarks/analyse_eval.py EVAL/per_frame.csv``
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
from _bench import print_table

from seqshape.evaluation.report import FLIP_DEG

BINS = (1, 2, 3, 6, 11, 21, 41, 81)  # detections so far: [1], [2], [3-5], ..., [81+]
# finer at the lengths training windows have (32, 64, 128 frames): a recurrent model run past
# the length it was trained on can drift
LENGTH_BINS = (1, 2, 9, 17, 33, 49, 65, 97, 129)
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
                  for k in ("n_det", "cd_m", "cd_true_pose_m", "trans_m", "rot_rad", "emd_m",
                            "distance_m", "n_points", "frame")}
        out[m]["track_id"] = np.array([r["track_id"] for r in sel])
    return out


def parked_tracks(rec: dict[str, np.ndarray], spread_m: float = 0.01) -> set[str]:
    """Track ids whose distance to the sensor spans less than ``spread_m``."""
    out = set()
    for tid in np.unique(rec["track_id"]):
        d = rec["distance_m"][rec["track_id"] == tid]
        if np.ptp(d) < spread_m:
            out.add(str(tid))
    return out


def _fmt(values: np.ndarray, scale: float, digits: int) -> str:
    """The NaN-skipping mean of ``values * scale``, or "n/a" when none is known."""
    v = values[np.isfinite(values)]
    return f"{scale * v.mean():.{digits}f}" if len(v) else "n/a"


def motion_table(data: dict[str, dict[str, np.ndarray]]) -> None:
    """Errors of parked and moving tracks side by side, and per-track CD wins."""
    parked = parked_tracks(next(iter(data.values())))
    rows = []
    for group in ("parked", "moving"):
        track_cd: dict[str, dict[str, float]] = {}
        for m, rec in data.items():
            sel = np.isin(rec["track_id"], sorted(parked)) == (group == "parked")
            tids = np.unique(rec["track_id"][sel])
            for tid in tids:
                track_cd.setdefault(str(tid), {})[m] = float(
                    np.nanmean(rec["cd_m"][rec["track_id"] == tid]))
            rows.append([group, m, str(len(tids)), str(int(sel.sum())),
                         f"{100 * np.nanmean(rec['cd_m'][sel]):.2f}",
                         _fmt(rec["emd_m"][sel], 1.0, 3),
                         f"{100 * np.nanmean(rec['trans_m'][sel]):.2f}",
                         f"{np.degrees(np.nanmean(rec['rot_rad'][sel])):.2f}"])
        if {"sequential", "baseline"} <= set(data):
            wins = sum(v["sequential"] < v["baseline"] for v in track_cd.values())
            rows[-1].append(f"{wins} of {len(track_cd)}")
            rows[-2].append("")
    width = max(len(r) for r in rows)
    rows = [r + [""] * (width - len(r)) for r in rows]
    head = ["tracks", "method", "tracks", "frames", "CD (cm)", "EMD (m)", "translation (cm)",
            "rotation (deg)", "tracks where sequential has the lower CD"][:width]
    print_table(head, rows)


def range_table(data: dict[str, dict[str, np.ndarray]], near_m: float = 15.0) -> None:
    """Parked and moving tracks split at ``near_m`` from the sensor (frame-pooled CD and
    translation), and the CD of each track's first frame (mean over tracks)."""
    parked = parked_tracks(next(iter(data.values())))
    rows = []
    for group in ("parked", "moving"):
        for m, rec in data.items():
            in_group = np.isin(rec["track_id"], sorted(parked)) == (group == "parked")
            row = [group, m]
            for near in (True, False):
                sel = in_group & ((rec["distance_m"] < near_m) == near)
                row += [str(int(sel.sum())), _fmt(rec["cd_m"][sel], 100.0, 2),
                        _fmt(rec["trans_m"][sel], 100.0, 2)]
            first = rec["n_det"] == 1
            firsts = [rec["cd_m"][first & (rec["track_id"] == t)][:1]
                      for t in np.unique(rec["track_id"][in_group])]
            row.append(_fmt(np.concatenate(firsts) if firsts else np.zeros(0), 100.0, 2))
            rows.append(row)
    print_table(["tracks", "method", f"frames < {near_m:g} m", "CD (cm)", "translation (cm)",
                 f"frames >= {near_m:g} m", "CD (cm)", "translation (cm)",
                 "first-frame CD, mean over tracks (cm)"], rows)


def _labels(bins) -> list[str]:
    edges = list(bins) + [np.inf]
    return [f"{lo}" if hi - lo == 1 else (f"{lo}+" if hi == np.inf else f"{lo}-{hi - 1}")
            for lo, hi in zip(edges[:-1], edges[1:], strict=True)]


def length_table(data: dict[str, dict[str, np.ndarray]]) -> None:
    """Frame-pooled CD by detections so far (:data:`LENGTH_BINS`), parked and moving tracks
    apart: how the estimate evolves as a track gets longer."""
    parked = parked_tracks(next(iter(data.values())))
    edges = list(LENGTH_BINS) + [np.inf]
    rows = []
    for group in ("parked", "moving"):
        first = True
        for m, rec in data.items():
            in_group = np.isin(rec["track_id"], sorted(parked)) == (group == "parked")
            n = rec["n_det"]
            sels = [in_group & (n >= lo) & (n < hi)
                    for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
            if first:
                rows.append([group, "frames", *[str(int(s.sum())) for s in sels]])
                first = False
            rows.append([group, f"CD {m} (cm)", *[_fmt(rec["cd_m"][s], 100.0, 2) for s in sels]])
    print_table(["tracks", "detections so far", *_labels(LENGTH_BINS)], rows)


def flipped_tracks_table(data: dict[str, dict[str, np.ndarray]], top: int = 8) -> None:
    """Per method, the ``top`` tracks with the most flipped frames (rotation error above
    :data:`FLIP_DEG`), with their frames, median points and range, and first flipped frame."""
    rows = []
    for m, rec in data.items():
        flip = np.degrees(rec["rot_rad"]) > FLIP_DEG
        counts = {str(t): int(flip[rec["track_id"] == t].sum())
                  for t in np.unique(rec["track_id"][flip])}
        for tid, n in sorted(counts.items(), key=lambda kv: -kv[1])[:top]:
            sel = rec["track_id"] == tid
            rows.append([m, tid, int(sel.sum()), n, f"{np.median(rec['n_points'][sel]):.0f}",
                         f"{np.median(rec['distance_m'][sel]):.1f}",
                         int(rec["frame"][sel & flip].min())])
    print_table(["method", "track", "frames", "flipped", "points (median)", "range (m, median)",
                 "first flipped frame"], rows)


def late_views_table(data: dict[str, dict[str, np.ndarray]], late: int = 17) -> None:
    """For the tracks that reach ``late`` detections: the median over tracks of the range and
    the point count at the first detection and (each track's mean) from the ``late``-th on."""
    rec = next(iter(data.values()))
    first, later = [], []
    for tid in np.unique(rec["track_id"]):
        sel = rec["track_id"] == tid
        n = rec["n_det"][sel]
        if n.max() < late:
            continue
        first.append([rec[k][sel][n == 1][0] for k in ("distance_m", "n_points")])
        later.append([rec[k][sel][n >= late].mean() for k in ("distance_m", "n_points")])
    if not first:
        return
    f, g = np.median(first, axis=0), np.median(later, axis=0)
    print_table([f"tracks reaching {late}+ detections", "range (m)", "points"],
                [[f"first detection ({len(first)} tracks)", f"{f[0]:.1f}", f"{f[1]:.0f}"],
                 [f"{late}+ detections", f"{g[0]:.1f}", f"{g[1]:.0f}"]])


def gains_table(data: dict[str, dict[str, np.ndarray]], floors: dict) -> None:
    """The sequential model against the baseline by detections so far (the first 10, from
    the 11th, from the 17th, all), CD and EMD above the floors of ``metrics.json``
    (``cd_floor_cm``, ``emd_floor_m``) and translation, in per cent: where along the tracks
    the fusion gain is (docs/results.md, issue 19's targets)."""
    if not {"sequential", "baseline"} <= set(data):
        return
    cd0, emd0 = floors["cd_floor_cm"] / 100.0, floors["emd_floor_m"]
    rows = []
    for label, lo, hi in (("1-10", 1, 10), ("11+", 11, np.inf), ("17+", 17, np.inf),
                          ("all", 1, np.inf)):
        mean = {}
        for m in ("sequential", "baseline"):
            rec = data[m]
            sel = (rec["n_det"] >= lo) & (rec["n_det"] <= hi)
            mean[m] = [np.nanmean(rec["cd_m"][sel]) - cd0, np.nanmean(rec["emd_m"][sel]) - emd0,
                       np.nanmean(rec["trans_m"][sel])]
        gain = 100 * (np.array(mean["sequential"]) / np.array(mean["baseline"]) - 1)
        frames = int(((data["sequential"]["n_det"] >= lo)
                      & (data["sequential"]["n_det"] <= hi)).sum())
        rows.append([label, str(frames), *[f"{g:+.1f}" for g in gain]])
    print_table(["detections so far", "frames", "CD above floor (%)", "EMD above floor (%)",
                 "translation (%)"], rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("per_frame", help="EVAL/per_frame.csv from seqshape evaluate")
    args = ap.parse_args()
    data = read(args.per_frame)
    edges = list(BINS) + [np.inf]
    labels = _labels(BINS)
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
        f = r > FLIP_DEG
        flips.append([m, f"{r.mean():.1f}", f"{100 * f.mean():.1f}", f"{r[f].sum() / len(r):.1f}",
                      f"{r[~f].mean():.1f}", f"{np.median(r):.1f}"])
    print_table(["method", "rotation mean (deg)", f"flips > {FLIP_DEG:.0f} deg (% frames)",
                 "flips' share of the mean (deg)", "mean without flips (deg)", "median (deg)"],
                flips)
    print()
    motion_table(data)
    print()
    range_table(data)
    print()
    length_table(data)
    print()
    metrics = Path(args.per_frame).with_name("metrics.json")
    if metrics.exists():  # the floors the evaluation measured
        gains_table(data, json.loads(metrics.read_text()))
        print()
    flipped_tracks_table(data)
    print()
    late_views_table(data)


if __name__ == "__main__":
    main()
