"""Accumulated reference shapes: the paper's stand-in for the complete shape of a real track.

A real track has no true complete surface. The paper evaluates on real tracks against a
reference made from the track itself, and so does seqshape (docs/reference.md):

1. every frame's points (sensor frame) are brought into the canonical vehicle frame with the
   ground-truth box pose of that frame (:func:`~seqshape.geometry.sensor_to_canonical`);
   frames whose pose is unknown (NaN) or that hold no points are skipped;
2. points farther than ``box_margin`` outside the box are dropped (what leaked through the crop),
   and so are points less than ``ground_guard`` above the box bottom (ground residue; the crop
   already removed the ground with a fitted plane, this is a small guard);
3. the cloud is mirrored about the vehicle's longitudinal symmetry plane, the canonical x-z
   plane (``y -> -y``, :func:`mirror_y`), vehicles being left-right symmetric;
4. it is thinned on a ``voxel`` grid (:func:`voxel_downsample`, one mean point per cell), so
   its density is even whatever the range of each frame;
5. statistical outliers are removed (:func:`remove_statistical_outliers`: a point whose mean
   distance to its ``outlier_k`` nearest neighbours is above the mean of that statistic plus
   ``outlier_std`` standard deviations);
6. it is resampled to exactly ``n_points`` (:func:`resample_even`): farthest point sampling
   when there are at least ``n_points`` points (even spacing, which matters for the Chamfer
   distance), else every point plus a seeded random choice of repeated points.

:func:`accumulated_reference` returns the reference and a JSON-serialisable ``info`` dict that
goes into ``meta["reference"]``; :func:`add_references` fills ``complete`` and
``meta["reference"]`` of a list of tracks. Such a reference is NOT a true surface: it holds only
what the sensor saw (and its mirror image), never the underside, rarely the roof of a tall
vehicle, nothing of a front or back the sensor never faced; glass returns little on real
cars.

The same accumulation (steps 1-4 without the ground guard and the outlier step) is the
GT-Accumulation labelling mode of :mod:`seqshape.amodal.accumulate`, which imports
:func:`accumulate_canonical`, :func:`mirror_y` and :func:`voxel_downsample` from here.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from seqshape.data.track import Track
from seqshape.geometry import sensor_to_canonical

_log = logging.getLogger(__name__)

VOXEL = 0.05  # m: default grid of the accumulated cloud
BOX_MARGIN = 0.10  # m: accumulated points farther than this outside the box are dropped
GROUND_GUARD = 0.05  # m: accumulated points less than this above the box bottom are dropped
OUTLIER_K = 16  # neighbours of the statistical outlier test
OUTLIER_STD = 3.0  # standard deviations above the mean neighbour distance
N_POINTS = 2048  # points of a reference (as the synthetic complete shapes, GenerateConfig)
MIN_POINTS = 50  # fewer accumulated points than this: no reference (docs/reference.md)


class NoReferenceError(ValueError):
    """A track has too few usable points to make an accumulated reference."""


def mirror_y(points) -> np.ndarray:
    """Reflect canonical points about the heading (x) axis: ``(x, y, z) -> (x, -y, z)``."""
    out = np.array(points, dtype=np.float32, copy=True).reshape(-1, 3)
    out[:, 1] *= -1
    return out


def voxel_downsample(points, voxel: float) -> np.ndarray:
    """One point per occupied ``voxel`` cell (the mean of its points); ``(M, 3)`` float32.

    Cells are ``[k * voxel, (k + 1) * voxel)`` on each axis, so a cloud symmetric about
    ``y = 0`` stays symmetric.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if voxel <= 0 or len(points) == 0:
        return points.astype(np.float32)
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(0)
    dims = keys.max(0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, inv, counts = np.unique(flat, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inv.reshape(-1), points)
    return (sums / counts[:, None]).astype(np.float32)


def canonical_points(track: Track) -> tuple[np.ndarray, int]:
    """All of ``track``'s points in its canonical frame and the number of frames they came from.

    Frames with a NaN pose or no points are skipped. Returns ``((P, 3) float32, frames)``.
    """
    parts = [sensor_to_canonical(p, pose) for p, pose in zip(track.points, track.poses,
                                                               strict=True)
             if len(p) and np.all(np.isfinite(pose))]
    if not parts:
        return np.zeros((0, 3), np.float32), 0
    return np.concatenate(parts).astype(np.float32), len(parts)


def inside_box(points, size, margin: float | None,
               ground_guard: float | None = None) -> np.ndarray:
    """Mask ``(P,)`` of canonical points inside the box ``size`` grown by ``margin``.

    ``margin=None`` keeps every point (as does a box of zero size). ``ground_guard`` (m), when
    given, also drops the points less than that above the box bottom (``z < -h/2 + guard``;
    not for a box of zero height).
    """
    points = np.asarray(points).reshape(-1, 3)
    size = np.asarray(size, dtype=np.float64).reshape(3)
    keep = np.ones(len(points), dtype=bool)
    if margin is not None and np.all(size > 0):
        keep &= np.all(np.abs(points) <= size / 2 + margin, axis=1)
    if ground_guard is not None and size[2] > 0:
        keep &= points[:, 2] >= -size[2] / 2 + ground_guard
    return keep


def accumulate_canonical(track: Track, mirror: bool = True, voxel: float = VOXEL,
                         box_margin: float | None = BOX_MARGIN) -> np.ndarray:
    """All of ``track``'s points in its canonical frame, ``(M, 3)`` float32.

    Args:
        track: points per frame in the sensor frame and ground-truth ``poses``; frames with a
            NaN pose are skipped.
        mirror: add the reflection about the heading axis (:func:`mirror_y`).
        voxel: thinning grid in metres (0 keeps every point).
        box_margin: drop points farther than this outside the ``track.size`` box (None keeps
            all); cropping was already done with a margin, this removes what leaked in.
    """
    pts, _ = canonical_points(track)
    pts = pts[inside_box(pts, track.size, box_margin)]
    if mirror:
        pts = np.concatenate([pts, mirror_y(pts)])
    return voxel_downsample(pts, voxel)


def remove_statistical_outliers(points, k: int = OUTLIER_K,
                                std_ratio: float = OUTLIER_STD) -> np.ndarray:
    """Mask ``(P,)`` of the points that are not statistical outliers.

    For each point the mean distance to its ``k`` nearest neighbours (itself excluded) is
    computed (``scipy.spatial.cKDTree``); a point is an outlier when that distance is above the
    mean over the cloud plus ``std_ratio`` standard deviations. A cloud of ``k`` points or
    fewer is kept whole.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if k < 1:
        raise ValueError(f"outlier k must be >= 1, got {k}")
    if len(points) <= k:
        return np.ones(len(points), dtype=bool)
    d, _ = cKDTree(points).query(points, k=k + 1)  # (P, k + 1), column 0 is the point itself
    mean_d = d[:, 1:].mean(1)  # (P,)
    return mean_d <= mean_d.mean() + std_ratio * mean_d.std()


def farthest_point_sample(points, n: int, seed: int = 0) -> np.ndarray:
    """Indices ``(n,)`` of ``n <= P`` points of ``points (P, 3)`` by farthest point sampling.

    The first point is drawn with ``seed``; each next one is the point farthest from those
    already chosen, so the chosen points are evenly spread over the cloud.
    """
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    if not 0 < n <= len(points):
        raise ValueError(f"cannot choose {n} points of a cloud of {len(points)}")
    x, y, z = (np.ascontiguousarray(points[:, k]) for k in range(3))  # (P,) each: fast loops
    idx = np.empty(n, dtype=np.int64)
    j = idx[0] = np.random.default_rng(seed).integers(len(points))
    dist = (x - x[j]) ** 2 + (y - y[j]) ** 2 + (z - z[j]) ** 2  # (P,) to the chosen set
    for i in range(1, n):
        j = idx[i] = int(dist.argmax())
        d = (x - x[j]) ** 2
        d += (y - y[j]) ** 2
        d += (z - z[j]) ** 2
        np.minimum(dist, d, out=dist)
    return idx


def resample_even(points, n: int, seed: int = 0) -> np.ndarray:
    """Exactly ``n`` points of ``points (P, 3)``, float32, deterministic for ``seed``.

    ``P >= n``: farthest point sampling (:func:`farthest_point_sample`). ``P < n``: every point
    once, then ``n - P`` of them again, chosen at random with replacement (the density is that
    of the voxel grid; repeats add no new surface).
    """
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    if len(points) == 0:
        raise ValueError("cannot resample an empty cloud")
    if len(points) >= n:
        return points[farthest_point_sample(points, n, seed)]
    extra = np.random.default_rng(seed).choice(len(points), size=n - len(points), replace=True)
    return np.concatenate([points, points[extra]])


def accumulated_reference(track: Track, n_points: int = N_POINTS, mirror: bool = True,
                          voxel: float = VOXEL, outlier_k: int = OUTLIER_K,
                          outlier_std: float | None = OUTLIER_STD,
                          box_margin: float | None = BOX_MARGIN,
                          ground_guard: float | None = GROUND_GUARD,
                          min_points: int = MIN_POINTS, seed: int = 0
                          ) -> tuple[np.ndarray, dict]:
    """The accumulated reference shape of ``track`` (module doc, steps 1-6).

    Args:
        track: points per frame (sensor frame), ground-truth ``poses`` and ``size``.
        n_points: points of the reference.
        mirror: add the mirror image about the canonical x-z plane.
        voxel: thinning grid (m); 0 keeps every point.
        outlier_k, outlier_std: the statistical outlier test; ``outlier_std=None`` skips it.
        box_margin: drop points farther than this outside the box (None keeps all).
        ground_guard: drop points less than this above the box bottom (None keeps all).
        min_points: fewest accumulated points (after the box and ground cuts, before
            mirroring) that make a reference.
        seed: the resampling seed.

    Returns:
        ``(complete (n_points, 3) float32 in the canonical frame, info)``; ``info`` is the
        JSON-serialisable ``meta["reference"]``: ``kind`` ("accumulated"), ``frames_used``,
        ``frames_total``, ``points_used``, ``points_outside_box``, ``points_ground``,
        ``mirrored``, ``voxel_points`` (after thinning), ``outliers_removed``, ``resampling``
        ("fps" or "repeat"), ``n_points`` and the parameters.

    Raises:
        NoReferenceError: (a ``ValueError``) the track has fewer than ``min_points`` usable
            points (the reason is in the message); no reference can be made.
        ValueError: a bad parameter.
    """
    if n_points < 1 or voxel < 0 or outlier_k < 1:
        raise ValueError(f"need n_points >= 1, voxel >= 0 and outlier_k >= 1, got {n_points}, "
                         f"{voxel} and {outlier_k}")
    raw, frames_used = canonical_points(track)
    in_box = inside_box(raw, track.size, box_margin)
    keep = in_box & inside_box(raw, track.size, None, ground_guard)
    pts = raw[keep]
    if len(pts) < max(min_points, 1):
        raise NoReferenceError(
            f"track {track.track_id}: {len(pts)} usable points in {frames_used} of "
            f"{len(track)} frames (need {max(min_points, 1)}); no accumulated reference")
    if mirror:
        pts = np.concatenate([pts, mirror_y(pts)])
    thinned = voxel_downsample(pts, voxel)
    clean = (remove_statistical_outliers(thinned, outlier_k, outlier_std)
             if outlier_std is not None else np.ones(len(thinned), dtype=bool))
    complete = resample_even(thinned[clean], n_points, seed)
    info = {"kind": "accumulated",
            "note": "observed points accumulated with the ground-truth boxes, not a true surface",
            "frames_used": int(frames_used), "frames_total": len(track),
            "points_used": int(keep.sum()), "points_outside_box": int((~in_box).sum()),
            "points_ground": int((in_box & ~keep).sum()), "mirrored": bool(mirror),
            "voxel_points": len(thinned), "outliers_removed": int((~clean).sum()),
            "resampling": "fps" if clean.sum() >= n_points else "repeat",
            "n_points": int(n_points), "voxel": float(voxel), "outlier_k": int(outlier_k),
            "outlier_std": None if outlier_std is None else float(outlier_std),
            "box_margin": None if box_margin is None else float(box_margin),
            "ground_guard": None if ground_guard is None else float(ground_guard),
            "seed": int(seed)}
    return complete, info


def add_references(tracks: Sequence[Track], **kwargs) -> list[Track]:
    """``tracks`` with ``complete`` set to their :func:`accumulated_reference` (``**kwargs``).

    Each returned Track shares its input's arrays but has its own ``meta`` with
    ``meta["reference"]`` = the reference's ``info``. A track that gets no reference (too few
    points) keeps ``complete=None`` and ``meta["reference"] = {"kind": None, "error": message}``
    (as ``seqshape tracks`` writes it); their number is logged as a warning.
    """
    out, skipped = [], 0
    for tr in tracks:
        try:
            complete, info = accumulated_reference(tr, **kwargs)
        except NoReferenceError as exc:
            complete, info = None, {"kind": None, "error": str(exc)}
            skipped += 1
        out.append(Track(tr.track_id, tr.points, tr.poses, complete, tr.size, tr.timestamps,
                         {**tr.meta, "reference": info}))
    if skipped:
        _log.warning("accumulated references: %d of %d tracks have too few points, left "
                     "without a reference", skipped, len(out))
    return out
