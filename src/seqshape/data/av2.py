"""Argoverse 2 sensor dataset: one log folder read as a :class:`DrivingLog`.

Layout of a log (``ROOT/LOG_ID/``, e.g. ``ROOT = .../sensor/val``), all tables Apache Feather,
read with pyarrow (neither pandas nor the ``av2`` package is needed):

========================================  ==================================================
``sensors/lidar/<timestamp_ns>.feather``  one sweep of both roof LiDARs: ``x y z intensity
                                          laser_number offset_ns``, ego frame
``annotations.feather``                   cuboids: ``timestamp_ns track_uuid category
                                          length_m width_m height_m qw qx qy qz tx_m ty_m tz_m
                                          num_interior_pts``, ego frame, box centre
``calibration/egovehicle_SE3_sensor.feather``  ``sensor_name qw qx qy qz tx_m ty_m tz_m``:
                                          each sensor's pose in the ego frame
``calibration/intrinsics.feather``        ``sensor_name fx_px fy_px cx_px cy_px k1 k2 k3
                                          height_px width_px``
``city_SE3_egovehicle.feather``           ``timestamp_ns qw qx qy qz tx_m ty_m tz_m``: ego pose
                                          in the city frame (LiDAR and camera times)
``sensors/cameras/<camera>/<ns>.jpg``     images (may be absent)
========================================  ==================================================

Conventions. Quaternions are scalar-first ``(qw, qx, qy, qz)``; ``a_SE3_b`` maps points of
frame ``b`` into frame ``a``. The ego frame has x forward, y left, z up, origin on the ground
under the rear axle. seqshape's **sensor frame** is the ego axes with the origin moved to the
``up_lidar`` position: points and box centres minus the ``up_lidar`` translation, never rotated
(``up_lidar``'s own small rotation is irrelevant: the sweeps are already in ego axes).

* Frames are the positions ``0..T-1`` of the sorted sweep timestamps;
  ``timestamp(frame) = ns * 1e-9``.
* ``points(frame)``: ``(N, 4)`` float32 ``x, y, z, intensity``, sensor frame.
* ``boxes(frame)``: the annotation rows whose ``timestamp_ns`` equals the sweep's; yaw is the
  heading of the box's rotated x axis in the x-y plane (AV2 cuboids are upright);
  ``num_points = num_interior_pts`` (it counts sweep points inside or on the box);
  ``extra = {"timestamp_ns": ...}``. Categories map with :data:`CATEGORY_TO_CLASS`.
* ``ego_pose(frame)``: from ``city_SE3_egovehicle`` at the sweep's timestamp (that row, or the
  nearest within :data:`POSE_TOLERANCE_NS`; None without one).
* Cameras: the ring cameras of ``intrinsics.feather`` (:data:`RING_CAMERAS`; stereo cameras
  can be asked for by name). AV2's camera extrinsics are already in the optical convention
  (camera x right, y down, z forward), so ``T_cam_sensor = inv(ego_SE3_cam) @ ego_SE3_sensor``.
  Projection is a plain pinhole, as in the official ``av2`` API: the released images are
  already undistorted (the maintainers, av2-api issues #219 and #226, and the AV2 user guide),
  so the radial ``k1..k3`` of ``intrinsics.feather`` describe the raw lens and are **not**
  applied by :meth:`Av2Log.camera`. :func:`distort_pixels` applies them for a caller working
  on raw images (``Av2Log.distortion(name)``).

Errors: a missing folder or file, an unreadable table, a missing or null column, a wrong column
type, a non-finite value, a sweep or image file name that is not a timestamp and a log without
sweeps raise :class:`~seqshape.errors.DataError` naming the file and the problem; so do a
quaternion whose norm is not 1 within 1e-3 (closer ones are normalised), a box dimension <= 0
or above 30 m, a box centre more than 1 km from the sensor, a negative ``num_interior_pts``,
a track twice at one timestamp, a sensor listed twice, a sensor more than 1 km from the ego
origin, an ego pose beyond 10,000 km and a non-positive focal length. Sweep points holding a
NaN or an infinity are dropped with one warning naming the file and the count. Category
names outside the AV2 taxonomy get class None and one counted warning per log. Tables are read
lazily: calibration on opening, annotations and ego poses once on first use, sweeps on demand.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

import seqshape.limits as limits
from seqshape._io import check_regular
from seqshape.camera import PinholeCamera
from seqshape.data.sequence import (
    MAX_RANGE,
    MAX_WORLD,
    Box3D,
    DrivingLog,
    box_problems,
    unit_quaternions,
)
from seqshape.errors import ConfigError, DataError, require

_log = logging.getLogger(__name__)

LIDAR_DIR = "sensors/lidar"
CAMERA_DIR = "sensors/cameras"
ANNOTATIONS = "annotations.feather"
EXTRINSICS = "calibration/egovehicle_SE3_sensor.feather"
INTRINSICS = "calibration/intrinsics.feather"
CITY_POSES = "city_SE3_egovehicle.feather"

#: The reference LiDAR: its position is the sensor-frame origin.
LIDAR_NAME = "up_lidar"

#: The seven ring cameras, front first (``camera_names`` keeps those in ``intrinsics``).
RING_CAMERAS = ("ring_front_center", "ring_front_left", "ring_front_right", "ring_side_left",
                "ring_side_right", "ring_rear_left", "ring_rear_right")

#: An ego pose this close to a timestamp (ns) stands in for it (nearest, no interpolation).
POSE_TOLERANCE_NS = 50_000_000

#: An image this close to a sweep (ns) is that sweep's image (cameras run at 20 Hz).
IMAGE_TOLERANCE_NS = 60_000_000

#: AV2 vehicle categories -> seqshape vehicle class. ``LARGE_VEHICLE`` ("extended passenger
#: vans, fire trucks, RVs") is a van: its usual member is a large van; the sizes in the boxes
#: tell the rest apart. ``TRUCK_CAB`` (semi tractor) is a truck. Every other category of the
#: taxonomy (:data:`OTHER_CATEGORIES`) is not a vehicle for seqshape (class None), including
#: ``MESSAGE_BOARD_TRAILER`` and ``TRAFFIC_LIGHT_TRAILER`` (a sign or a signal on a small
#: trailer, nothing like a vehicle body) and ``RAILED_VEHICLE`` (trains, trams).
CATEGORY_TO_CLASS = {
    "REGULAR_VEHICLE": "car",
    "LARGE_VEHICLE": "van",
    "BOX_TRUCK": "truck",
    "TRUCK": "truck",
    "TRUCK_CAB": "truck",
    "BUS": "bus",
    "SCHOOL_BUS": "bus",
    "ARTICULATED_BUS": "bus",
    "VEHICULAR_TRAILER": "trailer",
}

#: The rest of the AV2 sensor taxonomy (class None without a warning).
OTHER_CATEGORIES = frozenset({
    "ANIMAL", "BICYCLE", "BICYCLIST", "BOLLARD", "CONSTRUCTION_BARREL", "CONSTRUCTION_CONE",
    "DOG", "MESSAGE_BOARD_TRAILER", "MOBILE_PEDESTRIAN_CROSSING_SIGN", "MOBILE_PEDESTRIAN_SIGN",
    "MOTORCYCLE", "MOTORCYCLIST", "OFFICIAL_SIGNALER", "PEDESTRIAN", "RAILED_VEHICLE", "SIGN",
    "STOP_SIGN", "STROLLER", "TRAFFIC_LIGHT_TRAILER", "WHEELCHAIR", "WHEELED_DEVICE",
    "WHEELED_RIDER",
})

_POSE_COLUMNS = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
_ANNOTATION_COLUMNS = {"timestamp_ns": "int", "track_uuid": "str", "category": "str",
                       "length_m": "float", "width_m": "float", "height_m": "float",
                       **{c: "float" for c in _POSE_COLUMNS}, "num_interior_pts": "int"}
_EXTRINSIC_COLUMNS = {"sensor_name": "str", **{c: "float" for c in _POSE_COLUMNS}}
_INTRINSIC_COLUMNS = {"sensor_name": "str", "fx_px": "float", "fy_px": "float",
                      "cx_px": "float", "cy_px": "float", "k1": "float", "k2": "float",
                      "k3": "float", "height_px": "int", "width_px": "int"}
_CITY_COLUMNS = {"timestamp_ns": "int", **{c: "float" for c in _POSE_COLUMNS}}
_SWEEP_COLUMNS = {"x": "points", "y": "points", "z": "points", "intensity": "points"}


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of scalar-first quaternions ``(..., 4)`` (normalised
    here; ``q`` and ``-q`` give the same rotation).

    >>> quaternion_to_matrix([0.5, -0.5, 0.5, -0.5]).round(6).tolist()  # AV2 front camera
    [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    """
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def quaternion_to_yaw(q) -> np.ndarray:
    """Heading ``(...)`` of the rotated x axis in the x-y plane, for quaternions ``(..., 4)``
    (scalar first, any norm).

    >>> float(quaternion_to_yaw([np.cos(np.pi / 12), 0, 0, np.sin(np.pi / 12)]).round(12))
    0.523598775598
    """
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.arctan2(2 * (x * y + w * z), w * w + x * x - y * y - z * z)


