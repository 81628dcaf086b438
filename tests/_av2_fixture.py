"""Small Argoverse 2 sensor-dataset logs written in the official layout and schema (pyarrow).

Column names and types follow the released files: sweeps ``x y z`` float16, ``intensity`` and
``laser_number`` uint8, ``offset_ns`` int32; ``annotations.feather`` int64 timestamps, string
ids and categories, float64 sizes, quaternions (scalar first) and translations, int64
``num_interior_pts``; calibration and ``city_SE3_egovehicle`` float64 poses; intrinsics with
uint16 image sizes. Everything is in the ego frame, as in AV2.

:func:`write_log` writes a whole log whose ``num_interior_pts`` are known by construction: each
box gets points sampled strictly inside it (0.1 m from every face, more than the float16
rounding) plus points placed exactly on its faces, and the clutter is kept 0.1 m away from
every box.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather

#: The up_lidar pose of the fixture (translation from the real calibration, rounded to values
#: exact in float16/float32; a small yaw that the reader must NOT apply to the points).
UP_LIDAR = {"q": (np.cos(-0.0025), 0.0, 0.0, np.sin(-0.0025)), "t": (1.375, 0.0, 1.625)}

#: The optical-convention rotation of a forward-looking camera (camera x right, y down,
#: z forward in ego axes), as AV2 writes ring_front_center.
FRONT_CAMERA_Q = (0.5, -0.5, 0.5, -0.5)

RING = ("ring_front_center", "ring_front_left", "ring_front_right", "ring_side_left",
        "ring_side_right", "ring_rear_left", "ring_rear_right")
STEREO = ("stereo_front_left", "stereo_front_right")

#: Intrinsics of every fixture camera: fx = fy = 1000, cx = 775, cy = 1024, 1550 x 2048.
INTRINSICS = {"fx": 1000.0, "cx": 775.0, "cy": 1024.0, "width": 1550, "height": 2048}

T0 = 315966265259836000  # the first sweep's timestamp (ns), as in a real log
DT = 100_000_000  # 10 Hz


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(qw, qx, qy, qz) of a rotation by ``yaw`` about +z."""
    return (float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2)))


