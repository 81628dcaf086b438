"""KITTI tracking data: velodyne scans, ``label_02`` boxes, oxts ego motion, and tracks.

Layout of a root folder (the KITTI tracking ``training/`` or ``testing/`` folder, or a scene
written by ``seqshape scenes``)::

    velodyne/SSSS/FFFFFF.bin   float32 (x, y, z, reflectance) rows, velodyne frame
    image_02/SSSS/FFFFFF.png   left colour image
    label_02/SSSS.txt          one box per line (below)
    calib/SSSS.txt             see seqshape.camera
    oxts/SSSS.txt              one GPS/IMU row (30 numbers) per frame

``label_02`` columns: frame, track_id (-1 for DontCare), type, truncated, occluded, alpha,
bbox (left, top, right, bottom; pixels), dimensions (h, w, l; m), location (x, y, z; the BOTTOM
centre of the box in rectified camera-0 coordinates, m), rotation_y (about the camera y axis,
which points down; 0 = facing camera x), and an optional 18th column, score.

Our convention (seqshape.geometry): a box is ``pose = (x, y, z, yaw)``, its CENTRE in the
velodyne frame and its heading about velodyne z, and ``size = (l, w, h)``. The conversion
(:func:`label_to_pose`) goes through the calibration: ``yaw = -rotation_y - pi/2`` holds only
for an ideally aligned calibration; the general form maps the heading vector
``(cos ry, 0, -sin ry)`` from camera to velodyne coordinates.
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import seqshape.data.crop as _crop
import seqshape.limits as limits
from seqshape._deprecated import forward
from seqshape._io import atomic_write_bytes, atomic_write_text, open_regular, read_text
from seqshape.camera import KittiCalib, PinholeCamera, cam_to_velo, read_calib, velo_to_cam
from seqshape.data.categories import KITTI_CLASSES
from seqshape.data.crop import CropConfig
from seqshape.data.extract import extract_tracks as generic_tracks
from seqshape.data.sequence import (
    MAX_BOX_SIZE,
    MAX_RANGE,
    Box3D,
    DrivingLog,
    read_sweep,
)
from seqshape.data.track import Track
from seqshape.errors import ConfigError, DataError
from seqshape.geometry import wrap_angle

log = logging.getLogger(__name__)

#: ``crop_box`` moved to :mod:`seqshape.data.crop`; the old path warns for one release.
__getattr__ = forward(__name__, _crop, ("crop_box",))

FRAME_RATE_HZ = 10.0
OXTS_COLUMNS = ("lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu",
                "ax", "ay", "az", "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu",
                "pos_accuracy", "vel_accuracy", "navstat", "numsats", "posmode", "velmode",
                "orimode")
_OXTS_INT_COLUMNS = range(25, 30)
EARTH_RADIUS = 6378137.0  # m, as in the KITTI devkit


# ----------------------------------------------------------------------------- paths


def seq_name(sequence: int | str) -> str:
    """``3`` or ``"0003"`` -> ``"0003"``."""
    try:
        return f"{int(sequence):04d}"
    except (TypeError, ValueError):
        raise ValueError(f"KITTI sequence must be a number, got {sequence!r}") from None


def _is_number(name: str) -> bool:
    """``name`` is a frame or sequence number (ASCII digits only, as KITTI writes them)."""
    return name.isascii() and name.isdigit()


def velodyne_path(root, sequence, frame: int) -> Path:
    return Path(root) / "velodyne" / seq_name(sequence) / f"{int(frame):06d}.bin"


def image_path(root, sequence, frame: int, cam: int = 2) -> Path:
    return Path(root) / f"image_{cam:02d}" / seq_name(sequence) / f"{int(frame):06d}.png"


def label_path(root, sequence) -> Path:
    return Path(root) / "label_02" / f"{seq_name(sequence)}.txt"


def calib_path(root, sequence) -> Path:
    return Path(root) / "calib" / f"{seq_name(sequence)}.txt"


def oxts_path(root, sequence) -> Path:
    return Path(root) / "oxts" / f"{seq_name(sequence)}.txt"


def png_size(path) -> tuple[int, int]:
    """(width, height) of a PNG file, read from its header (no decoding)."""
    path = Path(path)
    with open_regular(path, "image", "image") as fh:
        try:
            head = fh.read(24)
        except OSError as exc:
            raise DataError(path, f"cannot read image ({exc})") from None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise DataError(path, "not a PNG file")
    width, height = struct.unpack(">II", head[16:24])
    if not (0 < width < 2**31 and 0 < height < 2**31):  # the PNG specification's limits
        raise DataError(path, f"PNG header gives an image size of {width} x {height}")
    return width, height


# ----------------------------------------------------------------------------- velodyne


def read_velodyne(path) -> np.ndarray:
    """A velodyne scan as ``(N, 4)`` float32 (x, y, z, reflectance), velodyne frame.

    A byte length that is not a multiple of 16 (4 float32 per point) is a :class:`DataError`;
    points holding a NaN or an infinity are dropped, with one warning naming the file and the
    count; so are up to 1 % of points with a coordinate beyond 1 km or a negative reflectance,
    and more refuses the file, naming the layout its bytes fit (float64, or (N, 3) float32):
    :func:`seqshape.limits.check_sweep`.
    """
    return read_sweep(Path(path), 4, "velodyne file", "x y z reflectance")


def write_velodyne(path, points) -> None:
    """Write ``(N, 3)`` (reflectance 0) or ``(N, 4)`` points as a KITTI ``.bin`` (atomic)."""
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise ValueError(f"points must be (N, 3) or (N, 4), got {pts.shape}")
    if pts.shape[1] == 3:
        pts = np.c_[pts, np.zeros(len(pts), np.float32)]
    atomic_write_bytes(path, np.ascontiguousarray(pts, dtype="<f4").tobytes())


# ----------------------------------------------------------------------------- labels


@dataclass
class KittiLabel:
    """One row of a KITTI tracking label file (see the module docstring for the frames)."""

    frame: int
    track_id: int
    type: str
    truncated: float
    occluded: int
    alpha: float
    bbox: np.ndarray          # (4,) left, top, right, bottom, pixels
    dimensions: np.ndarray    # (3,) h, w, l, m
    location: np.ndarray      # (3,) bottom centre, rectified camera 0, m
    rotation_y: float
    score: float | None = None
    extra: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        self.bbox = np.asarray(self.bbox, dtype=np.float64).reshape(4)
        self.dimensions = np.asarray(self.dimensions, dtype=np.float64).reshape(3)
        self.location = np.asarray(self.location, dtype=np.float64).reshape(3)

    @property
    def is_dontcare(self) -> bool:
        return self.type == "DontCare"


#: KITTI tracking/object types (anything else is read, with one warning per file).
KITTI_TYPES = frozenset({"Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Person",
                         "Cyclist", "Tram", "Misc", "DontCare"})

#: Names of the numeric label columns after ``type``, for messages.
_LABEL_FLOATS = ("truncated", "occluded", "alpha", "bbox left", "bbox top", "bbox right",
                 "bbox bottom", "height", "width", "length", "x", "y", "z", "rotation_y",
                 "score")

#: Largest magnitude of a 2D box coordinate (pixels) and of an angle (rad) in a label row
#: (:mod:`seqshape.limits`).
MAX_PIXEL = limits.MAX_PIXEL
MAX_ANGLE = limits.MAX_ANGLE
#: Largest frame number (KITTI names frames with six digits).
MAX_FRAME = 999_999
_OCCLUSION_LEVELS = frozenset({-1.0, 0.0, 1.0, 2.0, 3.0})


class _RowError(ValueError):
    """A label or oxts row that is not valid (the reader adds the file and line)."""


def _int_field(text: str, name: str) -> int:
    if len(text) > 20:  # beyond int64; int() of 5000 digits is slow, then refused anyway
        raise _RowError(f"{name} must be an integer of at most 20 characters, got "
                        f"{_short(text)}")
    try:
        return int(text)
    except ValueError:
        raise _RowError(f"{name} must be an integer, got {text!r}") from None


def _short(text: str) -> str:
    """``text`` quoted, cut to 24 characters (with its length) when longer."""
    return repr(text) if len(text) <= 24 else f"{text[:24]!r}... ({len(text)} characters)"


def _float_fields(parts: list[str], names) -> list[float]:
    try:
        values = [float(v) for v in parts]
    except ValueError as exc:
        raise _RowError(f"bad number ({exc})") from None
    if not math.isfinite(sum(values)):  # one sum in the common case; find the culprit after
        for v, name in zip(values, names, strict=False):
            if not math.isfinite(v):
                raise _RowError(f"{name} is not finite ({v})")
    return values


def _parse_label(parts: list[str]) -> KittiLabel:
    """One label row, validated (module docstring; docs/kitti.md lists what is refused)."""
    frame = _int_field(parts[0], "frame")
    track = _int_field(parts[1], "track_id")
    if not 0 <= frame <= MAX_FRAME:
        raise _RowError(f"frame {frame} is not in 0..{MAX_FRAME} (six-digit frame names)")
    if not -1 <= track <= limits.MAX_ID:
        raise _RowError(f"track_id must be in -1..{limits.MAX_ID} (-1 for DontCare), got "
                        f"{_short(parts[1])}")
    f = _float_fields(parts[3:], _LABEL_FLOATS)
    trunc, occ, alpha, bbox, dims, loc, ry = f[0], f[1], f[2], f[3:7], f[7:10], f[10:13], f[13]
    if not -1 <= trunc <= 2:
        raise _RowError(f"truncated must be in [-1, 2], got {trunc:g}")
    if occ not in _OCCLUSION_LEVELS:
        raise _RowError(f"occluded must be an integer in -1..3, got {occ:g}")
    left, top, right, bottom = bbox
    if not (-MAX_PIXEL <= left <= right <= MAX_PIXEL and -MAX_PIXEL <= top <= bottom <= MAX_PIXEL):
        raise _RowError(f"bbox {_g(bbox)} is not (left, top, right, bottom) pixels with "
                        f"left <= right and top <= bottom")
    if track >= 0 and parts[2] != "DontCare":
        _check_box(dims, loc, alpha, ry)
    return KittiLabel(frame=frame, track_id=track, type=parts[2], truncated=trunc,
                      occluded=int(occ), alpha=alpha, bbox=bbox, dimensions=dims, location=loc,
                      rotation_y=ry, score=f[14] if len(f) == 15 else None)


def _check_box(dims: list[float], loc: list[float], alpha: float, ry: float) -> None:
    """Refuse a physically absurd box (DontCare rows, with their -1/-1000 sentinels, skip this)."""
    h, w, length = dims
    if not (0 < h <= MAX_BOX_SIZE and 0 < w <= MAX_BOX_SIZE and 0 < length <= MAX_BOX_SIZE):
        raise _RowError(f"dimensions (h, w, l) {_g(dims)} m: each must be in "
                        f"(0, {MAX_BOX_SIZE:g}]")
    if math.hypot(*loc) > MAX_RANGE:
        raise _RowError(f"location {_g(loc)} is more than {MAX_RANGE:g} m from the camera")
    if abs(alpha) > MAX_ANGLE or abs(ry) > MAX_ANGLE:
        raise _RowError(f"alpha {alpha:g} / rotation_y {ry:g} rad: must be within "
                        f"+-{MAX_ANGLE:.4g}")


def _g(values) -> str:
    return "(" + ", ".join(f"{v:g}" for v in values) + ")"


def read_labels(path) -> list[KittiLabel]:
    """Read a ``label_02`` file (17 columns, or 18 with a score); DontCare rows are kept.

    Every row is validated; a malformed one is a :class:`DataError` naming the file and line
    (docs/kitti.md, "What the readers refuse"): a wrong column count, a frame or track id that
    is not an integer, a frame outside 0..999999, a track id outside -1..999999, a non-finite number, ``truncated`` outside [-1, 2], ``occluded`` not
    one of -1..3, a 2D box with left > right or top > bottom, and, for rows with a box (not
    DontCare, track id >= 0), a dimension <= 0 or above 30 m, a location more than 1 km away,
    an angle beyond 2 pi, or a second row of the same track in the same frame. Types KITTI does
    not define are read, with one warning per file.
    """
    path = Path(path)
    text = read_text(path, "label file")
    labels = []
    seen: dict[tuple[int, int], int] = {}
    unknown: dict[str, int] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) not in (17, 18):
            raise DataError(path, f"expected 17 or 18 columns, got {len(parts)}", line=lineno)
        try:
            lab = _parse_label(parts)
        except _RowError as exc:
            raise DataError(path, str(exc), line=lineno) from None
        if lab.track_id >= 0 and not lab.is_dontcare:
            first = seen.setdefault((lab.frame, lab.track_id), lineno)
            if first != lineno:
                raise DataError(path, f"track {lab.track_id} appears twice in frame "
                                      f"{lab.frame} (first on line {first})", line=lineno)
        if lab.type not in KITTI_TYPES:
            unknown[lab.type] = unknown.get(lab.type, 0) + 1
        labels.append(lab)
    if unknown:
        log.warning("%s: %d row(s) with types KITTI does not define %s (read, no vehicle "
                    "class)", path, sum(unknown.values()), sorted(unknown))
    return labels


def _f(v: float) -> str:
    return f"{float(v):.6f}"


def format_label(lab: KittiLabel) -> str:
    """One label line; floats with ``%.6f`` (truncated as an integer when it is one)."""
    trunc = f"{int(lab.truncated)}" if float(lab.truncated).is_integer() else _f(lab.truncated)
    cols = [str(int(lab.frame)), str(int(lab.track_id)), lab.type, trunc, str(int(lab.occluded)),
            _f(lab.alpha), *map(_f, lab.bbox), *map(_f, lab.dimensions), *map(_f, lab.location),
            _f(lab.rotation_y)]
    if lab.score is not None:
        cols.append(_f(lab.score))
    return " ".join(cols)


def write_labels(path, labels) -> None:
    """Write labels (sorted by frame, then track id as given) atomically."""
    if any(" " in lab.type or not lab.type for lab in labels):
        raise ValueError("label types must be non-empty words")
    rows = sorted(labels, key=lambda lab: lab.frame)
    atomic_write_text(path, "".join(format_label(lab) + "\n" for lab in rows))


def labels_by_frame(labels) -> dict[int, list[KittiLabel]]:
    out: dict[int, list[KittiLabel]] = {}
    for lab in labels:
        out.setdefault(lab.frame, []).append(lab)
    return out


# ----------------------------------------------------------------------------- boxes


def label_to_pose(label: KittiLabel, calib: KittiCalib) -> tuple[np.ndarray, np.ndarray]:
    """KITTI box -> ``(pose (4,) = box centre (x, y, z) in velodyne + yaw, size (l, w, h))``."""
    h, w, length = label.dimensions
    centre_rect = label.location - np.array([0.0, h / 2, 0.0])  # camera y points down
    centre = cam_to_velo(centre_rect, calib)[0]
    ry = float(label.rotation_y)
    heading = calib.rect_to_velo[:3, :3] @ np.array([np.cos(ry), 0.0, -np.sin(ry)])
    yaw = float(np.arctan2(heading[1], heading[0]))
    return np.r_[centre, yaw], np.array([length, w, h])


def pose_to_label_fields(pose, size, calib: KittiCalib) -> dict:
    """Inverse of :func:`label_to_pose`: ``{"location", "dimensions", "rotation_y", "alpha"}``.

    ``alpha = rotation_y - atan2(x, z)`` of the box centre in camera coordinates (KITTI's
    observation angle). The dict splats into :class:`KittiLabel`. ``rotation_y`` is chosen so
    that :func:`label_to_pose` gives back exactly ``pose[3]``, also for a calibration whose
    camera y axis is slightly tilted from the velodyne -z axis.
    """
    pose = np.asarray(pose, dtype=np.float64)
    length, w, h = (float(v) for v in size)
    centre_rect = velo_to_cam(pose[:3], calib)[0]
    # label_to_pose maps (cos ry, -sin ry) through the 2x2 block m to the velodyne heading;
    # invert that block so that the round trip is exact for any calibration
    m = calib.rect_to_velo[:2, [0, 2]]
    u = np.linalg.solve(m, np.array([np.cos(pose[3]), np.sin(pose[3])]))
    ry = float(np.arctan2(-u[1], u[0]))
    alpha = float(wrap_angle(ry - np.arctan2(centre_rect[0], centre_rect[2])))
    return {"location": centre_rect + np.array([0.0, h / 2, 0.0]),
            "dimensions": np.array([h, w, length]), "rotation_y": ry, "alpha": alpha}


# ----------------------------------------------------------------------------- oxts


#: oxts columns that are angles (rad) and how far they may go.
_OXTS_ANGLES = range(3, 6)
#: Largest altitude magnitude (m) an oxts row may hold.
MAX_ALTITUDE = 1.0e5


def read_oxts(path) -> np.ndarray:
    """An oxts file (one row of 30 numbers per frame) as ``(T, 30)`` float64.

    Every row is validated; a malformed one is a :class:`DataError` naming the file and line: a
    column count other than 30, a non-numeric or non-finite value, a latitude outside
    (-90, 90) (the poles have no Mercator position), a longitude outside [-180, 180], an
    altitude beyond 100 km, roll, pitch or yaw beyond 2 pi, or status columns (navstat,
    numsats, posmode, velmode, orimode) that are not non-negative integers.
    """
    path = Path(path)
    text = read_text(path, "oxts file")
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 30:
            raise DataError(path, f"expected 30 oxts columns, got {len(parts)}", line=lineno)
        try:
            rows.append(_oxts_row(parts))
        except _RowError as exc:
            raise DataError(path, str(exc), line=lineno) from None
    return np.array(rows, dtype=np.float64).reshape(-1, 30)


def _oxts_row(parts: list[str]) -> list[float]:
    row = _float_fields(parts, OXTS_COLUMNS)
    lat, lon, alt = row[:3]
    if not -90 < lat < 90:
        raise _RowError(f"latitude {lat:g} is not in (-90, 90) degrees")
    if not -180 <= lon <= 180:
        raise _RowError(f"longitude {lon:g} is not in [-180, 180] degrees")
    if abs(alt) > MAX_ALTITUDE:
        raise _RowError(f"altitude {alt:g} m is beyond {MAX_ALTITUDE:g} m")
    for j in _OXTS_ANGLES:
        if abs(row[j]) > MAX_ANGLE:
            raise _RowError(f"{OXTS_COLUMNS[j]} {row[j]:g} rad is beyond +-{MAX_ANGLE:.4g}")
    for j in _OXTS_INT_COLUMNS:
        if row[j] < 0 or not row[j].is_integer():
            raise _RowError(f"{OXTS_COLUMNS[j]} must be a non-negative integer, got {row[j]:g}")
    return row


def write_oxts(path, rows) -> None:
    """Write ``(T, 30)`` oxts rows (exact float repr; the 5 status columns as integers)."""
    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != 30:
        raise ValueError(f"oxts rows must be (T, 30), got {rows.shape}")
    lines = [" ".join(str(int(v)) if j in _OXTS_INT_COLUMNS else repr(float(v))
                      for j, v in enumerate(row)) for row in rows]
    atomic_write_text(path, "".join(line + "\n" for line in lines))


def _rot_rpy(roll, pitch, yaw) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch),
                              np.cos(yaw), np.sin(yaw))
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def oxts_to_poses(rows) -> np.ndarray:
    """IMU poses ``(T, 4, 4)`` relative to the first frame (KITTI devkit's Mercator convention).

    Position: ``mx = s * lon * pi * r / 180``, ``my = s * r * log(tan((90 + lat) * pi / 360))``
    with ``s = cos(lat_0)`` and r the earth radius; rotation ``Rz(yaw) Ry(pitch) Rx(roll)``.
    Pose t maps IMU-frame-t points to IMU-frame-0 points.
    """
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 30)
    if len(rows) == 0:
        return np.zeros((0, 4, 4))
    scale = np.cos(np.deg2rad(rows[0, 0]))
    rot = np.stack([_rot_rpy(r[3], r[4], r[5]) for r in rows])  # (T, 3, 3)
    trans = np.c_[scale * rows[:, 1] * np.pi * EARTH_RADIUS / 180,
                  scale * EARTH_RADIUS * np.log(np.tan((90 + rows[:, 0]) * np.pi / 360)),
                  rows[:, 2]]  # (T, 3), millions of metres: subtract before rotating
    out = np.zeros((len(rows), 4, 4))
    out[:, :3, :3] = rot[0].T @ rot
    out[:, :3, 3] = (trans - trans[0]) @ rot[0]
    out[:, 3, 3] = 1.0
    return out


def poses_to_oxts(poses, lat0: float = 49.011, lon0: float = 8.423, alt0: float = 112.0,
                  heading0: float = 0.0) -> np.ndarray:
    """Oxts rows ``(T, 30)`` for IMU poses ``(T, 4, 4)`` (made relative to the first one).

    The first frame sits at (lat0, lon0, alt0) with yaw ``heading0`` (rad, 0 = east). Only
    lat, lon, alt, roll, pitch, yaw and the status columns (navstat 4, numsats 10, modes 5, as
    for a good RTK fix) are filled; velocities and accelerations are 0. ``oxts_to_poses``
    of the result gives back the relative poses.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(poses) == 0:
        return np.zeros((0, 30))
    scale = np.cos(np.deg2rad(lat0))
    start = np.eye(4)
    start[:3, :3] = _rot_rpy(0.0, 0.0, heading0)
    start[:3, 3] = [scale * lon0 * np.pi * EARTH_RADIUS / 180,
                    scale * EARTH_RADIUS * np.log(np.tan((90 + lat0) * np.pi / 360)), alt0]
    absolute = start @ np.linalg.inv(poses[0]) @ poses  # (T, 4, 4)
    rows = np.zeros((len(poses), 30))
    mx, my = absolute[:, 0, 3], absolute[:, 1, 3]
    rows[:, 1] = mx * 180 / (np.pi * EARTH_RADIUS * scale)
    rows[:, 0] = 360 / np.pi * np.arctan(np.exp(my / (scale * EARTH_RADIUS))) - 90
    rows[0, :2] = lat0, lon0  # exact, so that the reader's scale is cos(lat0)
    rows[:, 2] = absolute[:, 2, 3]
    r = absolute[:, :3, :3]
    rows[:, 3] = np.arctan2(r[:, 2, 1], r[:, 2, 2])
    rows[:, 4] = -np.arcsin(np.clip(r[:, 2, 0], -1, 1))
    rows[:, 5] = np.arctan2(r[:, 1, 0], r[:, 0, 0])
    rows[:, 25:30] = [4, 10, 5, 5, 5]
    return rows


def imu_to_velo_poses(imu_poses, calib: KittiCalib) -> np.ndarray:
    """IMU poses ``(T, 4, 4)`` -> velodyne poses: frame-t velodyne -> frame-0 velodyne."""
    tv = calib.imu_to_velo
    return tv @ np.asarray(imu_poses, dtype=np.float64) @ np.linalg.inv(tv)


# ----------------------------------------------------------------------------- sequences


#: KITTI cameras as :class:`~seqshape.data.sequence.DrivingLog` camera names
CAMERAS = ("image_02", "image_03")


def _cam_index(camera) -> int:
    """``"image_02"``, ``2`` or None (the left colour camera) -> KITTI camera number."""
    if camera is None:
        return 2
    if isinstance(camera, (int, np.integer)):
        cam = int(camera)
    elif isinstance(camera, str) and camera.startswith("image_") and camera[6:].isdigit():
        cam = int(camera[6:])
    else:
        cam = -1
    if cam not in (2, 3):
        raise ConfigError(f"KITTI tracking has cameras {', '.join(CAMERAS)}, not {camera!r}")
    return cam


class KittiTrackingSequence(DrivingLog):
    """One sequence of a KITTI tracking root folder (layout in the module docstring), the
    KITTI implementation of :class:`~seqshape.data.sequence.DrivingLog`.

    ``name`` (and ``sequence``) the zero-padded sequence (``"0003"``); ``frames`` the frame
    indices with a velodyne scan (or, without velodyne, with an image, or else with labels);
    ``labels`` the label rows (empty without a label file); ``calib`` the calibration (its
    ``image_size`` taken from the first image when there is one); ``oxts`` the ``(T, 30)`` rows
    or None; ``ego_poses`` the velodyne poses ``(T, 4, 4)`` (frame-t velodyne -> frame-0
    velodyne) from oxts, or None.

    Protocol: ``timestamp(f) = f / 10`` s; ``points(f)`` the velodyne scan ``(N, 4)``;
    ``boxes(f)`` the label rows of the frame as :class:`~seqshape.data.sequence.Box3D`
    (:func:`label_to_pose`; ``track_id`` ``"TTTT"``, ``category`` the KITTI type, ``cls`` from
    :data:`KITTI_CLASSES`, ``visibility`` the ``occluded`` level 0-3, ``extra`` truncated,
    alpha, bbox, kitti_track_id; DontCare rows and rows with a negative track id are left
    out); ``ego_pose(f)`` from oxts; cameras ``image_02`` (default) and ``image_03`` when a
    calibration file exists, ``camera(name)`` = :meth:`KittiCalib.camera`;
    ``image_file_name`` keeps KITTI's ``SSSS/FFFFFF.png`` (for both cameras: one KINS file is
    written per camera).
    """

    dataset = "kitti"
    sensor = "hdl64"

    def __init__(self, root, sequence: int | str):
        self.root = Path(root)
        self.sequence = seq_name(sequence)
        self.name = self.sequence
        if not self.root.is_dir():
            raise DataError(self.root, "no such KITTI root folder")
        lpath = label_path(self.root, self.sequence)
        self.labels: list[KittiLabel] = read_labels(lpath) if lpath.exists() else []
        self.labels_by_frame = labels_by_frame(self.labels)
        self.frames = self._find_frames()
        opath = oxts_path(self.root, self.sequence)
        self.oxts: np.ndarray | None = read_oxts(opath) if opath.exists() else None
        self._calib: KittiCalib | None = None
        self._ego: np.ndarray | None = None
        has_calib = calib_path(self.root, self.sequence).exists()  # not a file: refused
        self.camera_names = CAMERAS if has_calib else ()
        self.default_camera = CAMERAS[0] if has_calib else None

    def _find_frames(self) -> list[int]:
        for folder, ext in (("velodyne", ".bin"), ("image_02", ".png")):
            d = self.root / folder / self.sequence
            if d.is_dir():
                frames = sorted(int(p.stem) for p in d.glob(f"*{ext}") if _is_number(p.stem))
                if frames:
                    return frames
        return sorted(self.labels_by_frame)

    @property
    def calib(self) -> KittiCalib:
        if self._calib is None:
            calib = read_calib(calib_path(self.root, self.sequence))
            if self.frames and self.image_path(self.frames[0]).exists():
                calib.image_size = png_size(self.image_path(self.frames[0]))
            self._calib = calib
        return self._calib

    @property
    def ego_poses(self) -> np.ndarray | None:
        if self.oxts is None:
            return None
        if self._ego is None:
            self._ego = imu_to_velo_poses(oxts_to_poses(self.oxts), self.calib)
        return self._ego

    def restrict(self, max_frames: int | None) -> KittiTrackingSequence:
        """The sequence as if it ended after its first ``max_frames`` frames (labels too)."""
        super().restrict(max_frames)
        keep = set(self.frames)
        self.labels = [lab for lab in self.labels if lab.frame in keep]
        self.labels_by_frame = {f: v for f, v in self.labels_by_frame.items() if f in keep}
        return self

    # ------------------------------------------------------------------ DrivingLog

    def timestamp(self, frame: int) -> float:
        return int(frame) / FRAME_RATE_HZ

    def points(self, frame: int) -> np.ndarray:
        return self.velodyne(frame)

    def boxes(self, frame: int) -> list[Box3D]:
        out = []
        for lab in self.frame_labels(frame):
            if lab.is_dontcare or lab.track_id < 0:
                continue
            pose, size = label_to_pose(lab, self.calib)
            out.append(Box3D(
                track_id=f"{lab.track_id:04d}", category=lab.type, cls=KITTI_CLASSES.get(lab.type),
                centre=pose[:3], size=size, yaw=pose[3], visibility=float(lab.occluded),
                extra={"truncated": lab.truncated, "alpha": lab.alpha, "bbox": lab.bbox.tolist(),
                       "kitti_track_id": lab.track_id}))
        return out

    def ego_pose(self, frame: int) -> np.ndarray | None:
        ego = self.ego_poses
        if ego is None or not 0 <= int(frame) < len(ego):
            return None
        return ego[int(frame)]

    def camera(self, name=None, frame: int | None = None) -> PinholeCamera:
        if not self.camera_names:
            raise ConfigError(f"KITTI sequence {self.sequence}: no calibration file "
                              f"{calib_path(self.root, self.sequence)}, so no cameras")
        return self.calib.camera(_cam_index(name))

    def image_path(self, frame: int, camera="image_02") -> Path:
        """The image of ``frame`` (``camera``: ``"image_02"``/``"image_03"`` or 2/3), where KITTI
        keeps it (the file may not exist)."""
        return image_path(self.root, self.sequence, frame, _cam_index(camera))

    def image_file_name(self, frame: int, camera=None) -> str:
        _cam_index(camera)
        return f"{self.sequence}/{int(frame):06d}.png"

    @classmethod
    def log_names(cls, root) -> list[str]:
        return cls.sequences(root)

    # ------------------------------------------------------------------ KITTI helpers

    def velodyne_path(self, frame: int) -> Path:
        return velodyne_path(self.root, self.sequence, frame)

    def velodyne(self, frame: int) -> np.ndarray:
        """The scan of ``frame``, ``(N, 4)`` float32."""
        return read_velodyne(self.velodyne_path(frame))

    def frame_labels(self, frame: int) -> list[KittiLabel]:
        return self.labels_by_frame.get(frame, [])

    @staticmethod
    def sequences(root) -> list[str]:
        """Sequence names found under ``root`` (from label_02, velodyne or calib)."""
        root = Path(root)
        names = {p.stem for p in (root / "label_02").glob("*.txt")}
        names |= {p.name for p in (root / "velodyne").glob("*") if p.is_dir()}
        names |= {p.stem for p in (root / "calib").glob("*.txt")}
        return sorted(n for n in names if _is_number(n))


def kitti_classes(types) -> tuple[str, ...]:
    """KITTI types (``("Car", "Van")``) -> seqshape classes; a type without one is an error."""
    bad = [t for t in types if t not in KITTI_CLASSES]
    if bad:
        raise ConfigError(f"KITTI types {bad} are not vehicles seqshape extracts (choose from "
                          f"{', '.join(KITTI_CLASSES)})")
    return tuple(dict.fromkeys(KITTI_CLASSES[t] for t in types))


def extract_tracks(seq: KittiTrackingSequence, classes=("car", "van"),
                   crop: CropConfig | None = None, min_points: int = 0,
                   types=None) -> list[Track]:
    """Tracks of one sequence: :func:`seqshape.data.extract.extract_tracks` (generic schema,
    crop by :func:`seqshape.data.crop.crop_vehicle`) plus the KITTI meta keys callers use.

    ``classes``: seqshape classes (KITTI Car -> car, Van -> van, Truck -> truck); ``types``:
    the same by KITTI type (overrides ``classes``). Track ids are ``"SSSS_TTTT"``; ``meta``
    adds ``sequence``, ``kitti_track_id`` (int) and ``type`` (the KITTI type) to the generic
    keys (``frames``, ``ego_poses`` when oxts cover the track's frames, ...).
    """
    if types is not None:
        classes = kitti_classes(types)
    tracks = generic_tracks(seq, classes=classes, crop=crop, min_points=min_points)
    for tr in tracks:
        tr.meta.update(sequence=seq.sequence, kitti_track_id=int(tr.meta["object_id"]),
                       type=tr.meta["category"])
    return tracks
