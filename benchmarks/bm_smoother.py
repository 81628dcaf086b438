"""The offline pose smoother on real and synthetic vehicle trajectories: error of noisy poses
smoothed by :func:`seqshape.model.smooth.smooth_track_poses` under four rules for a track
that travels less than ``min_travel``.

* ``line always``: the whole-track robust line (the rule before 2026-12-03);
* ``line if it follows``: the line only where it follows the local fit within the
  estimates' noise (docs/history/model.md "Stop and go");
* ``+ constant if parked``: that, and a line whose travel is within noise replaced by the
  robust constant (the shipped rule);
* ``local fit``: never the whole-track fit.

Trajectories: the true poses of KITTI tracking labels (``--kitti ROOT --sequences ...``; no
oxts there, so the poses stay in the moving sensor's frame and the smoother runs without ego
poses, as ``seqshape label`` does on a log without them) and of a synthetic dataset
(``--data DIR``; its ego poses are used). Each track's poses get Gaussian noise of
``--noise`` metres per axis (and 3 degrees of yaw), ``--repeats`` draws. The table gives the
mean and 95th-percentile centre error in the plane, over all frames of the tracks the rule
concerns (travel under ``min_travel``; other tracks are smoothed the same under every rule),
and the number of those tracks where the line was refused. A second table gives the heading
error of the synthetic sets' moving tracks (``--centre-noise`` metres, ``--yaw-noise`` degrees)
with the motion direction alone, with the sideslip correction (docs/history/model.md, "Sideslip"), and
with the estimates blended in where the motion direction is the less certain (shipped).

Run: ``python benchmarks/bm_smoother.py --kitti ../shared/realdata/kitti-tracking/training
--sequences 0000 0001 0016 [--data DIR --split val] [--noise 0.05 0.15 0.3] [--repeats 5]``
"""

from __future__ import annotations

import numpy as np
from _bench import bench_parser, print_table

from seqshape.camera import read_calib
from seqshape.data import kitti
from seqshape.geometry import matrix_to_pose, pose_to_matrix, wrap_angle
from seqshape.model.smooth import smooth_track_poses

RULES = {"line always": {"line_tolerance": np.inf, "parked_constant": False},
         "line if it follows": {"parked_constant": False},
         "+ constant if parked": {},
         "local fit": {"line_tolerance": -np.inf}}
HEADING_RULES = {"motion direction": {"sideslip": False, "blend": False},
                 "+ sideslip": {"blend": False},
                 "+ blend (shipped)": {}}
VEHICLES = ("Car", "Van", "Truck")


def kitti_tracks(root: str, sequences) -> list[tuple[str, np.ndarray, np.ndarray, None]]:
    """(name, frames, poses in the velodyne frame, None) of every labelled vehicle track with
    at least 5 frames."""
    out = []
    for seq in sequences:
        calib = read_calib(kitti.calib_path(root, seq))
        by_track: dict[int, list] = {}
        for lab in kitti.read_labels(kitti.label_path(root, seq)):
            if lab.type in VEHICLES:
                by_track.setdefault(lab.track_id, []).append(lab)
        for tid, labs in sorted(by_track.items()):
            if len(labs) < 5:
                continue
            labs.sort(key=lambda lab: lab.frame)
            poses = np.stack([kitti.label_to_pose(lab, calib)[0] for lab in labs])
            out.append((f"kitti {seq}/{tid}", np.array([lab.frame for lab in labs], float),
                        poses, None))
    return out


def dataset_tracks(data: str, split: str) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, frames, true sensor-frame poses, ego poses) of the frames with points of every
    track of a synthetic dataset's split."""
    from seqshape.data.dataset import TrackDataset

    ds = TrackDataset(data)
    ds = ds if split == "all" else ds.split(split)
    out = []
    for tr in ds:
        det = np.flatnonzero(tr.num_points > 0)
        if len(det) < 5:
            continue
        egos = [tr.ego_pose(int(t)) for t in det]
        ego = None if any(e is None for e in egos) else np.stack(egos)
        out.append((tr.track_id, det.astype(float), tr.poses[det], ego))
    return out


def travel(poses: np.ndarray, ego) -> float:
    """Distance (m) between the first and last true positions in the fixed frame (the sensor
    frame without ego poses)."""
    if ego is None:
        return float(np.linalg.norm(poses[-1, :2] - poses[0, :2]))
    world = matrix_to_pose(np.einsum("tij,tjk->tik", ego, pose_to_matrix(poses)))
    return float(np.linalg.norm(world[-1, :2] - world[0, :2]))


