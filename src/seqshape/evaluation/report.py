"""Averages as in the paper's Table I, ``metrics.json``, ``metrics.md`` and ``per_frame.csv``.

Averaging: every metric is the mean over all scored frames of all tracks pooled together (a
long track weighs more than a short one), skipping frames where it is undefined (EMD on frames
not sampled by ``emd_every``, unknown poses). The CD floor is averaged the same way: each
track's floor weighted by its number of frames with a CD.

``metrics.json``::

    {"sequential": {"cd_cm", "emd_m", "trans_cm", "rot_deg"},
     "baseline":   {"cd_cm", "emd_m", "trans_cm", "rot_deg"},
     "cd_floor_cm": float,
     "details": {method: {medians, per-track means, frame counts, "shape_cd_cm",
                          180-degree flips: "rot_flip_frames", "rot_flip_tracks",
                          "rot_deg_without_flips"}},
     "floor": {...}, "settings": {...}, "paper": {...}}
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from seqshape._io import atomic_open, atomic_write_json, atomic_write_text
from seqshape.errors import SeqshapeError
from seqshape.evaluation.runner import FIELDS, EvalResult

#: The paper's Table I (synthetic data): CD cm, EMD m, translation cm, rotation deg.
PAPER_TABLE = {
    "baseline": {"cd_cm": 3.1, "emd_m": 0.50, "trans_cm": 12.2, "rot_deg": 20.2},
    "sequential": {"cd_cm": 2.3, "emd_m": 0.25, "trans_cm": 9.4, "rot_deg": 12.0},
}
#: Report key -> (record column, scale from SI units).
METRICS = {"cd_cm": ("cd_m", 100.0), "emd_m": ("emd_m", 1.0),
           "trans_cm": ("trans_m", 100.0), "rot_deg": ("rot_rad", 180.0 / math.pi)}
LABELS = {"cd_cm": "CD (cm)", "emd_m": "EMD (m)", "trans_cm": "Translation (cm)",
          "rot_deg": "Rotation (deg)"}
#: Diagnostics beyond Table I, summarised the same way (not plotted).
EXTRA_METRICS = {"shape_cd_cm": ("cd_true_pose_m", 100.0)}
EXTRA_LABELS = {"shape_cd_cm": "shape CD at the true pose (cm)"}
#: A rotation error above this (degrees) counts as a 180-degree flip: the box faces backwards.
FLIP_DEG = 150.0


def _mean(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else None


def _median(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.median(x)) if len(x) else None


def method_summary(rec: dict[str, np.ndarray]) -> tuple[dict[str, float | None], dict[str, Any]]:
    """``(table, details)`` for one method's records: frame-pooled means in report units, and
    medians, per-track means and frame counts."""
    table, details = {}, {"n_frames": int(len(rec["frame"])),
                          "n_tracks": int(len(np.unique(rec["track_id"])))}
    tracks = rec["track_id"]
    for key, (col, scale) in {**METRICS, **EXTRA_METRICS}.items():
        v = rec[col] * scale
        (table if key in METRICS else details)[key] = _mean(v)
        details[f"{key}_median"] = _median(v)
        per_track = [_mean(v[tracks == t]) for t in np.unique(tracks)]
        per_track = np.array([p for p in per_track if p is not None])
        details[f"{key}_track_mean"] = _mean(per_track) if len(per_track) else None
        details[f"n_{col}"] = int(np.isfinite(v).sum())
    rot = np.degrees(rec["rot_rad"])
    known = np.isfinite(rot)
    flip = known & (rot > FLIP_DEG)
    details.update(rot_flip_frames=int(flip.sum()), rot_flip_tracks=len(np.unique(tracks[flip])),
                   rot_deg_without_flips=_mean(rot[known & ~flip]))
    return table, details


def floor_summary(result: EvalResult, method: str) -> dict[str, Any]:
    """The CD floor (cm) for ``method``'s point count, weighted by frames with a CD."""
    k = result.settings.get("n_pred_points", {}).get(method)
    fl = result.floors
    sel = fl["n_pred"] == k
    rec = result.of(method)
    frames = {t: int(np.isfinite(rec["cd_m"][rec["track_id"] == t]).sum())
              for t in np.unique(rec["track_id"])}
    w = np.array([frames.get(t, 0) for t in fl["track_id"][sel]], dtype=np.float64)
    vals = fl["floor_m"][sel]
    value = float((vals * w).sum() / w.sum() * 100.0) if w.sum() > 0 else None
    return {"cd_floor_cm": value, "n_pred": k, "n_tracks": int(sel.sum()),
            "methods": sorted(set(fl["method"][sel].tolist()))}


