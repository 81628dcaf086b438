"""The demo's shape-and-pose section: a table readable at a glance, what fusion over time buys.

Everything here reads what the evaluation already computed (the ``metrics.json`` summary of
:func:`seqshape.evaluation.report.summarize` and ``per_frame.csv``); nothing is re-scored.

* :func:`headline_table`: ours beside the paper's Table I with the CD floor next to the CD,
  the CD above the floor, the rotation without 180-degree flips and the flips as their own
  columns (the flip counts are :func:`seqshape.evaluation.metrics.flip_stats`'s, from
  ``details[method]["flips"]``).
* :func:`fusion_verdict`: plain sentences, computed from the numbers, on what the sequential
  model gains over the per-frame baseline on the same frames, and how each method's error
  changes from the first detection to 17 and more (``late_over_first``); when fusion gains
  nothing, the text says so.
* :func:`plot_fusion`: the errors against the detections so far, both methods on the same
  frames, and below them the paired difference (sequential - baseline) per frame: below 0 the
  sequential model is better. Pairing frames removes the change of which tracks are in a bin.

>>> s = {"sequential": {"cd_cm": 20.0, "trans_cm": 8.0}, "baseline": {"cd_cm": 21.0,
...      "trans_cm": 8.1}, "floor": {"per_method": {"sequential": {"cd_floor_cm": 15.0},
...      "baseline": {"cd_floor_cm": 15.0}}}, "details": {}}
>>> [(c.name, round(c.change, 3)) for c in compare_methods(s)]
[('CD above the floor', -0.167), ('translation error', -0.012)]
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from seqshape._io import atomic_open, read_text
from seqshape.errors import DataError
from seqshape.evaluation.report import FLIP_DEG, PAPER_TABLE

#: A relative difference smaller than this counts as "about the same" in the verdict.
SAME_WITHIN = 0.05
#: Detections-so-far bins of the plot (lower edges; the last is open).
PLOT_BINS = (1, 2, 3, 5, 9, 17, 33, 65)
METHODS = ("baseline", "sequential")
COLORS = {"sequential": "tab:blue", "baseline": "tab:orange"}


@dataclass(frozen=True)
class Comparison:
    """One metric, sequential against baseline: values (report units) and the relative change
    ``sequential / baseline - 1`` (when the baseline's value is not positive, as a CD at or
    below the floor can be: 0 when equal, else -inf or +inf by the sign of the difference)."""

    name: str
    unit: str
    sequential: float
    baseline: float

    @property
    def change(self) -> float:
        if self.baseline <= 0:
            if self.sequential == self.baseline:
                return 0.0
            return math.inf if self.sequential > self.baseline else -math.inf
        return self.sequential / self.baseline - 1.0

    @property
    def verdict(self) -> str:
        """``"better"``, ``"worse"`` or ``"same"`` (within :data:`SAME_WITHIN`)."""
        if self.change <= -SAME_WITHIN:
            return "better"
        return "worse" if self.change >= SAME_WITHIN else "same"

    def text(self) -> str:
        """``name (change: ours against baseline unit)``; a share of frames without the
        relative change (a few flipped frames make it huge)."""
        d = _digits(self.unit)
        values = f"{self.sequential:.{d}f} against {self.baseline:.{d}f} {self.unit}"
        if self.unit.startswith("%") or not math.isfinite(self.change):
            return f"{self.name} ({values})"
        return f"{self.name} ({100 * self.change:+.0f} %: {values})"

    def phrase(self) -> str:
        """What the sequential model has, in words: "a lower EMD", "more 180-degree flips"."""
        if self.unit.startswith("%"):
            return f"{'fewer' if self.verdict == 'better' else 'more'} {self.name}"
        return f"a {'lower' if self.verdict == 'better' else 'higher'} {self.name}"


def _digits(unit: str) -> int:
    return 3 if unit == "m" else 1 if unit == "% of frames" else 2


def _floor(summary: dict[str, Any], method: str) -> float | None:
    per = summary.get("floor", {}).get("per_method", {}).get(method, {})
    return per.get("cd_floor_cm", summary.get("cd_floor_cm"))


def _above_floor(summary: dict[str, Any], method: str) -> float | None:
    cd, fl = summary.get(method, {}).get("cd_cm"), _floor(summary, method)
    return None if cd is None or fl is None else cd - fl


def compare_methods(summary: dict[str, Any]) -> list[Comparison]:
    """Sequential against baseline on each metric both have: CD above the floor, EMD,
    translation, rotation without flips and the share of flipped frames (lower is better
    on every one)."""
    det = summary.get("details", {})

    def values(method):
        d = det.get(method, {})
        return {"CD above the floor": (_above_floor(summary, method), "cm"),
                "EMD": (summary.get(method, {}).get("emd_m"), "m"),
                "translation error": (summary.get(method, {}).get("trans_cm"), "cm"),
                "rotation error without flips": (d.get("rot_deg_without_flips"), "deg"),
                "180-degree flips": (d.get("flips", {}).get("flip_pct"), "% of frames")}

    seq, base = values("sequential"), values("baseline")
    return [Comparison(name, unit, seq[name][0], base[name][0])
            for name, (_, unit) in seq.items()
            if seq[name][0] is not None and base[name][0] is not None]


def _cell(v: float | None, digits: int) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def _flip_cells(d: dict[str, Any]) -> list[str]:
    f = d.get("flips")
    if not f:
        return ["n/a", "n/a"]
    return [_cell(f.get("flip_pct"), 1), f"{f['flipped_tracks']} of {f['n_tracks']}"]


#: Columns of :func:`headline_table`.
HEADLINE_COLUMNS = ("Method", "CD (cm)", "CD floor (cm)", "CD above floor (cm)", "EMD (m)",
                    "Translation (cm)", "Rotation (deg)", "Rotation w/o flips (deg)",
                    "Flips (% frames)", "Tracks with a flip")


def headline_table(summary: dict[str, Any]) -> str:
    """The demo's metrics table (markdown): ours, then the paper's Table I, with the CD floor
    beside the CD and the 180-degree flips as their own columns."""
    lines = ["| " + " | ".join(HEADLINE_COLUMNS) + " |",
             "|" + "---|" * len(HEADLINE_COLUMNS)]
    det = summary.get("details", {})
    for m in METHODS:
        if m not in summary:
            continue
        s, d = summary[m], det.get(m, {})
        lines.append(f"| {m} (ours) | " + " | ".join(
            [_cell(s.get("cd_cm"), 2), _cell(_floor(summary, m), 2),
             _cell(_above_floor(summary, m), 2), _cell(s.get("emd_m"), 3),
             _cell(s.get("trans_cm"), 2), _cell(s.get("rot_deg"), 2),
             _cell(d.get("rot_deg_without_flips"), 2), *_flip_cells(d)]) + " |")
    for m in METHODS:
        p = PAPER_TABLE[m]
        lines.append(f"| {m} (paper) | {p['cd_cm']:.2f} | not given | n/a | {p['emd_m']:.3f} | "
                     f"{p['trans_cm']:.2f} | {p['rot_deg']:.2f} | n/a | n/a | n/a |")
    return "\n".join(lines) + "\n"


def floor_note(summary: dict[str, Any]) -> str:
    """One sentence on the CD floor and what it means for the paper's CD."""
    fl = summary.get("floor", {})
    value = summary.get("cd_floor_cm")
    if value is None:
        return "CD floor: not computed (no ground-truth shape).\n"
    return (f"CD floor: the CD of the true shape against itself, two independent samplings of "
            f"its surface at the evaluation's density ({fl.get('n_pred', '?')} points, as "
            f"many as an estimate, against the stored ground truth): {value:.2f} cm. A "
            f"perfect estimate "
            f"scores this, so the paper's {PAPER_TABLE['sequential']['cd_cm']:.1f} cm cannot "
            f"be reached at this sampling: compare the CD above the floor.{_emd_floor_text(summary)}\n")


