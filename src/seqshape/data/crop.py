"""Cutting one vehicle out of a LiDAR sweep: the crop every real-data path uses.

:func:`crop_vehicle` is the single preprocessing step between a sweep and the estimator. Track
extraction (``seqshape tracks``), the labeller (``seqshape label``) and the training data path
call this one function, so what the network is trained on and what it sees at inference are
cut the same way:

1. the sweep points inside the box enlarged by ``margin`` metres on each side (length and
   width; the height too, by ``margin_z``);
2. minus the ground: a nearly horizontal plane fitted by RANSAC (as in
   :mod:`seqshape.data.ground`) to the low points around the box: outside its footprint, within
   ``context`` metres of it, from ``band_below`` m below to ``band_above`` m above the box
   bottom. So a slope, a camber or a box drawn a little too low or too high does not matter;
   points less than ``ground_threshold`` m above that plane are dropped. The vehicle's own
   lower body (sills, wheels, bumpers: many points in a broadside view) is excluded from the
   fit, and the band keeps out the bonnets and sills of the neighbours. ``ground_threshold`` =
   0.15 m keeps the road returns out and the lowest vehicle returns (tyres, bumpers) in. Both
   choices were measured on the Argoverse 2 development log (docs/results.md, "Figures behind
   defaults in the code"). With too few surrounding points (fewer than ``min_ground_points``)
   the sweep's own ground plane is used when the caller has one, else a cut at the box bottom
   plus ``box_ground``. ``ground="box"`` always cuts at the box bottom (the former rule);
   ``ground="none"`` keeps everything.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from seqshape.data.ground import _fit_plane, _ransac_plane
from seqshape.errors import ConfigError
from seqshape.geometry import points_in_box, sensor_to_canonical

GROUND_MODES = ("plane", "box", "none")


@dataclass(frozen=True)
class CropConfig:
    """How a vehicle is cut out of a sweep (module doc)."""

    margin: float = 0.2
    margin_z: float = 0.1
    ground: str = "plane"
    ground_threshold: float = 0.15
    box_ground: float = 0.15
    context: float = 2.0
    band_below: float = 0.5
    band_above: float = 0.25
    min_ground_points: int = 30
    iterations: int = 60
    max_tilt_deg: float = 10.0
    seed: int = 0

    def __post_init__(self):
        if self.ground not in GROUND_MODES:
            raise ConfigError(f"ground must be one of {GROUND_MODES}, got {self.ground!r}")
        if self.margin < 0 or self.margin_z < 0 or self.context < 0:
            raise ConfigError("crop margins must be >= 0")

    def to_dict(self) -> dict:
        return asdict(self)


def _surroundings(points: np.ndarray, pose, size, reach_extra: float):
    """The points within the box's bounding circle grown by ``reach_extra`` (x, y), as float64
    in the sensor frame and in the box's own frame: ``(near (K, 3), local (K, 3))``."""
    reach = float(np.hypot(size[0] / 2, size[1] / 2)) + reach_extra
    idx = np.flatnonzero((np.abs(points[:, 0] - pose[0]) <= reach)
                         & (np.abs(points[:, 1] - pose[1]) <= reach))
    near = points[idx].astype(np.float64)
    return near, sensor_to_canonical(near, pose)


def _ground_from(near: np.ndarray, local: np.ndarray, size: np.ndarray, cfg: CropConfig):
    """The local ground plane from the box's surroundings (``_surroundings`` with a reach of at
    least ``cfg.context``), or None."""
    if len(near) < cfg.min_ground_points:
        return None
    bottom = -size[2] / 2
    ax, ay = np.abs(local[:, 0]), np.abs(local[:, 1])
    keep = ((ax <= size[0] / 2 + cfg.context) & (ay <= size[1] / 2 + cfg.context)
            & ((ax > size[0] / 2) | (ay > size[1] / 2))
            & (local[:, 2] >= bottom - cfg.band_below) & (local[:, 2] <= bottom + cfg.band_above))
    cand = near[keep]
    if len(cand) < cfg.min_ground_points:
        return None
    rng = np.random.default_rng(cfg.seed)
    best, count = _ransac_plane(cand, rng, cfg.iterations, 0.08, cfg.max_tilt_deg)
    if best is None or count < cfg.min_ground_points:
        return None
    n, d = best
    inl = cand[np.abs(cand @ n + d) < 0.08]
    n2, d2 = _fit_plane(inl)
    if n2[2] >= np.cos(np.radians(cfg.max_tilt_deg)):
        n, d = n2, d2
    return n, float(d)


