"""Averages as in the paper's Table I, ``metrics.json``, ``metrics.md`` and ``per_frame.csv``.

Averaging: every metric is the mean over all scored frames of all tracks pooled together (a
long track weighs more than a short one), skipping frames where it is undefined (EMD on frames
not sampled by ``emd_every``, unknown poses). The CD floor is averaged the same way: each
track's floor weighted by its number of frames with a CD; the EMD floor (``emd_floor_m``, null
without EMD) by its frames with an EMD. ``"above_floor"`` compares the sequential model with
the baseline on the parts of their CD and EMD above the floors (issue 19):
``{"cd_pct", "emd_pct", "emd_raw_pct", "trans_pct", "rot_pct", "rot_noflip_pct"}``, the change
in % (negative: the sequential model is better; the last compares the rotation errors of the
frames that are not 180-degree flips, ``details[m]["rot_deg_without_flips"]``, so that a few
tracks held backwards do not hide the rest), or absent without both methods.

``metrics.json``::

    {"sequential": {"cd_cm", "emd_m", "trans_cm", "rot_deg"},
     "baseline":   {"cd_cm", "emd_m", "trans_cm", "rot_deg"},
     "cd_floor_cm": float, "emd_floor_m": float | null, "above_floor": {...},
     "details": {method: {medians, per-track means, frame counts, "shape_cd_cm",
                          180-degree flips: "rot_flip_frames", "rot_flip_tracks",
                          "rot_deg_without_flips"}},
     "floor": {...}, "settings": {...}, "paper": {...}}

``details`` also holds, per method, the flip rate (``rot_flip_rate``: flipped frames over frames
with a known pose), the rotation error modulo 180 degrees (``rot_axis_deg``), the signed radial
and absolute tangential translation errors and the signed and absolute length/width errors
(cm), each as a mean and a median.

Per track and per detection count (issue 19), ``details[method]`` also holds ``"flips"``
(:func:`seqshape.evaluation.metrics.flip_stats` at :data:`FLIP_DEG`: % of frames flipped, share
of tracks with any flip, median over tracks of each track's flipped share), ``"by_detections"``
(``{"all" | "moving" | "passed" | "parked": {"1" | "2-4" | "5-8" | "9-16" | "17+": {n_frames,
n_tracks, cd_cm, trans_cm, rot_deg, flip_pct}}}``, frame-pooled means; parked: the true distance
from the sensor spans less than :data:`PARKED_SPREAD_M`; passed: a vehicle parked in the fixed
frame of the ego poses, seen from a driving ego: :func:`motion_groups`), ``"flip_groups"`` (%
of frames flipped per group) and ``"late_over_first"`` (``{group: {"cd",
"trans", "cd_above_floor"}}``: the error at 17+ detections over the error at the first
detection, over the tracks that have both, each track weighing the same: :func:`late_over_first`;
the last of the CD minus the track's CD floor). ``metrics.md`` prints
the flips per track under the table and a table of errors by detections so far.

Real data (``settings["real"]``: a track's meta says ``source: "real"``): ``metrics.json`` gains
``"breakdown"``: ``{"all" | "class_group" | "class" | "distance" | "points" | "annotation" |
"face_gap": {group: {method: stats}}}`` with :data:`BREAKDOWN_STATS` (medians and means, cm / deg / %) per
group: all frames, car vs larger vehicles (van, truck, bus, trailer), each class, distance bins
:data:`DISTANCE_BINS` (m), points-per-frame bins :data:`POINT_BINS`, and whether the annotated
box holds the frame's points (``ref_face_gap_m`` at most :data:`BOX_FITS_M`: "box fits its
points", else "box off its points"; frames too sparse to tell are in neither) and, finer, by
that gap in the bins of :data:`GAP_EDGES_M` (``"face_gap"``). ``metrics.md`` labels
the CD "CD vs accumulated reference", leaves out the paper's rows (synthetic data) and adds the
breakdown tables (medians, then means).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from seqshape._io import atomic_open, atomic_write_json, atomic_write_text
from seqshape.errors import SeqshapeError
from seqshape.evaluation.metrics import flip_stats
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
EXTRA_METRICS = {"shape_cd_cm": ("cd_true_pose_m", 100.0),
                 "ref_to_est_cm": ("ref_to_est_m", 100.0)}
EXTRA_LABELS = {"shape_cd_cm": "shape CD at the true pose (cm)",
                "ref_to_est_cm": "reference to estimate, one-way (cm)"}
EXTRA_NOTES = {"shape_cd_cm": "the estimated shape alone, placed at the true pose; CD minus this "
                              "is the cost of the estimated placement",
               "ref_to_est_cm": "mean distance from each ground-truth or reference point to the "
                                "estimate: on real tracks, the half of the CD that an "
                                "accumulated reference, which lacks the unseen sides, can judge"}
REAL_CD_LABEL = "CD vs accumulated reference (cm)"
#: A rotation error above this (degrees) counts as a 180-degree flip: the box faces backwards.
FLIP_DEG = 150.0
#: Per-method diagnostics in ``details``: key -> (record column, scale, take absolute value).
POSE_EXTENT_METRICS = {
    "rot_axis_deg": ("rot_axis_rad", 180.0 / math.pi, False),
    "radial_cm": ("radial_m", 100.0, False), "radial_abs_cm": ("radial_m", 100.0, True),
    "tangential_abs_cm": ("tangential_m", 100.0, True),
    "length_err_cm": ("length_err_m", 100.0, False),
    "length_abs_cm": ("length_err_m", 100.0, True),
    "width_err_cm": ("width_err_m", 100.0, False), "width_abs_cm": ("width_err_m", 100.0, True),
}
#: Statistics of each breakdown group (medians and means): key -> (column, scale, absolute).
BREAKDOWN_STATS = {"centre_cm": ("trans_m", 100.0, False), **POSE_EXTENT_METRICS,
                   "rot_deg": ("rot_rad", 180.0 / math.pi, False),
                   "cd_cm": ("cd_m", 100.0, False),
                   "ref_to_est_cm": ("ref_to_est_m", 100.0, False),
                   "est_near_out_pct": ("est_near_out", 100.0, False),
                   "est_far_out_pct": ("est_far_out", 100.0, False),
                   "ref_near_out_pct": ("ref_near_out", 100.0, False),
                   "ref_far_out_pct": ("ref_far_out", 100.0, False),
                   "length_rel_abs_pct": ("length_rel_err", 100.0, True)}
LARGER = ("van", "truck", "bus", "trailer")
#: Distance bins (m, lower edges; the last is open) and points-per-frame bins (lower edges).
DISTANCE_BINS = (0.0, 10.0, 20.0, 30.0, 50.0)
POINT_BINS = (0, 1, 10, 30, 100, 300, 1000)
#: Detections-so-far groups (lower edges, the last open): 1, 2-4, 5-8, 9-16, 17+.
DETECTION_BINS = (1, 2, 5, 9, 17)
#: A track whose true distance from the sensor spans less than this (m) over its scored frames
#: is "parked": the sensor sees one repeated view (a static vehicle and a static sensor).
PARKED_SPREAD_M = 0.01
#: A track whose true centre travels less than this (m) in the fixed frame of its ego poses
#: while its view changes is a parked vehicle passed by a moving ego (the "passed" group).
PASSED_TRAVEL_M = 1.0
#: Errors followed by detections so far: report key -> (record column, scale).
DETECTION_METRICS = {"cd_cm": ("cd_m", 100.0), "trans_cm": ("trans_m", 100.0),
                     "rot_deg": ("rot_rad", 180.0 / math.pi)}


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
        if key in EXTRA_METRICS and col not in rec:  # records of an older version
            continue
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
                   rot_deg_without_flips=_mean(rot[known & ~flip]),
                   rot_deg_without_flips_median=_median(rot[known & ~flip]),
                   rot_flip_rate=float(flip.sum() / known.sum()) if known.any() else None)
    for key, (col, scale, absolute) in POSE_EXTENT_METRICS.items():
        if col in rec:
            v = rec[col] * scale
            v = np.abs(v) if absolute else v
            details[key], details[f"{key}_median"] = _mean(v), _median(v)
    details["flips"] = flip_stats(rec["rot_rad"], tracks, FLIP_DEG)
    if "distance_m" in rec:
        details["flip_groups"] = flip_groups(rec)
    if "n_det" in rec and "distance_m" in rec:
        details["by_detections"], details["late_over_first"] = detection_summary(rec)
    return table, details


def motion_groups(rec: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Frame masks ``{"all", "moving", "parked", "passed"}`` over one method's records (empty
    groups left out). Parked: the track's true distance from the sensor spans less than
    :data:`PARKED_SPREAD_M` (one repeated view); moving: every other track (its view changes;
    with a moving ego, real logs, nearly every track). Passed, a part of moving: the track
    itself travels less than :data:`PASSED_TRAVEL_M` in the fixed frame of its ego poses
    (``world_travel_m``): a parked vehicle seen from a driving ego, from changing angles."""
    tracks, dist = rec["track_id"], rec["distance_m"]
    names, which = np.unique(tracks, return_inverse=True)
    lo = np.full(len(names), np.inf)
    hi = np.full(len(names), -np.inf)
    ok = np.isfinite(dist)
    np.minimum.at(lo, which[ok], dist[ok])
    np.maximum.at(hi, which[ok], dist[ok])
    parked = (hi - lo < PARKED_SPREAD_M)[which]  # (N,) per frame
    groups = {"all": np.ones(len(tracks), bool), "moving": ~parked, "parked": parked}
    if "world_travel_m" in rec:  # records of an older version have no travel
        with np.errstate(invalid="ignore"):
            groups["passed"] = ~parked & (rec["world_travel_m"] < PASSED_TRAVEL_M)
    return {g: m for g, m in groups.items() if m.any()}


