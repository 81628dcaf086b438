"""Heading post-processing: undo 180-degree flips of the network's yaw, per track.

A partial view of a vehicle is nearly symmetric front to back, so the network's yaw is
sometimes off by pi. Three pieces of evidence disambiguate it, all over the track rather than
one frame:

* **motion**: vehicles drive forwards. The track's estimated centres, in a FIXED frame, are
  fitted with a straight line over the last ``motion_frames`` frames with points; when the
  fitted travel is at least ``min_travel`` and the positions advance steadily along it
  (correlation of frame order and position along the line at least ``min_consistency``), its
  direction is the heading up to the vehicle reversing. Sensor-frame positions are confounded
  by the ego vehicle's own motion (a parked car passed by the ego "moves" backwards), so this is
  used only with per-frame ego poses (sensor frame -> fixed frame) or when the sensor is
  declared static (``static_sensor``, e.g. the synthetic generator's).
* **vote** (on by default in a fixed frame): a decaying vote of the raw yaws (unit vectors in
  the fixed frame; with ``vote_fixed_only=False`` also in the sensor frame when there are no
  ego poses), with the motion-confirmed headings weighted ``motion_weight``. Where motion gives
  no answer, a raw yaw more than 90 degrees from the vote is flipped: a flip of a parked or
  slow vehicle is outvoted by the track's other frames (a parked car passed by the ego is seen
  from many sides, and the views that show its front outvote the ambiguous ones).
* **shape** (opt-in, ``shape=True``; needs the frame's points, ``update(..., points=...)``):
  where motion has given no answer on the track so far (a parked car, the first frames of a
  track), the observed points, accumulated over the track in the estimated box frame (x along
  the track's axis; frames more than ``shape_max_turn`` off the axis left out), form a side
  silhouette (:class:`EndProfile`). Cars and vans are front-low: a hood before the
  windscreen, a sedan's boot deck higher than its bonnet, the tall near-vertical tail of a
  hatchback, SUV or van; and the roof sits behind the middle. The score
  ``ends - shape_weight * roof`` (end-height difference and roof offset of the silhouette)
  names the front when its size reaches ``shape_margin``. The step abstains unless both ends
  were observed (``shape_min_points`` points in each end quarter of an extent of
  ``shape_min_length`` to ``shape_max_length`` centred on the box, over at least
  ``shape_min_frames`` frames), for classes other than car and van (a tractor's or flatbed's
  cab is its tallest part; buses and trailers are nearly symmetric), and on a track whose
  motion has decided once (motion wins). ``shape_weight`` and ``shape_margin`` were fitted on
  TRAIN tracks only (docs/model.md has the measurement). :func:`shape_flips` is the
  whole-track form (measured, it does not pay in the offline mode; not used there).

A flip sets ``yaw += pi`` and keeps the placed complete shape as it is (the same point set in
the sensor frame, i.e. the canonical shape turned by pi): the shape was fitted to the observed
points by the Chamfer loss and is right where it stands; only the label of which end is the
front was wrong. Centre, extents and Chamfer distance are therefore unchanged; only the yaw is.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from seqshape.errors import ConfigError
from seqshape.geometry import sensor_to_canonical
from seqshape.model.smooth import MAX_GAP


@dataclass(frozen=True)
class HeadingConfig:
    """Options of the :class:`seqshape.Estimator` heading post-processing."""

    motion: bool = True
    """Flip the yaw against a confident motion direction (needs ego poses per step, or
    ``static_sensor``; without either it does nothing)."""
    static_sensor: bool = False
    """The sensor does not move: sensor-frame positions are fixed-frame positions."""
    min_travel: float = 1.5
    """Fitted travel (m) over the motion frames needed to trust the motion direction."""
    motion_frames: int = 10
    """Frames with points (the latest ones) the motion line is fitted to (at least 3)."""
    min_consistency: float = 0.8
    """Minimum correlation of frame order and position along the motion line."""
    vote: bool = True
    """Also flip raw yaws that disagree by more than 90 degrees with the track's vote (where
    motion gives no answer). On by default since 2026-12-05 (docs/model.md)."""
    vote_decay: float = 0.95
    """Per-frame decay of the vote (memory of about 1 / (1 - decay) frames)."""
    vote_fixed_only: bool = True
    """Vote only in a fixed frame (ego poses given, or ``static_sensor``): without them the
    yaws are in the sensor frame, which turns with the ego over the vote's memory."""
    motion_weight: float = 3.0
    """Weight, in the vote, of a heading confirmed by motion (a raw yaw weighs 1)."""
    shape: bool = False
    """Where motion gives no answer, take the front from the observed points' side silhouette
    (:class:`EndProfile`): the lower end is the front (module doc). Opt-in: measured, it
    changes few frames on the val sets, not always for the better (docs/model.md)."""
    shape_margin: float = 0.4
    """Minimum |:meth:`EndProfile.score`| to decide; below it the shape step abstains."""
    shape_min_points: int = 40
    """Points needed in each end quarter of the observed extent (accumulated over the track)."""
    shape_min_length: float = 2.5
    """Minimum observed extent (m) along the axis: shorter, the view is of one end only."""
    shape_max_length: float = 6.5
    """Maximum observed extent (m): longer vehicles (trucks, buses, trailers) are not
    front-low (a tractor's or flatbed's cab is its tallest part), so the step abstains."""
    shape_weight: float = 4.0
    """Weight of the roof's rearward offset against the end-height difference in the score."""
    shape_min_frames: int = 5
    """Frames with points accumulated before the shape step may decide."""
    shape_max_turn: float = math.radians(30.0)
    """A frame whose yaw is further than this from the track's axis (either end) is left
    out of the silhouette (a sideways estimate would smear it)."""
    shape_min_heights: int = 5
    """Distinct 5 cm height cells the median column of the silhouette must hold: fewer, the
    view is a few scan rings (a far vehicle), whose heights along the body follow the
    rings' elevation and the range, not the vehicle's outline."""

    def __post_init__(self):
        if int(self.motion_frames) < 3:
            raise ConfigError(f"HeadingConfig.motion_frames must be >= 3, got "
                              f"{self.motion_frames}")
        if not 0.0 <= self.vote_decay < 1.0:
            raise ConfigError(f"HeadingConfig.vote_decay must be in [0, 1), got "
                              f"{self.vote_decay}")
        if min(int(self.shape_min_frames), int(self.shape_min_points),
               int(self.shape_min_heights)) < 1:
            raise ConfigError("HeadingConfig.shape_min_frames, shape_min_points and "
                              "shape_min_heights must be >= 1")
        if not 0.0 < self.shape_min_length < self.shape_max_length:
            raise ConfigError("HeadingConfig needs 0 < shape_min_length < shape_max_length, "
                              f"got {self.shape_min_length}, {self.shape_max_length}")
        if not (self.shape_margin >= 0.0 and self.shape_weight >= 0.0
                and 0.0 <= self.shape_max_turn <= math.pi / 2):
            raise ConfigError("HeadingConfig.shape_margin and shape_weight must be >= 0 and "
                              "shape_max_turn in [0, pi/2]")

    @property
    def active_without_poses(self) -> bool:
        """Whether anything is done on a step without ego poses."""
        return (self.vote and not self.vote_fixed_only) or (self.motion and self.static_sensor)