def main() -> None:
    ap = bench_parser(__doc__, repeats=5)
    ap.add_argument("--kitti", help="KITTI tracking root (label_02/, calib/)")
    ap.add_argument("--sequences", nargs="+", default=["0000"])
    ap.add_argument("--data", help="a synthetic dataset directory")
    ap.add_argument("--split", default="val")
    ap.add_argument("--noise", type=float, nargs="+", default=[0.05, 0.15, 0.3])
    ap.add_argument("--min-travel", type=float, default=3.0)
    ap.add_argument("--yaw-noise", type=float, nargs="+", default=[2.0, 6.0],
                    help="degrees of yaw noise for the heading table")
    ap.add_argument("--centre-noise", type=float, default=0.1,
                    help="metres of centre noise for the heading table (default 0.1)")
    args = ap.parse_args()
    sources = []
    if args.kitti:
        sources.append((f"KITTI {' '.join(args.sequences)}", kitti_tracks(args.kitti,
                                                                         args.sequences)))
    if args.data:
        sources.append((f"{args.data} ({args.split})", dataset_tracks(args.data, args.split)))
    if not sources:
        ap.error("give --kitti ROOT and/or --data DIR")
    rows = []
    for name, tracks in sources:
        short = [tr for tr in tracks if travel(tr[2], tr[3]) < args.min_travel]
        for noise in args.noise:
            rng = np.random.default_rng(args.seed)
            err = {r: [] for r in RULES}
            raw, refused = [], 0
            for _ in range(args.repeats):
                for _tid, frames, poses, ego in short:
                    noisy = poses + np.c_[rng.normal(0, noise, (len(poses), 3)),
                                          rng.normal(0, np.radians(3.0), len(poses))]
                    raw.append(np.linalg.norm(noisy[:, :2] - poses[:, :2], axis=1))
                    outs = {r: smooth_track_poses(noisy, frames, ego, min_travel=args.min_travel,
                                                  **kw) for r, kw in RULES.items()}
                    for r, out in outs.items():
                        err[r].append(np.linalg.norm(out[:, :2] - poses[:, :2], axis=1))
                    refused += not np.allclose(outs["line if it follows"],
                                               outs["line always"], atol=1e-9)
            raw_all = np.concatenate(raw) if raw else np.zeros(1)
            cells = []
            for r in RULES:
                e = np.concatenate(err[r]) if err[r] else np.zeros(1)
                cells.append(f"{100 * e.mean():.1f} / {100 * np.quantile(e, 0.95):.1f}")
            rows.append([name, f"{len(short)} of {len(tracks)}", f"{noise:g}",
                         f"{100 * raw_all.mean():.1f}", *cells,
                         f"{refused} of {len(short) * args.repeats}"])
    print_table(["trajectories", f"tracks under {args.min_travel:g} m", "noise (m)",
                 "raw (cm)", *[f"{r}: mean / p95 (cm)" for r in RULES], "line refused"], rows)
    # the heading of moving tracks (needs ego poses: the synthetic sets)
    rows = []
    for name, tracks in sources:
        moving = [tr for tr in tracks if tr[3] is not None
                  and travel(tr[2], tr[3]) >= args.min_travel]
        if not moving:
            continue
        for noise in args.yaw_noise:
            rng = np.random.default_rng(args.seed)
            err = {k: [] for k in HEADING_RULES}
            for _ in range(args.repeats):
                for _tid, frames, poses, ego in moving:
                    noisy = poses + np.c_[rng.normal(0, args.centre_noise, (len(poses), 3)),
                                          rng.normal(0, np.radians(noise), len(poses))]
                    for k, kw in HEADING_RULES.items():
                        out = smooth_track_poses(noisy, frames, ego, **kw)
                        err[k].append(np.degrees(np.abs(wrap_angle(out[:, 3] - poses[:, 3]))))
            cells = [f"{np.concatenate(e).mean():.2f} / {np.quantile(np.concatenate(e), 0.95):.2f}"
                     for e in err.values()]
            rows.append([name, f"{len(moving)} of {len(tracks)}", f"{noise:g}", *cells])
    if rows:
        print()
        print_table(["trajectories", "moving tracks", "yaw noise (deg)",
                     *[f"{k}: mean / p95 (deg)" for k in HEADING_RULES]], rows)


if __name__ == "__main__":
    main()
