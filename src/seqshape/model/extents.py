"""A track's extents bounded by what its frames observed (the offline mode's ``extents`` step).

The network's complete shape is a prior: a vehicle's length and width where the scans never
reached are guessed. Over a whole track, though, the sensor often sees a face in some frames
that it misses in others (a parked car passed by the ego shows its back, then its side, then
its front). :func:`bound_extents` takes every frame's points into that frame's estimated box
frame (canonical: x forward, y left, centred on the box; :mod:`seqshape.geometry`) and, per
segment of the track (:func:`seqshape.model.smooth.track_segments`) and per planar axis:

* a face counts as *seen* in a frame when the sensor stands at least ``margin`` beyond the
  face's plane (in front of the front, behind the back, to the left of the left side, ...)
  and the frame has ``min_points`` points; the face's observed position in that frame is the
  ``face_percentile`` of the frame's points along the axis (the outermost surface, each frame
  in its own estimated box frame, so the frames' pose errors do not blur it), and the face's
  position over the track the median over the frames that saw it (at least ``min_frames``);
* both faces seen: the extent is the observed span and the box is centred between the faces
  (the prior is not needed);
* one face seen: ``anchor=True`` puts the box's seen face where it was observed and keeps the
  network's extent behind it; ``anchor=False`` keeps the box as it is;
* either way the box never ends short of the points observed along the axis (each frame's
  ``1st``/``99th`` percentiles, median over the frames): what was seen bounds the extent from
  below; the network's prior fills in only the rest.

The complete shapes are stretched along the axis (an affine map of the canonical coordinates
from the network's box to the new one) and the poses' centres moved with the box. Frames
without points change with their segment. Measured in docs/model.md ("Track extents").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from seqshape.geometry import canonical_to_sensor, sensor_to_canonical, yaw_to_rotmat

#: Percentiles of a complete shape's canonical x and y that are its box's faces (as the
#: evaluation's ``EXTENT_PERCENTILES``: robust to a few stray points).
SHAPE_PERCENTILES = (1.0, 99.0)
#: Percentile of a frame's points along an axis (from the box centre outwards) taken as the
#: face the sensor saw.
FACE_PERCENTILE = 99.0
#: Metres the sensor must stand beyond a face's plane for the face to count as seen.
MARGIN = 0.5
#: Points a frame needs to tell where a face is.
MIN_POINTS = 20
#: Frames that must have seen a face before it counts.
MIN_FRAMES = 2
#: Percentiles of a frame's points along each axis that bound the box from below (inside the
#: outermost points: a tracker's crop holds stray returns of the ground and its neighbours).
OBSERVED_PERCENTILES = (1.0, 99.0)
#: Shortest extent (m) the step will set (a vehicle is no thinner).
MIN_EXTENT = 0.5


def bound_extents(points: Sequence[np.ndarray], complete: np.ndarray, poses: np.ndarray,
                  segments: np.ndarray | None = None, anchor: bool = False,
                  margin: float = MARGIN, min_points: int = MIN_POINTS,
                  min_frames: int = MIN_FRAMES, face_percentile: float = FACE_PERCENTILE
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A track's shapes and poses with their planar extents bounded by the observed points
    (module doc).

    Args:
        points: per frame ``(N_t, 3)`` points in that frame's sensor frame (N_t may be 0).
        complete: ``(T, K, 3)`` complete shapes, each in its frame's sensor frame.
        poses: ``(T, 4)`` box poses ``(x, y, z, yaw)`` of those shapes.
        segments: ``(T,)`` segment numbers (None: one segment); each is bounded on its own.
        anchor: where only one face of an axis was seen, move the box so that face sits
            where it was observed (keeping the network's extent behind it).

    Returns:
        ``(complete (T, K, 3) float32, poses (T, 4) float64)``.

    >>> from seqshape.testing import box_surface
    >>> truth = (4.6, 1.8, 1.5)  # a car 4.6 m long; the network says 4.0
    >>> shape = box_surface(400, 0, size=(4.0, 1.8, 1.5), pose=(0.0, 0.0, 0.0, 0.0))
    >>> poses = np.array([[-8.0, 0.0, 0.0, 0.0], [8.0, 0.0, 0.0, 0.0]])  # behind, ahead
    >>> seen = [box_surface(300, k, size=truth, pose=tuple(p)) for k, p in enumerate(poses)]
    >>> out, _ = bound_extents(seen, np.stack([shape + p[:3] for p in poses]), poses)
    >>> round(float(np.ptp(out[0][:, 0])), 1)  # both ends seen: the observed length
    4.6
    """
    complete = np.asarray(complete)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    n = len(poses)
    if complete.ndim != 3 or len(complete) != n or len(points) != n:
        raise ValueError(f"{len(points)} frames of points, complete {complete.shape} and "
                         f"poses {poses.shape} do not describe one track")
    out_c = np.array(complete, dtype=np.float32)
    out_p = poses.copy()
    segments = np.zeros(n, np.int64) if segments is None else np.asarray(segments).reshape(-1)
    for s in np.unique(segments):
        idx = np.flatnonzero(segments == s)
        canonical = [sensor_to_canonical(np.asarray(complete[t], np.float64), poses[t])
                     for t in idx]
        if not canonical or not len(canonical[0]):
            continue
        bounds = np.array([np.percentile(c[:, :2], SHAPE_PERCENTILES, axis=0)
                           for c in canonical])  # (F, 2 lo/hi, 2 axes)
        lo, hi = np.median(bounds[:, 0], axis=0), np.median(bounds[:, 1], axis=0)
        new_lo, new_hi = _bounds(points, poses, idx, lo, hi, anchor, margin, min_points,
                                 min_frames, face_percentile)
        if np.allclose(new_lo, lo) and np.allclose(new_hi, hi):
            continue
        scale = (new_hi - new_lo) / np.maximum(hi - lo, 1e-6)  # (2,)
        centre = 0.5 * (new_lo + new_hi)  # the new box's centre in the old box frame
        for c, t in zip(canonical, idx, strict=True):
            c[:, :2] = new_lo + (c[:, :2] - lo) * scale - centre
            pose = poses[t].copy()
            pose[:2] += yaw_to_rotmat(pose[3])[:2, :2] @ centre
            out_p[t] = pose
            out_c[t] = canonical_to_sensor(c, pose).astype(np.float32)
    return out_c, out_p