def pose_matrices(table: dict, path: Path, limit: float = MAX_WORLD) -> np.ndarray:
    """``(N, 4, 4)`` transforms from the ``qw qx qy qz tx_m ty_m tz_m`` columns of a table read
    from ``path`` (:class:`DataError` on a quaternion whose norm is not 1 within 1e-3, or a
    translation coordinate beyond ``limit`` m)."""
    q = _quaternions(table, path)
    t = np.stack([table[c] for c in _POSE_COLUMNS[4:]], -1).astype(np.float64)
    far = np.flatnonzero(np.abs(t).max(axis=-1, initial=0.0) > limit)
    if len(far):
        raise DataError(path, f"translation {t[far[0]].tolist()} (row {far[0]}) is beyond "
                              f"{limit:g} m")
    m = np.zeros((len(q), 4, 4))
    m[:, :3, :3] = quaternion_to_matrix(q)
    m[:, :3, 3] = t
    m[:, 3, 3] = 1.0
    return m


def _quaternions(table: dict, path: Path) -> np.ndarray:
    """``(N, 4)`` the ``qw qx qy qz`` columns as stored; a quaternion whose norm is not 1 within
    1e-3 is a :class:`DataError` (the others are normalised by :func:`quaternion_to_matrix`, and
    :func:`quaternion_to_yaw` does not depend on the norm)."""
    q = np.stack([table[c] for c in _POSE_COLUMNS[:4]], -1).reshape(-1, 4)
    unit_quaternions(q, path, "quaternion (qw qx qy qz)")
    return q


