"""How wide the estimator's completed shapes are against the true boxes, between the 1st and
99th percentiles and in full, per sc-gt track of a scene sequence (docs/amodal.md, trimming).
No timing; not part of ``make bench``.

Run: ``python benchmarks/analyse_shapes.py SCENES --sequence 0001 --frames 40``
"""

from __future__ import annotations

import argparse

import numpy as np
from _bench import print_table

from seqshape.amodal.labeler import gt_track_inputs, open_sequence
from seqshape.amodal.refine import complete_tracks
from seqshape.geometry import sensor_to_canonical
from seqshape.model.estimator import Estimator


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", help="scene set (KITTI tracking layout)")
    ap.add_argument("--sequence", default="0001")
    ap.add_argument("--frames", type=int, default=40, help="first F frames of the sequence")
    ap.add_argument("--checkpoint", default="pretrained")
    args = ap.parse_args()
    seq = open_sequence(args.scenes, args.sequence, args.frames)
    _, inputs = gt_track_inputs(seq)
    comps = complete_tracks(Estimator.load(args.checkpoint, refiner="none"), inputs, "smooth")
    rows = []
    for inp, comp in zip(inputs, comps, strict=True):
        i = len(inp.frames) // 2  # the track's middle frame
        can = sensor_to_canonical(np.asarray(comp.clouds[i], np.float64), comp.poses[i])
        robust = np.percentile(can, 99, axis=0) - np.percentile(can, 1, axis=0)
        full = np.ptp(can, axis=0)
        rows.append((float(np.hypot(*inp.poses[i][:2])), sum(len(p) for p in inp.points),
                     inp.size, robust, full))
    rows.sort(key=lambda r: r[0])
    print_table(["distance (m)", "points over the track", "true l x w (m)",
                 "p1-p99 l x w (m)", "full l x w (m)"],
                [[f"{d:.1f}", str(n), f"{s[0]:.2f} x {s[1]:.2f}", f"{r[0]:.2f} x {r[1]:.2f}",
                  f"{f[0]:.2f} x {f[1]:.2f}"] for d, n, s, r, f in rows])


if __name__ == "__main__":
    main()
