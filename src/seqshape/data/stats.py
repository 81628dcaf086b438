"""Statistics of a track dataset: tracks, frames, empty frames and points per frame by
distance band (``seqshape stats``).

Distances are planar, from the sensor to the box centre, in metres.
"""

from __future__ import annotations

import numpy as np

from seqshape._progress import progress

BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, np.inf))


def collect(ds) -> dict[str, dict]:
    """Per split (and "all"): track lengths, points per frame and frame distances (m)."""
    out: dict[str, dict] = {}
    for tr in progress(ds, total=len(ds), desc="stats", unit="track"):
        dist = np.hypot(tr.poses[:, 0], tr.poses[:, 1])
        for key in (tr.split or "none", "all"):
            d = out.setdefault(key, {"lengths": [], "points": [], "dist": []})
            d["lengths"].append(len(tr))
            d["points"].append(tr.num_points)
            d["dist"].append(dist)
    for d in out.values():
        d["points"] = np.concatenate(d["points"]) if d["points"] else np.zeros(0)
        d["dist"] = np.concatenate(d["dist"]) if d["dist"] else np.zeros(0)
    return out


def format_table(stats: dict[str, dict]) -> str:
    """A markdown table: one row per split, then points per frame by distance band."""
    def band_name(lo, hi):
        return f"{lo:.0f}+ m" if np.isinf(hi) else f"{lo:.0f}-{hi:.0f} m"

    head = ["split", "tracks", "frames", "frames/track (min-max)", "empty frames",
            "points/frame"]
    rows = []
    for split in sorted(stats, key=lambda s: (s == "all", s)):
        d = stats[split]
        n, pts = np.array(d["lengths"]), d["points"]
        rows.append([split, str(len(n)), str(int(n.sum())),
                     f"{n.mean():.1f} ({n.min()}-{n.max()})",
                     f"{100 * np.mean(pts == 0):.1f} %", f"{pts.mean():.1f}"])
    lines = _md(head, rows)
    head2 = ["distance band", "frames", "share", "empty", "points/frame mean",
             "median", "p90"]
    d = stats["all"]
    rows2 = []
    for lo, hi in BANDS:
        m = (d["dist"] >= lo) & (d["dist"] < hi)
        p = d["points"][m]
        if not m.any():
            rows2.append([band_name(lo, hi), "0", "0.0 %", "-", "-", "-", "-"])
            continue
        rows2.append([band_name(lo, hi), str(int(m.sum())), f"{100 * m.mean():.1f} %",
                      f"{100 * np.mean(p == 0):.1f} %", f"{p.mean():.1f}",
                      f"{np.median(p):.0f}", f"{np.percentile(p, 90):.0f}"])
    return "\n".join(lines + [""] + _md(head2, rows2))


def _md(head, rows) -> list[str]:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    fmt = "| " + " | ".join(f"{{:{w}}}" for w in widths) + " |"
    return [fmt.format(*head), "|" + "|".join("-" * (w + 2) for w in widths) + "|",
            *(fmt.format(*r) for r in rows)]