def write_table(path: Path, columns: dict[str, tuple[object, object]]) -> Path:
    """Write ``{name: (values, pyarrow type)}`` as a Feather v2 file (folders created)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    table = pa.table({k: pa.array(v, type=t) for k, (v, t) in columns.items()})
    feather.write_feather(table, str(path))
    return path


def write_sweep(log_dir: Path, ts: int, xyz: np.ndarray, intensity=None) -> Path:
    """``sensors/lidar/<ts>.feather`` with points ``xyz`` (N, 3) in the ego frame."""
    n = len(xyz)
    xyz = np.asarray(xyz, dtype=np.float16)
    inten = np.arange(n) % 256 if intensity is None else intensity
    return write_table(log_dir / "sensors" / "lidar" / f"{ts}.feather", {
        "x": (xyz[:, 0], pa.float16()), "y": (xyz[:, 1], pa.float16()),
        "z": (xyz[:, 2], pa.float16()), "intensity": (np.asarray(inten, np.uint8), pa.uint8()),
        "laser_number": (np.arange(n, dtype=np.uint8) % 64, pa.uint8()),
        "offset_ns": (np.arange(n, dtype=np.int32) * 1000, pa.int32())})


def write_annotations(log_dir: Path, rows: list[dict]) -> Path:
    """``annotations.feather`` from dicts with every official column."""
    f64 = pa.float64()
    cols = {"timestamp_ns": pa.int64(), "track_uuid": pa.string(), "category": pa.string(),
            "length_m": f64, "width_m": f64, "height_m": f64, "qw": f64, "qx": f64, "qy": f64,
            "qz": f64, "tx_m": f64, "ty_m": f64, "tz_m": f64, "num_interior_pts": pa.int64()}
    return write_table(log_dir / "annotations.feather",
                       {c: ([r[c] for r in rows], t) for c, t in cols.items()})


def _pose_columns(qs, ts) -> dict:
    qs, ts = np.asarray(qs, np.float64).reshape(-1, 4), np.asarray(ts, np.float64).reshape(-1, 3)
    names = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
    return {n: (v, pa.float64()) for n, v in zip(names, np.c_[qs, ts].T, strict=True)}


def write_calibration(log_dir: Path, cameras=RING + STEREO, camera_poses=None,
                      up_lidar=UP_LIDAR) -> None:
    """``calibration/egovehicle_SE3_sensor.feather`` and ``calibration/intrinsics.feather``.

    ``camera_poses``: ``{name: (q, t)}``; cameras not given look forward from (1.625, 0, 1.375)
    (the front camera's real pose, rounded).
    """
    camera_poses = camera_poses or {}
    names, qs, ts = [], [], []
    for cam in cameras:
        q, t = camera_poses.get(cam, (FRONT_CAMERA_Q, (1.625, 0.0, 1.375)))
        names.append(cam), qs.append(q), ts.append(t)
    names += ["up_lidar", "down_lidar"]
    qs += [up_lidar["q"], (0.0, -0.995, 0.1, 0.0)]
    ts += [up_lidar["t"], (1.35, 0.0, 1.53)]
    write_table(log_dir / "calibration" / "egovehicle_SE3_sensor.feather",
                {"sensor_name": (names, pa.string()), **_pose_columns(qs, ts)})
    n = len(cameras)
    i = INTRINSICS
    write_table(log_dir / "calibration" / "intrinsics.feather", {
        "sensor_name": (list(cameras), pa.string()),
        "fx_px": ([i["fx"]] * n, pa.float64()), "fy_px": ([i["fx"]] * n, pa.float64()),
        "cx_px": ([i["cx"]] * n, pa.float64()), "cy_px": ([i["cy"]] * n, pa.float64()),
        "k1": ([-0.25] * n, pa.float64()), "k2": ([-0.2] * n, pa.float64()),
        "k3": ([0.3] * n, pa.float64()),
        "height_px": ([i["height"]] * n, pa.uint16()), "width_px": ([i["width"]] * n, pa.uint16())})


def write_city_poses(log_dir: Path, timestamps, matrices) -> Path:
    """``city_SE3_egovehicle.feather`` from (M,) timestamps and (M, 4, 4) poses."""
    m = np.asarray(matrices, dtype=np.float64).reshape(-1, 4, 4)
    return write_table(log_dir / "city_SE3_egovehicle.feather", {
        "timestamp_ns": (np.asarray(timestamps, np.int64), pa.int64()),
        **_pose_columns([matrix_to_quaternion(r) for r in m[:, :3, :3]], m[:, :3, 3])})


def matrix_to_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(qw, qx, qy, qz) of a rotation matrix (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    tr = np.trace(r)
    if tr > 0:
        s = 2 * np.sqrt(1 + tr)
        q = (s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + r[i, i] - r[j, j] - r[k, k])
        v = np.zeros(3)
        v[i] = s / 4
        v[j] = (r[j, i] + r[i, j]) / s
        v[k] = (r[k, i] + r[i, k]) / s
        q = ((r[k, j] - r[j, k]) / s, *v)
    return tuple(float(x) for x in q)


def city_matrix(yaw: float, t, roll: float = 0.0) -> np.ndarray:
    """A (4, 4) ego -> city pose: roll about x, then yaw about z, then translation ``t``."""
    c, s = np.cos(yaw), np.sin(yaw)
    cr, sr = np.cos(roll), np.sin(roll)
    m = np.eye(4)
    m[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array(
        [[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    m[:3, 3] = t
    return m


@dataclass
class FixtureBox:
    """One annotated object (ego frame): centre, size (l, w, h), yaw, and how many points the
    fixture puts inside it (``n_inside``) and on its faces (``n_surface``)."""

    track: str
    category: str
    centre: tuple
    size: tuple
    yaw: float
    n_inside: int = 20
    n_surface: int = 0


@dataclass
class FixtureLog:
    """What :func:`write_log` wrote: the log folder, sweep timestamps, boxes per sweep and the
    written ``num_interior_pts`` per (sweep index, track)."""

    path: Path
    timestamps: list[int]
    boxes: list[list[FixtureBox]]
    num_interior: dict = field(default_factory=dict)


def default_boxes(sweep: int) -> list[FixtureBox]:
    """Six objects, some moving from sweep to sweep. The first is the hand-computed box (yaw 30
    degrees at (10, 5, 0.75) in sweep 0); the last is axis aligned with points exactly on its
    front face."""
    dx = 0.5 * sweep
    return [
        FixtureBox("car-0", "REGULAR_VEHICLE", (10.0 + dx, 5.0, 0.75), (4.5, 1.875, 1.5),
                   np.pi / 6, n_inside=40),
        FixtureBox("truck-1", "BOX_TRUCK", (-12.0, -6.0, 1.75), (8.0, 2.5, 3.5),
                   2.5 - 0.1 * sweep, n_inside=60),
        FixtureBox("bus-2", "ARTICULATED_BUS", (20.0, -15.0, 1.5), (18.0, 2.5, 3.0), -2.0,
                   n_inside=30),
        FixtureBox("ped-3", "PEDESTRIAN", (5.0, -4.0, 0.875), (0.625, 0.625, 1.75), 0.3,
                   n_inside=5),
        FixtureBox("van-4", "LARGE_VEHICLE", (-3.0, 12.0, 1.25), (6.0, 2.25, 2.5), 1.2,
                   n_inside=0),
        FixtureBox("car-5", "REGULAR_VEHICLE", (-15.0, 8.0, 0.75), (4.0, 2.0, 1.5), 0.0,
                   n_inside=10, n_surface=4),
    ]


def _rot(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _box_points(b: FixtureBox, rng: np.random.Generator) -> np.ndarray:
    """Points strictly inside ``b`` (0.1 m from every face) and exactly on its front face (ego).

    Face points need an axis-aligned box with a centre and size exact in float16: their
    coordinates are multiples of 1/64 m, exact in the float16 sweep and after the reader's
    shift by the (exact) up_lidar translation.
    """
    half = np.asarray(b.size) / 2
    local = rng.uniform(-(half - 0.1), half - 0.1, size=(b.n_inside, 3))
    assert b.n_surface == 0 or b.yaw == 0.0, "surface points need an axis-aligned box"
    face = np.zeros((b.n_surface, 3))
    face[:, 0] = half[0]  # on the front face, anywhere on it
    face[:, 1:] = np.round(rng.uniform(-(half[1:] - 0.1), half[1:] - 0.1,
                                       size=(b.n_surface, 2)) * 64) / 64
    return np.r_[local, face] @ _rot(b.yaw).T + np.asarray(b.centre)


def _outside_all(points: np.ndarray, boxes: list[FixtureBox], gap: float) -> np.ndarray:
    keep = np.ones(len(points), dtype=bool)
    for b in boxes:
        local = (points - np.asarray(b.centre)) @ _rot(b.yaw)
        keep &= ~np.all(np.abs(local) <= np.asarray(b.size) / 2 + gap, axis=1)
    return keep


def write_log(root: Path, name: str = "0a1b2c3d-0000-4000-8000-000000000001",
              n_sweeps: int = 3, boxes_fn=default_boxes, n_clutter: int = 400,
              seed: int = 0, city: bool = True, cameras=RING + STEREO) -> FixtureLog:
    """A complete small log under ``root/name``: sweeps, annotations, calibration, city poses
    (ego yawing, rolling a little and driving; one pose per sweep plus one 25 ms after each).
    """
    rng = np.random.default_rng(seed)
    log_dir = Path(root) / name
    stamps = [T0 + i * DT for i in range(n_sweeps)]
    rows, all_boxes, counts = [], [], {}
    for i, ts in enumerate(stamps):
        boxes = boxes_fn(i)
        inside = [_box_points(b, rng) for b in boxes]
        clutter = rng.uniform((-30, -30, -0.5), (30, 30, 4.0), size=(n_clutter, 3))
        clutter = clutter[_outside_all(clutter, boxes, 0.1)]
        write_sweep(log_dir, ts, np.concatenate(inside + [clutter]))
        for b, pts in zip(boxes, inside, strict=True):
            counts[(i, b.track)] = len(pts)
            q = yaw_quaternion(b.yaw)
            rows.append({"timestamp_ns": ts, "track_uuid": b.track, "category": b.category,
                         "length_m": b.size[0], "width_m": b.size[1], "height_m": b.size[2],
                         "qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3], "tx_m": b.centre[0],
                         "ty_m": b.centre[1], "tz_m": b.centre[2],
                         "num_interior_pts": len(pts)})
        all_boxes.append(boxes)
    # an annotated timestamp without a sweep (AV2 logs trimmed of sweeps have these)
    rows.append(dict(rows[0], timestamp_ns=stamps[-1] + DT, track_uuid="orphan"))
    write_annotations(log_dir, rows)
    write_calibration(log_dir, cameras=cameras)
    if city:
        ts_all, mats = [], []
        for i, ts in enumerate(stamps):
            for off in (0, 25_000_000):
                ts_all.append(ts + off)
                k = i + off / DT
                mats.append(city_matrix(0.4 + 0.05 * k, (100.0 + 2.0 * k, -50.0 + 0.5 * k, 20.0),
                                        roll=0.01 * k))
        write_city_poses(log_dir, ts_all, mats)
    return FixtureLog(log_dir, stamps, all_boxes, counts)
