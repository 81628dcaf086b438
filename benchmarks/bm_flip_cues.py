"""Front/back cues at test time: do the estimates themselves say where a flip happened?

Runs one network (shipped weights or ``--checkpoint``, with the shipped refiner and the hints
as ``seqshape evaluate`` gives them) over one split and, for every frame, computes two cues
that need no extra network:

* **the decoded shape's own asymmetry**: in the estimate's box frame, the height of the
  complete shape's top over its front quarter against its rear quarter, ``(rear - front) / H``
  (a car is front-low: positive when the shape agrees with its heading), and the offset of its
  roof (top 15 % of the height) from the middle over the length (a car's roof sits behind the
  middle: negative);
* **the turned fit**: the mean distance from the frame's points to the placed complete shape,
  against the same shape turned by pi about the box centre (``d_turned / d_own``: above 1 when
  the points prefer the estimate's own orientation).

A cue is worth a rule only if it separates the frames whose heading is right from the flipped
ones (rotation error above 150 degrees, ``report.FLIP_DEG``). The script prints each cue's
quantiles on both sets and, for thresholds of the turned fit, how many right frames a rule
"flip when the ratio is below t" would break against how many flipped frames it would mend.
docs/model.md ("What the remaining flips are") came from this script.

Run: ``python benchmarks/bm_flip_cues.py --data DATA [--split val] [--model sequential]
[--checkpoint pretrained] [--every 1]``
"""

from __future__ import annotations

import argparse

import numpy as np
from _bench import print_table
from scipy.spatial import cKDTree

from seqshape.data.dataset import TrackDataset
from seqshape.evaluation.evaluate import select_split
from seqshape.evaluation.report import FLIP_DEG
from seqshape.evaluation.runner import predict_track
from seqshape.model.estimator import Estimator


def shape_cues(complete: np.ndarray, pose) -> tuple[float, float]:
    """``(ends, roof)`` of a placed complete shape in its own box frame (module doc)."""
    x, y, _, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    q = complete[:, :2] - np.array([x, y])
    u = c * q[:, 0] + s * q[:, 1]
    w = complete[:, 2]
    lo, hi = np.percentile(u, [1, 99])
    length = hi - lo
    zmin = np.percentile(w, 1)
    height = np.percentile(w, 99) - zmin

    def top(a: float, b: float) -> float:
        m = (u >= lo + a * length) & (u <= lo + b * length)
        return float(np.percentile(w[m], 90) - zmin) if m.sum() > 5 else np.nan

    roof_pts = w > zmin + 0.85 * height
    roof = float((u[roof_pts].mean() - (lo + hi) / 2) / length) if roof_pts.any() else np.nan
    return (top(0.0, 0.25) - top(0.75, 1.0)) / height, roof


def turned_fit(points: np.ndarray, complete: np.ndarray, pose) -> float:
    """Mean distance of the points to the shape turned by pi about the box centre, over the
    mean distance to the shape as placed."""
    turned = complete.copy()
    turned[:, :2] = 2 * np.asarray(pose[:2]) - complete[:, :2]
    own = cKDTree(complete).query(points)[0].mean()
    return float(cKDTree(turned).query(points)[0].mean() / max(own, 1e-9))


def quantiles(v: np.ndarray) -> str:
    v = v[np.isfinite(v)]
    if not len(v):
        return "n/a"
    q10, q50, q90 = np.percentile(v, [10, 50, 90])
    return f"{q50:.3f} ({q10:.3f} .. {q90:.3f})"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="track dataset folder")
    ap.add_argument("--split", default="val", help="split to score: val, train or all")
    ap.add_argument("--model", default="sequential", choices=["sequential", "baseline"])
    ap.add_argument("--checkpoint", default="pretrained",
                    help="weights of --model: 'pretrained' or a path")
    ap.add_argument("--every", type=int, default=1, help="every K-th track of the split")
    args = ap.parse_args()
    ds = select_split(TrackDataset(args.data), args.split)
    tracks = [ds[i] for i in range(0, len(ds), args.every)]
    spec = args.model if args.checkpoint == "pretrained" else args.checkpoint
    est = Estimator.load(spec, kind=args.model, backend="auto-float", refiner="pretrained",
                         threads=1)
    flips, ends, roofs, ratios = [], [], [], []
    for tr in tracks:
        frames, estimates = predict_track(est, tr, hints=True)
        for t, e in zip(frames, estimates, strict=True):
            pts = tr.points[t]
            if not e.valid or len(pts) < 5:
                continue
            err = np.angle(np.exp(1j * (e.pose[3] - tr.poses[t][3])))
            flips.append(np.degrees(abs(err)) > FLIP_DEG)
            a, b = shape_cues(e.complete, e.pose)
            ends.append(a)
            roofs.append(b)
            ratios.append(turned_fit(pts, e.complete, e.pose))
    f = np.array(flips, bool)
    cues = {"shape: ends (rear - front) / H": np.array(ends),
            "shape: roof offset / L": np.array(roofs),
            "turned fit: d_turned / d_own": np.array(ratios)}
    print(f"{len(f)} frames with 5+ points, {f.sum()} flipped ({100 * f.mean():.2f} %)")
    print_table(["cue", "right frames: median (q10 .. q90)", "flipped frames"],
                [[name, quantiles(v[~f]), quantiles(v[f])] for name, v in cues.items()])
    r = cues["turned fit: d_turned / d_own"]
    print_table(["rule: flip when d_turned / d_own <", "right frames broken", "flipped mended"],
                [[f"{t:.2f}", int((r[~f] < t).sum()), int((r[f] < t).sum())]
                 for t in (0.8, 0.9, 0.95, 1.0)])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
