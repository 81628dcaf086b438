"""A classical estimator: a box fitted to each frame's bird's-eye points (docs/evaluation.md).

:class:`BoxFitEstimator` has the interface of :class:`~seqshape.model.estimator.Estimator`
(``step``, ``reset``, ``recurrent``, ``kind``) so the evaluation scores it beside the networks.
Per frame:

1. **Rectangle** of the points' ``(x, y)``, by one of two methods (``BoxFitConfig.method``):

   * ``"lshape"`` (default): the search-based L-shape fit of Zhang et al. 2017, "Efficient
     L-Shape Fitting for Vehicle Detection Using Laser Scanners" (IEEE IV), Algorithm 2 with
     the **closeness** criterion (their recommended one): for each heading ``theta`` in
     ``[0, 90)`` deg (``angle_step_deg`` apart) project the points on ``e1 = (cos, sin)`` and
     ``e2 = (-sin, cos)``; per axis take, for every point, its distance to the nearer of the two
     bounding edges, choosing per axis the edge whose distance vector has the smaller norm;
     score ``sum_i 1 / max(min(d1_i, d2_i), d0)`` (``d0 = 0.01`` m as in the paper); keep the
     best ``theta``. ``criterion="variance"`` uses their variance criterion instead. The
     rectangle spans the points' projections on the two axes.
   * ``"min_area_rect"``: :func:`cv2.minAreaRect` of the points (the smallest-area enclosing
     rectangle).

   By convention ``length >= width``: the heading is along the longer side, known modulo 180
   deg (``mod 90`` deg before this choice).
2. **Height**: ``z`` spans the points' min and max (the crops have the ground removed).
3. **Heading disambiguation**, with what a user has at run time, in this order:

   a. *direction of motion*: when the fitted centre of the current frame is more than
      ``min_move_m`` (1 m) from that of the track's first fitted frame, the heading is the one of
      the four axis directions of the rectangle closest to that displacement (so the motion
      also settles which side is the length). The estimator sees only sensor-frame points,
      **not the ego motion**: a parked car passed by a moving ego appears to move backwards
      along its axis, so its axis is right but its front/back is a coin toss, and a turning
      ego adds apparent motion. This is the limitation of a user without ego poses;
   b. else the previous frame's heading: of ``h`` and ``h + 180`` deg, the one closer to it;
   c. else (first frames, nothing moved yet) the front faces **away from the sensor**
      (``cos(h - bearing of the centre) >= 0``), the view of traffic ahead driving the same
      way; oncoming or crossing vehicles start flipped until they move.

4. ``complete``: ``num_complete`` points sampled uniformly (area-weighted) on the fitted box's
   surface, so a Chamfer distance is defined. A frame without points repeats the previous
   estimate (``num_points = 0``); a track with no points yet gets a NaN pose and no points.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from seqshape.errors import ConfigError, require
from seqshape.geometry import box_surface
from seqshape.model.estimator import Estimate

METHODS = ("lshape", "min_area_rect")
CRITERIA = ("closeness", "variance")


@dataclass
class BoxFitConfig:
    """Settings of :class:`BoxFitEstimator` (module doc)."""

    method: str = "lshape"
    criterion: str = "closeness"
    angle_step_deg: float = 1.0
    closeness_d0: float = 0.01
    min_move_m: float = 1.0
    num_complete: int = 1024
    seed: int = 0

    def __post_init__(self):
        if self.method not in METHODS:
            raise ConfigError(f"unknown box fit method {self.method!r}; choose from {METHODS}")
        if self.criterion not in CRITERIA:
            raise ConfigError(f"unknown L-shape criterion {self.criterion!r}; "
                              f"choose from {CRITERIA}")
        if not 0 < self.angle_step_deg <= 10 or self.num_complete < 1 or self.min_move_m < 0:
            raise ConfigError("angle_step_deg must be in (0, 10], num_complete >= 1, "
                              "min_move_m >= 0")


@dataclass
class Rectangle:
    """A bird's-eye rectangle: centre ``(x, y)``, ``length >= width`` along ``heading``
    (radians, in ``[0, pi)``)."""

    centre: np.ndarray
    length: float
    width: float
    heading: float


def _rectangle(c1_lo, c1_hi, c2_lo, c2_hi, theta: float) -> Rectangle:
    e1 = np.array([math.cos(theta), math.sin(theta)])
    e2 = np.array([-math.sin(theta), math.cos(theta)])
    centre = e1 * (c1_lo + c1_hi) / 2 + e2 * (c2_lo + c2_hi) / 2
    a, b = c1_hi - c1_lo, c2_hi - c2_lo
    if b > a:
        a, b, theta = b, a, theta + math.pi / 2
    return Rectangle(centre, float(a), float(b), float(theta % math.pi))


def _closeness(c1: np.ndarray, c2: np.ndarray, d0: float) -> np.ndarray:
    """Zhang et al.'s closeness score per heading; projections ``(N, A)`` -> ``(A,)``."""
    def nearer_edge(c):
        lo, hi = c - c.min(0), c.max(0) - c
        use_lo = np.linalg.norm(lo, axis=0) <= np.linalg.norm(hi, axis=0)
        return np.where(use_lo, lo, hi)

    d = np.minimum(nearer_edge(c1), nearer_edge(c2))
    return (1.0 / np.maximum(d, d0)).sum(0)