def _emd_floor_text(summary: dict[str, Any]) -> str:
    """The EMD floor's sentence of :func:`floor_note` (empty without EMD)."""
    value = summary.get("emd_floor_m")
    if value is None:
        return ""
    gain = summary.get("above_floor", {}).get("emd_pct")
    change = "" if gain is None else (f"; above it the sequential model's EMD is {abs(gain):.0f} % "
                                      f"{'below' if gain < 0 else 'above'} the baseline's")
    return (f" EMD floor, the same two samplings' EMD at the EMD's subsample size: "
            f"{value:.3f} m{change}.")


def _ratio_text(method: str, r: dict[str, float | None]) -> str | None:
    if r.get("cd") is None and r.get("trans") is None:
        return None
    parts = [f"{name} x{r[k]:.2f}" for k, name in (("cd", "CD"), ("trans", "translation"))
             if r.get(k) is not None]
    return f"{method} " + " and ".join(parts)


def _late_tracks(summary: dict[str, Any]) -> int:
    by = summary.get("details", {}).get("sequential", {}).get("by_detections", {})
    return int(by.get("all", {}).get("17+", {}).get("n_tracks", 0))


def _first_late_text(summary: dict[str, Any]) -> str | None:
    """The CD of both methods at the first detection and at 17 and more (frame-pooled), or
    None when a bin is missing."""
    det = summary.get("details", {})
    by = {m: det.get(m, {}).get("by_detections", {}).get("all", {}) for m in METHODS}
    try:
        cd = {(m, b): float(by[m][b]["cd_cm"]) for m in METHODS for b in ("1", "17+")}
    except (KeyError, TypeError):
        return None
    return (f"CD at the first detection (one frame seen, nothing to fuse yet): sequential "
            f"{cd['sequential', '1']:.2f} against baseline {cd['baseline', '1']:.2f} cm; at 17 "
            f"detections and more: {cd['sequential', '17+']:.2f} against "
            f"{cd['baseline', '17+']:.2f} cm.")