def _bounds(points, poses, idx, lo, hi, anchor, margin, min_points, min_frames, pct):
    """The new box's ``(lo (2,), hi (2,))`` in the network's box frame of one segment."""
    faces_lo: list[list[float]] = [[], []]
    faces_hi: list[list[float]] = [[], []]
    seen_lo, seen_hi = [], []
    for t in idx:
        pts = np.asarray(points[t], dtype=np.float64).reshape(-1, 3)
        if len(pts) < min_points:
            continue
        local = sensor_to_canonical(pts, poses[t])[:, :2]
        sensor = sensor_to_canonical(np.zeros((1, 3)), poses[t])[0, :2]
        first, last = np.percentile(local, OBSERVED_PERCENTILES, axis=0)
        seen_lo.append(first)
        seen_hi.append(last)
        for a in range(2):
            if sensor[a] > hi[a] + margin:
                faces_hi[a].append(float(np.percentile(local[:, a], pct)))
            if sensor[a] < lo[a] - margin:
                faces_lo[a].append(float(np.percentile(local[:, a], 100.0 - pct)))
    new_lo, new_hi = lo.copy(), hi.copy()
    if not seen_lo:
        return new_lo, new_hi
    observed_lo, observed_hi = np.median(seen_lo, axis=0), np.median(seen_hi, axis=0)
    for a in range(2):
        f_lo = float(np.median(faces_lo[a])) if len(faces_lo[a]) >= min_frames else None
        f_hi = float(np.median(faces_hi[a])) if len(faces_hi[a]) >= min_frames else None
        if f_lo is not None and f_hi is not None and f_hi - f_lo >= MIN_EXTENT:
            new_lo[a], new_hi[a] = f_lo, f_hi
            continue
        if anchor and f_hi is not None:
            new_lo[a], new_hi[a] = f_hi - (hi[a] - lo[a]), f_hi
        elif anchor and f_lo is not None:
            new_lo[a], new_hi[a] = f_lo, f_lo + (hi[a] - lo[a])
        new_lo[a] = min(new_lo[a], observed_lo[a])  # never short of what was seen
        new_hi[a] = max(new_hi[a], observed_hi[a])
    return new_lo, new_hi