def flip_groups(rec: dict[str, np.ndarray]) -> dict[str, float | None]:
    """% of frames flipped (rotation error above :data:`FLIP_DEG`) in each of
    :func:`motion_groups`; None where a group has no known rotation."""
    return {g: flip_stats(rec["rot_rad"][m], rec["track_id"][m], FLIP_DEG)["flip_pct"]
            for g, m in motion_groups(rec).items()}


#: The 17+ over first-detection ratios (:func:`detection_summary`): name -> record column;
#: ``cd_above_floor_m`` (the CD minus the track's CD floor) is added by :func:`summarize`.
RATIO_COLUMNS = (("cd", "cd_m"), ("trans", "trans_m"), ("cd_above_floor", "cd_above_floor_m"))


def with_floor(result: EvalResult, method: str) -> dict[str, np.ndarray]:
    """``method``'s records with ``cd_above_floor_m``: each frame's CD minus its track's CD
    floor at the method's point count (NaN where the track has none)."""
    rec = result.of(method)
    k = result.settings.get("n_pred_points", {}).get(method)
    fl = result.floors
    sel = fl["n_pred"] == k
    floor = dict(zip(fl["track_id"][sel].tolist(), fl["floor_m"][sel].tolist(), strict=True))
    per_frame = np.array([floor.get(t, np.nan) for t in rec["track_id"].tolist()], np.float64)
    return {**rec, "cd_above_floor_m": rec["cd_m"] - per_frame}