def local_ground(points, pose, size, cfg: CropConfig = CropConfig()):
    """The ground plane ``(n, d)`` around a box (module doc, step 2), or None (too few points)."""
    pose = np.asarray(pose, dtype=np.float64)
    size = np.asarray(size, dtype=np.float64)
    near, local = _surroundings(np.asarray(points)[:, :3], pose, size, cfg.context)
    return _ground_from(near, local, size, cfg)


def crop_vehicle(points, pose, size, cfg: CropConfig = CropConfig(),
                 sweep_plane=None) -> np.ndarray:
    """The points of one vehicle: ``points (N, 3+)`` of a sweep, the vehicle's box ``pose``
    (x, y, z, yaw) and ``size`` (l, w, h) in the sweep's sensor frame -> ``(M, 3)`` float32.

    ``sweep_plane``: the sweep's ground plane ``(n, d)`` (or a function returning it, called
    only when needed), used where the local fit fails. The sweep is scanned and transformed
    into the box frame once, for the crop and the ground fit together.
    """
    pose = np.asarray(pose, dtype=np.float64)
    size = np.asarray(size, dtype=np.float64)
    reach = max(cfg.margin, cfg.context) if cfg.ground == "plane" else cfg.margin
    near, local = _surroundings(np.asarray(points)[:, :3], pose, size, reach)
    half = size / 2 + [cfg.margin, cfg.margin, cfg.margin_z]
    inbox = np.all(np.abs(local) <= half, axis=1)
    cand = near[inbox]
    if cfg.ground == "none" or len(cand) == 0:
        return np.ascontiguousarray(cand, dtype=np.float32)
    plane = _ground_from(near, local, size, cfg) if cfg.ground == "plane" else None
    if plane is None and cfg.ground == "plane":
        plane = sweep_plane() if callable(sweep_plane) else sweep_plane
    if plane is not None:
        n, d = plane
        above = cand @ np.asarray(n, dtype=np.float64) + d >= cfg.ground_threshold
    else:
        above = local[inbox, 2] >= -size[2] / 2 + cfg.box_ground
    return np.ascontiguousarray(cand[above], dtype=np.float32)


def crop_box(points, pose, size, margin: float = 0.2, ground: float | None = 0.15) -> np.ndarray:
    """Points ``(N, 3+)`` inside a posed box enlarged by ``margin`` (m), as ``(M, 3)`` float32.

    With ``ground`` set, points lower than the box bottom + ``ground`` (in the box's own
    frame) are dropped: the road under the wheels. The former KITTI crop, kept for callers
    that want a plain box cut; track extraction and the labeller use :func:`crop_vehicle`
    (ground by a locally fitted plane).
    """
    pts = np.asarray(points)[:, :3]
    pose = np.asarray(pose, dtype=np.float64)
    reach = float(np.hypot(size[0] / 2 + margin, size[1] / 2 + margin))  # cheap x, y pre-filter
    idx = np.flatnonzero((np.abs(pts[:, 0] - pose[0]) <= reach)
                         & (np.abs(pts[:, 1] - pose[1]) <= reach))
    cand = pts[idx]
    keep = points_in_box(cand, size, pose, margin)
    if ground is not None and keep.any():
        local_z = sensor_to_canonical(cand.astype(np.float64), pose)[:, 2]
        keep &= local_z >= -float(size[2]) / 2 + ground
    return np.ascontiguousarray(cand[keep], dtype=np.float32)
