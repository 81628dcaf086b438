"""Track-level pose smoothing for offline labelling (refinement ``"smooth"``).

Labelling is offline, so every estimate of a track is known at once. The per-frame pose
estimates of the network are noisy (tens of centimetres, and now and then a heading flipped
by 180 degrees), but a vehicle moves smoothly in the world. :func:`smooth_track_poses`:

1. maps every frame's estimated pose into a common world frame with the ego poses
   (``ego[t]`` maps frame t's sensor frame into the common frame);
2. fits the positions with a local robust quadratic in time: for each frame, the frames
   within ``window`` frames of it, weighted least squares with Tukey biweights recomputed
   from the residuals (``iterations`` times), so a few bad estimates do not pull the fit;
3. the heading: a vehicle that travels at least ``min_travel`` metres over the track takes the
   direction of its fitted velocity wherever it moves faster than ``min_speed`` m/s
   (vehicles drive forwards), less the sideslip of its centre in a turn (``sideslip``: the
   rear axle moves along the heading, the centre drifts to the inside by ``atan(arm *
   curvature)``, ``arm`` fitted per track to the estimated yaws), and blended with the
   estimated yaws where they are the more certain (``blend``). A track that does not
   travel that far (parked, or creeping) is refitted over all its frames at once as a
   straight line if that line follows the local fit within the estimates' noise
   (``line_tolerance``, ``line_sigmas``; a vehicle that stops or starts within the track is
   no constant-velocity line: it keeps the local fit); when that line's travel is within
   noise (``parked_constant``: 2.5 standard errors) the track is parked and takes the robust
   constant position instead (a line's slope only adds noise at the track's ends); its
   heading is the axial mean of the estimated headings (angles doubled, averaged, halved: a
   flip does not count against it), turned to the side most estimates point to;
4. maps the smoothed poses back into each frame's sensor frame.

A track as a tracker delivers it may have holes: frames are numbered from their timestamps
(:func:`frame_numbers`: a frame 0.5 s after the last is five frames on, not one), and a gap
longer than ``MAX_GAP`` seconds between two detections, or a jump of the estimated centre
faster than a vehicle moves (``MAX_SPEED`` plus ``JUMP_MARGIN``: another vehicle under the
same id), starts a new *segment* (:func:`track_segments`) that is smoothed on its own: no
fit, heading vote or shape average crosses it. A smoothed centre more than ``MAX_SHIFT``
metres from the frame's own estimate is not trusted (:func:`limit_shift`: the frame keeps its
estimate), so whatever a tracker delivers, the smoothers never move an estimate far.

Without ego poses the sensor's own motion is unknown, so the motion direction in the sensor
frame says nothing about the heading: the positions are still fitted (relative motion is
smooth too) and the heading of a track that moves relative to the sensor is, in each frame,
the axial mean of the estimates within ``2 * window`` frames of it.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from seqshape.errors import ConfigError
from seqshape.geometry import (
    canonical_to_sensor,
    matrix_to_pose,
    pose_to_matrix,
    sensor_to_canonical,
    wrap_angle,
    yaw_to_rotmat,
)


def _local_fit(t: np.ndarray, y: np.ndarray, window: float, iterations: int,
               scale: float, max_deg: int = 2, query: np.ndarray | None = None,
               prior: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Robust local polynomial (degree ``max_deg``) fit of ``y (T, D)`` over times ``t (T,)``,
    evaluated at ``query (Q,)`` (default ``t``): (values, slopes), each ``(Q, D)``. A query
    with at most one sample within ``window`` uses the nearest sample's window. ``prior (T,)``: the
    samples' weights, multiplied into the robust (Tukey) weights (None: equal).

    All queries are fitted at once: each query's window is padded to the longest with rows
    of weight 0 and a degree below ``max_deg`` leaves its higher columns at zero, so the
    minimum-norm least-squares solutions (batched pseudo-inverses, with the cut-off of
    ``numpy.linalg.lstsq``) are those of the per-query fits (tested against them)."""
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    query = t if query is None else np.asarray(query, dtype=np.float64)
    val = np.empty((len(query), y.shape[1]))
    slope = np.zeros_like(val)
    if len(query) == 0:
        return val, slope
    if math.isinf(window):  # every query's window is the whole track, every fit one-sided
        # (degree <= 1): one fit, at the samples' mid-time, evaluated along its line
        mid = np.array([0.5 * (t.min() + t.max())])
        v, s = _local_fit_batch(t, y, window, iterations, scale, max_deg, mid, prior)
        return v + s * (query - mid)[:, None], np.repeat(s, len(query), axis=0)
    # queries in chunks that keep the padded windows to a few million cells
    step = max(1, _CELLS // max(1, len(t) * (max_deg + 1) * max(1, y.shape[1])))
    for lo in range(0, len(query), step):
        part = slice(lo, lo + step)
        val[part], slope[part] = _local_fit_batch(t, y, window, iterations, scale, max_deg,
                                                  query[part], prior)
    return val, slope


_CELLS = 4_000_000  #: padded window cells per batch of queries in _local_fit


def _local_fit_batch(t, y, window, iterations, scale, max_deg, query, prior=None):
    offset = np.abs(t[None, :] - query[:, None])  # (Q, T)
    inside = offset <= window
    # a query with at most one sample in its window (a frame without points past a track's
    # last detection) takes the window of its nearest sample: one sample is no motion
    lonely = inside.sum(axis=1) < 2
    if lonely.any():
        near = t[np.argmin(offset[lonely], axis=1)]
        inside[lonely] = np.abs(t[None, :] - near[:, None]) <= window
    width = int(inside.sum(axis=1).max())
    idx = np.argsort(~inside, axis=1, kind="stable")[:, :width]  # each window's samples first
    valid = np.take_along_axis(inside, idx, axis=1)  # (Q, M)
    dt = np.where(valid, t[idx] - query[:, None], 0.0)
    # degree per query: at most the distinct times - 1, a line where the window is one-sided
    _, rank = np.unique(t, return_inverse=True)
    ranks = np.sort(np.where(valid, rank[idx], -1), axis=1)
    distinct = np.count_nonzero(np.diff(ranks, axis=1) != 0, axis=1) + (ranks[:, 0] >= 0)
    deg = np.minimum(max_deg, distinct - 1)
    sided = np.minimum(np.count_nonzero(valid & (dt < 0), axis=1),
                       np.count_nonzero(valid & (dt > 0), axis=1)) < window / 2
    deg = np.where(sided, np.minimum(deg, 1), deg)
    powers = np.arange(max_deg + 1)
    a = dt[:, :, None] ** powers  # (Q, M, P): 1, dt, dt^2
    a = np.where(powers[None, None, :] <= deg[:, None, None], a, 0.0)
    ys = y[idx]  # (Q, M, D)
    count = valid.sum(axis=1)
    cutoff = np.finfo(np.float64).eps * np.maximum(count, deg + 1)
    w0 = valid.astype(np.float64) if prior is None else np.where(valid, prior[idx], 0.0)
    w = w0
    for _ in range(iterations + 1):
        sw = np.sqrt(w)[:, :, None]
        coef = np.linalg.pinv(a * sw, rcond=cutoff) @ (ys * sw)  # (Q, P, D)
        r = np.linalg.norm(ys - a @ coef, axis=2)
        u = r / (4.685 * scale)
        tukey = np.where(valid & (u < 1), (1 - u ** 2) ** 2, 0.0)
        rejected = tukey.sum(axis=1) < deg + 1  # everything rejected: the prior weights alone
        w = tukey if prior is None else tukey * w0
        w[rejected] = w0[rejected]
    slope = np.where((deg >= 1)[:, None], coef[:, min(1, max_deg)], 0.0)
    return coef[:, 0], slope


def _axial(angles: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi/2, pi/2): a heading and its flip count as the same axis."""
    return (angles + np.pi / 2) % np.pi - np.pi / 2


def _noise(residuals: np.ndarray) -> float:
    """Per-axis standard deviation of 2-D ``residuals (N, 2)`` from their median length (the
    median distance of a 2-D normal is 1.177 sigma)."""
    return float(np.median(np.linalg.norm(residuals, axis=1))) / 1.177


def _robust_sd(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation (the standard deviation of a normal)."""
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def _windows(times: np.ndarray, query: np.ndarray, half: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """For each query, the samples of the sorted ``times`` within ``half`` of it, as a padded
    index matrix: ``(idx (Q, M), inside (Q, M))``, ``idx`` clipped into range where
    ``inside`` is False."""
    lo = np.searchsorted(times, query - half, side="left")
    hi = np.searchsorted(times, query + half, side="right")
    idx = lo[:, None] + np.arange(max(int((hi - lo).max()), 1))
    return np.minimum(idx, len(times) - 1), idx < hi[:, None]


def _window_median(values: np.ndarray, idx: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Median of ``values`` over each row's samples of :func:`_windows`; 0 for an empty row."""
    out = np.zeros(len(idx))
    some = inside.any(axis=1)
    # numpy.nanmedian of the rows, without its masked-array path (the rows are short):
    # sorted, the NaNs last, the mean of the middle one or two of each row's n samples
    ordered = np.sort(np.where(inside[some], values[idx[some]], np.nan), axis=1)
    n = inside[some].sum(axis=1)
    rows = np.arange(len(ordered))
    out[some] = (ordered[rows, (n - 1) // 2] + ordered[rows, n // 2]) / 2
    return out


#: Largest distance (m) from the rear axle to the box centre :func:`_sideslip` will fit.
MAX_REAR_ARM = 4.0
#: Largest sideslip (rad) :func:`_sideslip` returns (a car at full lock: about 17 degrees).
MAX_SIDESLIP = np.radians(25.0)
#: Half-width (frames) of the running median of the path's curvature in :func:`_sideslip`.
CURVATURE_HALF = 4
#: RMS curvature (1/m) of a track's moving frames below which it counts as straight and gets no
#: rear-axle arm (radius 10 km: a road's own curvature is larger, rounding noise far smaller;
#: an arm fitted to noise would turn the heading at the track's next real bend).
MIN_RMS_CURVATURE = 1e-4


def _sideslip(t: np.ndarray, direction: np.ndarray, step: np.ndarray, yaws: np.ndarray,
              valid: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """The angle (rad) between the motion direction of a vehicle's box centre and its heading,
    per frame: ``atan(arm * curvature)``. A vehicle turns about its rear axle (kinematic
    bicycle), so the centre, ``arm`` metres ahead of the axle, drifts to the inside of the
    turn. The curvature is that of the fitted path (change of ``direction`` per metre,
    ``step`` metres per frame); ``arm``, one number per track, is fitted to the estimated
    ``yaws`` of the valid moving frames (their offsets from the motion direction, modulo pi,
    least squares with one round of 3-MAD outlier rejection, clipped to [0,
    MAX_REAR_ARM]). A straight track (RMS curvature under :data:`MIN_RMS_CURVATURE`) gets
    no correction."""
    theta = np.unwrap(direction)
    curv = np.zeros(len(t))
    if len(t) > 1:
        rate = np.gradient(theta, t)  # rad per frame
        curv = np.where(step > 1e-6, rate / np.maximum(step, 1e-6), 0.0)
        # a running median over +-CURVATURE_HALF frames: the fit's degree changes near the
        # track's ends, which puts a kink, not a turn, into the direction
        curv = _window_median(curv, *_windows(t, t, CURVATURE_HALF))
    use = valid & moving
    k = curv[use]
    off = _axial((yaws - direction[valid])[use[valid]])  # a flip counts as its axis
    if len(k) < 3 or float(np.sqrt(np.mean(k * k))) < MIN_RMS_CURVATURE:
        return np.zeros(len(t))
    keep = np.ones(len(k), bool)
    for _ in range(2):
        arm = -float(np.sum(k[keep] * off[keep]) / max(np.sum(k[keep] ** 2), 1e-12))
        r = off + arm * k
        keep = np.abs(r) <= 3.0 * max(_robust_sd(r), 1e-3)
        if keep.sum() < 3:
            break
    arm = float(np.clip(arm, 0.0, MAX_REAR_ARM))
    return np.clip(np.arctan(arm * curv), -MAX_SIDESLIP, MAX_SIDESLIP)


def _blend(tv: np.ndarray, t: np.ndarray, residuals: np.ndarray, yaws: np.ndarray,
           model: np.ndarray, step: np.ndarray, window: float) -> np.ndarray:
    """Per frame, the share of the estimated yaws' local median offset from the motion
    heading ``model`` (at the valid times ``tv``) to add to it: inverse-variance weights of
    the motion direction (the centres' noise over the speed and the window's time spread) and
    of the median of the estimates within ``window`` (their robust spread over the square
    root of their count). A slow or noisy track leans on its estimates, a fast one on its
    motion."""
    off = _axial(yaws - model)
    idx, inside = _windows(tv, t, window)
    count = inside.sum(axis=1)
    spread = np.where(inside, (tv[idx] - t[:, None]) ** 2, 0.0).sum(axis=1)
    var_dir = _noise(residuals) ** 2 / np.maximum(step ** 2 * np.maximum(spread, 1.0), 1e-12)
    var_med = (1.2533 * _robust_sd(off)) ** 2 / np.maximum(count, 1)
    weight = np.where(count > 0, var_dir / np.maximum(var_dir + var_med, 1e-12), 0.0)
    return weight * _window_median(off, idx, inside)


def axial_mean(angles) -> float:
    """Mean direction of ``angles`` ignoring 180-degree flips, turned to the majority side."""
    angles = np.asarray(angles, dtype=np.float64)
    axis = 0.5 * np.arctan2(np.sin(2 * angles).mean(), np.cos(2 * angles).mean())
    forward = np.cos(angles - axis) >= 0
    return float(wrap_angle(axis if forward.mean() >= 0.5 else axis + np.pi))


#: Points (after the network's subset) at which a frame's estimate counts fully in the
#: smoothers' position fits; a frame with n < FULL_POINTS points weighs (n / FULL_POINTS)^2
#: (:func:`frame_weights`).
FULL_POINTS = 160
#: Detections over which a track's first estimates weigh less in the smoothers' fits: the
#: k-th detection weighs min(1, k / RAMP) (:func:`frame_weights`).
RAMP = 16


def frame_weights(counts, full_points: float | None = FULL_POINTS,
                  ramp: float | None = RAMP) -> np.ndarray:
    """``(T,)`` weights of a track's frame estimates in the smoothers' position fits, from the
    points each frame had, ``counts (T,)``: ``min(1, n / full_points) ** 2`` (an estimate from
    a few points is noisier: its centre error grows as the points thin out) times
    ``min(1, k / ramp)`` at the track's k-th frame with points (the sequential model's first
    estimates have fused little). None turns a factor off. A frame without points weighs 0.
    Measured in docs/model.md, "Causal pose smoothing (online)"."""
    counts = np.asarray(counts, dtype=np.float64).reshape(-1)
    check_weighting("frame_weights", full_points, ramp)
    return _weights(counts, np.cumsum(counts > 0), full_points, ramp)


def _weights(counts: np.ndarray, detections: np.ndarray, full_points, ramp) -> np.ndarray:
    """:func:`frame_weights` of frames with ``counts`` points at their track's
    ``detections``-th frame with points."""
    w = (counts > 0).astype(np.float64)
    if full_points is not None:
        w *= np.minimum(1.0, counts / float(full_points)) ** 2
    if ramp is not None:
        w *= np.minimum(1.0, detections / float(ramp))
    return w


def check_weighting(owner: str, full_points, ramp) -> None:
    """Raise a ConfigError naming ``owner`` unless ``full_points`` and ``ramp`` (of
    :func:`frame_weights`) are each None or a positive finite number."""
    for name, value in (("full_points", full_points), ("ramp", ramp)):
        if value is not None and (isinstance(value, bool) or not isinstance(
                value, int | float | np.integer | np.floating) or not value > 0
                or not math.isfinite(value)):
            raise ConfigError(f"{owner} {name} must be a positive number or None, got "
                              f"{value!r}")


#: Longest time (s) between two detections of a track that the smoothers bridge: a longer gap
#: (a track lost and found again) starts a new segment (:func:`track_segments`). A vehicle can
#: turn, stop or be another vehicle after a few seconds; within one second a 10 Hz track is
#: at most ten frames apart, which the local fits span.
MAX_GAP = 1.0
#: Fastest (m/s) an estimated centre may move between two detections in the fixed frame before
#: :func:`track_segments` calls it another vehicle (an identity switch of the tracker).
MAX_SPEED = 40.0
#: Metres on top of ``MAX_SPEED * dt`` for the two estimates' own errors (:func:`track_segments`).
JUMP_MARGIN = 2.5
#: Largest planar distance (m) a smoother may move a frame's estimated centre
#: (:func:`limit_shift`): a bound on what a fit pulled by another vehicle can do. The
#: smoothers' corrections are tens of centimetres, but they rightly move an outlier estimate
#: by more: 1.5 m cost the traffic set's causal translation 0.8 % (docs/history/model.md).
MAX_SHIFT = 3.0


def frame_numbers(times, n: int) -> np.ndarray:
    """``(n,)`` whole frame numbers (float) of a track's frames from their ``times`` (s): the
    time since the first frame in periods of the track's median step, rounded, and at least
    one more than the previous frame's; ``0..n-1`` without times (or with no step > 0).

    >>> frame_numbers([0.0, 0.1, 0.2, 0.7, 0.8], 5).tolist()
    [0.0, 1.0, 2.0, 7.0, 8.0]
    """
    if times is None:
        return np.arange(n, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    steps = np.diff(t)
    steps = steps[steps > 0]
    if len(t) != n or len(steps) == 0 or not np.all(np.isfinite(t)):
        return np.arange(n, dtype=np.float64)
    f = np.round((t - t[0]) / float(np.median(steps)))
    return np.maximum.accumulate(f - np.arange(n)) + np.arange(n)  # strictly increasing


#: Hardest acceleration (m/s^2) :class:`SegmentRule` allows a vehicle between detections.
MAX_ACCEL = 8.0
#: Seconds of a segment's past over which :class:`SegmentRule` measures its velocity.
VELOCITY_SPAN = 0.5


class SegmentRule:
    """Where a track's segments start, detection by detection (:func:`track_segments` over a
    whole track, :class:`CausalSmoother` online).

    A detection starts a new segment when it comes more than ``max_gap`` seconds after the
    previous one, or when its planar centre in a fixed frame is further from where the
    segment's motion puts it than ``margin`` plus what an acceleration of ``MAX_ACCEL`` and a
    1 m/s error of the measured velocity allow: the velocity comes from the segment's
    detections over the last ``VELOCITY_SPAN`` seconds; before a segment has two detections the
    centre may have moved ``max_speed * dt`` instead. A vehicle under the same id that is not
    where the track was going (a tracker's identity switch, even to the next lane) starts a new
    segment. Without times one ``period`` per detection; without centres (no fixed frame) or
    with ``max_speed=inf`` only holes count.
    """

    def __init__(self, max_gap: float = MAX_GAP, max_speed: float = MAX_SPEED,
                 margin: float = JUMP_MARGIN, period: float = 0.1):
        self.max_gap, self.max_speed, self.margin = float(max_gap), float(max_speed), \
            float(margin)
        self.period = float(period)
        self._recent: deque = deque()  # (time, centre) of the segment's latest detections
        self._clock = 0.0  # time of the last detection when times are unknown

    def step(self, time: float | None, centre) -> bool:
        """Feed one detection (``time`` s or None, ``centre`` (2,) in a fixed frame or None);
        True when it starts a new segment (the first detection of a track does not)."""
        t = self._clock + self.period if time is None else float(time)
        c = None if centre is None else np.asarray(centre, dtype=np.float64)[:2]
        new = False
        if self._recent:
            t0, c0 = self._recent[-1]
            dt = t - t0
            if time is not None and dt > self.max_gap:
                new = True
            elif c is not None and c0 is not None:
                new = float(np.linalg.norm(c - self._predict(t))) > self._allowed(dt)
        if new:
            self._recent.clear()
        self._recent.append((t, c))
        while len(self._recent) > 2 and self._recent[-1][0] - self._recent[1][0] \
                >= VELOCITY_SPAN:
            self._recent.popleft()
        self._clock = t
        return new

    def _predict(self, t: float) -> np.ndarray:
        """Where the segment's motion puts the centre at time ``t``."""
        t1, c1 = self._recent[-1]
        t0, c0 = self._recent[0]
        if len(self._recent) < 2 or c0 is None or t1 - t0 <= 0:
            return c1
        return c1 + (c1 - c0) / (t1 - t0) * (t - t1)

    def _allowed(self, dt: float) -> float:
        """Metres a detection ``dt`` seconds on may lie from the prediction."""
        dt = max(dt, 0.0)
        if not math.isfinite(self.max_speed):  # max_speed=inf: no jump test
            return math.inf
        if len(self._recent) < 2 or self._recent[0][1] is None:
            return self.max_speed * dt + self.margin
        return self.margin + 0.5 * MAX_ACCEL * dt ** 2 + 1.0 * dt


def track_segments(times, valid, centres=None, max_gap: float = MAX_GAP,
                   max_speed: float = MAX_SPEED, margin: float = JUMP_MARGIN,
                   period: float = 0.1) -> np.ndarray:
    """``(T,)`` segment number of each frame of a track by :class:`SegmentRule` (a hole longer
    than ``max_gap`` seconds, or a detection whose centre is not where the segment was going);
    a frame without points belongs to the segment of the detection before it. ``times (T,)``
    in seconds, or None: one ``period`` per frame; ``centres (T, 2)`` planar centres in a
    fixed frame, or None (no jump test).

    >>> track_segments([0.0, 0.1, 0.2, 5.0, 5.1], [True] * 5).tolist()
    [0, 0, 0, 1, 1]
    """
    valid = np.asarray(valid, dtype=bool).reshape(-1)
    rule = SegmentRule(max_gap, max_speed, margin, period)
    seg = np.zeros(len(valid), dtype=np.int64)
    current = 0
    for i in range(len(valid)):
        if valid[i] and rule.step(None if times is None else float(times[i]),
                                  None if centres is None else centres[i]):
            current += 1
        seg[i] = current
    return seg


def limit_shift(smoothed: np.ndarray, poses: np.ndarray, valid=None,
                max_shift: float = MAX_SHIFT) -> np.ndarray:
    """``smoothed (T, 4)`` with every frame (of the ``valid`` ones: frames with points; None:
    all) whose planar centre moved more than ``max_shift`` metres from its estimate in
    ``poses (T, 4)`` put back to that estimate (a fit pulled by another vehicle never moves an
    estimate far). A frame without points has a stale estimate, which the fit's value at its
    time rightly leaves behind; how far it is carried is bounded by ``MAX_GAP``."""
    out = np.array(smoothed, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    far = np.linalg.norm(out[:, :2] - poses[:, :2], axis=1) > max_shift
    if valid is not None:
        far &= np.asarray(valid, dtype=bool).reshape(-1)
    out[far] = poses[far]
    return out


def world_centres(poses: np.ndarray, egos) -> np.ndarray | None:
    """``(T, 2)`` planar centres of ``poses (T, 4)`` in the fixed frame of ``egos`` (per frame
    a (4, 4) sensor -> fixed matrix); None unless every frame has one."""
    if egos is None or any(e is None for e in egos):
        return None
    e = np.asarray(list(egos), dtype=np.float64).reshape(-1, 4, 4)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    return (np.einsum("tij,tj->ti", e[:, :3, :3], poses[:, :3]) + e[:, :3, 3])[:, :2]


#: Robust reweighting rounds of the smoother's fits (:func:`smooth_track_poses`).
ITERATIONS = 3
#: Residual scale (m) of the smoother's Tukey weights (:func:`smooth_track_poses`).
SCALE = 0.3


def smooth_track_poses(poses, frames, ego=None, rate_hz: float = 10.0, window: int = 8,
                       iterations: int = ITERATIONS, scale: float = SCALE, min_travel: float = 3.0,
                       min_speed: float = 1.0, valid=None, line_tolerance: float = 0.05,
                       line_sigmas: float = 1.7, parked_constant: bool = True,
                       sideslip: bool = True, blend: bool = True, *,
                       local_fit=None, weights=None) -> np.ndarray:
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
        line_tolerance, line_sigmas: a track travelling less than ``min_travel`` takes the
            whole-track line only when, at 95 % of the fitted frames, the line lies within
            ``line_tolerance + line_sigmas * sigma`` metres of the local fit (sigma: the
            estimates' noise, from the local fit's median residual); otherwise (a vehicle
            that stops or starts within the track) it keeps the local fit.
        sideslip: a moving frame's heading is the motion direction corrected for the
            centre's drift to the inside of a turn (:func:`_sideslip`: the rear axle moves
            along the heading, the centre does not; up to 15-20 degrees in a tight turn),
            with the centre's distance from the rear axle fitted to the estimated yaws.
            False: the motion direction alone.
        blend: add to a moving frame's heading the estimated yaws' median offset from it
            over the frames within ``window``, weighted by how much less certain the motion
            direction is than that median (:func:`_blend`).
        parked_constant: a short track whose line travels less than 2.5 standard errors of
            a line's travel (``sigma * sqrt(12 / n)`` over n fitted frames) takes the robust
            constant position over the whole track instead.
        valid: ``(T,)`` bool, the frames whose estimates are fitted (default all); the others
            (frames without points, whose estimates are stale) get the fit's value at their
            time. With no valid frame the poses are returned unchanged.
        weights: ``(T,)`` non-negative weights of the frames' estimates in the position fits
            (:func:`frame_weights`), multiplied into the robust weights; a frame of weight 0
            is not fitted, as an invalid one. None: equal weights.
        local_fit: None, or a callable ``(tv, y, t, prior) -> (pos, vel)`` that stands in for
            the local fit ``_local_fit(tv, y, window, iterations, scale, query=t,
            prior=prior)`` of the positions ``y`` at the valid frames' times ``tv`` with their
            weights ``prior`` (:class:`CausalSmoother` passes one that keeps the fits that can
            no longer change).
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    t = np.asarray(frames, dtype=np.float64).reshape(-1)
    if len(poses) != len(t):
        raise ValueError(f"{len(poses)} poses but {len(t)} frames")
    if len(poses) == 0:
        return poses.copy()
    valid = np.ones(len(t), bool) if valid is None else np.asarray(valid, bool).reshape(-1)
    prior = None
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64).reshape(-1)
        if len(weights) != len(t) or not np.all(np.isfinite(weights)) or np.any(weights < 0):
            raise ValueError(f"weights must be {len(t)} finite non-negative numbers")
        valid = valid & (weights > 0)
        prior = weights[valid]
    if not valid.any():
        return poses.copy()
    e = np.broadcast_to(np.eye(4), (len(t), 4, 4)) if ego is None else np.asarray(
        ego, dtype=np.float64).reshape(-1, 4, 4)
    world = np.einsum("tij,tjk->tik", e, pose_to_matrix(poses))
    w = matrix_to_pose(world)[valid]  # (V, 4): yaw about the common frame's z
    tv = t[valid]
    if local_fit is None:
        pos, vel = _local_fit(tv, w[:, :3], window, iterations, scale, query=t, prior=prior)
    else:
        pos, vel = local_fit(tv, w[:, :3], t, prior)
    travel = float(np.linalg.norm(pos[valid][-1, :2] - pos[valid][0, :2]))
    if travel < min_travel:  # parked or creeping: one robust line over the whole track,
        # unless the vehicle stopped or started within the track (a line through a stop
        # misplaces frames by metres): the line must follow the local fit within what the
        # estimates' noise lets the local fit wander (sigma from its residuals)
        sigma = _noise(w[:, :2] - pos[valid, :2])
        line, line_vel = _local_fit(tv, w[:, :3], np.inf, iterations, scale, max_deg=1,
                                    query=t, prior=prior)
        off = np.linalg.norm(line[valid, :2] - pos[valid, :2], axis=1)
        if float(np.quantile(off, 0.95)) <= line_tolerance + line_sigmas * sigma:
            pos, vel = line, line_vel
            # a parked car: the line's travel within 2.5 times its standard error per axis
            # (sigma * sqrt(12 / n) for n frames evenly spread; a 2-D drift of pure noise
            # exceeds that in 4 % of tracks) -> a constant position
            span = float(tv.max() - tv.min())
            drift = float(np.linalg.norm(line_vel[0, :2])) * span
            if parked_constant and drift <= 2.5 * sigma * np.sqrt(12.0 / len(tv)):
                pos, vel = _local_fit(tv, w[:, :3], np.inf, iterations, scale, max_deg=0,
                                      query=t, prior=prior)
    speed = np.linalg.norm(vel[:, :2], axis=1) * rate_hz  # m/s
    yaw = np.full(len(t), axial_mean(w[:, 3]))
    if travel >= min_travel:
        if ego is None:  # sensor motion unknown: no heading from motion, local axial means
            yaw = np.array([axial_mean(w[np.abs(tv - ti) <= 2 * window, 3])
                            if np.any(np.abs(tv - ti) <= 2 * window) else np.nan for ti in t])
            yaw = np.where(np.isfinite(yaw), yaw, axial_mean(w[:, 3]))
        else:
            moving = speed >= min_speed
            direction = np.arctan2(vel[:, 1], vel[:, 0])
            yaw[moving] = direction[moving]
            if sideslip:
                yaw[moving] -= _sideslip(t, direction, speed / rate_hz, w[:, 3], valid,
                                         moving)[moving]
            if blend:
                yaw[moving] += _blend(tv, t, w[:, :2] - pos[valid, :2], w[:, 3],
                                      yaw[valid], speed / rate_hz, window)[moving]
    smooth = pose_to_matrix(np.c_[pos, yaw])
    back = np.einsum("tij,tjk->tik", np.linalg.inv(e), smooth)
    return matrix_to_pose(back)


def place_shapes(complete: np.ndarray, own: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Shapes ``complete`` (T, K, 3) estimated with poses ``own`` (T, 4), moved to ``poses``:
    each taken into its canonical frame with its own pose (turned by pi when that is nearer
    the new yaw: the shape stays where it was estimated, only its front is relabelled) and
    placed with the new pose. Frames whose pose is unchanged keep their shape as it is."""
    out = np.array(complete, dtype=np.float32)
    kind = np.asarray(complete).dtype
    between = kind if kind.kind == "f" else np.dtype(np.float64)
    own = np.asarray(own, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    moved = np.flatnonzero(~np.all(own == poses, axis=1))
    if len(moved) == 0:
        return out
    # all moved frames at once, the operations of geometry.sensor_to_canonical and
    # canonical_to_sensor frame by frame (the canonical shape in the input's float type)
    mine = own[moved].copy()
    turn = np.abs(wrap_angle(mine[:, 3] - poses[moved, 3])) > math.pi / 2
    mine[turn, 3] = wrap_angle(mine[turn, 3] + math.pi)
    new = poses[moved]
    canonical = ((np.asarray(complete)[moved].astype(np.float64) - mine[:, None, :3])
                 @ yaw_to_rotmat(mine[:, 3])).astype(between)
    out[moved] = (canonical.astype(np.float64) @ np.swapaxes(yaw_to_rotmat(new[:, 3]), 1, 2)
                  + new[:, None, :3]).astype(np.float32)
    return out


#: Per-frame decay of the track shape average (:func:`average_shapes`, :class:`CausalSmoother`):
#: frame j's shape weighs ``SHAPE_DECAY ** |t - j|`` (times its frame weight) at frame t. 1
#: (no decay) measured 0.02-0.04 cm of CD better on the synthetic sets; 0.95 forgets within
#: a few seconds what a real tracker's identity switch or a changed vehicle brought in.
SHAPE_DECAY = 0.95


def check_decay(owner: str, decay) -> None:
    """Raise a ConfigError naming ``owner`` unless ``decay`` is None or in (0, 1]."""
    if decay is not None and (isinstance(decay, bool) or not isinstance(
            decay, int | float | np.integer | np.floating) or not 0.0 < decay <= 1.0):
        raise ConfigError(f"{owner} shape_decay must be in (0, 1] or None, got {decay!r}")


def average_shapes(complete, poses, weights, decay: float = SHAPE_DECAY,
                   causal: bool = True, frames=None, segments=None) -> np.ndarray:
    """A track's complete shapes averaged point by point in their canonical frames.

    The decoder's outputs are slots: output k of one frame and of the next are the same part
    of the vehicle in the canonical frame (the decoder is a fixed function of the track state),
    so a track's canonical shapes can be averaged slot by slot; what varies from frame to frame
    in a slot is mostly the network's noise. Frame t gets the average over frames j (``j <=
    t`` if ``causal``, else all) weighted ``weights[j] * decay ** |t - j|``, placed with its
    own pose (a frame before any weight keeps its own shape).

    Args:
        complete: ``(T, K, 3)`` shapes, each in its frame's sensor frame.
        poses: ``(T, 4)`` the poses the shapes were decoded in (the network's, before a
            heading flip turned a yaw by pi: the canonical frame must be the decoder's).
        weights: ``(T,)`` non-negative (:func:`frame_weights`; 0: the frame adds nothing).
        decay: per-frame decay in (0, 1]; 1 averages the whole past (or track) evenly.
        frames: ``(T,)`` frame numbers (:func:`frame_numbers`; None: ``0..T-1``): the decay
            counts frames, so a frame after a hole weighs the frames before it less.
        segments: ``(T,)`` segment numbers (:func:`track_segments`; None: one): no average
            crosses a segment's border.
    Returns ``(T, K, 3)`` float32.
    """
    check_decay("average_shapes", decay)
    complete = np.asarray(complete)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if complete.ndim != 3 or complete.shape[-1] != 3 or not len(complete) == len(poses) \
            == len(w):
        raise ValueError(f"complete {complete.shape}, poses {poses.shape} and weights "
                         f"{w.shape} do not describe one track")
    canonical = np.stack([sensor_to_canonical(c.astype(np.float64), p)
                          for c, p in zip(complete, poses, strict=True)]) \
        if len(complete) else np.zeros(complete.shape)
    factors = _decay_factors(len(w), decay, frames, segments)
    total, mass = _decayed_sums(canonical, w, factors)
    if not causal:  # add the frames after t: the reversed run, less frame t counted twice
        back, back_mass = _decayed_sums(canonical[::-1], w[::-1],
                                        np.r_[0.0, factors[::-1][:-1]])
        total = total + back[::-1] - w[:, None, None] * canonical
        mass = mass + back_mass[::-1] - w
    out = np.array(complete, dtype=np.float32)
    for t in np.flatnonzero(mass > 0):
        out[t] = canonical_to_sensor(total[t] / mass[t], poses[t])
    return out


def _decay_factors(n: int, decay: float, frames=None, segments=None) -> np.ndarray:
    """``(n,)`` factor by which frame t's running shape sums keep frame t-1's: ``decay`` to
    the power of the frames between them, 0 where a new segment starts (factor 0 of frame 0)."""
    steps = np.diff(frame_numbers(None, n) if frames is None
                    else np.asarray(frames, dtype=np.float64).reshape(-1))
    factors = np.r_[0.0, float(decay) ** steps]
    if segments is not None:
        segments = np.asarray(segments).reshape(-1)
        factors[1:][segments[1:] != segments[:-1]] = 0.0
    return factors


def _decayed_sums(canonical: np.ndarray, w: np.ndarray, factors: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per frame t, ``sum_j<=t f(j, t) w_j canonical_j`` and ``sum_j<=t f(j, t) w_j``, where
    ``f(j, t)`` is the product of ``factors`` over ``j+1..t`` (:func:`_decay_factors`)."""
    total, mass = np.zeros_like(canonical), np.zeros(len(w))
    run, run_mass = np.zeros(canonical.shape[1:]), 0.0
    for t in range(len(w)):
        run, run_mass = _decay_step(run, run_mass, canonical[t], w[t], factors[t])
        total[t], mass[t] = run, run_mass
    return total, mass


def _decay_step(total: np.ndarray, mass: float, canonical: np.ndarray, w: float,
                decay: float) -> tuple[np.ndarray, float]:
    """One frame of the shape average's decayed sums (:func:`average_shapes` over a track,
    :class:`CausalSmoother` frame by frame)."""
    return decay * total + w * canonical, decay * mass + w


#: Frames of a track's past that :class:`CausalSmoother` fits (the oldest are dropped).
CAUSAL_HISTORY = 64
#: Half-width (frames) of the causal smoother's local fit: it sees only the past half.
CAUSAL_WINDOW = 5
#: Frames with points a track needs before the causal smoother replaces its estimates.
CAUSAL_MIN_FRAMES = 5


class CausalSmoother:
    """Online (causal) pose smoothing of one track: each new estimate is replaced by the value
    at the newest frame of :func:`smooth_track_poses` fitted to the track's past estimates
    (at most ``history`` frames, this one included), so it uses frames ``<= t`` only.

    The fit is the offline smoother's (robust local quadratic of the centres in the fixed
    frame of the ego poses, a whole-history line or constant for a parked or creeping track,
    the heading of a moving track from its motion) with a local window of ``window`` frames,
    of which only the past half exists. Two differences make it safe to run online:

    * until the track has had ``min_frames`` frames with points the estimate is returned as
      it is (a motion direction from two or three noisy centres is worse than the network);
    * the smoother sets the heading *axis*; which end is the front stays the estimate's (the
      network's and the online heading step's, as with the placement refiner): a smoothed yaw
      more than 90 degrees from the estimate's is turned by pi (``keep_front=False``: the
      smoother's own heading, measured worse, docs/model.md).

    Each frame's estimate weighs in the position fits by :func:`frame_weights` of the points
    it had (``full_points``) and of how many detections the track had then (``ramp``); None
    turns either off (equal weights, the smoother before session 30).

    :meth:`update_estimate` also replaces the shape by the track's shape average so far
    (:func:`average_shapes`: the canonical shapes averaged slot by slot, frame j weighted by
    its frame weight times ``shape_decay ** (t - j)``); ``shape_decay=None``: the shape only
    moves rigidly with the smoothed pose.

    Frames are numbered by their times (a frame after a hole of the tracker's is as many frames
    on as the time says), and a detection more than ``max_gap`` seconds after the previous one,
    or a jump of the centre faster than a vehicle drives (:func:`track_segments`), starts a new
    segment: the smoother forgets the track's past (poses and shape average) and lets estimates
    through until ``min_frames`` new detections; a smoothed centre more than ``MAX_SHIFT`` from
    the estimate is not trusted (:func:`limit_shift`).

    Measured in docs/model.md, "Causal pose smoothing (online)". ``update`` costs one
    :func:`smooth_track_poses` over the history, whose local fits it keeps from frame to frame
    where they can no longer change (only the newest ``window + 1`` frames' are refitted, and
    the first frames' as the history drops its oldest): about 1-2 ms per track and frame.
    :class:`~seqshape.model.estimator.Estimator` updates the smoothers of all the tracks of a
    step at once instead (:func:`seqshape.model.causal.update_estimates`: the same bookkeeping,
    the newest frame's fit of every track in one vectorised pass, equal to this to rounding;
    0.1-0.2 ms per track at 100 tracks); this class's :meth:`update` stays the reference.
    """

    def __init__(self, window: int = CAUSAL_WINDOW, history: int = CAUSAL_HISTORY,
                 min_frames: int = CAUSAL_MIN_FRAMES, keep_front: bool = True,
                 full_points: float | None = FULL_POINTS, ramp: float | None = RAMP,
                 shape_decay: float | None = SHAPE_DECAY, max_gap: float = MAX_GAP,
                 max_speed: float = MAX_SPEED, max_shift: float = MAX_SHIFT):
        for name, value, low in (("window", window, 1), ("history", history, 2),
                                 ("min_frames", min_frames, 1)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) \
                    or value < low:
                raise ConfigError(f"CausalSmoother {name} must be a whole number >= {low}, "
                                  f"got {value!r}")
        check_weighting("CausalSmoother", full_points, ramp)
        check_decay("CausalSmoother", shape_decay)
        for name, value in (("max_gap", max_gap), ("max_speed", max_speed),
                            ("max_shift", max_shift)):
            if isinstance(value, bool) or not isinstance(
                    value, int | float | np.integer | np.floating) or not value > 0:
                raise ConfigError(f"CausalSmoother {name} must be a positive number (inf: "
                                  f"never), got {value!r}")
        self.window, self.min_frames = int(window), int(min_frames)
        self.keep_front = bool(keep_front)
        self.full_points, self.ramp = full_points, ramp
        self.shape_decay = shape_decay
        self.history, self.max_gap = int(history), float(max_gap)
        self.max_speed, self.max_shift = float(max_speed), float(max_shift)
        self.detections = 0  # the track's detections (the frame weights' ramp counts them)
        self.segments = 0  # segments started after the first (gaps, jumps)
        self._rule = SegmentRule(self.max_gap, self.max_speed)  # where segments start
        self._last_detection: float | None = None  # time (s) of the last frame with points
        self._steps: deque = deque(maxlen=16)  # the track's first time steps (s)
        self._start_segment()

    def _start_segment(self) -> None:
        """Forget the past: a new segment of the track starts with the next frame."""
        # the decayed, weighted sum of the canonical shapes so far and its weight
        self._shape_sum: np.ndarray | None = None
        self._shape_mass = 0.0
        self._poses: deque = deque(maxlen=self.history)
        self._valid: deque = deque(maxlen=self.history)
        self._weights: deque = deque(maxlen=self.history)
        self._egos: deque = deque(maxlen=self.history)
        self._times: deque = deque(maxlen=self.history)
        self._frames: deque = deque(maxlen=self.history)  # frame numbers (whole, float)
        self._dropped = -np.inf  # the newest frame number the history has dropped
        self._step = 1.0  # decay exponent of the shape sums at this frame (frames since last)
        self.segment_detections = 0
        # local fits that can no longer change, by frame number: those whose whole window
        # (+-window frames, with a sample) is in the history; with the fixed frame they
        # were made in (True: the ego poses', False: the sensor's)
        self._fits: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self._fixed: bool | None = None
        # the same for the vectorised path (seqshape.model.causal), by place in the history:
        # whether a frame's (position, velocity) fit is kept, and the fit
        self._kept = np.zeros(self.history, bool)
        self._kept_fit = np.zeros((self.history, 2, 3))

    def _advance(self, pose: np.ndarray, has_points: bool, ego, time: float | None,
                 rate_hz: float) -> float:
        """This frame's number; starts a new segment first when the frame is a detection too
        long after the last one or too far from it (:func:`track_segments`' rule)."""
        if has_points:
            centre = None if ego is None else (ego[:3, :3] @ pose[:3] + ego[:3, 3])[:2]
            self._rule.period = 1.0 / rate_hz  # the time per frame when there are no times
            if self._rule.step(time, centre):
                self._start_segment()
                self.segments += 1
            self._last_detection = time
        if not self._frames:
            return 0.0
        previous = self._times[-1]
        if time is None or not math.isfinite(previous):
            return self._frames[-1] + 1.0
        if time - previous > 0 and len(self._steps) < self._steps.maxlen:
            self._steps.append(time - previous)  # the track's first steps set its period
        if not self._steps:
            return self._frames[-1] + 1.0
        return self._frames[-1] + max(1.0, round((time - previous) / np.median(self._steps)))

    def update(self, pose, has_points: bool, ego=None, time: float | None = None,
               rate_hz: float = 10.0, num_points: int | None = None) -> np.ndarray:
        """The smoothed ``(4,)`` pose of this frame given its estimated ``pose`` (sensor
        frame), whether the frame had points (a frame without them is not fitted, it gets the
        fit's value), its ``ego`` pose ((4, 4) sensor -> fixed frame, or None: the fit is
        made in the sensor frames unless every remembered frame has one), its ``time``
        (s; the frame rate for the smoother's speed threshold comes from the remembered
        times, else ``rate_hz``) and how many points it had (``num_points``: its weight in
        the fits, :func:`frame_weights`; None: as many as count fully)."""
        pose, ego, time, smooth = self._record(pose, has_points, ego, time, rate_hz,
                                               num_points)
        if not smooth:
            return pose.copy()
        egos, rate_hz = self._fit_setup(rate_hz)
        out = smooth_track_poses(np.stack(self._poses), np.asarray(self._frames), egos,
                                 rate_hz=rate_hz, window=self.window,
                                 valid=np.asarray(self._valid),
                                 local_fit=self._local_fit,
                                 weights=np.asarray(self._weights))[-1]
        return self._finish(out, pose, has_points, time)

    def _record(self, pose, has_points: bool, ego, time: float | None, rate_hz: float,
                num_points: int | None) -> tuple[np.ndarray, np.ndarray | None, float | None,
                                                 bool]:
        """:meth:`update`'s bookkeeping of a new frame (its number, segment, weight; the
        arguments checked): ``(pose, ego, time, smooth)`` as arrays and floats, ``smooth``
        whether the frame's estimate is replaced by a fit (else it is returned as it is)."""
        if num_points is not None and (isinstance(num_points, bool) or not isinstance(
                num_points, int | np.integer) or num_points < 0):
            raise ConfigError(f"CausalSmoother.update num_points must be a whole number >= 0 "
                              f"or None, got {num_points!r}")
        pose = np.asarray(pose, dtype=np.float64).reshape(4)
        ego = None if ego is None else np.asarray(ego, dtype=np.float64)
        time = None if time is None else float(time)
        frame = self._advance(pose, bool(has_points), ego, time, rate_hz)
        self._step = frame - self._frames[-1] if self._frames else 1.0
        if len(self._frames) == self.history:  # the oldest frame leaves the history
            self._dropped = self._frames[0]
            self._kept[:-1], self._kept[-1] = self._kept[1:], False
            self._kept_fit[:-1] = self._kept_fit[1:]
        self._frames.append(frame)
        self._poses.append(pose.copy())
        self._valid.append(bool(has_points))
        self._egos.append(ego)
        self._times.append(np.nan if time is None else time)
        self.detections += bool(has_points)
        self.segment_detections += bool(has_points)
        n = np.inf if num_points is None else float(num_points)
        self._weights.append(float(_weights(np.array([n if has_points else 0.0]),
                                            np.array([self.detections]), self.full_points,
                                            self.ramp)[0]))
        smooth = self.segment_detections >= self.min_frames and any(self._valid)
        return pose, ego, time, smooth

    def _fit_setup(self, rate_hz: float) -> tuple[np.ndarray | None, float]:
        """``(egos (T, 4, 4) or None, rate_hz)`` of the fit over the history: the ego poses when
        every remembered frame has one, the frame rate from the remembered times."""
        egos = None if any(e is None for e in self._egos) else np.stack(self._egos)
        times = np.fromiter(self._times, np.float64, len(self._times))
        if len(times) > 1 and np.isfinite(times).all():
            steps = np.sort(np.diff(times))  # their median (numpy's, without its overhead)
            step = float((steps[(len(steps) - 1) // 2] + steps[len(steps) // 2]) / 2)
            rate_hz = 1.0 / step if step > 0 else rate_hz
        if self._fixed is not (egos is not None):  # another frame: no kept fit holds
            self._fits.clear()
            self._kept[:] = False
            self._fixed = egos is not None
        return egos, rate_hz

    def _finish(self, out: np.ndarray, pose: np.ndarray, has_points: bool,
                time: float | None) -> np.ndarray:
        """The fit's value ``out`` of the newest frame (estimate ``pose``) as :meth:`update`
        returns it: within ``max_shift`` of a detection, no further than ``max_gap`` from one,
        the front the estimate's (``keep_front``)."""
        if has_points:
            out = limit_shift(out[None], pose[None], max_shift=self.max_shift)[0]
        elif time is not None and self._last_detection is not None \
                and time - self._last_detection > self.max_gap:
            return pose.copy()  # a fit is carried no further than MAX_GAP from a detection
        if self.keep_front and abs(wrap_angle(out[3] - pose[3])) > math.pi / 2:
            out[3] = wrap_angle(out[3] + math.pi)  # the front stays the estimate's
        return out

    def _local_fit(self, tv: np.ndarray, y: np.ndarray, t: np.ndarray, prior=None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """``_local_fit(tv, y, window, iterations, scale, query=t, prior=prior)`` over the
        history (``t``: its frame numbers), taking the kept fits of frames whose window has not
        changed since and keeping the new ones whose window is complete: a fit uses the samples
        within ``window`` frames (their times relative to its own, exact for whole frame
        numbers, and their weights, fixed when a frame is added), so it is final once a frame
        ``window`` or more frames newer exists, until the history drops a frame of its window
        (or a new segment starts)."""
        w = self.window
        for k in [k for k in self._fits if k - w <= self._dropped]:
            del self._fits[k]
        n = len(t)
        pos, vel = np.empty((n, y.shape[1])), np.empty((n, y.shape[1]))
        todo = []
        for i in range(n):
            kept = self._fits.get(float(t[i]))
            if kept is None:
                todo.append(i)
            else:
                pos[i], vel[i] = kept
        if todo:
            pos[todo], vel[todo] = _local_fit(tv, y, w, ITERATIONS, SCALE, query=t[todo],
                                              prior=prior)
            newest = float(t[-1])
            lo = np.searchsorted(tv, t[todo] - w, side="left")
            hi = np.searchsorted(tv, t[todo] + w, side="right")
            for i, a, b in zip(todo, lo, hi, strict=True):
                if t[i] - w > self._dropped and t[i] + w <= newest and b - a >= 2:
                    self._fits[float(t[i])] = (pos[i].copy(), vel[i].copy())
        return pos, vel

    def update_estimate(self, est, ego=None, time: float | None = None,
                        rate_hz: float = 10.0) -> None:
        """:meth:`update` with an estimate (``.pose``, ``.complete``, ``.num_points`` and
        ``.flipped``, e.g. a :class:`~seqshape.model.estimator.Estimate`), in place: the pose
        replaced by the smoothed one and the complete shape moved rigidly with it; with
        ``shape_decay``, the shape replaced first by the track's shape average so far
        (:func:`average_shapes`, causal, with the frames' weights)."""
        self._apply(est, self.update(est.pose, est.num_points > 0, ego, time, rate_hz,
                                     est.num_points))

    def _apply(self, est, new: np.ndarray) -> None:
        """The estimate given its smoothed pose ``new`` (:meth:`update_estimate`), in place."""
        if self.shape_decay is not None:
            self._average_shape(est)
        if not np.array_equal(new, est.pose):  # moved rigidly with the smoothed pose
            est.complete = place_shapes(est.complete[None], est.pose[None], new[None])[0]
            est.pose = new

    def _average_shape(self, est) -> None:
        """The estimate's shape replaced by the track's shape average so far, in place
        (:meth:`update_estimate`, after :meth:`update` of the frame)."""
        # the decoder's frame: a heading flip turned the yaw by pi and kept the shape
        own = np.array(est.pose, dtype=np.float64)
        own[3] = wrap_angle(own[3] + (math.pi if getattr(est, "flipped", False) else 0.0))
        canonical = sensor_to_canonical(np.asarray(est.complete, dtype=np.float64), own)
        if self._shape_sum is None or self._shape_sum.shape != canonical.shape:
            self._shape_sum, self._shape_mass = np.zeros_like(canonical), 0.0
        self._shape_sum, self._shape_mass = _decay_step(
            self._shape_sum, self._shape_mass, canonical, self._weights[-1],
            self.shape_decay ** self._step)
        if self._shape_mass > 0:  # the average, where the decoder would have placed it
            est.complete = canonical_to_sensor(self._shape_sum / self._shape_mass,
                                               own).astype(np.float32)