def wrap_angle(a: float) -> float:
    """``a`` wrapped to [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def motion_direction(positions: np.ndarray, min_travel: float,
                     min_consistency: float) -> float | None:
    """Direction (rad) of a confident straight motion through ``positions`` (k, 2) in frame
    order, or None.

    Least-squares line ``p = a + v t`` over t = 0..k-1: travel ``|v| (k - 1)`` must reach
    ``min_travel`` and the correlation of t with the positions' projections on ``v`` must reach
    ``min_consistency`` (steady progress, not noise around a parked position).
    """
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    k = len(p)
    if k < 3:
        return None
    t = np.arange(k, dtype=np.float64) - (k - 1) / 2.0
    v = (t[:, None] * (p - p.mean(0))).sum(0) / (t * t).sum()
    speed = float(np.hypot(*v))
    if speed * (k - 1) < min_travel:
        return None
    along = (p - p.mean(0)) @ (v / speed)
    sd = float(along.std())
    if sd <= 0 or float((t * along).mean() / (t.std() * sd)) < min_consistency:
        return None
    return math.atan2(v[1], v[0])


def pose_yaw(ego_pose: np.ndarray) -> float:
    """Yaw of a (4, 4) pose's rotation about z."""
    return math.atan2(float(ego_pose[1, 0]), float(ego_pose[0, 0]))


