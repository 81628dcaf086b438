"""The sequence layer: one small protocol for a driving log, whatever dataset it comes from.

A :class:`DrivingLog` is a sequence of LiDAR frames with their timestamps, the annotated 3D
boxes of each frame, the ego motion and the cameras. Every reader in :mod:`seqshape.data`
(KITTI tracking, Argoverse 2, nuScenes) implements it, and everything above (track extraction,
evaluation, the amodal labeller) takes a ``DrivingLog``, never a dataset's own class. A new
dataset is one file in ``seqshape.data`` with a subclass and an entry in :data:`DATASETS`.

Frames and units (docs/architecture.md):

* **Sensor frame** of a frame: the ego vehicle's axes (x forward, y left, z up) with the origin
  at the (top) LiDAR. KITTI's velodyne frame is one; Argoverse 2 (ego frame, origin on the
  ground under the rear axle) is shifted by the ``up_lidar`` position; nuScenes LIDAR_TOP
  points are rotated into the ego axes and keep the LiDAR's position as origin.
* **Boxes** (:class:`Box3D`) are in that frame: ``centre`` of the box, ``size`` (length, width,
  height), ``yaw`` about +z (0 = facing +x); ``pose = (x, y, z, yaw)`` as in
  :mod:`seqshape.geometry`.
* **Ego pose** of a frame: (4, 4) mapping its sensor-frame points into the log's reference
  frame, the sensor frame of the log's first frame (small numbers, whatever the dataset's
  world frame is).
* **Frames** are integers: KITTI frame numbers, or positions in the log's sorted sweeps
  (Argoverse 2) or keyframes (nuScenes). ``timestamp(frame)`` is in seconds.

Vehicle classes: each dataset category maps to one of :data:`VEHICLE_CLASSES` or to None
(not a vehicle). ``Box3D.category`` keeps the dataset's own name. The class names and their KINS
ids (``VEHICLE_CLASSES``, ``CLASS_TO_KINS``, re-exported here) are defined once, in
:mod:`seqshape.data.categories`.
"""

from __future__ import annotations

import abc
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import seqshape.limits as limits
from seqshape._io import check_regular
from seqshape.camera import PinholeCamera
from seqshape.data.categories import CLASS_TO_KINS as CLASS_TO_KINS  # re-exported
from seqshape.data.categories import VEHICLE_CLASSES
from seqshape.errors import ConfigError, DataError


def parse_classes(text: str | Iterable[str] | None) -> tuple[str, ...]:
    """``"car,van"`` (or a list) -> ``("car", "van")``; None -> every vehicle class."""
    if text is None:
        return VEHICLE_CLASSES
    items = [c.strip().lower() for c in (text.split(",") if isinstance(text, str) else text)]
    items = [c for c in items if c]
    bad = [c for c in items if c not in VEHICLE_CLASSES]
    if bad or not items:
        raise ConfigError(f"unknown vehicle class(es) {bad or items}: choose from "
                          f"{', '.join(VEHICLE_CLASSES)}")
    return tuple(dict.fromkeys(items))


# ---------------------------------------------------------------------------------------------
# what every reader refuses (docs/datasets.md, "What the readers refuse")

# the limits themselves live in seqshape.limits (one module for every reader); named here too
MAX_BOX_SIZE = limits.MAX_BOX_SIZE
MAX_RANGE = limits.MAX_RANGE
MAX_WORLD = limits.MAX_WORLD
QUATERNION_TOLERANCE = limits.QUATERNION_TOLERANCE


def box_problems(centres, sizes, yaws=None) -> tuple[np.ndarray, list[str]]:
    """Which boxes are garbage, and why: ``(bad (N,) bool, reasons)`` with one reason per bad
    box (in order).

    A box is refused for a non-finite centre, size or yaw, a dimension <= 0 or above
    :data:`MAX_BOX_SIZE`, or a centre farther than :data:`MAX_RANGE` from the sensor.

    >>> bad, why = box_problems([[1.0, 2, 0], [2e3, 0, 0]], [[4.0, 2, 1.5], [4, 0, 1.5]])
    >>> bad.tolist(), why
    ([False, True], ['size (4, 0, 1.5) m: each dimension must be in (0, 30]'])
    """
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    s = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    y = np.zeros(len(c)) if yaws is None else np.asarray(yaws, dtype=np.float64).reshape(-1)
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(c).all(1) & np.isfinite(s).all(1) & np.isfinite(y)
        size_ok = ((s > 0) & (s <= MAX_BOX_SIZE)).all(1)
        near = np.sqrt((c * c).sum(1)) <= MAX_RANGE
    bad = ~(finite & size_ok & near)
    reasons = []
    for i in np.flatnonzero(bad):
        if not finite[i]:
            reasons.append(f"non-finite box (centre {_g(c[i])}, size {_g(s[i])}, yaw {y[i]:g})")
        elif not size_ok[i]:
            reasons.append(f"size {_g(s[i])} m: each dimension must be in (0, {MAX_BOX_SIZE:g}]")
        else:
            reasons.append(f"box centre {_g(c[i])} is more than {MAX_RANGE:g} m from the sensor")
    return bad, reasons