def fusion_gain_over_time(summary: dict[str, Any]) -> dict[str, float] | None:
    """Per error ("cd", "trans"): the sequential model's 17+-over-first ratio divided by the
    baseline's (all tracks; below 1: its error falls faster as detections accumulate), or
    None when either ratio is missing."""
    det = summary.get("details", {})
    ratios = [det.get(m, {}).get("late_over_first", {}).get("all", {}) for m in
              ("sequential", "baseline")]
    out = {k: ratios[0][k] / ratios[1][k] for k in ("cd", "trans")
           if ratios[0].get(k) is not None and ratios[1].get(k)}
    return out or None


def fusion_verdict(summary: dict[str, Any]) -> str:
    """What fusion over time buys on this evaluation, in plain sentences computed from the
    numbers (module doc); says so when it buys nothing."""
    comps = compare_methods(summary)
    if not comps:
        return "Fusion over time: not measured (the evaluation lacks one of the methods).\n"
    groups = {v: [c.text() for c in comps if c.verdict == v] for v in ("better", "same", "worse")}
    n = summary.get("details", {}).get("sequential", {}).get("n_frames", "?")
    parts = [f"Sequential model against the per-frame baseline on the same {n} frames:"]
    for v, label in (("better", "better on"), ("same", f"within {100 * SAME_WITHIN:.0f} % on"),
                     ("worse", "worse on")):
        if groups[v]:
            parts.append(f"{label} " + ", ".join(groups[v]) + ";")
    parts[-1] = parts[-1].rstrip(";") + "."
    lines = [" ".join(parts)]
    det = summary.get("details", {})
    ratios = [_ratio_text(m, det.get(m, {}).get("late_over_first", {}).get("all", {}))
              for m in ("sequential", "baseline")]
    if all(ratios):
        lines.append(f"From the first detection to 17 and more, on the {_late_tracks(summary)} "
                     f"tracks that reach 17 (each against its own first detection; below 1 the "
                     f"error falls): {ratios[0]}; {ratios[1]}.")
    first_late = _first_late_text(summary)
    if first_late:
        lines[-1] += " " + first_late
    gain = fusion_gain_over_time(summary)
    falls = [name for k, name in (("cd", "CD"), ("trans", "translation"))
             if gain and k in gain and gain[k] <= 1.0 - SAME_WITHIN]
    better = [c.phrase() for c in comps if c.verdict == "better"]
    if falls:
        better.append(f"a {falls[0]} error that falls faster as detections accumulate"
                      if len(falls) == 1 else f"{' and '.join(falls)} errors that fall faster "
                      f"as detections accumulate")
    if not better:
        lines.append("**On this demo set, fusion over time buys nothing:** the sequential "
                     "model is not better than the per-frame baseline on any metric, and its "
                     "errors do not fall faster than the baseline's as detections accumulate.")
    else:
        worse = [c.phrase() for c in comps if c.verdict == "worse"]
        lines.append(f"**On this demo set, fusion over time buys {_join(better)}**"
                     + (f"; it costs {_join(worse)}." if worse else "."))
    return "\n\n".join(lines) + "\n"