def detection_summary(rec: dict[str, np.ndarray]) -> tuple[dict, dict]:
    """Errors by detections so far, per motion group (:func:`motion_groups`).

    Returns ``(by_detections, late_over_first)``: ``{group: {bin: stats}}`` over the bins of
    :data:`DETECTION_BINS` (labels "1", "2-4", ..., "17+"), stats = ``n_frames``,
    ``n_tracks``, frame-pooled means of :data:`DETECTION_METRICS` and ``flip_pct``; and
    ``{group: {"cd": r, "trans": r, "cd_above_floor": r}}`` (the last with
    :func:`with_floor`'s column), the error at 17+ detections over the error at the first
    detection on the same tracks (:func:`late_over_first`). The bins pool their frames
    (the 17+ bin holds only the tracks that reach 17 detections, each weighted by its frames
    there); the ratios do not.
    """
    labels = DETECTION_LABELS
    which = np.digitize(rec["n_det"], DETECTION_BINS) - 1  # -1: before any detection
    by_det: dict[str, dict[str, dict[str, Any]]] = {}
    ratios: dict[str, dict[str, float | None]] = {}
    for group, in_group in motion_groups(rec).items():
        by_det[group] = {}
        for i, label in enumerate(labels):
            sel = in_group & (which == i)
            if not sel.any():
                continue
            st: dict[str, Any] = {"n_frames": int(sel.sum()),
                                  "n_tracks": int(len(np.unique(rec["track_id"][sel])))}
            for key, (col, scale) in DETECTION_METRICS.items():
                st[key] = _mean(rec[col][sel] * scale)
            st["flip_pct"] = flip_stats(rec["rot_rad"][sel], rec["track_id"][sel],
                                        FLIP_DEG)["flip_pct"]
            by_det[group][label] = st
        ratios[group] = {name: late_over_first(rec, in_group, which == 0,
                                               which == len(labels) - 1, col)
                         for name, col in RATIO_COLUMNS if col in rec}
    return by_det, ratios