def _g(v) -> str:
    return "(" + ", ".join(f"{float(x):g}" for x in np.ravel(v)) + ")"


def unit_quaternions(q, path, what: str = "quaternion") -> np.ndarray:
    """Quaternions ``(N, 4)`` (or one ``(4,)``) normalised, or a :class:`DataError` naming
    ``path`` (and the first bad row) when one is non-finite or its norm is more than
    :data:`QUATERNION_TOLERANCE` from 1.

    >>> unit_quaternions([1.0005, 0, 0, 0], "a.json").tolist()
    [1.0, 0.0, 0.0, 0.0]
    """
    q = np.asarray(q, dtype=np.float64)
    norm = np.sqrt(np.einsum("...i,...i->...", q, q))[..., None]  # no overflow warning
    ok = np.abs(norm - 1) <= QUATERNION_TOLERANCE  # False for NaN
    if not ok.all():
        bad = np.flatnonzero(~ok.reshape(-1))
        i = int(bad[0])
        where = f" (row {i}; {len(bad)} row(s) in all)" if q.ndim > 1 else ""
        raise DataError(path, f"{what} {_g(q.reshape(-1, 4)[i])} has norm "
                              f"{float(norm.reshape(-1)[i]):.6g}, not 1 (tolerance "
                              f"{QUATERNION_TOLERANCE:g}){where}")
    return q / norm


def read_float32(path, columns: int, what: str, names: str) -> np.ndarray:
    """The little-endian float32 values of a headerless point file (KITTI ``.bin``, nuScenes
    ``.pcd.bin``) as a flat array; a missing, unreadable or non-regular file (a FIFO, a
    folder), one larger than ``limits.MAX_FILE_BYTES["points"]``, or a byte length that is
    not a whole number of ``columns``-float points (naming the layout the file likely has,
    :func:`seqshape.limits.likely_layout`) is a :class:`DataError` naming it."""
    path = Path(path)
    size = check_regular(path, what, "points")
    try:
        raw = np.fromfile(path, dtype=np.uint8)
    except (OSError, ValueError) as exc:
        raise DataError(path, f"unreadable {what} ({exc})") from None
    if len(raw) % (4 * columns) or len(raw) != size:
        layout = limits.likely_layout(raw, columns)
        hint = f"; it reads as {layout} points: likely written in that layout" if layout else ""
        raise DataError(path, f"size {len(raw)} bytes is not a multiple of {4 * columns} "
                              f"({columns} float32 per point: {names}): truncated or not a "
                              f"{what}{hint}")
    return raw.view("<f4")


def read_sweep(path, columns: int, what: str, names: str, strength: int | None = 3
               ) -> np.ndarray:
    """A headerless float32 point file as ``(N, columns)`` float32, checked by
    :func:`seqshape.limits.check_sweep` (non-finite and impossible points dropped with a
    warning; a file of another layout refused, naming the layout its length fits)."""
    raw = read_float32(path, columns, what, names)
    points = raw.reshape(-1, columns)
    return limits.check_sweep(points, path, what, names, strength, file_bytes=raw.nbytes)


def drop_nonfinite_points(points: np.ndarray, path) -> np.ndarray:
    """``points`` (N, C) without its rows holding a NaN or an infinity; when there are any,
    one ``warnings.warn`` naming ``path`` and how many were dropped.

    The common all-finite case costs one pass and no copy.
    """
    finite = np.isfinite(points)
    if finite.all():
        return points
    keep = finite.all(axis=1)
    dropped = int(len(points) - keep.sum())
    warnings.warn(f"{path}: dropped {dropped} of {len(points)} points with a non-finite value",
                  stacklevel=3)
    return points[keep]


@dataclass
class Box3D:
    """One annotated 3D box of one frame, in that frame's sensor frame.

    ``track_id``: the dataset's id of the object (stable over the log); ``category``: the
    dataset's own category name; ``cls``: seqshape's vehicle class (None: not a vehicle);
    ``num_points``: the dataset's count of LiDAR points inside the box, where it has one;
    ``visibility``: the dataset's visibility or occlusion value, where it has one;
    ``extra``: anything else the reader keeps (documented by the reader).
    """

    track_id: str
    category: str
    cls: str | None
    centre: np.ndarray
    size: np.ndarray
    yaw: float
    num_points: int | None = None
    visibility: float | None = None
    extra: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        self.centre = np.asarray(self.centre, dtype=np.float64).reshape(3)
        self.size = np.asarray(self.size, dtype=np.float64).reshape(3)
        self.yaw = float(self.yaw)

    @property
    def pose(self) -> np.ndarray:
        """(4,) ``(x, y, z, yaw)`` of the box centre, sensor frame."""
        return np.r_[self.centre, self.yaw]


