"""Check a log's ego poses against LiDAR odometry: are they good enough for the smoothers?

The causal and offline smoothers, the shape average and the heading vote work in the fixed
frame of the ego poses (docs/model.md): a parked car is a constant there only if the poses are
right. This script registers pairs of the log's own sweeps (:func:`seqshape.data.odometry.register`:
point-to-point ICP with trimmed pairs, started from the ego poses' relative motion; the
ground, the ego's own returns and far points left out) and prints, per pair, the travel the ego poses give, the travel the sweeps
give, their ratio and the difference of the two relative motions. A ratio far from 1 means the
fixed frame stretches or shrinks: a vehicle parked while the ego drives by appears to move by
``|1 - ratio|`` times the ego's travel.

    python benchmarks/bm_ego_poses.py --dataset kitti \\
        --root ../shared/realdata/kitti-tracking/training --log 0000 [--pairs 0:10 0:19 124:153]

Without ``--root`` there is nothing to measure (real data is never part of the repository).
Measured on the shared KITTI tracking log 0000 (2026-12-07): the oxts poses give 3-4 % less
travel than the sweeps (0 -> 19: 5.92 m against 6.11 m; 124 -> 153: 17.79 against 18.31 m),
so its parked cars drift 0.3-0.5 m over a track in the fixed frame (docs/results.md).
``seqshape tracks --ego-poses lidar`` (and ``label --ego-poses lidar``) replaces such poses by
the chained registrations of consecutive sweeps (:mod:`seqshape.data.odometry`).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from _bench import print_table

from seqshape.data.odometry import OdometryConfig, register, registration_cloud, thin
from seqshape.data.sequence import log_names, open_log

#: A registration whose median pair distance stays above this (m) has not converged (too much
#: motion between the sweeps, or too little structure): it is shown, not counted.
MAX_RESIDUAL = OdometryConfig().max_residual
#: Pairs whose registered travel is under this (m) give no ratio (a stopped ego).
MIN_TRAVEL = 1.0


def check_pair(log, a: int, b: int) -> dict | None:
    """Ego-pose motion of sweep ``b`` into sweep ``a``'s frame against the registered one."""
    ea, eb = log.ego_pose(a), log.ego_pose(b)
    if ea is None or eb is None:
        return None
    given = np.linalg.inv(ea) @ eb
    cfg = OdometryConfig()
    moving = thin(registration_cloud(log.points(b), cfg), cfg.voxel)
    found, med = register(moving, registration_cloud(log.points(a), cfg), given, cfg)
    tg, tf = float(np.linalg.norm(given[:3, 3])), float(np.linalg.norm(found[:3, 3]))
    return {"pair": f"{a} -> {b}", "ego travel m": tg, "sweeps travel m": tf,
            "ratio": tg / tf if tf >= MIN_TRAVEL and med <= MAX_RESIDUAL else np.nan,
            "difference cm": 100 * float(np.linalg.norm(given[:3, 3] - found[:3, 3])),
            "residual cm": 100 * med}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="kitti", help="reader: kitti, av2, nuscenes")
    ap.add_argument("--root", default=None, help="dataset folder (real data)")
    ap.add_argument("--log", default=None, help="log name (default: the first)")
    ap.add_argument("--pairs", nargs="*", default=None, metavar="A:B",
                    help="frame pairs (default: in each run of consecutive frames, its first "
                         "with the 10th after it and with the run's last, at most 30 on)")
    args = ap.parse_args()
    if args.root is None:
        print("bm_ego_poses: no --root given; real data is not part of the repository, so "
              "there is nothing to measure (see the docstring for the command)")
        return 0
    name = args.log or log_names(args.dataset, args.root)[0]
    log = open_log(args.dataset, args.root, name)
    frames = list(log.frames)
    if args.pairs:
        pairs = [tuple(int(v) for v in p.split(":")) for p in args.pairs]
    else:
        runs = np.split(np.asarray(frames), np.flatnonzero(np.diff(frames) != 1) + 1)
        pairs = sorted({(int(r[0]), int(r[min(k, len(r) - 1)])) for r in runs if len(r) > 1
                        for k in (10, 30)})
    rows = [r for a, b in pairs if (r := check_pair(log, a, b)) is not None]
    if not rows:
        sys.exit(f"{args.dataset} log {name}: no ego poses to check")
    print(f"### ego poses of {args.dataset} log {name} against LiDAR odometry\n")
    print_table(list(rows[0]), [[r["pair"]] + [
        ("n/a" if not np.isfinite(r[k]) else f"{r[k]:.4f}") if k == "ratio" else f"{r[k]:.2f}"
        for k in list(r)[1:]] for r in rows])
    ratios = np.array([r["ratio"] for r in rows])
    ratios = ratios[np.isfinite(ratios)]
    if not len(ratios):
        print(f"\nno pair with a converged registration over at least {MIN_TRAVEL:g} m of "
              f"travel: nothing to say about the scale of the ego poses")
        return 0
    print(f"\nmedian ratio {np.median(ratios):.4f} ({len(ratios)} pairs): a vehicle parked "
          f"while the ego drives by moves about {100 * abs(1 - np.median(ratios)):.1f} % of "
          f"the ego's travel in the fixed frame of these poses")
    return 0


if __name__ == "__main__":
    sys.exit(main())
