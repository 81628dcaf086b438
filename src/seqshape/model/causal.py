"""The causal smoother over all the tracks of a streaming step at once.

:meth:`CausalSmoother.update <seqshape.model.smooth.CausalSmoother.update>` replaces a track's
newest estimate by the newest frame of :func:`~seqshape.model.smooth.smooth_track_poses` over
its past (at most ``history`` frames): per track and step, a few dozen small numpy calls and
batched pseudo-inverses, 2-4 ms. :func:`update_estimates` does what
``[s.update_estimate(e, ego, time, rate_hz) for s, e, ...]`` does (the same per-track
bookkeeping: frame numbers, segments, weights, the shape average), but computes only the
newest frame's value, for all the step's tracks in one vectorised pass:

* the histories right-aligned in ``(K, T)`` arrays (``T`` the longest history; ``present``
  marks the real frames, the newest is column ``T - 1`` for every track);
* the robust local fits of every frame (:func:`_robust_fits`: the weighted least squares of
  ``_local_fit_batch`` by its normal equations, a 3 x 3 solve per window instead of an SVD;
  a window whose equations are ill-conditioned is solved by the pseudo-inverse as there);
  frame numbers are whole and increasing, so a frame's window is the ``2 * window + 1``
  columns around it;
* the whole-track line and constant of a parked or creeping track, the sideslip and the blend
  of a moving one, with masked medians and quantiles (numpy's formulas).

The result equals the per-track smoother's to rounding (tested on random tracks with holes,
segments, runs without points, with and without ego poses: within 1e-6 m and rad; a straight
run gets no sideslip arm in either, ``smooth.MIN_RMS_CURVATURE``, so no arm is fitted to
curvatures of rounding size);
:class:`~seqshape.model.smooth.CausalSmoother` stays the reference (and the path of a smoother
that is not the default one's window).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from seqshape.geometry import matrix_to_pose, pose_to_matrix, wrap_angle, yaw_to_rotmat
from seqshape.model.smooth import (
    CURVATURE_HALF,
    ITERATIONS,
    MAX_REAR_ARM,
    MAX_SIDESLIP,
    MIN_RMS_CURVATURE,
    SCALE,
    CausalSmoother,
    _axial,
    _decay_step,
)

#: Parameters of :func:`~seqshape.model.smooth.smooth_track_poses` the causal smoother uses
#: (its defaults): min_travel, min_speed, line_tolerance, line_sigmas.
MIN_TRAVEL, MIN_SPEED, LINE_TOLERANCE, LINE_SIGMAS = 3.0, 1.0, 0.05, 1.7
#: Bytes of float64 shapes :func:`_update_shapes` transforms at a time: below glibc's mmap
#: threshold (128 KiB), so that its arrays are reused from the heap rather than page-faulted
#: in anew on every step (measured: a step of 90 tracks' 1024 points 4.6 -> 1.4 ms).
SHAPE_CHUNK_BYTES = 100_000
#: Largest ``det`` of a window's normal equations scaled to a unit diagonal below which
#: :func:`_robust_fits` solves that window by the pseudo-inverse instead.
ILL_CONDITIONED = 1e-9


def update_estimates(smoothers: Sequence[CausalSmoother], estimates: Sequence,
                     egos: Sequence, times: Sequence, rate_hz: float = 10.0) -> None:
    """``smoothers[i].update_estimate(estimates[i], egos[i], times[i], rate_hz)`` for every
    track of a step, in place, with one vectorised fit of all the tracks that are smoothed
    (module doc). ``egos[i]``: (4, 4) or None; ``times[i]``: seconds or None."""
    if not len(smoothers):
        return
    ready, news = [], [None] * len(smoothers)
    for i, (sm, est) in enumerate(zip(smoothers, estimates, strict=True)):
        pose, ego, time, smooth = sm._record(est.pose, est.num_points > 0, egos[i], times[i],
                                             rate_hz, est.num_points)
        if smooth:
            ready.append((i, pose, time))
        else:
            news[i] = pose.copy()
    groups: dict[int, list] = {}
    for item in ready:
        groups.setdefault(smoothers[item[0]].window, []).append(item)
    for window, items in groups.items():
        subset = [smoothers[i] for i, _, _ in items]
        out = smooth_newest(subset, [sm._fit_setup(rate_hz) for sm in subset], window)
        for (i, pose, time), value in zip(items, out, strict=True):
            news[i] = smoothers[i]._finish(value, pose, estimates[i].num_points > 0, time)
    _update_shapes(smoothers, estimates, news)


def smooth_newest(smoothers: Sequence[CausalSmoother], setups: Sequence[tuple],
                  window: int) -> np.ndarray:
    """``(K, 4)``: for each smoother, the newest frame of ``smooth_track_poses`` over its
    history (before :meth:`CausalSmoother._finish`), ``setups[k]`` its ``(egos, rate_hz)``
    (:meth:`CausalSmoother._fit_setup`)."""
    h = _Histories(smoothers, setups)
    pos, vel = _kept_local_fits(h, smoothers, window)
    k_all = np.arange(h.k)
    first = np.argmax(h.valid, axis=1)  # (K,) the first and last valid columns
    last = h.t.shape[1] - 1 - np.argmax(h.valid[:, ::-1], axis=1)
    travel = np.linalg.norm(pos[k_all, last, :2] - pos[k_all, first, :2], axis=1)  # (K,)
    n_valid = h.valid.sum(axis=1)
    resid = np.linalg.norm(h.w[..., :2] - pos[..., :2], axis=2)  # (K, T)
    sigma = _masked_median(resid, h.valid) / 1.177
    slow = travel < MIN_TRAVEL
    if slow.any():  # parked or creeping: the whole-track line, or a constant
        line, line_vel = _whole_fits(h, 1)
        off = np.linalg.norm(line[..., :2] - pos[..., :2], axis=2)
        take = slow & (_masked_quantile(off, h.valid, 0.95)
                       <= LINE_TOLERANCE + LINE_SIGMAS * sigma)
        span = np.where(h.valid, h.t, -np.inf).max(axis=1) \
            - np.where(h.valid, h.t, np.inf).min(axis=1)
        drift = np.linalg.norm(line_vel[:, -1, :2], axis=1) * span
        const = take & (drift <= 2.5 * sigma * np.sqrt(12.0 / np.maximum(n_valid, 1)))
        pos = np.where(take[:, None, None], line, pos)
        vel = np.where(take[:, None, None], line_vel, vel)
        if const.any():
            flat, flat_vel = _whole_fits(h, 0)
            pos = np.where(const[:, None, None], flat, pos)
            vel = np.where(const[:, None, None], flat_vel, vel)
    speed = np.linalg.norm(vel[..., :2], axis=2) * h.rate[:, None]  # (K, T) m/s
    yaw_w = h.w[..., 3]
    default = _axial_mean(yaw_w, h.valid)
    yaw = default.copy()
    moving = ~slow
    blind = moving & ~h.fixed  # no ego poses: the axial mean of the recent estimates
    if blind.any():
        near = h.valid & (h.t >= h.t[:, -1:] - 2 * window)
        local = _axial_mean(yaw_w, near)
        yaw = np.where(blind, np.where(near.any(axis=1), local, default), yaw)
    driven = moving & h.fixed
    if driven.any():
        yaw = np.where(driven, _motion_yaw(h, pos, vel, speed, default, sigma, window), yaw)
    smooth = pose_to_matrix(np.c_[pos[:, -1], yaw])
    return matrix_to_pose(np.linalg.inv(h.e_last) @ smooth)


class _Histories:
    """The smoothers' histories right-aligned in ``(K, T)`` arrays (module doc): ``t`` frame
    numbers (-1e9 before a track's first frame), ``valid`` (fitted frames: points and weight
    > 0), ``prior`` their weights, ``w (K, T, 4)`` the poses in the fixed frame (the ego
    poses' where every frame has one: ``fixed``), ``e_last (K, 4, 4)`` the newest frame's
    ego pose (identity without), ``rate (K,)`` Hz."""

    def __init__(self, smoothers: Sequence[CausalSmoother], setups: Sequence[tuple]):
        lens = np.array([len(sm._frames) for sm in smoothers])
        self.k, t_max = len(smoothers), int(lens.max())
        self.present = np.arange(t_max)[None, :] >= (t_max - lens)[:, None]  # (K, T)
        rows, cols = np.nonzero(self.present)
        self.t = np.full((self.k, t_max), -1e9)
        self.t[rows, cols] = [f for sm in smoothers for f in sm._frames]
        prior = np.zeros((self.k, t_max))
        prior[rows, cols] = [w for sm in smoothers for w in sm._weights]
        valid = np.zeros((self.k, t_max), bool)
        valid[rows, cols] = [v for sm in smoothers for v in sm._valid]
        self.valid = valid & (prior > 0)
        self.prior = np.where(self.valid, prior, 0.0)
        poses = np.zeros((self.k, t_max, 4))
        poses[rows, cols] = np.concatenate([np.asarray(sm._poses) for sm in smoothers])
        e = np.broadcast_to(np.eye(4), (self.k, t_max, 4, 4)).copy()
        self.fixed = np.array([egos is not None for egos, _ in setups])
        for k in np.flatnonzero(self.fixed):
            e[k, t_max - lens[k]:] = setups[k][0]
        self.w = matrix_to_pose(e @ pose_to_matrix(poses))
        self.e_last = e[:, -1]
        self.rate = np.array([r for _, r in setups], dtype=np.float64)
        # the local fits kept from earlier steps (CausalSmoother._kept) and what the history
        # has dropped since they were made
        self.kept = np.zeros((self.k, t_max), bool)
        self.kept[rows, cols] = np.concatenate([sm._kept[:n] for sm, n in
                                                zip(smoothers, lens, strict=True)])
        self.kept_fit = np.zeros((self.k, t_max, 2, 3))
        self.kept_fit[rows, cols] = np.concatenate([sm._kept_fit[:n] for sm, n in
                                                    zip(smoothers, lens, strict=True)])
        self.dropped = np.array([sm._dropped for sm in smoothers], dtype=np.float64)


def _kept_local_fits(h: _Histories, smoothers: Sequence[CausalSmoother], window: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_local_fits` of every frame, taking the fits kept from earlier steps whose
    window is unchanged and keeping the final ones (``CausalSmoother._local_fit``'s rule: a
    fit is final once a frame ``window`` frames newer exists, until the history drops a frame
    of its window; with at least two samples in its own window)."""
    whole = h.t - window > h.dropped[:, None]  # no frame of the window dropped
    usable = h.kept & whole
    pos, vel, lonely = _local_fits(h, window, h.present & ~usable)
    pos = np.where(usable[..., None], h.kept_fit[:, :, 0], pos)
    vel = np.where(usable[..., None], h.kept_fit[:, :, 1], vel)
    final = h.present & whole & ~lonely & (h.t + window <= h.t[:, -1:])
    fits = np.stack([pos, vel], axis=2)  # (K, T, 2, 3)
    t_max = h.t.shape[1]
    for k, sm in enumerate(smoothers):
        n = len(sm._frames)
        sm._kept[:n], sm._kept_fit[:n] = final[k, t_max - n:], fits[k, t_max - n:]
    return pos, vel


def _local_fits(h: _Histories, window: int, todo: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(pos, vel, lonely)``: ``(K, T, 3)`` ``_local_fit(tv, y, window, ITERATIONS, SCALE,
    query=t, prior=prior)`` of every track's valid positions at the frames ``todo (K, T)``
    (0 elsewhere), and ``(K, T)`` whether a frame has fewer than two samples within its
    window (it takes its nearest sample's)."""
    k, t_max = h.t.shape
    cols = np.arange(t_max)
    centre = np.broadcast_to(cols, (k, t_max))
    inside, _ = _window(h, centre, h.t, window)
    # a frame with at most one sample within the window takes its nearest sample's window
    lonely = h.present & (inside.sum(axis=2) < 2) & h.valid.any(axis=1)[:, None]
    if lonely.any():
        before = np.maximum.accumulate(np.where(h.valid, cols, -1), axis=1)
        after = np.minimum.accumulate(np.where(h.valid, cols, t_max)[:, ::-1], axis=1)[:, ::-1]
        tb = np.take_along_axis(h.t, np.maximum(before, 0), axis=1)
        ta = np.take_along_axis(h.t, np.minimum(after, t_max - 1), axis=1)
        prev = (before >= 0) & ((after >= t_max) | (h.t - tb <= ta - h.t))  # ties: earlier
        centre = np.where(lonely, np.where(prev, before, after), centre)
    rows = np.flatnonzero(todo.ravel())
    centre_t = np.take_along_axis(h.t, centre, axis=1)
    inside, slots = _window(h, centre, centre_t, window)
    kk = np.repeat(np.arange(k), t_max)[rows]
    inside, slots = inside.reshape(k * t_max, -1)[rows], slots.reshape(k * t_max, -1)[rows]
    dt = np.where(inside, h.t[kk[:, None], slots] - h.t.ravel()[rows, None], 0.0)  # (R, M)
    count = inside.sum(axis=1)
    sided = np.minimum((inside & (dt < 0)).sum(axis=1),
                       (inside & (dt > 0)).sum(axis=1)) < window / 2
    deg = np.minimum(2, count - 1)
    deg = np.where(sided, np.minimum(deg, 1), deg)
    val, slope = _robust_fits(dt, h.w[kk[:, None], slots, :3], inside,
                              np.where(inside, h.prior[kk[:, None], slots], 0.0), deg, 2)
    pos, vel = np.zeros((k * t_max, 3)), np.zeros((k * t_max, 3))
    pos[rows], vel[rows] = val, slope
    return pos.reshape(k, t_max, 3), vel.reshape(k, t_max, 3), lonely


def _window(h: _Histories, centre: np.ndarray, centre_t: np.ndarray, window: int
            ) -> tuple[np.ndarray, np.ndarray]:
    """``(inside (K, T, M), slots (K, T, M))``: the valid samples within ``window`` frames of
    ``centre_t`` among the ``M = 2 * window + 1`` columns around ``centre`` (clipped)."""
    t_max = h.t.shape[1]
    raw = centre[..., None] + np.arange(-window, window + 1)
    slots = np.clip(raw, 0, t_max - 1)
    ts = np.take_along_axis(h.t[:, None, :], slots.reshape(len(h.t), 1, -1), axis=2
                            ).reshape(slots.shape)
    vs = np.take_along_axis(h.valid[:, None, :], slots.reshape(len(h.t), 1, -1), axis=2
                            ).reshape(slots.shape)
    inside = (raw == slots) & vs & (np.abs(ts - centre_t[..., None]) <= window)
    return inside, slots


def _whole_fits(h: _Histories, max_deg: int) -> tuple[np.ndarray, np.ndarray]:
    """``(values, slopes)`` ``(K, T, 3)``: ``_local_fit(tv, y, inf, ITERATIONS, SCALE,
    max_deg, query=t, prior)``: one robust fit of degree ``max_deg`` (at most 1) over all of a
    track's valid frames, at their mid-time, along its line."""
    tv_max = np.where(h.valid, h.t, -np.inf).max(axis=1)
    tv_min = np.where(h.valid, h.t, np.inf).min(axis=1)
    mid = 0.5 * (tv_min + tv_max)  # (K,)
    dt = np.where(h.valid, h.t - mid[:, None], 0.0)
    deg = np.minimum(max_deg, h.valid.sum(axis=1) - 1)
    v, s = _robust_fits(dt, h.w[..., :3], h.valid, h.prior, np.minimum(deg, 1), max_deg)
    q = h.t - mid[:, None]
    return v[:, None, :] + s[:, None, :] * q[..., None], np.repeat(s[:, None, :], h.t.shape[1],
                                                                   axis=1)


def _robust_fits(dt: np.ndarray, ys: np.ndarray, inside: np.ndarray, w0: np.ndarray,
                 deg: np.ndarray, max_deg: int) -> tuple[np.ndarray, np.ndarray]:
    """``_local_fit_batch``'s robust polynomial fits, one a row: ``dt (R, M)`` sample times
    from the query, ``ys (R, M, D)``, ``inside (R, M)`` the samples, ``w0 (R, M)`` their prior
    weights (0 outside), ``deg (R,)`` each row's degree (<= ``max_deg``); ``ITERATIONS``
    Tukey reweightings with residual scale ``SCALE``. Returns (values, slopes), ``(R, D)``."""
    powers = np.arange(max_deg + 1)
    a = np.where(powers <= deg[:, None, None], dt[..., None] ** powers, 0.0)  # (R, M, P)
    unused = powers[None, :] > deg[:, None]  # (R, P): columns left at 0
    w = w0
    for it in range(ITERATIONS + 1):
        coef = _weighted_solve(a, ys, w, unused, inside, deg)  # (R, P, D)
        if it == ITERATIONS:
            break
        r = np.linalg.norm(ys - a @ coef, axis=2)
        u = r / (4.685 * SCALE)
        tukey = np.where(inside & (u < 1), (1 - u ** 2) ** 2, 0.0)
        rejected = tukey.sum(axis=1) < deg + 1  # everything rejected: the prior weights
        w = np.where(rejected[:, None], w0, tukey * w0)
    slope = np.where((deg >= 1)[:, None], coef[:, min(1, max_deg)], 0.0)
    return coef[:, 0], slope


def _weighted_solve(a, ys, w, unused, inside, deg) -> np.ndarray:
    """``(R, P, D)`` weighted least-squares coefficients by the normal equations (unused
    columns pinned to 0); the ill-conditioned rows (:data:`ILL_CONDITIONED`) by the
    pseudo-inverse with ``numpy.linalg.lstsq``'s cut-off, as ``_local_fit_batch``."""
    wa = np.swapaxes(a * w[..., None], 1, 2)  # (R, P, M)
    gram, rhs = wa @ a, wa @ ys  # (R, P, P), (R, P, D)
    p = gram.shape[1]
    diag = np.arange(p)
    gram[:, diag, diag] += unused  # a pinned column: 1 * c = 0
    scale = np.sqrt(gram[:, diag, diag])
    det = np.linalg.det(gram / (scale[:, :, None] * scale[:, None, :]))
    bad = ~(det > ILL_CONDITIONED)
    if bad.any():
        gram[bad] = np.eye(p)
    coef = np.linalg.solve(gram, rhs)
    if bad.any():
        count = inside[bad].sum(axis=1)
        cutoff = np.finfo(np.float64).eps * np.maximum(count, deg[bad] + 1)
        sw = np.sqrt(w[bad])[..., None]
        coef[bad] = np.linalg.pinv(a[bad] * sw, rcond=cutoff) @ (ys[bad] * sw)
    return coef


def _motion_yaw(h: _Histories, pos, vel, speed, default, sigma, window: int) -> np.ndarray:
    """``(K,)`` newest yaws of moving tracks with ego poses: the motion direction less the
    sideslip (``_sideslip``) where the track moves, blended with the estimates (``_blend``)."""
    moving = speed >= MIN_SPEED  # (K, T)
    direction = np.arctan2(vel[..., 1], vel[..., 0])
    slip = _sideslip(h, direction, speed / h.rate[:, None], moving)
    yaw = np.where(moving, direction - slip, default[:, None])  # (K, T)
    off = _axial(h.w[..., 3] - yaw)
    win = h.valid & (h.t >= h.t[:, -1:] - window)  # the newest frame's window
    count = win.sum(axis=1)
    spread = np.where(win, (h.t - h.t[:, -1:]) ** 2, 0.0).sum(axis=1)
    step = speed[:, -1] / h.rate
    var_dir = sigma ** 2 / np.maximum(step ** 2 * np.maximum(spread, 1.0), 1e-12)
    var_med = (1.2533 * _robust_sd(off, h.valid)) ** 2 / np.maximum(count, 1)
    weight = np.where(count > 0, var_dir / np.maximum(var_dir + var_med, 1e-12), 0.0)
    blend = weight * _masked_median(off, win)
    return np.where(moving[:, -1], yaw[:, -1] + blend, yaw[:, -1])


def _sideslip(h: _Histories, direction, step, moving) -> np.ndarray:
    """``(K, T)`` ``_sideslip`` of every frame: the curvature of the fitted path (its running
    median over +-CURVATURE_HALF frames) times the rear-axle arm fitted per track."""
    k, t_max = h.t.shape
    first = np.argmax(h.present, axis=1)
    rows = np.arange(k)
    theta = np.where(h.present, direction, direction[rows, first][:, None])
    theta = np.unwrap(theta, axis=1)
    rate = _gradient(theta, h.t, first)
    curv = np.where(step > 1e-6, rate / np.maximum(step, 1e-6), 0.0)
    raw = np.arange(t_max)[:, None] + np.arange(-CURVATURE_HALF, CURVATURE_HALF + 1)
    slots = np.clip(raw, 0, t_max - 1)  # (T, M)
    near = (raw == slots) & h.present[:, slots] \
        & (np.abs(h.t[:, slots] - h.t[:, :, None]) <= CURVATURE_HALF)
    curv = np.where(h.present, _masked_median(curv[:, slots], near), 0.0)
    use = h.valid & moving
    off = np.where(use, _axial(h.w[..., 3] - direction), 0.0)
    kc = np.where(use, curv, 0.0)
    n_use = use.sum(axis=1)
    rms = np.sqrt((kc ** 2).sum(axis=1) / np.maximum(n_use, 1))
    active = (n_use >= 3) & (rms >= MIN_RMS_CURVATURE)  # a straight track: no arm
    fitted = active.copy()
    keep, arm = use, np.zeros(k)
    for _ in range(2):
        num = np.where(keep, kc * off, 0.0).sum(axis=1)
        den = np.maximum(np.where(keep, kc ** 2, 0.0).sum(axis=1), 1e-12)
        arm = np.where(active, -(num / den), arm)
        r = off + arm[:, None] * kc
        sd = np.maximum(_robust_sd(r, use), 1e-3)
        keep = np.where(active[:, None], use & (np.abs(r) <= 3.0 * sd[:, None]), keep)
        active = active & (keep.sum(axis=1) >= 3)
    arm = np.clip(arm, 0.0, MAX_REAR_ARM)
    slip = np.clip(np.arctan(arm[:, None] * curv), -MAX_SIDESLIP, MAX_SIDESLIP)
    return np.where(fitted[:, None], slip, 0.0)


def _gradient(f: np.ndarray, x: np.ndarray, first: np.ndarray) -> np.ndarray:
    """``numpy.gradient(f, x)`` of each row's columns ``first..T-1`` (second order inside,
    first order at the ends; 0 for a row of one column)."""
    k, t_max = f.shape
    out = np.zeros_like(f)
    if t_max < 2:
        return out
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        dx1, dx2 = np.diff(x, axis=1)[:, :-1], np.diff(x, axis=1)[:, 1:]
        a = -dx2 / (dx1 * (dx1 + dx2))
        b = (dx2 - dx1) / (dx1 * dx2)
        c = dx1 / (dx2 * (dx1 + dx2))
        out[:, 1:-1] = a * f[:, :-2] + b * f[:, 1:-1] + c * f[:, 2:]
    rows = np.arange(k)
    two = first <= t_max - 2  # rows of at least two frames
    r, f0 = rows[two], first[two]
    out[r, f0] = (f[r, f0 + 1] - f[r, f0]) / (x[r, f0 + 1] - x[r, f0])
    out[two, -1] = (f[two, -1] - f[two, -2]) / (x[two, -1] - x[two, -2])
    out[~two] = 0.0
    return out


def _masked_median(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median of ``x`` over the last axis where ``mask`` (numpy's: the mean of the middle two
    of an even count); 0 where no entry."""
    ordered = np.sort(np.where(mask, x, np.nan), axis=-1)
    n = mask.sum(axis=-1)
    lo = np.take_along_axis(ordered, np.maximum((n - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    hi = np.take_along_axis(ordered, (n // 2)[..., None], axis=-1)[..., 0] \
        if ordered.shape[-1] else lo
    return np.where(n > 0, (lo + hi) / 2, 0.0)


def _masked_quantile(x: np.ndarray, mask: np.ndarray, q: float) -> np.ndarray:
    """``numpy.quantile(x[mask_row], q)`` per row (linear, numpy's interpolation); 0 where
    no entry."""
    ordered = np.sort(np.where(mask, x, np.inf), axis=1)
    n = mask.sum(axis=1)
    vi = q * (np.maximum(n, 1) - 1)
    lo = np.floor(vi).astype(np.int64)
    hi = np.minimum(lo + 1, np.maximum(n, 1) - 1)
    g = vi - lo
    a = np.take_along_axis(ordered, lo[:, None], axis=1)[:, 0]
    b = np.take_along_axis(ordered, hi[:, None], axis=1)[:, 0]
    with np.errstate(invalid="ignore"):
        diff = b - a
        out = np.where(g >= 0.5, b - diff * (1 - g), a + diff * g)
    return np.where(n > 0, out, 0.0)


def _robust_sd(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per row, 1.4826 x the median absolute deviation of ``x`` where ``mask``."""
    med = _masked_median(x, mask)
    return 1.4826 * _masked_median(np.abs(x - med[:, None]), mask)


def _axial_mean(angles: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per row, :func:`~seqshape.model.smooth.axial_mean` of ``angles`` where ``mask``."""
    n = np.maximum(mask.sum(axis=1), 1)
    s = np.where(mask, np.sin(2 * angles), 0.0).sum(axis=1) / n
    c = np.where(mask, np.cos(2 * angles), 0.0).sum(axis=1) / n
    axis = 0.5 * np.arctan2(s, c)
    forward = (mask & (np.cos(angles - axis[:, None]) >= 0)).sum(axis=1)
    return wrap_angle(np.where(2 * forward >= mask.sum(axis=1), axis, axis + math.pi))


def _update_shapes(smoothers: Sequence[CausalSmoother], estimates: Sequence,
                   news: Sequence[np.ndarray]) -> None:
    """What :meth:`CausalSmoother.update_estimate` does to the shapes after the poses, for
    every track (in place): the track's shape average (with a ``shape_decay``: the canonical
    shapes' decayed sums, ``CausalSmoother._average_shape``) placed where the decoder would
    have put it, then moved rigidly with the smoothed pose ``news[i]``
    (:func:`~seqshape.model.smooth.place_shapes`), the two transforms composed into one
    (float32 out: equal to the two steps' to its rounding). The transforms are computed for
    all tracks at once, the shapes in groups of :data:`SHAPE_CHUNK_BYTES`."""
    if len({np.shape(est.complete) for est in estimates}) > 1:
        for sm, est, new in zip(smoothers, estimates, news, strict=True):
            sm._apply(est, new)  # shapes of several sizes: one track at a time
        return
    k = len(estimates)
    pose = np.array([est.pose for est in estimates], dtype=np.float64)  # (K, 4)
    new = np.array(news, dtype=np.float64)
    rot = np.broadcast_to(np.eye(3), (k, 3, 3)).copy()  # (K, 3, 3): placed = src @ rot + off
    off = np.zeros((k, 3))
    avg = np.array([sm.shape_decay is not None for sm in smoothers])
    own = pose.copy()  # the decoder's frame: a flip turned the yaw, not the shape
    flips = np.array([bool(getattr(est, "flipped", False)) for est in estimates])
    own[:, 3] = wrap_angle(own[:, 3] + np.where(flips, math.pi, 0.0))
    r_own = yaw_to_rotmat(own[:, 3])
    decay = np.array([sm.shape_decay ** sm._step if a else 0.0
                      for sm, a in zip(smoothers, avg, strict=True)])
    mass = np.array([(decay[i] * sm._shape_mass if sm._shape_sum is not None else 0.0)
                     + sm._weights[-1] if avg[i] else 0.0 for i, sm in enumerate(smoothers)])
    mean = avg & (mass > 0)  # the average, placed with the decoder's pose
    rot[mean], off[mean] = np.swapaxes(r_own[mean], 1, 2), own[mean, :3]
    moved = ~np.all(pose == new, axis=1)
    if moved.any():  # then from the estimate's pose (its front nearer the new yaw) to the new
        mine = pose[moved].copy()
        turn = np.abs(wrap_angle(mine[:, 3] - new[moved, 3])) > math.pi / 2
        mine[turn, 3] = wrap_angle(mine[turn, 3] + math.pi)
        step = yaw_to_rotmat(mine[:, 3]) @ np.swapaxes(yaw_to_rotmat(new[moved, 3]), 1, 2)
        rot[moved] = rot[moved] @ step
        off[moved] = ((off[moved] - mine[:, :3])[:, None, :] @ step)[:, 0] + new[moved, :3]
    size = 3 * 8 * max(1, int(np.prod(np.shape(estimates[0].complete)[:-1])))
    chunk = max(1, SHAPE_CHUNK_BYTES // size)
    for lo in range(0, k, chunk):
        part = slice(lo, lo + chunk)
        src = np.stack([np.asarray(est.complete, dtype=np.float64)
                        for est in estimates[part]])  # (C, N, 3) sensor frame
        if avg[part].any():
            canonical = (src - own[part, None, :3]) @ r_own[part]
            for j in np.flatnonzero(avg[part]):
                sm = smoothers[lo + j]
                if sm._shape_sum is None or sm._shape_sum.shape != canonical[j].shape:
                    sm._shape_sum, sm._shape_mass = np.zeros_like(canonical[j]), 0.0
                sm._shape_sum, sm._shape_mass = _decay_step(
                    sm._shape_sum, sm._shape_mass, canonical[j], sm._weights[-1],
                    decay[lo + j])
                if mean[lo + j]:
                    src[j] = sm._shape_sum / sm._shape_mass
        placed = (src @ rot[part] + off[part, None, :]).astype(np.float32)
        for j in np.flatnonzero(avg[part] | moved[part]):
            estimates[lo + j].complete = placed[j]
    for i in np.flatnonzero(moved):
        estimates[i].pose = news[i]