#: Vehicle classes (the ``classes`` hint of ``Estimator.step``) whose front the shape step may
#: decide; unknown (None) counts as allowed, the length limits still apply.
SHAPE_CLASSES = ("car", "van")


class EndProfile:
    """A track's observed points accumulated in the canonical frame of its estimated box, x
    along one fixed end of the axis: counts on an (x, z) grid, its side silhouette.

    :meth:`score` compares the two ends of the observed extent (module doc); positive: the +x
    end is the front. The grid is 0.1 m along x (+-8 m) by 0.05 m in z (+-3 m); points outside
    it are dropped.
    """

    BIN_X = 0.1
    BIN_Z = 0.05
    HALF_X = 8.0
    HALF_Z = 3.0
    #: percentile of z taken as a column's top (robust to a stray point above the body)
    TOP = 0.9

    def __init__(self):
        self.nx = int(round(2 * self.HALF_X / self.BIN_X))
        self.nz = int(round(2 * self.HALF_Z / self.BIN_Z))
        self.grid = np.zeros((self.nx, self.nz), np.float64)
        self.frames = 0

    def add(self, local: np.ndarray) -> None:
        """Add one frame's points ``local`` (N, 3) given in the box's canonical frame (a frame
        with no point on the grid does not count)."""
        local = np.asarray(local, dtype=np.float64).reshape(-1, 3)
        ix = np.floor((local[:, 0] + self.HALF_X) / self.BIN_X)
        iz = np.floor((local[:, 2] + self.HALF_Z) / self.BIN_Z)
        keep = (ix >= 0) & (ix < self.nx) & (iz >= 0) & (iz < self.nz)
        if not keep.any():
            return
        flat = ix[keep].astype(np.int64) * self.nz + iz[keep].astype(np.int64)
        self.grid += np.bincount(flat, minlength=self.nx * self.nz).reshape(self.nx, self.nz)
        self.frames += 1

    def score(self, cfg: HeadingConfig) -> float | None:
        """Front/back asymmetry of the silhouette, ``ends - cfg.shape_weight * roof`` of
        :meth:`features`, or None when both ends were not observed. Positive: +x is the
        front."""
        f = self.features(cfg)
        return None if f is None else f[0] - cfg.shape_weight * f[1]

    def features(self, cfg: HeadingConfig) -> tuple[float, float] | None:
        """``(ends, roof)``: the end-height difference and the roof's offset, or None when
        both ends were not observed.

        Over the observed extent [x_lo, x_hi] (1st to 99th percentile of the points' x; it must
        be ``shape_min_length`` to ``shape_max_length`` long and centred on the box centre
        within 15 % of its length, else only one end was seen), each 0.1 m column's top (90th
        percentile of z) above the cloud's bottom (2nd percentile), h(x), H its maximum (the
        median column must hold points in ``shape_min_heights`` height cells):
        ``ends = (mean h of the -x end quarter - mean h of the +x end quarter) / H`` and
        ``roof = (x-centroid of h**4 - centre of the extent) / extent``. Both end quarters
        need ``shape_min_points`` points. The +x end is the front when it is lower (ends > 0)
        and the roof sits towards -x (roof < 0).
        """
        per_x = self.grid.sum(1)
        n = per_x.sum()
        if n < 2 * cfg.shape_min_points or self.frames < cfg.shape_min_frames:
            return None
        cum = np.cumsum(per_x)
        lo = int(np.searchsorted(cum, 0.01 * n))
        hi = int(np.searchsorted(cum, 0.99 * n))
        xs = (np.arange(self.nx) + 0.5) * self.BIN_X - self.HALF_X
        extent = xs[hi] - xs[lo] + self.BIN_X
        mid = 0.5 * (xs[lo] + xs[hi])
        if not cfg.shape_min_length <= extent <= cfg.shape_max_length \
                or abs(mid) > 0.15 * extent:
            return None
        quarter = max(1, int(round(0.25 * (hi - lo + 1))))
        rear, front = slice(lo, lo + quarter), slice(hi + 1 - quarter, hi + 1)
        if min(per_x[rear].sum(), per_x[front].sum()) < cfg.shape_min_points:
            return None
        zs = (np.arange(self.nz) + 0.5) * self.BIN_Z - self.HALF_Z
        per_z = self.grid.sum(0)
        bottom = zs[min(int(np.searchsorted(np.cumsum(per_z), 0.02 * n)), self.nz - 1)]
        col = self.grid[lo:hi + 1]
        seen = col.sum(1) > 0
        if np.median((col[seen] > 0).sum(1)) < cfg.shape_min_heights:
            return None  # a few scan rings: no outline
        tops = (np.cumsum(col, axis=1) < self.TOP * col.sum(1, keepdims=True)).sum(1)
        h = np.where(col.sum(1) >= 3, zs[np.minimum(tops, self.nz - 1)] - bottom, np.nan)
        height = np.nanmax(h) if np.isfinite(h).any() else 0.0
        h_rear, h_front = h[:quarter], h[-quarter:]
        if height <= 0.3 or not (np.isfinite(h_rear).any() and np.isfinite(h_front).any()):
            return None
        ends = (np.nanmean(h_rear) - np.nanmean(h_front)) / height
        w = np.nan_to_num(np.clip(h / height, 0.0, None)) ** 4
        roof = float((w * (xs[lo:hi + 1] - mid)).sum() / w.sum()) / extent
        return float(ends), roof


