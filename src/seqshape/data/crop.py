"""Cutting one vehicle out of a LiDAR sweep: the crop every real-data path uses.

:func:`crop_vehicle` is the single preprocessing step between a sweep and the estimator. Track
extraction (``seqshape tracks``), the labeller (``seqshape label``) and the training data path
call this one function, so what the network is trained on and what it sees at inference are
cut the same way (:func:`crop_vehicles`: every box of one sweep at once, crop for crop the
same, the sweep bucketed once by :class:`SweepIndex`):

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


def _reach(size, reach_extra: float) -> float:
    """Half the side of the square (x, y) around a box that :func:`_surroundings` scans."""
    return float(np.hypot(size[0] / 2, size[1] / 2)) + reach_extra


def _surroundings(points: np.ndarray, pose, size, reach_extra: float):
    """The points within the box's bounding circle grown by ``reach_extra`` (x, y), as float64
    in the sensor frame and in the box's own frame: ``(near (K, 3), local (K, 3))``."""
    reach = _reach(size, reach_extra)
    idx = np.flatnonzero((np.abs(points[:, 0] - pose[0]) <= reach)
                         & (np.abs(points[:, 1] - pose[1]) <= reach))
    near = points[idx].astype(np.float64)
    return near, sensor_to_canonical(near, pose)


class SweepIndex:
    """The points of a sweep bucketed on a coarse (x, y) grid, so that cropping many boxes
    scans the sweep once (:func:`crop_vehicles`) instead of once per box.

    :meth:`rows` gives, for squares around boxes, the sorted indices of the points in the grid
    cells those squares touch: a superset of the points in the squares (each square is widened
    by ``slack`` metres against rounding), on which the exact test then runs. Points with a
    non-finite x or y are in no cell (the exact test never keeps them either). The cells are
    ``cell`` metres wide, wider when the sweep spans more than ``max_cells`` cells a side.
    """

    def __init__(self, points: np.ndarray, cell: float = 4.0, slack: float = 0.01,
                 max_cells: int = 2048):
        pts = np.asarray(points)
        self.dtype = pts.dtype if pts.dtype.kind == "f" else np.dtype(np.float64)
        x, y = pts[:, 0].astype(self.dtype, copy=False), pts[:, 1].astype(self.dtype, copy=False)
        finite = None
        bounds = np.array([x.min(), y.min(), x.max(), y.max()]) if len(x) else np.zeros(4)
        if not np.isfinite(bounds).all():  # rare: bound and bucket the finite points only
            finite = np.isfinite(x) & np.isfinite(y)
            x, y = np.where(finite, x, 0), np.where(finite, y, 0)
            bounds = (np.array([x[finite].min(), y[finite].min(), x[finite].max(),
                                y[finite].max()]) if finite.any() else np.zeros(4))
        self.lo = bounds[:2].astype(self.dtype)
        span = float(max(bounds[2] - bounds[0], bounds[3] - bounds[1]))
        self.cell = self.dtype.type(max(float(cell), span / max_cells))
        self.slack = float(slack)
        self.shape = self._cells(bounds[2:].astype(self.dtype)[None])[0] + 1
        n = int(self.shape[0] * self.shape[1])
        # x - lo >= 0 for every point, so truncation is the floor of _cells
        keys = ((x - self.lo[0]) / self.cell).astype(np.int64)
        keys *= self.shape[1]
        keys += ((y - self.lo[1]) / self.cell).astype(np.int64)
        self.keys = keys if finite is None else np.where(finite, keys, n)  # n: in no cell

    def _cells(self, xy: np.ndarray) -> np.ndarray:
        """Grid cells ``(K, 2)`` of points ``(K, 2)`` (the operations of the points' keys, in
        the same dtype, so monotone: a point of a square lies between its corners' cells)."""
        return np.floor((xy.astype(self.dtype, copy=False) - self.lo) / self.cell).astype(
            np.int64)

    def cells(self, centres, reaches) -> np.ndarray:
        """``(cells + 1,)`` bool: the grid cells touched by the squares
        ``|x - cx| <= reach, |y - cy| <= reach`` (``centres (B, 2)``, ``reaches (B,)``), indexed
        by :attr:`keys` (the last entry, the points in no cell, is False)."""
        n0, n1 = int(self.shape[0]), int(self.shape[1])
        wanted = np.zeros(n0 * n1 + 1, dtype=bool)  # the last entry: points in no cell
        c = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
        half = (np.asarray(reaches, dtype=np.float64).reshape(-1) + self.slack)[:, None]
        lo = np.maximum(self._cells(c - half), 0)
        hi = np.minimum(self._cells(c + half), [n0 - 1, n1 - 1])
        grid = wanted[:-1].reshape(n0, n1)
        for (i0, j0), (i1, j1) in zip(lo, hi, strict=True):
            if i0 <= i1 and j0 <= j1:
                grid[i0:i1 + 1, j0:j1 + 1] = True
        return wanted

    def rows(self, centres, reaches) -> np.ndarray:
        """Sorted indices of the points in the cells touched by the squares
        ``|x - cx| <= reach, |y - cy| <= reach`` (``centres (B, 2)``, ``reaches (B,)``)."""
        return np.flatnonzero(self.cells(centres, reaches)[self.keys])


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
    into the box frame once, for the crop and the ground fit together. Many boxes of one
    sweep: :func:`crop_vehicles` (the same crops, the sweep scanned once for all).
    """
    return _crop_one(np.asarray(points)[:, :3], pose, size, cfg, sweep_plane)


def crop_vehicles(points, poses, sizes, cfg: CropConfig = CropConfig(),
                  sweep_plane=None) -> list[np.ndarray]:
    """:func:`crop_vehicle` of every box ``poses[i], sizes[i]`` of one sweep, equal to it crop
    by crop, point by point: the sweep is bucketed once (:class:`SweepIndex`) and each box
    tests only the points of the grid cells around it."""
    pts = np.asarray(points)[:, :3]
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    if len(poses) == 0:
        return []
    extra = _reach_extra(cfg)
    reaches = np.array([_reach(s, extra) for s in sizes])
    # the points that can be near any box, in sweep order, then those of each box's own cells:
    # each box finds the same points in the same order among them as in the whole sweep
    index = SweepIndex(pts)
    rows = index.rows(poses[:, :2], reaches)
    near, keys = pts[rows], index.keys[rows]
    out = []
    for p, s, r in zip(poses, sizes, reaches, strict=True):
        own = near[np.flatnonzero(index.cells(p[None, :2], [r])[keys])] if len(poses) > 1 else near
        out.append(_crop_one(own, p, s, cfg, sweep_plane))
    return out


def _reach_extra(cfg: CropConfig) -> float:
    """How far beyond the box's bounding circle the crop looks (the ground fit's context)."""
    return max(cfg.margin, cfg.context) if cfg.ground == "plane" else cfg.margin


def _crop_one(pts: np.ndarray, pose, size, cfg: CropConfig, sweep_plane) -> np.ndarray:
    """:func:`crop_vehicle` on the sweep points ``pts (N, 3)`` (or those of them that can be
    near the box, in sweep order)."""
    pose = np.asarray(pose, dtype=np.float64)
    size = np.asarray(size, dtype=np.float64)
    near, local = _surroundings(pts, pose, size, _reach_extra(cfg))
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
