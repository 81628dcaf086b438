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

from seqshape.data.ground import _fit_plane, _minus, _ransac_plane
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
    idx = np.flatnonzero(_in_square(points[:, 0], points[:, 1], pose, reach))
    near = np.take(points, idx, axis=0).astype(np.float64)
    return near, _to_box(near, pose)


def _in_square(x: np.ndarray, y: np.ndarray, pose: np.ndarray, reach: float) -> np.ndarray:
    """Which points ``(x, y)`` lie in the square ``|x - cx| <= reach, |y - cy| <= reach``
    around the box centre (the differences taken in float64, the centre's dtype)."""
    return (np.abs(x - pose[0]) <= reach) & (np.abs(y - pose[1]) <= reach)


def _to_box(near: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """``sensor_to_canonical(near, pose)`` of float64 points ``near (K, 3)``: the same product
    ``(near - pose[:3]) @ R`` of the same operands (so the same bits), without its two copies
    of ``near``, the differences taken column by column (:func:`~seqshape.data.ground._minus`)."""
    return _minus(near, pose[:3]) @ _yaw_matrix(pose[3])


def _yaw_matrix(yaw) -> np.ndarray:
    """``yaw_to_rotmat(yaw)`` of one yaw, the same matrix (the same ``np.cos`` and ``np.sin``
    of the same 0-d array, exact zeros and ones), without its four ``np.stack`` calls."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class SweepIndex:
    """The points of a sweep bucketed on a coarse (x, y) grid, so that cropping many boxes
    scans the sweep once (:func:`crop_vehicles`) instead of once per box.

    :meth:`rows` gives, for squares around boxes, the sorted indices of the points in the grid
    cells those squares touch: a superset of the points in the squares (each square is widened
    by ``slack`` metres against rounding), on which the exact test then runs. Points with a
    non-finite x or y are in no cell (the exact test never keeps them either). The cells are
    ``cell`` metres wide, wider when the sweep spans more than ``max_cells`` cells a side.
    :meth:`near` sorts such a superset by cell once, so that each box then finds its own
    cells' points without a pass over the whole superset (:class:`_NearBoxes`).

    :attr:`x` and :attr:`y` are contiguous copies of the x and y columns in :attr:`dtype` (the
    points' own float dtype, float64 for integers): the same values the exact test converts
    to float64, read with one strided pass each instead of one per operation.
    """

    def __init__(self, points: np.ndarray, cell: float = 4.0, slack: float = 0.01,
                 max_cells: int = 2048):
        pts = np.asarray(points)
        self.dtype = pts.dtype if pts.dtype.kind == "f" else np.dtype(np.float64)
        self.x = x = np.ascontiguousarray(pts[:, 0], dtype=self.dtype)
        self.y = y = np.ascontiguousarray(pts[:, 1], dtype=self.dtype)
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

    def _ranges(self, centres, reaches) -> tuple[np.ndarray, np.ndarray]:
        """The first and last grid cells ``(B, 2)``, ``(B, 2)`` (clipped to the grid) touched by
        the squares ``|x - cx| <= reach, |y - cy| <= reach`` widened by :attr:`slack`."""
        c = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
        half = (np.asarray(reaches, dtype=np.float64).reshape(-1) + self.slack)[:, None]
        lo = np.maximum(self._cells(c - half), 0)
        hi = np.minimum(self._cells(c + half), [int(self.shape[0]) - 1, int(self.shape[1]) - 1])
        return lo, hi

    def cells(self, centres, reaches) -> np.ndarray:
        """``(cells + 1,)`` bool: the grid cells touched by the squares
        ``|x - cx| <= reach, |y - cy| <= reach`` (``centres (B, 2)``, ``reaches (B,)``), indexed
        by :attr:`keys` (the last entry, the points in no cell, is False)."""
        n0, n1 = int(self.shape[0]), int(self.shape[1])
        wanted = np.zeros(n0 * n1 + 1, dtype=bool)  # the last entry: points in no cell
        grid = wanted[:-1].reshape(n0, n1)
        for (i0, j0), (i1, j1) in zip(*self._ranges(centres, reaches), strict=True):
            if i0 <= i1 and j0 <= j1:
                grid[i0:i1 + 1, j0:j1 + 1] = True
        return wanted

    def rows(self, centres, reaches) -> np.ndarray:
        """Sorted indices of the points in the cells touched by the squares
        ``|x - cx| <= reach, |y - cy| <= reach`` (``centres (B, 2)``, ``reaches (B,)``)."""
        return np.flatnonzero(self.cells(centres, reaches)[self.keys])

    def near(self, centres, reaches) -> _NearBoxes:
        """The points of :meth:`rows` for these squares, arranged so that each square finds
        its own cells' points without a pass over them all (:class:`_NearBoxes`)."""
        return _NearBoxes(self, centres, reaches)


class _NearBoxes:
    """The points of a sweep in the grid cells touched by the squares around some boxes
    (:attr:`rows`: :meth:`SweepIndex.rows`, sorted sweep indices), sorted by cell once, with
    their x and y in contiguous arrays, so that each box finds the points of its own square
    (:meth:`square`) without a pass over them all.

    The cell order is a stable sort of the points' cells, so each cell's points keep the sweep
    order. A box's cells of one grid row are consecutive keys, so one slice of the cell order
    each: the points of the same cells as :meth:`SweepIndex.rows` of that box alone, a
    superset of its square. The exact test of :func:`_surroundings` runs on them, then the
    sort of the points kept (runs already sorted, merged by a stable sort) restores the sweep
    order: the same points in the same order as the test on the whole sweep.
    """

    def __init__(self, index: SweepIndex, centres, reaches):
        self.index, self.rows = index, index.rows(centres, reaches)
        self.x, self.y = index.x[self.rows], index.y[self.rows]
        keys = index.keys[self.rows]
        self.order = np.argsort(keys, kind="stable")
        n = int(index.shape[0] * index.shape[1])
        # starts[k]: where cell k begins in the cell order (rows hold no point in no cell)
        self.starts = [0] + np.cumsum(np.bincount(keys, minlength=n + 1)).tolist()
        lo, hi = index._ranges(centres, reaches)
        self._cells = np.c_[lo, hi].tolist()  # per box: i0, j0, i1, j1

    def square(self, b: int, pose: np.ndarray, reach: float) -> np.ndarray:
        """Sorted positions (into :attr:`rows`) of the points in the square of box ``b``
        (``centres[b]``, ``reaches[b]`` of the constructor; its ``pose`` and ``reach``)."""
        i0, j0, i1, j1 = self._cells[b]
        if i0 > i1 or j0 > j1:  # the square misses the grid
            return np.zeros(0, dtype=np.intp)
        n1, st = int(self.index.shape[1]), self.starts
        own = np.concatenate([self.order[st[k + j0]:st[k + j1 + 1]]
                              for k in range(i0 * n1, i1 * n1 + 1, n1)])
        own = own[_in_square(self.x[own], self.y[own], pose, reach)]
        return np.sort(own, kind="stable")


def _ground_from(near: np.ndarray, local: np.ndarray, size: np.ndarray, cfg: CropConfig,
                 absolute: np.ndarray | None = None, fresh_rng=None):
    """The local ground plane from the box's surroundings (``_surroundings`` with a reach of at
    least ``cfg.context``), or None. ``absolute``: ``np.abs(local)`` when the caller has it;
    ``fresh_rng``: a :class:`_FreshRng` of ``cfg.seed`` when the caller has one."""
    if len(near) < cfg.min_ground_points:
        return None
    bottom = -size[2] / 2
    a = np.abs(local) if absolute is None else absolute
    ax, ay, z = a[:, 0], a[:, 1], local[:, 2]
    keep = ((ax <= size[0] / 2 + cfg.context) & (ay <= size[1] / 2 + cfg.context)
            & ((ax > size[0] / 2) | (ay > size[1] / 2))
            & (z >= bottom - cfg.band_below) & (z <= bottom + cfg.band_above))
    cand = np.compress(keep, near, axis=0)
    if len(cand) < cfg.min_ground_points:
        return None
    rng = np.random.default_rng(cfg.seed) if fresh_rng is None else fresh_rng()
    best, count = _ransac_plane(cand, rng, cfg.iterations, 0.08, cfg.max_tilt_deg)
    if best is None or count < cfg.min_ground_points:
        return None
    n, d = best
    inl = np.compress(np.abs(cand @ n + d) < 0.08, cand, axis=0)
    n2, d2 = _fit_plane(inl)
    if n2[2] >= np.cos(np.radians(cfg.max_tilt_deg)):
        n, d = n2, d2
    return n, float(d)


class _FreshRng:
    """``np.random.default_rng(seed)`` for box after box, six times cheaper: one generator,
    set back to its first state at each call. The state (of its bit generator) is all a
    ``Generator`` remembers, so the draws are those of a new ``default_rng(seed)``."""

    def __init__(self, seed):
        self.rng = np.random.default_rng(seed)
        self.state = self.rng.bit_generator.state

    def __call__(self) -> np.random.Generator:
        self.rng.bit_generator.state = self.state
        return self.rng


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
    by crop, point by point: the sweep is bucketed once (:class:`SweepIndex`), the points of
    the cells near any box sorted by cell once (:class:`_NearBoxes`), and each box tests only
    the points of the grid cells around it.

    Why the crops are the same: each box's points of its cells are a superset of its
    surroundings, in sweep order; the exact test of :func:`_surroundings` runs on them with
    the same operands (the float x, y values against the box's float64 centre and reach), so
    it keeps the same points in the same order; their float64 coordinates are the same values
    (a conversion), and everything after (:func:`_crop_near`) is the code of
    :func:`crop_vehicle` on the same arrays.
    """
    pts = np.asarray(points)[:, :3]
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    if len(poses) == 0:
        return []
    extra = _reach_extra(cfg)
    reaches = [_reach(s, extra) for s in sizes]
    index = SweepIndex(pts)
    near = index.near(poses[:, :2], reaches)
    fresh_rng = _FreshRng(cfg.seed)
    z = pts[:, 2][near.rows]
    out = []
    for b, (p, s, r) in enumerate(zip(poses, sizes, reaches, strict=True)):
        own = near.square(b, p, r)
        box = np.empty((len(own), 3))  # = pts[near.rows[own]].astype(np.float64)
        box[:, 0], box[:, 1], box[:, 2] = near.x[own], near.y[own], z[own]
        out.append(_crop_near(box, _to_box(box, p), s, cfg, sweep_plane, fresh_rng))
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
    return _crop_near(near, local, size, cfg, sweep_plane)


def _crop_near(near: np.ndarray, local: np.ndarray, size: np.ndarray, cfg: CropConfig,
               sweep_plane, fresh_rng=None) -> np.ndarray:
    """The crop from the box's surroundings ``near (K, 3)`` (float64, sensor frame) and
    ``local`` (the same in the box frame): the points in the enlarged box above the ground.

    The box test compares each of the three absolute coordinates with its half side, the
    test ``np.all(np.abs(local) <= half, axis=1)`` column by column (the same comparisons,
    without a slow reduction over rows of three), and the absolute values serve the ground
    fit too."""
    a = np.abs(local)
    half = size / 2 + [cfg.margin, cfg.margin, cfg.margin_z]
    inbox = (a[:, 0] <= half[0]) & (a[:, 1] <= half[1]) & (a[:, 2] <= half[2])
    cand = np.compress(inbox, near, axis=0)
    if cfg.ground == "none" or len(cand) == 0:
        return np.ascontiguousarray(cand, dtype=np.float32)
    plane = (_ground_from(near, local, size, cfg, a, fresh_rng) if cfg.ground == "plane"
             else None)
    if plane is None and cfg.ground == "plane":
        plane = sweep_plane() if callable(sweep_plane) else sweep_plane
    if plane is not None:
        n, d = plane
        above = cand @ np.asarray(n, dtype=np.float64) + d >= cfg.ground_threshold
    else:
        above = local[inbox, 2] >= -size[2] / 2 + cfg.box_ground
    return np.compress(above, cand, axis=0).astype(np.float32)


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