def shape_allowed(cls: str | None) -> bool:
    """Whether the shape step may decide for a vehicle of class ``cls`` (None: unknown)."""
    return not cls or str(cls) in SHAPE_CLASSES


class HeadingFilter:
    """One track's heading evidence; :meth:`update` says whether to flip this frame's yaw."""

    def __init__(self, cfg: HeadingConfig, max_gap: float = MAX_GAP):
        self.cfg = cfg
        self.max_gap = float(max_gap)
        self.last_detection: float | None = None  # time (s) of the last frame with points
        self._forget()

    def _forget(self) -> None:
        """Drop the track's heading evidence (a new segment of the track starts)."""
        self.positions: deque[tuple[float, float]] = deque(maxlen=int(self.cfg.motion_frames))
        self.vote = np.zeros(2)
        self.profile = EndProfile() if self.cfg.shape else None
        self.axis: float | None = None  # the track's axis (a yaw, either end) in the fixed frame
        self.moved = False  # motion has decided on some frame of the track

    def update(self, pose: np.ndarray, ego_pose: np.ndarray | None, has_points: bool,
               points: np.ndarray | None = None, cls: str | None = None,
               time: float | None = None) -> bool:
        """Feed this frame's raw estimate ``pose`` (x, y, z, yaw) in the sensor frame;
        ``ego_pose`` (4, 4) sensor -> fixed frame (None: none given); ``points`` (N, 3) this
        frame's observed points in the sensor frame (None: the shape step is skipped);
        ``cls`` the vehicle class hint; ``time`` (s) the frame's timestamp (None: unknown).
        A detection more than ``max_gap`` seconds after the previous one starts the evidence
        afresh (the smoothers' segment rule, :func:`seqshape.model.smooth.track_segments`: a
        track lost and found may be another vehicle, or the same one turned). Returns True
        when the yaw is to be flipped by pi."""
        if has_points and time is not None:
            if self.last_detection is not None and time - self.last_detection > self.max_gap:
                self._forget()
            self.last_detection = float(time)
        cfg = self.cfg
        fixed = ego_pose is not None or cfg.static_sensor
        yaw = float(pose[3])
        if ego_pose is not None:
            centre = ego_pose[:3, :3] @ np.asarray(pose[:3], np.float64) + ego_pose[:3, 3]
            yaw += pose_yaw(ego_pose)
        else:
            centre = np.asarray(pose[:3], np.float64)
        target = None
        if cfg.motion and fixed:
            if has_points:
                self.positions.append((float(centre[0]), float(centre[1])))
            target = motion_direction(np.array(self.positions), cfg.min_travel,
                                      cfg.min_consistency)
        moving = target is not None
        self.moved = self.moved or moving
        if self.profile is not None and has_points and points is not None and len(points):
            self._accumulate(pose, yaw, points)
        confirmed = moving
        if not moving and not self.moved and self.profile is not None and shape_allowed(cls):
            target = self._shape_target()
            confirmed = target is not None
        vote = cfg.vote and (fixed or not cfg.vote_fixed_only)
        if target is None and vote and self.vote.any():
            target = math.atan2(self.vote[1], self.vote[0])
        flip = target is not None and abs(wrap_angle(yaw - target)) > math.pi / 2
        if vote and has_points:
            # a majority vote of the raw yaws, plus the confirmed ones (weighted)
            vote_yaw, w = (yaw + math.pi if flip else yaw, cfg.motion_weight) if confirmed \
                else (yaw, 1.0)
            self.vote = cfg.vote_decay * self.vote + w * np.array([math.cos(vote_yaw),
                                                                   math.sin(vote_yaw)])
        return flip

    def _accumulate(self, pose: np.ndarray, yaw: float, points: np.ndarray) -> None:
        """Add the frame's points in the box frame whose x is the track's axis end nearest
        this frame's yaw (``yaw`` in the fixed frame); the axis follows the yaw. A frame more
        than ``shape_max_turn`` off the axis is left out."""
        aligned = yaw
        if self.axis is not None:
            off = abs(wrap_angle(yaw - self.axis))
            if self.cfg.shape_max_turn < min(off, math.pi - off):
                return
            aligned = yaw if off <= math.pi / 2 else yaw + math.pi
        self.axis = wrap_angle(aligned)
        box = np.array(pose, dtype=np.float64)
        box[3] += aligned - yaw
        points = np.asarray(points, np.float64).reshape(-1, 3)
        self.profile.add(sensor_to_canonical(points[np.all(np.isfinite(points), axis=1)], box))

    def _shape_target(self) -> float | None:
        """The front the silhouette shows (a yaw in the fixed frame), or None."""
        if self.axis is None:
            return None
        score = self.profile.score(self.cfg)
        if score is None or abs(score) < self.cfg.shape_margin:
            return None
        return self.axis if score > 0 else wrap_angle(self.axis + math.pi)