def late_over_first(rec: dict[str, np.ndarray], in_group: np.ndarray, first: np.ndarray,
                    late: np.ndarray, col: str) -> float | None:
    """The late error over the first, on the same tracks with the same weight each.

    Over the tracks of ``in_group`` with a finite ``col`` in both the ``first`` and the
    ``late`` frames: the mean over tracks of each track's mean error over its late frames,
    divided by the mean over the same tracks of their mean error over their first frames.
    Matching the tracks keeps the ratio free of who reaches the late bin and of how long they
    stay there (a per-frame estimator on a repeated view scores about 1). None without such
    a track or when the first errors are all 0.
    """
    v = rec[col]
    means = []
    for sel in (first, late):
        ok = in_group & sel & np.isfinite(v)
        names, which = np.unique(rec["track_id"][ok], return_inverse=True)
        means.append(dict(zip(names.tolist(), np.bincount(which, weights=v[ok])
                              / np.bincount(which), strict=True)))
    common = sorted(set(means[0]) & set(means[1]))
    if not common:
        return None
    a = np.mean([means[0][t] for t in common])
    return float(np.mean([means[1][t] for t in common]) / a) if a > 0 else None


def group_stats(rec: dict[str, np.ndarray], sel: np.ndarray) -> dict[str, Any]:
    """:data:`BREAKDOWN_STATS` (``*_median`` and ``*_mean``), frame and track counts, the flip
    rate (%) and the rotation without flips over the frames ``sel`` of one method."""
    out: dict[str, Any] = {"n_frames": int(sel.sum()),
                           "n_tracks": int(len(np.unique(rec["track_id"][sel])))}
    for key, (col, scale, absolute) in BREAKDOWN_STATS.items():
        if col not in rec:  # records of an older version
            continue
        v = rec[col][sel] * scale
        v = np.abs(v) if absolute else v
        out[f"{key}_median"], out[f"{key}_mean"] = _median(v), _mean(v)
    rot = np.degrees(rec["rot_rad"][sel])
    known = np.isfinite(rot)
    flip = known & (rot > FLIP_DEG)
    out["flip_pct"] = float(100.0 * flip.sum() / known.sum()) if known.any() else None
    out["rot_deg_without_flips_median"] = _median(rot[known & ~flip])
    out["rot_deg_without_flips_mean"] = _mean(rot[known & ~flip])
    return out


def _bin_labels(edges: tuple, unit: str, integer: bool) -> list[str]:
    labels = []
    for i, lo in enumerate(edges):
        hi = edges[i + 1] if i + 1 < len(edges) else None
        if integer:
            top = None if hi is None else hi - 1
            labels.append(f"{lo}+" if top is None else str(lo) if top == lo else f"{lo}-{top}")
        else:
            labels.append(f"{lo:g}+ {unit}" if hi is None else f"{lo:g}-{hi:g} {unit}")
    return labels


#: Labels of :data:`DETECTION_BINS`: "1", "2-4", "5-8", "9-16", "17+".
DETECTION_LABELS = tuple(_bin_labels(DETECTION_BINS, "", True))


#: A box whose faces seen head-on lie at most this far in front of the frame's points (m)
#: "fits its points" (the synthetic traffic set's median face gap is 0.04 m).
BOX_FITS_M = 0.15
#: Edges (m) of the finer "face_gap" breakdown: at most 5 cm (the box holds its points, or they
#: stand out of it), 5-15, 15-30 and over 30 cm. On the Argoverse 2 log every method's radial
#: error follows the gap:
#: (docs/history/results.md, "Fusion above the sampling floors; the encoder in int8 (2026-12-04, session 21)")
GAP_EDGES_M = (0.05, 0.15, 0.30)