def translation(t) -> np.ndarray:
    """The (4, 4) transform adding ``t`` (3,)."""
    m = np.eye(4)
    m[:3, 3] = t
    return m


def distort_pixels(uv, K, k) -> np.ndarray:
    """Apply radial distortion ``k = (k1, k2, k3)`` to undistorted pixels ``uv`` (N, 2):
    ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6)`` in normalised coordinates ``x = K^-1 uv``.

    >>> distort_pixels([[150.0, 100.0]], np.array([[100.0, 0, 50], [0, 100, 100], [0, 0, 1]]),
    ...                (-0.1, 0.0, 0.0)).tolist()  # r = 1: 10 % towards the centre
    [[140.0, 100.0]]
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    K = np.asarray(K, dtype=np.float64)
    xy = (uv - K[:2, 2]) / np.diag(K)[:2]  # (N, 2) normalised
    r2 = np.sum(xy * xy, axis=1, keepdims=True)
    scale = 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
    return xy * scale * np.diag(K)[:2] + K[:2, 2]


def read_table(path: Path, columns: dict[str, str], what: str) -> dict[str, np.ndarray]:
    """Read ``columns`` of a Feather table as numpy arrays, validated.

    ``columns`` maps a column to its kind: ``"int"`` (int64 array), ``"float"`` (finite
    numbers, stored dtype kept), ``"points"`` (numbers, non-finite allowed: the caller drops
    those points) or ``"str"`` (object array of str). Any problem (missing or unreadable file,
    missing column, nulls, wrong type, non-finite value, an integer beyond int64) raises
    :class:`DataError` naming ``path``.
    """
    feather = require("pyarrow.feather", "Argoverse 2 logs", "pyarrow")
    pa = require("pyarrow", "Argoverse 2 logs")
    if not path.exists():
        raise DataError(path, f"missing {what}")
    check_regular(path, what, "table")  # a FIFO would block pyarrow's open
    try:
        table = feather.read_table(path, memory_map=False)
        table.validate(full=True)  # offsets and lengths inside their buffers, UTF-8 strings
        names = table.column_names
    except (OSError, pa.ArrowException, ValueError, MemoryError) as exc:
        # UnicodeDecodeError (a corrupt column name) is a ValueError
        raise DataError(path, f"cannot read {what} as a Feather table: "
                              f"{str(exc)[:300]}") from None
    missing = [c for c in columns if c not in names]
    if missing:
        raise DataError(path, f"{what}: missing column(s) {missing} (found {names})")
    return {name: _column(path, table[name], name, kind, pa) for name, kind in columns.items()}


def _column(path: Path, col, name: str, kind: str, pa) -> np.ndarray:
    if col.null_count:
        raise DataError(path, f"column {name}: {col.null_count} null value(s)")
    typ = col.type
    if pa.types.is_dictionary(typ):
        col, typ = col.cast(typ.value_type), typ.value_type
    if kind == "str":
        if not (pa.types.is_string(typ) or pa.types.is_large_string(typ)):
            raise DataError(path, f"column {name}: expected strings, got {typ}")
        return np.asarray(col.to_pylist(), dtype=object)
    if kind == "int" and not pa.types.is_integer(typ):
        raise DataError(path, f"column {name}: expected integers, got {typ}")
    if not (pa.types.is_integer(typ) or pa.types.is_floating(typ)):
        raise DataError(path, f"column {name}: expected numbers, got {typ}")
    values = col.to_numpy()
    if kind == "int":
        if values.dtype == np.uint64 and len(values) and values.max() > np.iinfo(np.int64).max:
            raise DataError(path, f"column {name}: integer {values.max()} beyond int64")
        return values.astype(np.int64)
    if kind == "points":
        return values
    if not np.all(np.isfinite(values)):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        raise DataError(path, f"column {name}: {bad} non-finite value(s)")
    return values


def _unique(names: np.ndarray, path: Path, column: str) -> None:
    """A :class:`DataError` when ``names`` repeats a value."""
    seen: set = set()
    for name in names:
        if name in seen:
            raise DataError(path, f"{column} {name!r} appears twice")
        seen.add(name)


def _check_annotations(t: dict, centre: np.ndarray, size: np.ndarray, path: Path) -> None:
    """Refuse absurd boxes, negative point counts and a track twice at one timestamp."""
    bad, reasons = box_problems(centre, size)
    if len(reasons):
        i = int(np.flatnonzero(bad)[0])
        raise DataError(path, f"row {i} (track {t['track_uuid'][i]}): {reasons[0]} "
                              f"({len(reasons)} bad row(s))")
    neg = np.flatnonzero(t["num_interior_pts"] < 0)
    if len(neg):
        raise DataError(path, f"row {neg[0]}: negative num_interior_pts "
                              f"{t['num_interior_pts'][neg[0]]}")
    seen: dict[tuple[int, str], int] = {}
    for i, key in enumerate(zip(t["timestamp_ns"].tolist(), t["track_uuid"].tolist(),
                                strict=True)):
        first = seen.setdefault(key, i)
        if first != i:
            raise DataError(path, f"rows {first} and {i}: track {key[1]} twice at timestamp "
                                  f"{key[0]}")


def _timestamps(folder: Path, suffix: str) -> tuple[np.ndarray, list[Path]]:
    """Sorted timestamps (int64 ns) and paths of the ``<ns><suffix>`` files of ``folder``."""
    found = []
    for path in folder.glob(f"*{suffix}"):
        stem = path.name[: -len(suffix)]
        if not (stem.isascii() and stem.isdigit() and len(stem) <= 19
                and int(stem) <= np.iinfo(np.int64).max):
            raise DataError(path, f"file name is not a timestamp in nanoseconds: {path.name}")
        found.append((int(stem), path))
    found.sort()
    return np.array([t for t, _ in found], dtype=np.int64), [p for _, p in found]


def _nearest(sorted_ts: np.ndarray, t: int, tolerance: int) -> int | None:
    """Index of the entry of ``sorted_ts`` nearest to ``t`` within ``tolerance``, or None."""
    if len(sorted_ts) == 0:
        return None
    i = int(np.searchsorted(sorted_ts, t))
    best = min((j for j in (i - 1, i) if 0 <= j < len(sorted_ts)),
               key=lambda j: abs(int(sorted_ts[j]) - t))
    return best if abs(int(sorted_ts[best]) - t) <= tolerance else None


class Av2Log(DrivingLog):
    """One Argoverse 2 sensor-dataset log, ``root / name`` (module doc).

    ``sweep_ns`` holds the sorted sweep timestamps (ns; frame ``f`` is ``sweep_ns[f]``);
    ``lidar_offset`` the ``up_lidar`` translation in the ego frame (the sensor-frame origin);
    ``unknown_categories`` the annotation rows per category name outside the AV2 taxonomy
    (filled when the annotations are first read).
    """

    dataset = "av2"
    #: Two Velodyne VLP-32C on the roof (``up_lidar``, ``down_lidar``), merged in every sweep.
    sensor = "vlp32c-x2"

    def __init__(self, root, name: str):
        self.root = Path(root)
        self.name = str(name)
        self.path = self.root / self.name
        if not self.path.is_dir():
            raise DataError(self.path, "no such Argoverse 2 log folder")
        lidar_dir = self.path / LIDAR_DIR
        if not lidar_dir.is_dir():
            raise DataError(lidar_dir, "missing LiDAR folder of the log")
        self.sweep_ns, self._sweep_paths = _timestamps(lidar_dir, ".feather")
        if len(self.sweep_ns) == 0:
            raise DataError(lidar_dir, "no LiDAR sweeps (<timestamp_ns>.feather)")
        self.frames = list(range(len(self.sweep_ns)))
        self._extrinsics = self._read_extrinsics()
        self.lidar_offset = self._extrinsics[LIDAR_NAME][:3, 3].copy()
        self._intrinsics = self._read_intrinsics()
        self.camera_names = tuple(c for c in RING_CAMERAS if c in self._intrinsics)
        self.default_camera = ("ring_front_center" if "ring_front_center" in self.camera_names
                               else (self.camera_names[0] if self.camera_names else None))
        self._boxes: dict[int, list[Box3D]] | None = None
        self._city: tuple[np.ndarray, np.ndarray] | None = None
        self._images: dict[str, np.ndarray] = {}
        self.unknown_categories: dict[str, int] = {}

    # tables

    def _read_extrinsics(self) -> dict[str, np.ndarray]:
        path = self.path / EXTRINSICS
        table = read_table(path, _EXTRINSIC_COLUMNS, "sensor extrinsics")
        _unique(table["sensor_name"], path, "sensor_name")
        poses = dict(zip(table["sensor_name"], pose_matrices(table, path, MAX_RANGE),
                         strict=True))
        if LIDAR_NAME not in poses:
            raise DataError(path, f"no {LIDAR_NAME} row (sensors: {sorted(poses)})")
        return poses

    def _read_intrinsics(self) -> dict[str, tuple[np.ndarray, tuple[int, int], np.ndarray]]:
        """Camera name -> (K (3, 3), (width, height), (k1, k2, k3)); empty without the file."""
        path = self.path / INTRINSICS
        if not path.exists():  # a FIFO or folder in its place is refused by read_table
            return {}
        t = read_table(path, _INTRINSIC_COLUMNS, "camera intrinsics")
        _unique(t["sensor_name"], path, "sensor_name")
        out = {}
        for i, name in enumerate(t["sensor_name"]):
            if not (t["fx_px"][i] > 0 and t["fy_px"][i] > 0):
                raise DataError(path, f"{name}: focal lengths must be positive, got "
                                      f"{t['fx_px'][i]:g}, {t['fy_px'][i]:g}")
            k = np.array([[t["fx_px"][i], 0.0, t["cx_px"][i]], [0.0, t["fy_px"][i], t["cy_px"][i]],
                          [0.0, 0.0, 1.0]])
            size = (int(t["width_px"][i]), int(t["height_px"][i]))
            if min(size) <= 0:
                raise DataError(path, f"{name}: image size must be positive, got {size}")
            out[str(name)] = (k, size, np.array([t[c][i] for c in ("k1", "k2", "k3")]))
        return out

    def _load_boxes(self) -> dict[int, list[Box3D]]:
        path = self.path / ANNOTATIONS
        t = read_table(path, _ANNOTATION_COLUMNS, "annotations (AV2 test logs have none)")
        yaw = quaternion_to_yaw(_quaternions(t, path))  # (R,)
        centre = np.stack([t["tx_m"], t["ty_m"], t["tz_m"]], -1) - self.lidar_offset  # (R, 3)
        size = np.stack([t["length_m"], t["width_m"], t["height_m"]], -1)  # (R, 3)
        _check_annotations(t, centre, size, path)
        wanted = {int(ts): f for f, ts in enumerate(self.sweep_ns)}
        boxes: dict[int, list[Box3D]] = {f: [] for f in range(len(self.sweep_ns))}
        unknown: dict[str, int] = {}
        for i in np.flatnonzero(np.isin(t["timestamp_ns"], self.sweep_ns)):
            cat = str(t["category"][i])
            cls = CATEGORY_TO_CLASS.get(cat)
            if cls is None and cat not in OTHER_CATEGORIES:
                unknown[cat] = unknown.get(cat, 0) + 1
            ts = int(t["timestamp_ns"][i])
            boxes[wanted[ts]].append(Box3D(
                track_id=str(t["track_uuid"][i]), category=cat, cls=cls, centre=centre[i],
                size=size[i], yaw=yaw[i], num_points=int(t["num_interior_pts"][i]),
                extra={"timestamp_ns": ts}))
        if unknown:
            _log.warning("%s: %d box(es) with categories outside the AV2 taxonomy %s: "
                         "kept with class None", path, sum(unknown.values()), sorted(unknown))
        self.unknown_categories = unknown
        return boxes

    def _city_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Sorted timestamps (ns) and (M, 4, 4) ``city_SE3_egovehicle``."""
        if self._city is None:
            path = self.path / CITY_POSES
            t = read_table(path, _CITY_COLUMNS, "ego poses")
            order = np.argsort(t["timestamp_ns"], kind="stable")
            self._city = t["timestamp_ns"][order], pose_matrices(t, path)[order]
        return self._city

    def city_pose(self, timestamp_ns: int) -> np.ndarray | None:
        """(4, 4) ``city_SE3_egovehicle`` at ``timestamp_ns`` (nearest row within
        :data:`POSE_TOLERANCE_NS`), or None."""
        ts, poses = self._city_poses()
        i = _nearest(ts, int(timestamp_ns), POSE_TOLERANCE_NS)
        return None if i is None else poses[i]

    # the DrivingLog protocol

    def _ns(self, frame: int) -> int:
        if not 0 <= int(frame) < len(self.sweep_ns):
            raise ConfigError(f"av2 log {self.name} has frames 0..{len(self.sweep_ns) - 1}, "
                              f"not {frame}")
        return int(self.sweep_ns[int(frame)])

    def sweep_path(self, frame: int) -> Path:
        """The Feather file of the frame's sweep."""
        self._ns(frame)
        return self._sweep_paths[int(frame)]

    def timestamp(self, frame: int) -> float:
        return self._ns(frame) * 1e-9

    def points(self, frame: int) -> np.ndarray:
        """``(N, 4)`` float32 ``x, y, z, intensity``, sensor frame (module doc), checked by
        :func:`seqshape.limits.check_sweep`: a sweep whose points lie beyond 1 km of the
        sensor (another log's sweep, points in city coordinates) is refused."""
        path = self.sweep_path(frame)
        t = read_table(path, _SWEEP_COLUMNS, "LiDAR sweep")
        xyz = np.stack([t["x"], t["y"], t["z"]], -1).astype(np.float64) - self.lidar_offset
        out = np.empty((len(xyz), 4), dtype=np.float32)
        out[:, :3] = xyz
        out[:, 3] = t["intensity"]
        return limits.check_sweep(out, path, "LiDAR sweep", "x y z intensity")

    def boxes(self, frame: int) -> list[Box3D]:
        self._ns(frame)
        if self._boxes is None:
            self._boxes = self._load_boxes()
        return list(self._boxes[int(frame)])

    def ego_pose(self, frame: int) -> np.ndarray | None:
        """(4, 4) sensor frame of ``frame`` -> sensor frame of frame 0, or None when either
        sweep has no ego pose within :data:`POSE_TOLERANCE_NS`."""
        c_t = self.city_pose(self._ns(frame))
        c_0 = self.city_pose(self._ns(0))
        if c_t is None or c_0 is None:
            return None
        s = translation(self.lidar_offset)  # sensor -> ego
        return np.linalg.inv(s) @ np.linalg.inv(c_0) @ c_t @ s

    def camera(self, name: str | None = None, frame: int | None = None) -> PinholeCamera:
        """Camera ``name`` (any camera of ``intrinsics.feather``) seen from the sensor frame.

        With ``frame`` and an image of that camera at another time than the sweep, the
        extrinsics follow the ego motion from the sweep to the image
        (``inv(ego_SE3_cam) @ inv(city_SE3_ego(image)) @ city_SE3_ego(sweep) @ ego_SE3_sensor``)
        when both ego poses exist. Distortion is ignored (module doc).
        """
        name = name or self.default_camera
        if not self._intrinsics:
            raise DataError(self.path / INTRINSICS, "missing camera intrinsics")
        if name not in self._intrinsics:
            raise ConfigError(f"av2 log {self.name} has no camera {name!r}: choose from "
                              f"{sorted(self._intrinsics)}")
        if name not in self._extrinsics:
            raise DataError(self.path / EXTRINSICS, f"no extrinsics for camera {name}")
        k, size, _ = self._intrinsics[name]
        ego_to_cam = np.linalg.inv(self._extrinsics[name])
        motion = np.eye(4)
        if frame is not None:
            motion = self._motion_to_image(frame, name)
        t = ego_to_cam @ motion @ translation(self.lidar_offset)
        return PinholeCamera.from_intrinsics(k, t, size, name=name)

    def distortion(self, name: str | None = None) -> np.ndarray:
        """(3,) radial distortion ``k1, k2, k3`` of camera ``name`` (for :func:`distort_pixels`)."""
        name = name or self.default_camera
        if name not in self._intrinsics:
            raise ConfigError(f"av2 log {self.name} has no camera {name!r}")
        return self._intrinsics[name][2].copy()

    def _motion_to_image(self, frame: int, camera: str) -> np.ndarray:
        """(4, 4) ego frame at the sweep -> ego frame at the camera's image (identity without an
        image, at the same time, or without both ego poses)."""
        sweep = self._ns(frame)
        i = self._image_index(sweep, camera)
        if i is None or int(self._images[camera][i]) == sweep:
            return np.eye(4)
        c_img = self.city_pose(int(self._images[camera][i]))
        c_sweep = self.city_pose(sweep)
        if c_img is None or c_sweep is None:
            return np.eye(4)
        return np.linalg.inv(c_img) @ c_sweep

    def _image_index(self, sweep_ns: int, camera: str) -> int | None:
        if camera not in self._images:
            self._images[camera] = _timestamps(self.path / CAMERA_DIR / camera, ".jpg")[0]
        return _nearest(self._images[camera], sweep_ns, IMAGE_TOLERANCE_NS)

    def image_path(self, frame: int, camera: str | None = None) -> Path | None:
        """``sensors/cameras/<camera>/<ns>.jpg`` nearest to the sweep within
        :data:`IMAGE_TOLERANCE_NS`, or None."""
        camera = camera or self.default_camera
        if camera is None:
            return None
        i = self._image_index(self._ns(frame), camera)
        if i is None:
            return None
        return self.path / CAMERA_DIR / camera / f"{int(self._images[camera][i])}.jpg"

    @classmethod
    def log_names(cls, root) -> list[str]:
        """Sub-folders of ``root`` with an ``annotations.feather`` or ``sensors/lidar``."""
        root = Path(root)
        if not root.is_dir():
            raise DataError(root, "no such Argoverse 2 folder")
        return sorted(p.name for p in root.iterdir()
                      if p.is_dir() and ((p / ANNOTATIONS).is_file() or (p / LIDAR_DIR).is_dir()))