class DrivingLog(abc.ABC):
    """One driving log (a KITTI sequence, an Argoverse 2 log, a nuScenes scene).

    Subclasses set ``dataset`` (short name, e.g. ``"av2"``), ``name`` (the log id), ``root``
    (the dataset folder it was read from), ``sensor`` (LiDAR model) and ``frames`` (sorted
    frame numbers), and implement the abstract methods. ``camera_names`` lists the cameras
    (empty without any); ``default_camera`` is the one labels are written for by default.
    """

    dataset: str = ""
    name: str = ""
    root: Path = Path(".")
    sensor: str = ""
    frames: list[int]
    camera_names: tuple[str, ...] = ()
    default_camera: str | None = None
    #: Where :meth:`ego_pose` comes from: the log's own poses (``"given"``), or LiDAR odometry
    #: of its sweeps (``"lidar"``, :func:`seqshape.data.odometry.with_lidar_odometry`).
    ego_pose_source: str = "given"

    def __len__(self) -> int:
        return len(self.frames)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.dataset}:{self.name}, {len(self.frames)} frames, "
                f"cameras {list(self.camera_names)})")

    @abc.abstractmethod
    def timestamp(self, frame: int) -> float:
        """Time of the frame's LiDAR sweep, seconds (any fixed origin)."""

    @abc.abstractmethod
    def points(self, frame: int) -> np.ndarray:
        """The frame's LiDAR sweep, ``(N, C)`` float32 with ``C >= 3``; x, y, z in the sensor
        frame (extra columns: the reader's, e.g. intensity)."""

    @abc.abstractmethod
    def boxes(self, frame: int) -> list[Box3D]:
        """The annotated boxes of the frame (empty when it has none)."""

    def ego_pose(self, frame: int) -> np.ndarray | None:
        """(4, 4) sensor frame of ``frame`` -> the log's reference frame, or None (unknown)."""
        return None

    def camera(self, name: str | None = None, frame: int | None = None) -> PinholeCamera:
        """Camera ``name`` (default: ``default_camera``) as seen from the sensor frame of
        ``frame`` (its extrinsics may follow the ego motion between the sweep and the image)."""
        raise ConfigError(f"{self.dataset} log {self.name} has no cameras")

    def image_path(self, frame: int, camera: str | None = None) -> Path | None:
        """The image of ``camera`` nearest to the frame's sweep, or None when there is none."""
        return None

    def image_file_name(self, frame: int, camera: str | None = None) -> str:
        """The ``file_name`` of the frame's image in KINS/COCO files: the image's path relative
        to ``root`` when it exists, else a made-up ``LOG/CAMERA/FFFFFF`` name."""
        path = self.image_path(frame, camera)
        if path is not None:
            try:
                return Path(path).relative_to(self.root).as_posix()
            except ValueError:
                return Path(path).as_posix()
        return f"{self.name}/{camera or self.default_camera}/{frame:06d}"

    # convenience, shared by every dataset

    def timestamps(self, frames: Sequence[int] | None = None) -> np.ndarray:
        """Timestamps (s) of ``frames`` (default: all)."""
        return np.array([self.timestamp(f) for f in (self.frames if frames is None else frames)],
                        dtype=np.float64)

    def restrict(self, max_frames: int | None) -> DrivingLog:
        """The log as if it ended after its first ``max_frames`` frames (in place; returns it)."""
        if max_frames is not None:
            if max_frames < 1:
                raise ConfigError(f"max_frames must be >= 1, got {max_frames}")
            self.frames = list(self.frames[:max_frames])
        return self

    def vehicle_boxes(self, frame: int, classes: Iterable[str] | None = None) -> list[Box3D]:
        """The frame's boxes whose class is one of ``classes`` (default: every vehicle class)."""
        wanted = set(VEHICLE_CLASSES if classes is None else classes)
        return [b for b in self.boxes(frame) if b.cls in wanted]

    @classmethod
    def log_names(cls, root) -> list[str]:
        """The names of the logs found under ``root`` (for ``--sequence`` defaults)."""
        raise NotImplementedError


#: dataset name -> "module:class" of its reader (a :class:`DrivingLog` subclass whose
#: constructor takes ``(root, name)`` and whose ``log_names(root)`` lists the logs).
DATASETS = {
    "kitti": "seqshape.data.kitti:KittiTrackingSequence",
    "av2": "seqshape.data.av2:Av2Log",
    "nuscenes": "seqshape.data.nuscenes:NuScenesLog",
}


def log_class(dataset: str) -> type[DrivingLog]:
    """The reader class of ``dataset`` (a key of :data:`DATASETS`)."""
    import importlib

    if dataset not in DATASETS:
        raise ConfigError(f"unknown dataset {dataset!r}: choose from {', '.join(DATASETS)}")
    module, cls = DATASETS[dataset].split(":")
    return getattr(importlib.import_module(module), cls)


def log_names(dataset: str, root) -> list[str]:
    """The logs of ``dataset`` under ``root``."""
    return log_class(dataset).log_names(root)


def open_log(dataset: str, root, name: str) -> DrivingLog:
    """Open log ``name`` of ``dataset`` under ``root``."""
    return log_class(dataset)(root, name)