def _join(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


# ----------------------------------------------------------------------------- the plot


def read_per_frame(path: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """``{method: {"track_id", "frame", "n_det", "cd_cm", "trans_cm", "rot_deg"}}`` from the
    evaluation's ``per_frame.csv`` (empty cells: NaN). A malformed file is a DataError."""
    path = Path(path)
    rows = list(csv.DictReader(read_text(path, "per-frame errors").splitlines()))
    out: dict[str, dict[str, list]] = {}
    try:
        for r in rows:
            d = out.setdefault(r["method"], {k: [] for k in ("track_id", "frame", "n_det",
                                                             "cd_cm", "trans_cm", "rot_deg")})
            d["track_id"].append(r["track_id"])
            d["frame"].append(int(r["frame"]))
            d["n_det"].append(int(r["n_det"]))
            for key, col, scale in (("cd_cm", "cd_m", 100.0), ("trans_cm", "trans_m", 100.0),
                                    ("rot_deg", "rot_rad", 180.0 / math.pi)):
                d[key].append(float(r[col]) * scale if r[col] else math.nan)
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(path, f"not an evaluation per_frame.csv ({exc!r})") from None
    return {m: {k: np.asarray(v) for k, v in d.items()} for m, d in out.items()}


def paired_frames(a: dict[str, np.ndarray], b: dict[str, np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(ia, ib)`` of the frames (same track and frame) both record sets hold."""
    index_b = {(t, f): i for i, (t, f) in enumerate(zip(b["track_id"].tolist(),
                                                        b["frame"].tolist(), strict=True))}
    pairs = [(i, index_b[(t, f)]) for i, (t, f) in enumerate(zip(
        a["track_id"].tolist(), a["frame"].tolist(), strict=True)) if (t, f) in index_b]
    if not pairs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ia, ib = np.array(pairs, dtype=np.int64).T
    return ia, ib


def _bin_labels(edges: tuple[int, ...]) -> list[str]:
    labels = []
    for i, lo in enumerate(edges):
        top = edges[i + 1] - 1 if i + 1 < len(edges) else None
        labels.append(f"{lo}+" if top is None else str(lo) if top == lo else f"{lo}-{top}")
    return labels


def _binned(which: np.ndarray, y: np.ndarray, n_bins: int):
    """Per bin: mean, 25th and 75th percentile of the finite ``y`` (NaN for empty bins)."""
    out = np.full((3, n_bins), np.nan)
    for i in range(n_bins):
        v = y[(which == i) & np.isfinite(y)]
        if len(v):
            out[:, i] = v.mean(), *np.percentile(v, [25, 75])
    return out


_PANELS = (("cd_cm", "CD (cm)"), ("trans_cm", "translation (cm)"),
           ("rot_deg", "rotation w/o flips (deg)"))


def plot_fusion(per_frame: str | Path, path: str | Path, floor_cm: float | None = None) -> Path:
    """Write the fusion plot (module doc) of ``per_frame.csv`` to the PNG ``path``.

    Upper row: each method's mean error per bin of detections so far (:data:`PLOT_BINS`)
    over the frames both methods scored; lower row: the mean and 25-75th percentile band of
    the per-frame difference sequential - baseline. Rotation leaves out the frames flipped
    (> :data:`~seqshape.evaluation.report.FLIP_DEG`) by either method. The tick labels give
    the number of tracks in each bin.
    """
    rec = read_per_frame(per_frame)
    if not all(m in rec for m in METHODS):
        raise DataError(Path(per_frame), f"needs both methods {METHODS}, has {sorted(rec)}")
    ia, ib = paired_frames(rec["sequential"], rec["baseline"])
    seq = {k: v[ia] for k, v in rec["sequential"].items()}
    base = {k: v[ib] for k, v in rec["baseline"].items()}
    flipped = (seq["rot_deg"] > FLIP_DEG) | (base["rot_deg"] > FLIP_DEG)
    for r in (seq, base):
        r["rot_deg"] = np.where(flipped, np.nan, r["rot_deg"])
    which = np.digitize(seq["n_det"], PLOT_BINS) - 1  # (N,) bin of each paired frame
    n_bins = len(PLOT_BINS)
    tracks = [len(set(seq["track_id"][which == i].tolist())) for i in range(n_bins)]
    used = [i for i in range(n_bins) if tracks[i] > 0]
    ticks = [f"{lab}\n{n}" for lab, n in zip(_bin_labels(PLOT_BINS), tracks, strict=True)]
    plt = _pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.6), sharex=True)
    x = np.arange(n_bins)
    for col, (key, label) in enumerate(_PANELS):
        top, bottom = axes[0, col], axes[1, col]
        for m, r in (("baseline", base), ("sequential", seq)):
            mean = _binned(which, r[key], n_bins)[0]
            top.plot(x[used], mean[used], "-o", ms=3, color=COLORS[m], label=m)
        if key == "cd_cm" and floor_cm is not None:
            top.axhline(floor_cm, color="gray", ls="--", lw=1, label="CD floor")
        mean, q1, q3 = _binned(which, seq[key] - base[key], n_bins)
        bottom.axhline(0.0, color="black", lw=0.8)
        bottom.plot(x[used], mean[used], "-o", ms=3, color="tab:purple")
        bottom.fill_between(x[used], q1[used], q3[used], color="tab:purple", alpha=0.25, lw=0)
        top.set_ylabel(label)
        bottom.set_ylabel(f"sequential - baseline,\n{label}")
        bottom.set_xticks(x, ticks, fontsize=7)
        bottom.set_xlabel("detections so far (tracks in the bin)")
        top.set_ylim(bottom=0)
        for ax in (top, bottom):
            ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="best", fontsize=8)
    fig.suptitle("What fusion over time buys: both methods on the same frames (top: means)\n"
                 "and their per-frame difference (bottom: mean, band 25-75th percentile; "
                 "below 0 the sequential model is better)", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=100)
    plt.close(fig)
    return path


def _pyplot():
    import matplotlib  # heavy: plotting only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: plotting only

    return plt