def _variance(c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """Zhang et al.'s variance criterion (negated, so larger is better), ``(A,)``."""
    def nearer_edge(c):
        lo, hi = c - c.min(0), c.max(0) - c
        use_lo = np.linalg.norm(lo, axis=0) <= np.linalg.norm(hi, axis=0)
        return np.where(use_lo, lo, hi)

    d1, d2 = nearer_edge(c1), nearer_edge(c2)
    on1 = d1 < d2
    score = np.empty(c1.shape[1])
    for a in range(c1.shape[1]):
        e1, e2 = d1[on1[:, a], a], d2[~on1[:, a], a]
        score[a] = -((e1.var() if len(e1) else 0.0) + (e2.var() if len(e2) else 0.0))
    return score


def fit_lshape(xy, criterion: str = "closeness", angle_step_deg: float = 1.0,
               d0: float = 0.01) -> Rectangle:
    """The search-based L-shape rectangle of ``xy (N, 2)`` points (module doc), ``N >= 1``."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) == 0:
        raise ValueError("an L-shape fit needs at least one point")
    xy0 = xy.mean(0)
    pts = xy - xy0
    theta = np.radians(np.arange(0.0, 90.0, angle_step_deg))
    c1 = pts @ np.stack([np.cos(theta), np.sin(theta)])    # (N, A)
    c2 = pts @ np.stack([-np.sin(theta), np.cos(theta)])   # (N, A)
    score = _closeness(c1, c2, d0) if criterion == "closeness" else _variance(c1, c2)
    a = int(np.argmax(score))
    rect = _rectangle(c1[:, a].min(), c1[:, a].max(), c2[:, a].min(), c2[:, a].max(),
                      float(theta[a]))
    rect.centre = rect.centre + xy0
    return rect


def fit_min_area_rect(xy) -> Rectangle:
    """The minimum-area enclosing rectangle of ``xy (N, 2)`` (:func:`cv2.minAreaRect`)."""
    cv2 = require("cv2", "the min_area_rect box fit", "opencv-python-headless")
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) == 0:
        raise ValueError("a rectangle fit needs at least one point")
    xy0 = xy.mean(0)
    (cx, cy), (w, h), angle = cv2.minAreaRect((xy - xy0).astype(np.float32).reshape(-1, 1, 2))
    theta = math.radians(angle)  # the side of extent w runs along theta
    rect = _rectangle(-w / 2, w / 2, -h / 2, h / 2, theta)
    rect.centre = np.array([cx, cy], dtype=np.float64) + xy0
    return rect


def box_surface_points(size, pose, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniform on the surface of a posed box ``size (l, w, h)``, ``pose (4,)``
    (float32; :func:`seqshape.geometry.box_surface`, the one box sampler)."""
    return box_surface(n, rng, size, pose=pose, dtype=np.float32)


@dataclass
class BoxEstimate(Estimate):
    """An :class:`~seqshape.model.estimator.Estimate` plus the fitted box ``size (l, w, h)``
    (the evaluation reads the extents from it instead of from the sampled surface)."""

    size: np.ndarray | None = None


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


@dataclass
class _BoxTrack:
    first_centre: np.ndarray | None = None
    heading: float | None = None
    last: BoxEstimate | None = None
    frames: int = 0


class BoxFitEstimator:
    """Per-frame box fit with the :class:`~seqshape.model.estimator.Estimator` interface.

    Args:
        config: a :class:`BoxFitConfig`; keyword arguments override its fields (e.g.
            ``BoxFitEstimator(method="min_area_rect")``).
    """

    recurrent = False

    def __init__(self, config: BoxFitConfig | None = None, **overrides):
        base = config or BoxFitConfig()
        self.config = BoxFitConfig(**{**base.__dict__, **overrides})
        self._tracks: dict[str, _BoxTrack] = {}

    @property
    def kind(self) -> str:
        return f"boxfit:{self.config.method}"

    @property
    def track_ids(self) -> list[str]:
        return list(self._tracks)

    def reset(self, track_id: str | None = None) -> None:
        """Forget one track (unknown ids are ignored), or every track with None."""
        if track_id is None:
            self._tracks.clear()
        else:
            self._tracks.pop(track_id, None)

    def fit(self, xy: np.ndarray) -> Rectangle:
        """The configured rectangle fit of ``xy (N, 2)``."""
        c = self.config
        if c.method == "min_area_rect":
            return fit_min_area_rect(xy)
        return fit_lshape(xy, c.criterion, c.angle_step_deg, c.closeness_d0)

    def choose_heading(self, state: _BoxTrack, rect: Rectangle) -> tuple[float, float, float]:
        """``(heading, length, width)``: the rectangle's heading disambiguated (module doc)."""
        h, ln, w = rect.heading, rect.length, rect.width
        if state.first_centre is not None:
            move = rect.centre - state.first_centre
            if np.hypot(*move) > self.config.min_move_m:
                along = math.atan2(move[1], move[0])
                cands = [(h + k * math.pi / 2, ln if k % 2 == 0 else w, w if k % 2 == 0 else ln)
                         for k in range(4)]
                return min(cands, key=lambda c: _angle_diff(c[0], along))
        if state.heading is not None:
            if _angle_diff(h + math.pi, state.heading) < _angle_diff(h, state.heading):
                h += math.pi
            return h, ln, w
        bearing = math.atan2(rect.centre[1], rect.centre[0])
        if math.cos(h - bearing) < 0:
            h += math.pi
        return h, ln, w

    def _estimate(self, tid: str, state: _BoxTrack, pts: np.ndarray) -> BoxEstimate:
        rect = self.fit(pts[:, :2])
        heading, ln, w = self.choose_heading(state, rect)
        heading = (heading + math.pi) % (2 * math.pi) - math.pi
        z_lo, z_hi = float(pts[:, 2].min()), float(pts[:, 2].max())
        pose = np.array([rect.centre[0], rect.centre[1], (z_lo + z_hi) / 2, heading])
        rng = np.random.default_rng([self.config.seed, zlib.crc32(tid.encode()), state.frames])
        complete = box_surface_points((ln, w, z_hi - z_lo), pose, self.config.num_complete, rng)
        if state.first_centre is None:
            state.first_centre = rect.centre.copy()
        state.heading = heading
        return BoxEstimate(tid, complete, pose, len(pts), np.array([ln, w, z_hi - z_lo]))

    def step(self, track_ids: Sequence[str],
             point_lists: Sequence[np.ndarray]) -> list[BoxEstimate]:
        """Fit each listed track's frame ``(N_i, 3)`` (sensor frame); one Estimate per track."""
        track_ids = [str(t) for t in track_ids]
        if len(track_ids) != len(point_lists):
            raise ConfigError(f"{len(track_ids)} track ids but {len(point_lists)} point lists")
        if len(set(track_ids)) != len(track_ids):
            raise ConfigError("a track id appears twice in one step")
        out = []
        for i, (tid, pts) in enumerate(zip(track_ids, point_lists, strict=True)):
            pts = np.asarray(pts, dtype=np.float64)
            if pts.ndim != 2 or pts.shape[1] < 3:
                raise ConfigError(f"point_lists[{i}] must have shape (N, 3), got {pts.shape}")
            pts = pts[np.all(np.isfinite(pts[:, :3]), axis=1), :3]
            state = self._tracks.setdefault(tid, _BoxTrack())
            if len(pts):
                est = self._estimate(tid, state, pts)
            elif state.last is not None:
                last = state.last
                est = BoxEstimate(tid, last.complete, last.pose.copy(), 0, last.size)
            else:
                est = BoxEstimate(tid, np.zeros((0, 3), np.float32), np.full(4, np.nan), 0,
                                  np.full(3, np.nan))
            state.last = est
            state.frames += 1
            out.append(est)
        return out