def frame_groups(rec: dict[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
    """Boolean masks of the breakdown groups (module doc) over one method's records; empty
    groups are left out."""
    cls = rec["class"]
    groups: dict[str, dict[str, np.ndarray]] = {
        "all": {"all": np.ones(len(cls), bool)},
        "class_group": {"car": cls == "car", "larger (van/truck/bus/trailer)": np.isin(cls, LARGER),
                        "unknown class": cls == ""},
        "class": {c: cls == c for c in sorted(set(cls.tolist())) if c},
    }
    for name, col, edges, unit, integer in (("distance", "distance_m", DISTANCE_BINS, "m", False),
                                            ("points", "n_points", POINT_BINS, "", True)):
        which = np.digitize(rec[col], edges) - 1
        groups[name] = {lab: which == i
                        for i, lab in enumerate(_bin_labels(edges, unit, integer))}
    if "ref_face_gap_m" in rec:
        gap = np.asarray(rec["ref_face_gap_m"], dtype=np.float64)
        with np.errstate(invalid="ignore"):
            groups["annotation"] = {f"box fits its points (<= {BOX_FITS_M:g} m)": gap <= BOX_FITS_M,
                                    f"box off its points (> {BOX_FITS_M:g} m)": gap > BOX_FITS_M}
            edges = (-np.inf, *GAP_EDGES_M, np.inf)
            groups["face_gap"] = {_gap_label(lo, hi): (gap > lo) & (gap <= hi)
                                  for lo, hi in zip(edges[:-1], edges[1:], strict=True)}
    return {k: {g: m for g, m in v.items() if m.any()} for k, v in groups.items()}


def _gap_label(lo: float, hi: float) -> str:
    """The label of one face-gap bin (cm)."""
    if not np.isfinite(lo):
        return f"gap <= {100 * hi:g} cm"
    if not np.isfinite(hi):
        return f"gap > {100 * lo:g} cm"
    return f"gap {100 * lo:g}-{100 * hi:g} cm"


def breakdown(result: EvalResult) -> dict[str, dict[str, dict[str, Any]]]:
    """``{breakdown: {group: {method: group_stats}}}`` (module doc)."""
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for m in result.methods:
        rec = result.of(m)
        for kind, groups in frame_groups(rec).items():
            for g, sel in groups.items():
                out.setdefault(kind, {}).setdefault(g, {})[m] = group_stats(rec, sel)
    return out


def floor_summary(result: EvalResult, method: str) -> dict[str, Any]:
    """The CD floor (cm) for ``method``'s point count, weighted by frames with a CD, and the
    EMD floor (m), weighted by frames with an EMD (None without)."""
    k = result.settings.get("n_pred_points", {}).get(method)
    fl = result.floors
    sel = fl["n_pred"] == k
    rec = result.of(method)

    def weighted(values: np.ndarray, column: str) -> float | None:
        frames = {t: int(np.isfinite(rec[column][rec["track_id"] == t]).sum())
                  for t in np.unique(rec["track_id"])}
        w = np.array([frames.get(t, 0) for t in fl["track_id"][sel]], dtype=np.float64)
        ok = np.isfinite(values) & (w > 0)
        return float((values[ok] * w[ok]).sum() / w[ok].sum()) if ok.any() else None

    cd = weighted(fl["floor_m"][sel], "cd_m")
    emd = fl.get("emd_floor_m")
    return {"cd_floor_cm": None if cd is None else cd * 100.0,
            "emd_floor_m": None if emd is None else weighted(emd[sel], "emd_m"),
            "n_pred": k, "n_tracks": int(sel.sum()),
            "methods": sorted(set(fl["method"][sel].tolist()))}


def above_floor(summary: dict[str, Any], floors: dict[str, dict[str, Any]],
                details: dict[str, dict[str, Any]] | None = None
                ) -> dict[str, float | None] | None:
    """The sequential model against the baseline (issue 19): the change (%) of the CD and EMD
    above their floors, of the raw EMD, the translation, the rotation and (with ``details``)
    the rotation without flipped frames; None without both."""
    if "sequential" not in summary or "baseline" not in summary:
        return None
    seq, base = summary["sequential"], summary["baseline"]

    def change(a: float | None, b: float | None) -> float | None:
        if a is None or b is None or not np.isfinite(a) or not np.isfinite(b) or b <= 0:
            return None
        return float(100.0 * (a - b) / b)

    def above(key: str, floor_key: str) -> tuple[float | None, float | None]:
        fs, fb = floors["sequential"].get(floor_key), floors["baseline"].get(floor_key)
        if None in (seq.get(key), base.get(key), fs, fb):
            return None, None
        return seq[key] - fs, base[key] - fb

    return {"cd_pct": change(*above("cd_cm", "cd_floor_cm")),
            "emd_pct": change(*above("emd_m", "emd_floor_m")),
            "emd_raw_pct": change(seq.get("emd_m"), base.get("emd_m")),
            "trans_pct": change(seq.get("trans_cm"), base.get("trans_cm")),
            "rot_pct": change(seq.get("rot_deg"), base.get("rot_deg")),
            "rot_noflip_pct": change(*[(details or {}).get(m, {}).get("rot_deg_without_flips")
                                       for m in ("sequential", "baseline")])}


def summarize(result: EvalResult, reference: str = "sequential") -> dict[str, Any]:
    """The ``metrics.json`` dictionary (see the module docstring)."""
    out: dict[str, Any] = {}
    details = {}
    for m in result.methods:
        out[m], details[m] = method_summary(with_floor(result, m))
    floors = {m: floor_summary(result, m) for m in result.methods}
    ref = reference if reference in floors else result.methods[0]
    out["cd_floor_cm"] = floors[ref]["cd_floor_cm"]
    out["emd_floor_m"] = floors[ref]["emd_floor_m"]
    gains = above_floor(out, floors, details)
    if gains is not None:
        out["above_floor"] = gains
    out["details"] = details
    out["floor"] = {"reference_method": ref, **floors[ref], "per_method": floors}
    out["settings"] = result.settings
    out["paper"] = PAPER_TABLE
    if result.settings.get("real"):
        out["breakdown"] = breakdown(result)
    return out


def _fmt(v: float | None, key: str) -> str:
    if v is None:
        return "n/a"
    return f"{v:.3f}" if key == "emd_m" else f"{v:.2f}"


def metrics_markdown(summary: dict[str, Any]) -> str:
    """A markdown table of ours beside the paper's Table I, plus the CD floor and settings."""
    s = summary.get("settings", {})
    real = bool(s.get("real"))
    labels = {**LABELS, "cd_cm": REAL_CD_LABEL} if real else LABELS
    head = "| Method | " + " | ".join(labels.values()) + " |"
    lines = [head, "|" + "---|" * (len(labels) + 1)]
    methods = [m for m in ("baseline", "sequential") if m in summary]
    methods += [m for m in summary.get("details", {}) if m not in methods]
    for m in methods:
        row = [_fmt(summary[m].get(k), k) for k in labels]
        lines.append(f"| {m}{'' if real else ' (ours)'} | " + " | ".join(row) + " |")
        if m in PAPER_TABLE and not real:
            row = [_fmt(PAPER_TABLE[m][k], k) for k in labels]
            lines.append(f"| {m} (paper) | " + " | ".join(row) + " |")
    fl = summary.get("floor", {})
    floor = summary.get("cd_floor_cm")
    surface = ("two halves of the accumulated reference" if real
               else "two independent samplings of the true surface")
    lines += ["", f"CD floor ({surface}, "
                  f"{fl.get('n_pred', '?')} estimated points, method "
                  f"{'/'.join(fl.get('methods', [])) or '?'}): "
                  f"{'n/a' if floor is None else f'{floor:.2f}'} cm"
                  + ("." if summary.get("emd_floor_m") is None else
                     f"; EMD floor (the same, at the EMD's subsample size): "
                     f"{_fmt(summary.get('emd_floor_m'), 'emd_m')} m."),
              f"Frame-pooled means over {s.get('n_tracks', '?')} tracks, each run from its first "
              f"to its last detection; EMD exact on {s.get('emd_points', '?')}-point subsamples, "
              f"every {s.get('emd_every', '?')} frame(s)."]
    for m in methods:
        d = summary.get("details", {}).get(m, {})
        lines.append(f"- {m}: {d.get('n_frames', '?')} frames, {d.get('n_emd_m', '?')} with EMD.")
    gains = summary.get("above_floor")
    if gains:
        def pct(key: str) -> str:
            return "n/a" if gains.get(key) is None else f"{gains[key]:+.1f} %"

        paper = {k: 100.0 * (PAPER_TABLE["sequential"][k] / PAPER_TABLE["baseline"][k] - 1.0)
                 for k in PAPER_TABLE["baseline"]}
        lines.append(f"- Sequential against baseline (the paper's Table I: CD {paper['cd_cm']:+.0f} %, "
                     f"EMD {paper['emd_m']:+.0f} %, translation {paper['trans_cm']:+.0f} %, "
                     f"rotation {paper['rot_deg']:+.0f} %): CD above its floor {pct('cd_pct')}, "
                     f"EMD above its floor {pct('emd_pct')} (raw EMD {pct('emd_raw_pct')}), "
                     f"translation {pct('trans_pct')}, rotation {pct('rot_pct')} "
                     f"(without 180-degree flips {pct('rot_noflip_pct')}).")
    for key, label in EXTRA_LABELS.items():
        det = summary.get("details", {})
        vals = [f"{m} {_fmt(det[m][key], key)}" for m in methods
                if det.get(m, {}).get(key) is not None]
        if vals:
            lines.append(f"- Diagnostic, {label}: " + ", ".join(vals)
                         + f" ({EXTRA_NOTES[key]}).")
    flips = [_flip_text(m, summary["details"][m]) for m in methods
             if "rot_flip_frames" in summary.get("details", {}).get(m, {})]
    if flips:
        lines.append(f"- Diagnostic, 180-degree flips (rotation error > {FLIP_DEG:.0f} deg): "
                     + "; ".join(flips) + ". A flip costs a nearly symmetric car little CD but "
                     "a large rotation error; over few tracks one flipped track can dominate "
                     "the mean.")
    track_flips = [_track_flip_text(m, summary["details"][m]["flips"]) for m in methods
                   if "flips" in summary.get("details", {}).get(m, {})]
    if track_flips:
        lines.append("- Flips per track: " + "; ".join(track_flips) + ".")
    group_flips = [_group_flip_text(m, summary["details"][m]["flip_groups"]) for m in methods
                   if summary.get("details", {}).get(m, {}).get("flip_groups")]
    if len(group_flips) and any("passed" in summary["details"][m].get("flip_groups", {})
                                for m in methods):
        lines.append("- Flips by track group (% of frames): " + "; ".join(group_flips) + ".")
    lines += detections_markdown(summary.get("details", {}), methods)
    if real:
        lines += _real_notes(s, methods)
        for stat in ("median", "mean"):
            for kind, title in BREAKDOWN_TITLES.items():
                if kind in summary.get("breakdown", {}):
                    lines += ["", f"### {title} ({stat}s)", ""]
                    lines += breakdown_markdown(summary["breakdown"][kind], methods, stat)
    return "\n".join(lines) + "\n"


def _real_notes(settings: dict[str, Any], methods: list[str]) -> list[str]:
    n_ref = settings.get("n_reference_tracks", "?")
    return [f"- Real data: CD and EMD are against each track's accumulated reference (its "
            f"points of all frames in the box frame, mirrored and cleaned: not a true surface), "
            f"on the {n_ref} of {settings.get('n_tracks', '?')} tracks that have one; pose and "
            f"extent errors are against the annotated boxes on every track.",
            "- Columns below (medians, then the same tables as means; cm, deg): centre = planar centre error; "
            "radial = signed error along the line of sight (+: estimate too far); |tang| = "
            "absolute error across it; yaw w/o flips = over frames without a 180-degree flip; "
            "yaw mod 180 = ignoring the direction of travel; flips = share of frames flipped; "
            "length, width = signed extent errors (estimate - box), |.| absolute, "
            "|length| % = |length error| / true length; "
            "CD vs reference."]


BREAKDOWN_TITLES = {"all": "All frames",
                    "class_group": "Cars vs larger vehicles",
                    "class": "By class", "distance": "By distance from the sensor",
                    "points": "By points per frame",
                    "annotation": "By whether the annotated box holds the frame's points",
                    "face_gap": "By the annotated box's face gap (its faces the sensor sees to "
                                "the frame's points)"}
_BD_COLUMNS = (("frames", "n_frames", None), ("centre", "centre_cm", 1),
               ("radial", "radial_cm", 1), ("\\|tang\\|", "tangential_abs_cm", 1),
               ("yaw", "rot_deg", 1), ("yaw w/o flips", "rot_deg_without_flips", 1),
               ("yaw mod 180", "rot_axis_deg", 1), ("flips %", "flip_pct", None),
               ("length", "length_err_cm", 1), ("\\|length\\|", "length_abs_cm", 1),
               ("\\|length\\| %", "length_rel_abs_pct", 1),
               ("width", "width_err_cm", 1), ("\\|width\\|", "width_abs_cm", 1),
               ("CD vs ref.", "cd_cm", 2))


def breakdown_markdown(groups: dict[str, dict[str, dict[str, Any]]], methods: list[str],
                       stat: str = "median") -> list[str]:
    """Markdown table lines of one breakdown: a row per group and method."""
    lines = ["| group | method | " + " | ".join(c[0] for c in _BD_COLUMNS) + " |",
             "|" + "---|" * (len(_BD_COLUMNS) + 2)]
    for g, per_method in groups.items():
        for m in methods:
            st = per_method.get(m)
            if st is None:
                continue
            cells = []
            for _, key, digits in _BD_COLUMNS:
                v = st.get(key) if key in ("n_frames", "flip_pct") else st.get(f"{key}_{stat}")
                cells.append("n/a" if v is None else str(v) if digits is None and
                             isinstance(v, int) else f"{v:.{digits or 1}f}")
            lines.append(f"| {g} | {m} | " + " | ".join(cells) + " |")
    return lines


def _flip_text(method: str, d: dict[str, Any]) -> str:
    n = d["rot_flip_tracks"]
    return (f"{method} {d['rot_flip_frames']} of {d.get('n_rot_rad', '?')} frames in {n} "
            f"track{'' if n == 1 else 's'}, rotation without them "
            f"{_fmt(d.get('rot_deg_without_flips'), 'rot_deg')} deg")


def _group_flip_text(method: str, groups: dict[str, float | None]) -> str:
    return f"{method} " + ", ".join(
        f"{GROUP_NAMES.get(g, g)} {'n/a' if v is None else f'{v:.1f}'}"
        for g, v in groups.items())


#: How the flips line names the motion groups.
GROUP_NAMES = {"all": "all", "moving": "view changing", "passed": "parked passed by the ego",
               "parked": "parked, one view"}


def _track_flip_text(method: str, f: dict[str, Any]) -> str:
    pct = {k: "n/a" if f.get(k) is None else f"{f[k]:.1f} %"
           for k in ("flip_pct", "tracks_with_flip_pct", "track_flip_median_pct")}
    return (f"{method} {pct['flip_pct']} of frames, {f['flipped_tracks']} of {f['n_tracks']} "
            f"tracks ({pct['tracks_with_flip_pct']}) with a flip, median track "
            f"{pct['track_flip_median_pct']} of its frames")


def detections_markdown(details: dict[str, dict[str, Any]], methods: list[str]) -> list[str]:
    """The "errors by detections so far" table (frame-pooled means; moving and parked tracks
    apart when both occur) and the 17+ over first-detection ratios, as markdown lines."""
    rows = [(m, g, per) for m in methods
            for g, per in details.get(m, {}).get("by_detections", {}).items()]
    if not rows:
        return []
    labels = DETECTION_LABELS
    cols = [f"{what} {lab}" for what in ("CD", "transl.") for lab in labels]
    lines = ["", "### Errors by detections so far (frame-pooled means, cm)", "",
             "| tracks | method | frames at 1 / 17+ | " + " | ".join(cols)
             + " | CD 17+/1 | transl. 17+/1 | CD above floor 17+/1 |",
             "|" + "---|" * (len(cols) + 6)]
    for g in ("all", "moving", "passed", "parked"):
        for m, group, per in rows:
            if group != g:
                continue
            n = [str(per.get(lab, {}).get("n_frames", 0)) for lab in (labels[0], labels[-1])]
            cells = [_fmt(per.get(lab, {}).get(key), key)
                     for key in ("cd_cm", "trans_cm") for lab in labels]
            r = details[m]["late_over_first"].get(g, {})
            cells += ["n/a" if r.get(k) is None else f"{r[k]:.2f}"
                      for k in ("cd", "trans", "cd_above_floor")]
            lines.append(f"| {g} | {m} | {' / '.join(n)} | " + " | ".join(cells) + " |")
    passed = (f"; passed (a part of moving): the vehicle travels less than "
              f"{PASSED_TRAVEL_M:g} m in the fixed frame of the ego poses while the ego drives "
              f"past it" if any(group == "passed" for _, group, _ in rows) else "")
    lines += ["", f"Parked: the true distance from the sensor spans less than "
                  f"{100 * PARKED_SPREAD_M:g} cm over the track (one repeated view){passed}. The bins "
                  f"pool their frames (17+ holds only the tracks that reach 17 detections); "
                  f"the ratios compare each track reaching 17+ with its own first detection "
                  f"(mean over those tracks): below 1, the error falls as detections "
                  f"accumulate; CD above floor: the CD minus the track's CD floor, the part an "
                  f"estimate can still lose."]
    return lines


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