def shape_flips(points, poses: np.ndarray, ego_poses=None, cfg: HeadingConfig | None = None,
                cls: str | None = None) -> np.ndarray | None:
    """Whole-track shape step (offline): which frames' yaws to turn by pi so that all face the
    front the track's accumulated side silhouette shows (:class:`EndProfile`).

    Returns None when the step abstains: the shape is off, the class is not one of
    :data:`SHAPE_CLASSES`, there is no fixed frame (neither ``ego_poses`` nor
    ``cfg.static_sensor``), the silhouette does not decide, or the track moves (motion, where
    present, decides: a window of ``cfg.motion_frames`` frames with points shows a confident
    motion).

    Args:
        points: per frame an (N_t, 3) array of observed points in that frame's sensor frame.
        poses: (T, 4) estimated (x, y, z, yaw) per frame, in each frame's sensor frame.
        ego_poses: per frame a (4, 4) sensor -> fixed frame (entries may be None: that frame
            takes no part), or None.
        cfg: the options (:class:`HeadingConfig`).
        cls: the vehicle class hint, or None.

    Returns:
        (T,) bool or None.
    """
    cfg = cfg or HeadingConfig()
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    if not cfg.shape or not shape_allowed(cls) or (ego_poses is None and not cfg.static_sensor):
        return None
    filt = HeadingFilter(cfg)
    yaws = np.full(len(poses), np.nan)
    centres = []
    for t, pts in enumerate(points):
        ego = None if ego_poses is None else ego_poses[t]
        if ego_poses is not None and ego is None:
            continue
        ego = None if ego is None else np.asarray(ego, dtype=np.float64)
        yaw = float(poses[t, 3]) + (0.0 if ego is None else pose_yaw(ego))
        yaws[t] = yaw
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        if len(pts):
            centre = poses[t, :3] if ego is None else ego[:3, :3] @ poses[t, :3] + ego[:3, 3]
            centres.append(centre[:2])
            filt._accumulate(poses[t], yaw, pts)
    if cfg.motion and _moves(np.array(centres).reshape(-1, 2), cfg):
        return None
    front = filt._shape_target()
    if front is None:
        return None
    return np.where(np.isfinite(yaws), np.abs(wrap_angle(yaws - front)) > math.pi / 2, False)


def _moves(centres: np.ndarray, cfg: HeadingConfig) -> bool:
    """Whether some ``cfg.motion_frames`` consecutive centres (k, 2) move confidently."""
    k = min(int(cfg.motion_frames), len(centres))
    if k < 3:
        return False
    return any(motion_direction(centres[s:s + k], cfg.min_travel, cfg.min_consistency)
               is not None for s in range(len(centres) - k + 1))
