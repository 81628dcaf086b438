"""A geometric placement step after the network: does "contain the observed points" help?

The shipped networks put real cars 15-20 cm too far from the sensor (docs/history/results.md, "Why real
cars are placed too far from the sensor"): on the Argoverse 2 log the front of the estimated
shape of a car seen nose-on lies 10-27 cm behind the car's own front points. The step measured
here moves each estimate (bird's eye, in its own box frame, per axis) by the least amount that
puts the observed points' robust extent (``--points-pct`` .. 100 - it) inside the estimated
shape's extent (``--shape-pct`` .. 100 - it); when the shape is too short to contain them on
both sides it is centred on them. Yaw and shape are unchanged. Rows: each shipped network with
and without the step, fed what ``seqshape evaluate`` feeds (class and ego poses); ``--refiner
pretrained`` puts the shipped refiner before the step (as ``evaluate`` runs it). On real tracks
the frames are also split by whether the annotated box holds the frame's points
(``ref_face_gap_m``, docs/evaluation.md), so that a gain against boxes displaced from their
own points is told apart from one against boxes that fit.

    python benchmarks/bm_placement.py --data TRACKS --split all   # e.g. bm_realdata's tracks
    python benchmarks/bm_placement.py --data /work/data/paper --split val --shape-pct 0

No timing: the quantity measured is accuracy (frame-pooled; centre and radial in cm, median).
"""

from __future__ import annotations

import argparse

import numpy as np
from _bench import print_table

from seqshape.data import TrackDataset
from seqshape.evaluation import evaluate_tracks
from seqshape.evaluation.report import FLIP_DEG, frame_groups
from seqshape.model.estimator import Estimator


def contain_shift(points: np.ndarray, complete: np.ndarray, pose: np.ndarray,
                  points_pct: float = 2.0, shape_pct: float = 1.0) -> np.ndarray:
    """The (dx, dy) sensor-frame shift of the step for one estimate (see the module doc)."""
    c, yaw = pose[:2], pose[3]
    ca, sa = np.cos(yaw), np.sin(yaw)
    rot = np.array([[ca, sa], [-sa, ca]])  # sensor -> estimated box frame, bird's eye
    p = (points[:, :2] - c) @ rot.T
    q = (complete[:, :2] - c) @ rot.T
    pa, pb = np.percentile(p, [points_pct, 100 - points_pct], axis=0)
    qa, qb = np.percentile(q, [shape_pct, 100 - shape_pct], axis=0)
    low, high = pb - qb, pa - qa  # the shifts that contain the points: [low, high]
    s = np.where(low <= high, np.clip(0.0, low, high), 0.5 * (low + high))
    return rot.T @ s


class Contained(Estimator):
    """An :class:`Estimator` whose estimates then get the placement step (an ``Estimator``
    subclass, so that the evaluation hands it the same hints)."""

    points_pct, shape_pct = 2.0, 1.0

    def step(self, track_ids, point_lists, sizes=None, classes=None, ego_poses=None,
             timestamps=None):
        out = super().step(track_ids, point_lists, sizes=sizes, classes=classes,
                           ego_poses=ego_poses, timestamps=timestamps)
        for e, pts in zip(out, point_lists, strict=True):
            pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
            pts = pts[np.isfinite(pts).all(axis=1)]
            if e.num_points == 0 or len(pts) < 10:
                continue
            d = contain_shift(pts, e.complete, e.pose, self.points_pct, self.shape_pct)
            e.pose = e.pose.copy()
            e.pose[:2] += d
            e.complete = e.complete.copy()
            e.complete[:, :2] += d.astype(e.complete.dtype)
        return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="track dataset folder")
    ap.add_argument("--split", default="val", help="train, val or all (default val)")
    ap.add_argument("--max-tracks", type=int, default=None)
    ap.add_argument("--points-pct", type=float, default=2.0,
                    help="robust extent of the points: this percentile .. 100 - it (default 2)")
    ap.add_argument("--shape-pct", type=float, default=1.0,
                    help="extent of the estimated shape: this percentile .. 100 - it (default 1)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--refiner", default="none",
                    help="placement refiner inside both estimators, before the step: 'none' "
                         "(default, the networks alone), 'pretrained' or a file")
    args = ap.parse_args()
    ds = TrackDataset(args.data)
    ds = ds if args.split == "all" else ds.split(args.split)
    Contained.points_pct, Contained.shape_pct = args.points_pct, args.shape_pct
    ests = {}
    extra = {"refiner": args.refiner}
    for kind in ("sequential", "baseline"):
        ests[kind] = Estimator.from_pretrained(kind, threads=args.threads, **extra)
        ests[f"{kind} + step"] = Contained.from_pretrained(kind, threads=args.threads, **extra)
    res = evaluate_tracks(ests, ds, max_tracks=args.max_tracks, emd_every=0, workers=0)
    rec = res.records
    # the evaluation report's own groups (all frames; on classed, real tracks also cars and
    # larger vehicles, and whether the annotated box holds the frame's points)
    found = frame_groups(rec)
    groups = dict(found["all"])
    if (rec["class"] != "").any():
        groups.update({k: v for k, v in found["class_group"].items() if k != "unknown class"})
        groups.update(found.get("annotation", {}))
    rows = []
    for group, sel in groups.items():
        for method in ests:
            m = (rec["method"] == method) & sel
            if not m.any():
                continue
            rot = np.degrees(rec["rot_rad"][m])
            rows.append((group, method, int(m.sum()), f"{np.nanmean(rec['cd_m'][m]) * 100:.2f}",
                         f"{np.median(rec['trans_m'][m]) * 100:.1f}",
                         f"{np.mean(rec['trans_m'][m]) * 100:.1f}",
                         f"{np.median(rec['radial_m'][m]) * 100:+.1f}",
                         f"{np.mean(rot):.2f}", f"{np.mean(rot > FLIP_DEG) * 100:.1f}"))
    print(f"\n### placement step on {args.data} ({args.split}), points {args.points_pct}-"
          f"{100 - args.points_pct} %, shape {args.shape_pct}-{100 - args.shape_pct} %, "
          f"refiner {args.refiner}\n")
    print_table(["group", "method", "frames", "CD mean", "centre med", "centre mean",
                 "radial med", "rot mean (deg)", "flips %"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
