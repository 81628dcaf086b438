"""Does a synthetic preset put the points where a real LiDAR does? Point layout, real vs synthetic.

Compares the per-frame point layout of vehicle crops in two or more track folders (a real one made
by ``seqshape tracks``, synthetic ones made by ``seqshape generate``), in each frame's ground-truth
box normalised by its size, for cars with ``--min-points`` to ``--max-points`` points per frame:

* ``far half %``: share of a frame's points beyond the box centre as seen from the sensor (the
  far half of the car, reached over the roof or through the glass);
* ``top %``: share above 0.7 of the box height; ``low %``: below 0.3;
* ``mean offset``: distance (m) from the points' mean to the box centre toward the sensor, the
  offset a network that demeans its input has to learn (a different offset on real data is a
  radial bias);
* ``face gap``: for frames with a face seen head-on (|view component| >= 0.5 along the box
  axis), the distance (m) from that face to the 98th percentile of the points along the axis;
* ``beyond far %``: share of a frame's points outside the box's footprint on the side away
  from the sensor (the crop reaches past the box): 0 for an exact box around the whole car;
  where it is not, the box sits nearer the sensor than the car's own points (a loose or
  shifted annotation), which a network trained on exact boxes reads as a radial error;
* a table of the points' share by height band and radial position (near face ... far face);
* the view-angle histogram of each folder's frames (``seqshape.sim.trajectories.view_angle``:
  0 deg the sensor sees the car's nose, 90 a side, 180 its tail).

``--min-view-deg`` / ``--max-view-deg`` keep only frames with a view angle in that range, so
that the layout is compared at equal views (a preset with another view mix than the real log
otherwise differs in every layout number). The histogram counts the frames before this filter
(after the points filter).

    python benchmarks/bm_sim_realism.py REAL_TRACKS SYNTHETIC_DATASET [MORE ...] --labels av2 real
    python benchmarks/bm_sim_realism.py REAL_TRACKS SYNTHETIC_DATASET --max-view-deg 70
    python benchmarks/bm_sim_realism.py REAL A_SEED0 A_SEED1 B --labels real a a b  # a: pooled

``--per-frame`` also lists the first folder's frames one by one (track, frame, points, range,
view angle, and the face gap of each box face the sensor sees within 60 degrees: on an exact
box a few cm; a gap of decimetres on a face seen head-on at close range is a box that does
not hold its own points).

``--placements N`` also samples N trajectories of a 4.6 x 1.85 m car per placement of
``seqshape.sim.trajectories.sample_trajectory`` (seed 0, no raycasting) and prints the view
histogram of their frames within ``--view-range`` m of the sensor (folders then optional).

Each folder is any ``TrackDataset`` folder; a folder with a ``val`` split is read whole (the
layout does not depend on the split). Nothing is timed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _bench import print_table

from seqshape.data.dataset import TrackDataset
from seqshape.evaluation.runner import face_gaps as face_gaps_of
from seqshape.geometry import sensor_to_canonical
from seqshape.sim.trajectories import PLACEMENTS, sample_trajectory, view_angle

Z_BANDS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2)
R_BANDS = (-1.3, -0.75, -0.25, 0.25, 0.75, 1.3)
VIEW_BINS = (0, 20, 45, 70, 110, 135, 160, 180.001)


def frame_layout(points: np.ndarray, pose: np.ndarray, size: np.ndarray) -> dict:
    """The layout numbers of one frame (module doc); points (N, 3) in the sensor frame."""
    c = pose[:2]
    dist = float(np.linalg.norm(c))
    q = sensor_to_canonical(points, pose).astype(np.float64)
    half = np.asarray(size[:2], np.float64) / 2
    yaw = pose[3]
    to_box = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    view = to_box @ (-c / dist)  # unit direction box -> sensor, box axes
    # radial coordinate: -1 at the face nearest the sensor, +1 at the far one
    reach = abs(view[0]) * half[0] + abs(view[1]) * half[1]
    radial = -(q[:, :2] @ view) / reach
    z = (q[:, 2] + size[2] / 2) / size[2]
    # per box axis, the gap of the face seen within 60 degrees (NaN: that face is not)
    face_gaps = face_gaps_of(points, pose, size).tolist()
    outside = (np.abs(q[:, 0]) > half[0]) | (np.abs(q[:, 1]) > half[1])
    return {"far": float(np.mean(radial > 0)), "top": float(np.mean(z > 0.7)),
            "beyond": float(np.mean(outside & (radial > 0))),
            "low": float(np.mean(z < 0.3)),
            "offset": float(q[:, :2].mean(0) @ view),
            "gaps": [g for g in face_gaps if not np.isnan(g)], "face_gaps": face_gaps,
            "radial": radial, "z": z, "range": dist}


def _car_tracks(folders: list[Path], max_tracks: int):
    for folder in folders:
        ds = TrackDataset(folder)
        for i in range(min(len(ds), max_tracks)):
            tr = ds[i]
            if tr.meta.get("class", "car") == "car":
                yield tr


def layout(folders: list[Path], min_points: int, max_points: int, max_tracks: int,
           views: tuple[float, float] = (0.0, 180.0)) -> dict:
    """The layout numbers of the car frames of ``folders`` (pooled); ``frames`` 0 (and no
    layout numbers) when no frame passes the points and view filters."""
    rows, gaps, radial, z, angles = [], [], [], [], []
    for tr in _car_tracks(folders, max_tracks):
        for t, pts in enumerate(tr.points):
            if not min_points <= len(pts) <= max_points:
                continue
            x, y, _, yaw = tr.poses[t]
            angles.append(float(view_angle(x, y, yaw)))
            if not views[0] <= angles[-1] <= views[1]:
                continue
            f = frame_layout(pts, tr.poses[t], tr.size)
            rows.append((f["far"], f["top"], f["low"], f["offset"], f["range"], len(pts),
                         f["beyond"]))
            gaps += f["gaps"]
            radial.append(f["radial"])
            z.append(f["z"])
    view_hist, _ = np.histogram(angles, VIEW_BINS)
    views_pct = 100 * view_hist / max(len(angles), 1)
    if not rows:
        return {"frames": 0, "views": views_pct, "view_frames": len(angles)}
    a = np.array(rows)
    hist, _, _ = np.histogram2d(np.concatenate(z).clip(0, 1.19), np.concatenate(radial).clip(
        -1.29, 1.29), bins=[Z_BANDS, R_BANDS])
    return {"frames": len(a), "far": np.median(a[:, 0]), "top": np.median(a[:, 1]),
            "low": np.median(a[:, 2]), "offset": np.median(a[:, 3]), "range": np.median(a[:, 4]),
            "points": np.median(a[:, 5]), "gap": np.median(gaps) if gaps else float("nan"),
            "beyond": np.mean(a[:, 6]), "beyond_any": np.mean(a[:, 6] > 0.02),
            "hist": 100 * hist / hist.sum(), "views": views_pct,
            "view_frames": len(angles)}


def placement_views(n: int, max_range: float) -> list[list]:
    """Rows ``[placement, frames, % per VIEW_BINS bin]`` of ``n`` sampled tracks each."""
    rows = []
    for placement in PLACEMENTS:
        rng = np.random.default_rng(0)
        angles = []
        for _ in range(n):
            tr = sample_trajectory(rng, length=4.6, width=1.85, placement=placement)
            near = np.hypot(tr.x, tr.y) <= max_range
            angles.append(view_angle(tr.x, tr.y, tr.yaw)[near])
        a = np.concatenate(angles)
        hist, _ = np.histogram(a, VIEW_BINS)
        rows.append([placement, len(a), *(f"{v:.0f}" for v in 100 * hist / max(len(a), 1))])
    return rows


def _view_names() -> list[str]:
    names = [f"{lo:g}-{hi:g}" for lo, hi in zip(VIEW_BINS[:-1], VIEW_BINS[1:], strict=True)]
    names[-1] = f"{VIEW_BINS[-2]:g}-180"
    return names


def frame_rows(folder: Path, min_points: int, max_points: int, max_tracks: int) -> list[list]:
    """``--per-frame``: one row per car frame of ``folder`` within the points filter."""
    rows = []
    for tr in _car_tracks([folder], max_tracks):
        for t, pts in enumerate(tr.points):
            if not min_points <= len(pts) <= max_points:
                continue
            x, y, _, yaw = tr.poses[t]
            f = frame_layout(pts, tr.poses[t], tr.size)
            rows.append([tr.track_id[-12:], t, len(pts), f"{f['range']:.1f}",
                         f"{view_angle(x, y, yaw):.0f}",
                         *("-" if np.isnan(g) else f"{g:+.2f}" for g in f["face_gaps"])])
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="*", type=Path, help="track folders (real first)")
    ap.add_argument("--labels", nargs="*",
                    help="a short name per folder; folders with the same name are pooled")
    ap.add_argument("--min-points", type=int, default=100)
    ap.add_argument("--max-points", type=int, default=1000)
    ap.add_argument("--max-tracks", type=int, default=400,
                    help="read at most this many tracks per folder (default 400)")
    ap.add_argument("--min-view-deg", type=float, default=0.0,
                    help="keep frames whose view angle (0 nose, 180 tail) is at least this")
    ap.add_argument("--max-view-deg", type=float, default=180.0,
                    help="keep frames whose view angle is at most this")
    ap.add_argument("--per-frame", action="store_true",
                    help="also list the first folder's frames one by one (face gaps)")
    ap.add_argument("--placements", type=int, default=0, metavar="N",
                    help="also print the view histogram of N sampled tracks per placement")
    ap.add_argument("--view-range", type=float, default=40.0,
                    help="--placements: count frames within this range (m, default 40)")
    args = ap.parse_args()
    if not 0 <= args.min_view_deg <= args.max_view_deg <= 180:
        raise SystemExit("need 0 <= --min-view-deg <= --max-view-deg <= 180")
    views = (args.min_view_deg, args.max_view_deg)
    if args.placements:
        print(f"\nsampled trajectories ({args.placements} per placement, frames within "
              f"{args.view_range:g} m): % by view angle\n")
        print_table(["placement", "frames", *_view_names()],
                    placement_views(args.placements, args.view_range))
    if not args.folders:
        if not args.placements:
            raise SystemExit("give track folders and/or --placements N")
        return
    labels = args.labels or [f.name for f in args.folders]
    if len(labels) != len(args.folders):
        raise SystemExit("--labels needs one name per folder")
    groups: dict[str, list[Path]] = {}
    for lab, f in zip(labels, args.folders, strict=True):
        groups.setdefault(lab, []).append(f)
    res = {lab: layout(fs, args.min_points, args.max_points, args.max_tracks, views)
           for lab, fs in groups.items()}
    print(f"\ncar frames with {args.min_points}-{args.max_points} points: % by view angle "
          "(0 deg nose ... 180 deg tail), all views\n")
    print_table(["folder", "frames", *_view_names()],
                [[lab, r["view_frames"], *(f"{v:.0f}" for v in r["views"])]
                 for lab, r in res.items()])
    print(f"\ncar frames with {args.min_points}-{args.max_points} points and views "
          f"{views[0]:g}-{views[1]:g} deg (medians over frames)\n")
    print_table(["folder", "frames", "range m", "points", "far half %", "top %", "low %",
                 "mean offset m", "face gap m", "beyond far % (mean)",
                 "frames with > 2 % beyond"],
                [[lab, r["frames"], f"{r['range']:.1f}", int(r["points"]), f"{100 * r['far']:.0f}",
                  f"{100 * r['top']:.0f}", f"{100 * r['low']:.0f}", f"{r['offset']:.2f}",
                  f"{r['gap']:.2f}", f"{100 * r['beyond']:.1f}",
                  f"{100 * r['beyond_any']:.0f} %"] if r["frames"] else [lab, 0, *["-"] * 9]
                 for lab, r in res.items()])
    if args.per_frame:
        print(f"\n{labels[0]}: car frames with {args.min_points}-{args.max_points} points, "
              "face gap (m) of the faces seen within 60 degrees\n")
        print_table(["track", "frame", "points", "range m", "view deg", "length face gap",
                     "width face gap"],
                    frame_rows(args.folders[0], args.min_points, args.max_points,
                               args.max_tracks))
    bands = [f"{lo:+.2f}..{hi:+.2f}" for lo, hi in zip(R_BANDS[:-1], R_BANDS[1:], strict=True)]
    for lab, r in res.items():
        if not r["frames"]:
            continue
        print(f"\n{lab}: % of points by height (share of box height) and radial position "
              "(-1 near face, +1 far face)\n")
        rows = [[f"{Z_BANDS[i]:.1f}-{Z_BANDS[i + 1]:.1f}", *(f"{v:.1f}" for v in r["hist"][i])]
                for i in range(len(Z_BANDS) - 2, -1, -1)]
        print_table(["height", *bands], rows)


if __name__ == "__main__":
    main()
