"""PNG plots of the per-frame errors (matplotlib, Agg backend, no display needed).

* :func:`plot_vs_detections`: each metric against the number of detections so far, like the
  paper's Argoverse figure: per bin of detections, the mean (line) and the interquartile range
  (band) of each method.
* :func:`plot_vs_distance`: the same against the distance of the vehicle from the sensor.

Bins: detections are grouped into bins of ``bin_width`` (1-5, 6-10, ...), chosen so that there
are at most ``max_bins`` bins; distances into ``max_bins`` equal-width bins. A bin is drawn only
if it holds at least ``min_count`` frames for that method.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seqshape._io import atomic_open
from seqshape.evaluation.report import LABELS, METRICS, REAL_CD_LABEL, floor_summary
from seqshape.evaluation.runner import EvalResult

COLORS = {"sequential": "tab:blue", "baseline": "tab:orange", "boxfit": "tab:green"}


def _pyplot():
    import matplotlib  # heavy: plotting only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: plotting only

    return plt


def binned_stats(x: np.ndarray, y: np.ndarray, edges: np.ndarray, min_count: int = 3):
    """Per bin ``[edges[i], edges[i+1])``: centre, mean, 25th and 75th percentile of finite y.

    Returns four arrays over the bins holding at least ``min_count`` values.
    """
    ok = np.isfinite(y)
    x, y = x[ok], y[ok]
    which = np.digitize(x, edges) - 1
    rows = []
    for i in range(len(edges) - 1):
        v = y[which == i]
        if len(v) >= min_count:
            rows.append(((edges[i] + edges[i + 1]) / 2, v.mean(), *np.percentile(v, [25, 75])))
    if not rows:
        return tuple(np.zeros(0) for _ in range(4))
    return tuple(np.array(c) for c in zip(*rows, strict=True))


def _detection_edges(n_det: np.ndarray, max_bins: int) -> np.ndarray:
    top = int(n_det.max()) if len(n_det) else 1
    width = max(1, int(np.ceil(top / max_bins)))
    return np.arange(1, top + width + 1, width, dtype=np.float64)


def _floor_cm(result: EvalResult) -> float | None:
    methods = result.methods
    ref = "sequential" if "sequential" in methods else methods[0]
    return floor_summary(result, ref)["cd_floor_cm"]


def _plot_against(result: EvalResult, x_col: str, edges: np.ndarray, xlabel: str, title: str,
                  path: str | Path, min_count: int) -> Path:
    floor_cm = _floor_cm(result)
    plt = _pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(10, 7.2))
    axes = axes.ravel()
    for ax, (key, (col, scale)) in zip(axes, METRICS.items(), strict=True):
        for m in result.methods:
            rec = result.of(m)
            c, mean, q1, q3 = binned_stats(rec[x_col].astype(np.float64), rec[col] * scale,
                                           edges, min_count)
            if not len(c):
                continue
            color = COLORS.get(m)
            ax.plot(c, mean, "-o", ms=3, color=color, label=m)
            ax.fill_between(c, q1, q3, color=color, alpha=0.25, linewidth=0)
        if key == "cd_cm" and floor_cm is not None:
            ax.axhline(floor_cm, color="gray", ls="--", lw=1, label="CD floor")
        ax.set_xlabel(xlabel)
        real_cd = key == "cd_cm" and result.settings.get("real")
        ax.set_ylabel(REAL_CD_LABEL if real_cd else LABELS[key])
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
        if not ax.lines:
            computed = np.isfinite(result.records[col]).any()
            msg = f"fewer than {min_count} frames per bin" if computed else "not computed"
            ax.text(0.5, 0.5, msg, ha="center",
                    va="center", transform=ax.transAxes, fontsize=8, color="gray")
    if axes[0].lines:
        axes[0].legend(loc="best", fontsize=8)
    fig.suptitle(f"{title} (line: mean, band: 25-75th percentile)", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    with atomic_open(path) as fh:  # a full disk leaves no half-written PNG
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)
    return path


def plot_vs_detections(result: EvalResult, path: str | Path, max_bins: int = 25,
                       min_count: int = 3) -> Path:
    """Each error against the number of detections so far; writes a PNG at ``path``."""
    n_det = result.records["n_det"]
    return _plot_against(result, "n_det", _detection_edges(n_det, max_bins),
                         "detections so far", "Errors vs number of detections", path, min_count)


def plot_vs_distance(result: EvalResult, path: str | Path, max_bins: int = 15,
                     min_count: int = 3) -> Path:
    """Each error against the planar distance from the sensor (m); writes a PNG at ``path``."""
    d = result.records["distance_m"]
    d = d[np.isfinite(d)]
    hi = float(np.ceil(d.max())) if len(d) else 1.0
    lo = float(np.floor(d.min())) if len(d) else 0.0
    edges = np.linspace(lo, max(hi, lo + 1.0), max_bins + 1)
    return _plot_against(result, "distance_m", edges, "distance from sensor (m)",
                         "Errors vs distance", path, min_count)


def write_plots(out_dir: str | Path, result: EvalResult) -> list[Path]:
    """``errors_vs_detections.png`` and ``errors_vs_distance.png`` in ``out_dir``."""
    out_dir = Path(out_dir)
    return [plot_vs_detections(result, out_dir / "errors_vs_detections.png"),
            plot_vs_distance(result, out_dir / "errors_vs_distance.png")]