def summarize(result: EvalResult, reference: str = "sequential") -> dict[str, Any]:
    """The ``metrics.json`` dictionary (see the module docstring)."""
    out: dict[str, Any] = {}
    details = {}
    for m in result.methods:
        out[m], details[m] = method_summary(result.of(m))
    floors = {m: floor_summary(result, m) for m in result.methods}
    ref = reference if reference in floors else result.methods[0]
    out["cd_floor_cm"] = floors[ref]["cd_floor_cm"]
    out["details"] = details
    out["floor"] = {"reference_method": ref, **floors[ref], "per_method": floors}
    out["settings"] = result.settings
    out["paper"] = PAPER_TABLE
    return out


def _fmt(v: float | None, key: str) -> str:
    if v is None:
        return "n/a"
    return f"{v:.3f}" if key == "emd_m" else f"{v:.2f}"


def metrics_markdown(summary: dict[str, Any]) -> str:
    """A markdown table of ours beside the paper's Table I, plus the CD floor and settings."""
    head = "| Method | " + " | ".join(LABELS.values()) + " |"
    lines = [head, "|" + "---|" * (len(LABELS) + 1)]
    methods = [m for m in ("baseline", "sequential") if m in summary]
    methods += [m for m in summary.get("details", {}) if m not in methods]
    for m in methods:
        row = [_fmt(summary[m].get(k), k) for k in LABELS]
        lines.append(f"| {m} (ours) | " + " | ".join(row) + " |")
        if m in PAPER_TABLE:
            row = [_fmt(PAPER_TABLE[m][k], k) for k in LABELS]
            lines.append(f"| {m} (paper) | " + " | ".join(row) + " |")
    s = summary.get("settings", {})
    fl = summary.get("floor", {})
    floor = summary.get("cd_floor_cm")
    lines += ["", f"CD floor (two independent samplings of the true surface, "
                  f"{fl.get('n_pred', '?')} estimated points, method "
                  f"{'/'.join(fl.get('methods', [])) or '?'}): "
                  f"{'n/a' if floor is None else f'{floor:.2f}'} cm.",
              f"Frame-pooled means over {s.get('n_tracks', '?')} tracks, each run from its first "
              f"to its last detection; EMD exact on {s.get('emd_points', '?')}-point subsamples, "
              f"every {s.get('emd_every', '?')} frame(s)."]
    for m in methods:
        d = summary.get("details", {}).get(m, {})
        lines.append(f"- {m}: {d.get('n_frames', '?')} frames, {d.get('n_emd_m', '?')} with EMD.")
    for key, label in EXTRA_LABELS.items():
        det = summary.get("details", {})
        vals = [f"{m} {_fmt(det[m][key], key)}" for m in methods
                if det.get(m, {}).get(key) is not None]
        if vals:
            lines.append(f"- Diagnostic, {label}: " + ", ".join(vals) + " (the estimated "
                         "shape alone, placed at the true pose; CD minus this is the cost of "
                         "the estimated placement).")
    flips = [_flip_text(m, summary["details"][m]) for m in methods
             if "rot_flip_frames" in summary.get("details", {}).get(m, {})]
    if flips:
        lines.append(f"- Diagnostic, 180-degree flips (rotation error > {FLIP_DEG:.0f} deg): "
                     + "; ".join(flips) + ". A flip costs a nearly symmetric car little CD but "
                     "a large rotation error; over few tracks one flipped track can dominate "
                     "the mean.")
    return "\n".join(lines) + "\n"


def _flip_text(method: str, d: dict[str, Any]) -> str:
    n = d["rot_flip_tracks"]
    return (f"{method} {d['rot_flip_frames']} of {d.get('n_rot_rad', '?')} frames in {n} "
            f"track{'' if n == 1 else 's'}, rotation without them "
            f"{_fmt(d.get('rot_deg_without_flips'), 'rot_deg')} deg")


def write_per_frame_csv(path: str | Path, result: EvalResult) -> None:
    """One row per method and scored frame, columns :data:`FIELDS` (SI units)."""
    rec = result.records
    with atomic_open(path, "w") as fh:
        w = csv.writer(fh)
        w.writerow(FIELDS)
        for i in range(len(rec["method"])):
            w.writerow([_csv_value(rec[k][i]) for k in FIELDS])


def _csv_value(v):
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.6g}"
    return v.item() if isinstance(v, np.generic) else v


def write_metrics(out_dir: str | Path, result: EvalResult,
                  required: tuple[str, ...] = ("sequential", "baseline")) -> dict[str, Any]:
    """Write ``metrics.json``, ``metrics.md`` and ``per_frame.csv`` into ``out_dir``."""
    missing = [m for m in required if m not in result.methods]
    if missing:
        raise SeqshapeError(f"evaluation lacks the methods {missing} (has {result.methods})")
    out_dir = Path(out_dir)
    summary = summarize(result)
    atomic_write_json(out_dir / "metrics.json", summary)
    atomic_write_text(out_dir / "metrics.md", metrics_markdown(summary))
    write_per_frame_csv(out_dir / "per_frame.csv", result)
    return summary
