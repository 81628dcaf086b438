"""Track-level pose smoothing for offline labelling (refinement ``"smooth"``).

Labelling is offline, so every estimate of a track is known at once. The per-frame pose
estimates of the network are noisy (tens of centimetres, and now and then a heading flipped
by 180 degrees), but a vehicle moves smoothly in the world. :func:`smooth_track_poses`:

1. maps every frame's estimated pose into a common world frame with the ego poses
   (``ego[t]`` maps frame t's sensor frame into the common frame);
2. fits the positions with a local robust quadratic in time: for each frame, the frames
   within ``window`` frames of it, weighted least squares with Tukey biweights recomputed
   from the residuals (``iterations`` times), so a few bad estimates do not pull the fit;
3. the heading: a vehicle that travels at least ``min_travel`` metres over the track takes
   the direction of its fitted velocity wherever it moves faster than ``min_speed`` m/s
   (vehicles drive forwards). A track that does not travel that far (parked, or creeping)
   is refitted over all its frames at once as a straight line, and its heading is the axial
   mean of the estimated headings (angles doubled, averaged, halved: a flip does not count
   against it), turned to the side most estimates point to;
4. maps the smoothed poses back into each frame's sensor frame.

Without ego poses the sensor's own motion is unknown, so the motion direction in the sensor
frame says nothing about the heading: the positions are still fitted (relative motion is
smooth too) and the heading of a track that moves relative to the sensor is, in each frame,
the axial mean of the estimates within ``2 * window`` frames of it.
"""

from __future__ import annotations

import numpy as np

from seqshape.geometry import matrix_to_pose, pose_to_matrix, wrap_angle


def _local_fit(t: np.ndarray, y: np.ndarray, window: float, iterations: int,
               scale: float, max_deg: int = 2, query: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Robust local polynomial (degree ``max_deg``) fit of ``y (T, D)`` over times ``t (T,)``,
    evaluated at ``query (Q,)`` (default ``t``): (values, slopes), each ``(Q, D)``. A query
    with no sample within ``window`` uses the nearest samples' window."""
    query = t if query is None else np.asarray(query, dtype=np.float64)
    val = np.empty((len(query), y.shape[1]))
    slope = np.zeros_like(val)
    for i, tq in enumerate(query):
        sel = np.flatnonzero(np.abs(t - tq) <= window)
        if len(sel) == 0:
            near = t[np.argmin(np.abs(t - tq))]
            sel = np.flatnonzero(np.abs(t - near) <= window)
        dt = t[sel] - tq
        deg = min(max_deg, len(np.unique(dt)) - 1)
        if min(np.count_nonzero(dt < 0), np.count_nonzero(dt > 0)) < window / 2:
            # near a track's end the window is one-sided: a quadratic there extrapolates its
            # curvature (the first detection's error grew: docs/model.md, "Offline mode"), a
            # line does not
            deg = min(deg, 1)
        a = np.vander(dt, deg + 1, increasing=True)  # (M, deg+1): 1, dt, dt^2
        w = np.ones(len(sel))
        for _ in range(iterations + 1):
            sw = np.sqrt(w)[:, None]
            coef, *_ = np.linalg.lstsq(a * sw, y[sel] * sw, rcond=None)
            r = np.linalg.norm(y[sel] - a @ coef, axis=1)
            u = r / (4.685 * scale)
            w = np.where(u < 1, (1 - u ** 2) ** 2, 0.0)
            if w.sum() < deg + 1:  # everything rejected: fall back to equal weights
                w = np.ones(len(sel))
        val[i] = coef[0]
        if deg >= 1:
            slope[i] = coef[1]
    return val, slope


def axial_mean(angles) -> float:
    """Mean direction of ``angles`` ignoring 180-degree flips, turned to the majority side."""
    angles = np.asarray(angles, dtype=np.float64)
    axis = 0.5 * np.arctan2(np.sin(2 * angles).mean(), np.cos(2 * angles).mean())
    forward = np.cos(angles - axis) >= 0
    return float(wrap_angle(axis if forward.mean() >= 0.5 else axis + np.pi))


def smooth_track_poses(poses, frames, ego=None, rate_hz: float = 10.0, window: int = 8,
                       iterations: int = 3, scale: float = 0.3, min_travel: float = 3.0,
                       min_speed: float = 1.0, valid=None) -> np.ndarray:
    """Smoothed ``(T, 4)`` sensor-frame poses of one track (module doc).

    Args:
        poses: ``(T, 4)`` estimated ``(x, y, z, yaw)`` in each frame's sensor frame.
        frames: ``(T,)`` frame numbers (increasing; gaps allowed).
        ego: ``(T, 4, 4)`` sensor-to-common transforms of those frames, or None (unknown).
        rate_hz: frame rate (for ``min_speed``).
        window: half-width of the local fit, in frames.
        iterations: robust reweighting rounds.
        scale: residual scale (m) of the Tukey weights (rejects beyond 4.7 * scale).
        min_travel: metres the fitted track must cover to count as moving.
        min_speed: m/s below which a moving track's heading falls back to the estimates.
        valid: ``(T,)`` bool, the frames whose estimates are fitted (default all); the others
            (frames without points, whose estimates are stale) get the fit's value at their
            time. With no valid frame the poses are returned unchanged.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    t = np.asarray(frames, dtype=np.float64).reshape(-1)
    if len(poses) != len(t):
        raise ValueError(f"{len(poses)} poses but {len(t)} frames")
    if len(poses) == 0:
        return poses.copy()
    valid = np.ones(len(t), bool) if valid is None else np.asarray(valid, bool).reshape(-1)
    if not valid.any():
        return poses.copy()
    e = np.broadcast_to(np.eye(4), (len(t), 4, 4)) if ego is None else np.asarray(
        ego, dtype=np.float64).reshape(-1, 4, 4)
    world = np.einsum("tij,tjk->tik", e, pose_to_matrix(poses))
    w = matrix_to_pose(world)[valid]  # (V, 4): yaw about the common frame's z
    tv = t[valid]
    pos, vel = _local_fit(tv, w[:, :3], window, iterations, scale, query=t)
    travel = float(np.linalg.norm(pos[valid][-1, :2] - pos[valid][0, :2]))
    if travel < min_travel:  # parked or creeping: one robust line over the whole track
        pos, vel = _local_fit(tv, w[:, :3], np.inf, iterations, scale, max_deg=1, query=t)
    speed = np.linalg.norm(vel[:, :2], axis=1) * rate_hz  # m/s
    yaw = np.full(len(t), axial_mean(w[:, 3]))
    if travel >= min_travel:
        if ego is None:  # sensor motion unknown: no heading from motion, local axial means
            yaw = np.array([axial_mean(w[np.abs(tv - ti) <= 2 * window, 3])
                            if np.any(np.abs(tv - ti) <= 2 * window) else np.nan for ti in t])
            yaw = np.where(np.isfinite(yaw), yaw, axial_mean(w[:, 3]))
        else:
            moving = speed >= min_speed
            yaw[moving] = np.arctan2(vel[moving, 1], vel[moving, 0])
    smooth = pose_to_matrix(np.c_[pos, yaw])
    back = np.einsum("tij,tjk->tik", np.linalg.inv(e), smooth)
    return matrix_to_pose(back)
