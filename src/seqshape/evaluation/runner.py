"""Run estimators over a dataset's tracks and score every frame (docs/evaluation.md).

What is computed, per method and per scored frame ``t`` of a track:

* the track runs from its first to its last detection (frames with >= 1 point), as in the
  paper; every frame in between is fed to the estimator (an empty frame is a ``(0, 3)`` array)
  and scored. Frames before the first or after the last detection are not run;
* ``cd_m``: :func:`~seqshape.evaluation.metrics.chamfer_distance` between the estimate's complete
  cloud and the ground-truth complete shape placed in frame t (``Track.complete_in_frame(t)``),
  both in frame t's sensor frame, all points;
* ``emd_m``: exact EMD between equal-size random subsets (``emd_points`` each, fixed seed per
  track and frame, the same ground-truth subset for every method) on every ``emd_every``-th
  scored frame of the track (counted from its first detection), NaN elsewhere;
* ``trans_m``, ``rot_rad``: planar translation and wrapped yaw errors of the estimated pose;
* ``cd_true_pose_m`` (a diagnostic, not in the paper): the CD of the estimated shape alone,
  taken into its canonical frame with its own estimated pose and placed at the true pose; set
  beside ``cd_m`` it splits the error between shape and placement;
* ``ref_to_est_m``: the one-way half of the CD, mean over the reference points of the distance
  to the nearest estimated point. Against an accumulated reference (real tracks), which holds
  only surface the sensor saw, this is the part of the CD that measures the estimate; the
  other half also charges the estimate for the sides the reference lacks (docs/reference.md);
* ``n_det``: detections so far (frames with >= 1 point up to and including t), ``n_points``:
  points in frame t, ``distance_m``: planar distance of the true box centre from the sensor;
* ``class``: the track's vehicle class (``meta["class"]``, real tracks; empty when unknown);
* ``radial_m``, ``tangential_m``: the planar translation error ``(x, y)_est - (x, y)_true``
  split along the unit vector from the sensor to the true centre (signed: positive = the
  estimate is too far from the sensor) and along its left-hand normal (signed, counter-clockwise
  positive); ``trans_m**2 == radial_m**2 + tangential_m**2``;
* ``rot_axis_rad``: the rotation error ignoring the direction of travel,
  ``min(rot, pi - rot)`` in ``[0, pi/2]`` (a box flipped by 180 degrees scores 0);
* ``length_err_m``, ``width_err_m``: signed errors (estimate - truth) of the estimate's extents
  against the true box size (:func:`estimate_extents`); ``length_rel_err``: the length error
  as a fraction of the true length (the issue's yardstick for trucks and buses: 10 %);
* ``est_near_out``, ``est_far_out``: the share of frame t's points outside the estimate's
  bird's-eye footprint (:func:`footprint`) on the side facing the sensor / the far side
  (:func:`outside_shares`); ``ref_near_out``, ``ref_far_out``: the same for the true box. On
  synthetic tracks the true box holds every point of the vehicle (ground and clutter left by a
  crop are outside it); on an annotated real log ``ref_*`` tells how well the annotation
  encloses the car's own points. ``est_*`` compares methods on the same tracks (a box too far
  from the sensor leaves more points in front); across sets it depends on the point layout as
  much as on the placement;
* ``world_travel_m``: the track's own travel, the diagonal of the box holding its true centres
  in the fixed frame of its ego poses (:func:`world_travel`; the same in every frame of
  the track; NaN for a real track without ego poses). A track that travels less than a metre
  while its view changes is a parked vehicle passed by a moving ego (the report's "passed"
  group);
* ``ref_face_gap_m``: how far the true box's faces lie outside the frame's points
  (:func:`face_gaps`; the larger of the faces seen within 60 degrees of head-on; NaN under
  :data:`FACE_GAP_MIN_POINTS` points). A few cm on a box that holds its vehicle's points; on
  an annotated real log decimetres mean a box displaced from, or looser than, its own points,
  which every method's errors against it inherit (the report's "annotation" breakdown).

Frames whose ground-truth pose is unknown (NaN) are fed but get NaN metrics; tracks without a
complete shape get NaN CD/EMD. Tracks are processed in chunks of ``batch_tracks``: within a
chunk, all active tracks go through one ``step`` call per frame index (with each frame's
timestamp when the estimator's ``step`` takes ``timestamps=``). A whole-track estimator
(``estimate_track``, :class:`seqshape.model.offline.OfflineEstimator`: the offline mode) gets
each track's whole span at once; ``settings["modes"]`` records each method's mode.
"""

from __future__ import annotations

import inspect
import logging
import multiprocessing
import os
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from seqshape._progress import progress
from seqshape._runner import watch_parent
from seqshape.data import Track
from seqshape.errors import ConfigError, SeqshapeError
from seqshape.evaluation.metrics import (
    cd_floor,
    emd_batch,
    emd_floor_pair,
    nearest_distances,
    pose_errors,
    stable_seed,
    subsample_pair,
)
from seqshape.geometry import canonical_to_sensor, sensor_to_canonical
from seqshape.model.smooth import world_centres
from seqshape.vehicles import procedural_vehicle, sample_outer_surface

log = logging.getLogger(__name__)

#: Columns of the per-frame records, in CSV order.
FIELDS = ("method", "track_id", "frame", "n_det", "n_points", "distance_m",
          "cd_m", "emd_m", "trans_m", "rot_rad", "cd_true_pose_m", "class", "radial_m",
          "tangential_m", "rot_axis_rad", "length_err_m", "width_err_m", "ref_to_est_m",
          "est_near_out", "est_far_out", "ref_near_out", "ref_far_out", "length_rel_err",
          "ref_face_gap_m", "world_travel_m")
_STR_FIELDS = ("method", "track_id", "class")
_INT_FIELDS = ("frame", "n_det", "n_points")
#: Percentiles of the estimated cloud's canonical coordinates taken as its extents.
EXTENT_PERCENTILES = (1.0, 99.0)
_EMD_TASK = 16  # pairs per process-pool task
#: seconds of one exact EMD between an estimate and its reference at 1024 points per worker
#: process, for the up-front time estimate (measured: ``seqshape evaluate`` on the tiny preset,
#: 160 EMD frames in 36 s on 2 workers of a busy 2-core machine; 0.27 s alone on one core; the
#: assignment costs about N^3)
EMD_SECONDS_1024 = 0.45


class EstimatorLike(Protocol):
    recurrent: bool

    def step(self, track_ids: Sequence[str], point_lists: Sequence[np.ndarray]) -> list: ...

    def reset(self, track_id: str | None = None) -> None: ...


@dataclass
class EvalResult:
    """Per-frame records (columns :data:`FIELDS`, one row per method and scored frame),
    the CD floor per track, and the settings used."""

    records: dict[str, np.ndarray]
    floors: dict[str, np.ndarray]          # "track_id", "floor_m", "n_pred", "method",
                                           # "emd_floor_m" (NaN without EMD)
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def methods(self) -> list[str]:
        return list(dict.fromkeys(self.records["method"].tolist()))

    def of(self, method: str) -> dict[str, np.ndarray]:
        """The records of one method."""
        m = self.records["method"] == method
        return {k: v[m] for k, v in self.records.items()}


def detection_span(track: Track) -> tuple[int, int] | None:
    """``(first, last + 1)`` frame indices spanning the detections, or None without any."""
    det = np.flatnonzero(track.num_points > 0)
    return None if len(det) == 0 else (int(det[0]), int(det[-1]) + 1)


def track_hints(est, tracks: Sequence[Track], frames: Sequence[int]) -> dict:
    """What a user's pipeline knows besides the points, as keyword arguments of
    :meth:`seqshape.model.Estimator.step`: each track's class (``meta["class"]``) and the ego
    pose of its frame (``meta["ego_poses"]`` of real tracks; the identity for synthetic tracks,
    whose sensor is static; none for real tracks without ego motion). Never the true box size:
    it would hand the network the length it is scored on. Other estimators (the box fit, test
    doubles) get nothing."""
    # lazy: torch; the EMD worker processes (spawned) import this module and need no torch
    from seqshape.model.estimator import Estimator

    if not isinstance(est, Estimator):
        return {}
    egos = [tr.ego_pose(t) for tr, t in zip(tracks, frames, strict=True)]
    return {"classes": [tr.meta.get("class") or None for tr in tracks],
            "ego_poses": egos if any(e is not None for e in egos) else None}


def step_takes_timestamps(estimator) -> bool:
    """Whether ``estimator.step`` accepts ``timestamps=`` (checked once per class: the box
    fit and older estimators do not)."""
    cls = type(estimator)
    if cls not in _TAKES_TIMESTAMPS:
        try:
            params = inspect.signature(cls.step).parameters
        except (TypeError, ValueError, AttributeError):
            params = {}
        _TAKES_TIMESTAMPS[cls] = "timestamps" in params
    return _TAKES_TIMESTAMPS[cls]


_TAKES_TIMESTAMPS: dict[type, bool] = {}


def step_kwargs(estimator, tracks: Sequence[Track], frames: Sequence[int],
                hints: bool) -> dict:
    """Keyword arguments of one ``step`` call: the :func:`track_hints` (when ``hints``) and
    each track's timestamp of its frame (when the estimator's ``step`` takes them)."""
    kw = track_hints(estimator, tracks, frames) if hints else {}
    if step_takes_timestamps(estimator):
        kw["timestamps"] = [float(tr.timestamps[t]) for tr, t in
                            zip(tracks, frames, strict=True)]
    return kw


def is_whole_track(estimator) -> bool:
    """Whether ``estimator`` estimates whole tracks at once (its ``whole_track`` attribute is
    true and it has ``estimate_track``, e.g. :class:`seqshape.model.offline.OfflineEstimator`)
    rather than stepping frame by frame."""
    return bool(getattr(estimator, "whole_track", False)) and callable(
        getattr(estimator, "estimate_track", None))


def track_kwargs(estimator, track: Track, frames: range, hints: bool) -> dict:
    """Keyword arguments of ``estimator.estimate_track`` for ``frames`` of ``track``: the
    timestamps, the track id and (when ``hints``) its class and ego poses as
    :func:`track_hints` gives them frame by frame."""
    kw: dict[str, Any] = {"timestamps": track.timestamps[frames.start:frames.stop],
                          "track_id": track.track_id}
    if hints:
        inner = getattr(estimator, "estimator", estimator)
        per_frame = [track_hints(inner, [track], [t]) for t in frames]
        kw["cls"] = per_frame[0].get("classes", [None])[0] if per_frame else None
        egos = [(h.get("ego_poses") or [None])[0] for h in per_frame]
        kw["ego_poses"] = egos if any(e is not None for e in egos) else None
    return kw


def predict_track(estimator: EstimatorLike, track: Track,
                  hints: bool = False) -> tuple[range, list]:
    """Run one track from its first to its last detection; returns ``(frames, estimates)``.
    ``hints``: pass :func:`track_hints` to the estimator; the frames' timestamps go to a
    ``step`` that takes them. A whole-track estimator (:func:`is_whole_track`) gets the whole
    span at once."""
    span = detection_span(track)
    if span is None:
        raise SeqshapeError(f"track {track.track_id} has no frame with points")
    frames = range(*span)
    if is_whole_track(estimator):
        return frames, estimator.estimate_track(
            [track.points[t] for t in frames], **track_kwargs(estimator, track, frames, hints))
    estimator.reset(track.track_id)
    out = [estimator.step([track.track_id], [track.points[t]],
                          **step_kwargs(estimator, [track], [t], hints))[0]
           for t in frames]
    estimator.reset(track.track_id)
    return frames, out


_MESH_KEYS = ("vehicle_source", "mesh_source", "source", "mesh", "mesh_id", "vehicle")
_mesh_cache: dict[str, Any] = {}


def surface_resampler(track: Track):
    """A function ``(n, seed) -> (n, 3)`` re-sampling the track's true outer surface in the
    canonical frame, or None when the surface cannot be rebuilt.

    Works for procedural vehicles: the track's meta names the mesh as
    ``"procedural:<kind>:<seed>"`` (looked up under the keys of ``_MESH_KEYS``, then any string
    value), rebuilt with ``seqshape.vehicles.procedural_vehicle`` and sampled with
    ``seqshape.vehicles.sample_outer_surface``. Meshes are cached per source.
    """
    values = [track.meta.get(k) for k in _MESH_KEYS] + list(track.meta.values())
    source = next((v for v in values if isinstance(v, str) and v.startswith("procedural:")),
                  None)
    if source is None:
        return None
    if source not in _mesh_cache:
        _, kind, vseed = source.split(":", 2)
        try:
            _mesh_cache[source] = procedural_vehicle(kind, int(vseed)).mesh
        except (ValueError, KeyError) as exc:
            log.warning("cannot rebuild %s for the CD floor (%s); using the split estimate",
                        source, exc)
            return None
    mesh = _mesh_cache[source]
    return lambda n, seed: sample_outer_surface(mesh, n=n, seed=seed)


class _Collector:
    """Accumulates rows and EMD jobs (inline or on a process pool)."""

    def __init__(self, workers: int):
        self.rows: dict[str, list] = {k: [] for k in FIELDS}
        self._travel: dict[str, float] = {}
        self.pool = None
        if workers > 0:
            # the workers end themselves when this process dies (a kill -9 of evaluate)
            self.pool = ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=watch_parent, initargs=(os.getpid(),))
        self.pending: list[tuple[list[tuple[bool, int]], Future | list[float]]] = []
        self.batch: list[tuple[tuple[bool, int], tuple[np.ndarray, np.ndarray]]] = []
        self.floor_emd: dict[int, float] = {}  # the EMD floors' EMDs (:func:`_floors`)

    def travel(self, track: Track) -> float:
        """:func:`world_travel` of ``track``, computed once per track id."""
        if track.track_id not in self._travel:
            self._travel[track.track_id] = world_travel(track)
        return self._travel[track.track_id]

    def add(self, **row) -> int:
        for k in FIELDS:
            self.rows[k].append(row[k])
        return len(self.rows["method"]) - 1

    def add_emd(self, row: int, pair: tuple[np.ndarray, np.ndarray], floor: bool = False) -> None:
        """The EMD of ``pair`` into row ``row``'s ``emd_m``, or with ``floor`` into
        ``floor_emd[row]``."""
        self.batch.append(((floor, row), pair))
        if len(self.batch) >= _EMD_TASK:
            self.flush()

    def flush(self) -> None:
        if not self.batch:
            return
        idx = [i for i, _ in self.batch]
        pairs = [p for _, p in self.batch]
        self.batch = []
        job = self.pool.submit(emd_batch, pairs) if self.pool else emd_batch(pairs)
        self.pending.append((idx, job))

    def finish(self) -> dict[str, np.ndarray]:
        self.flush()
        self._collect_emd()
        if self.pool:
            self.pool.shutdown()
        out = {k: np.asarray(v) for k, v in self.rows.items()}
        for k in FIELDS:
            out[k] = out[k].astype(str if k in _STR_FIELDS
                                   else np.int64 if k in _INT_FIELDS else np.float64)
        return out

    def _collect_emd(self) -> None:
        """Wait for the EMD jobs, with a bar over frames (ETA) that starts at those done."""
        emd = self.rows["emd_m"]

        def put(idx: list[tuple[bool, int]], values: list[float]) -> None:
            for (floor, i), v in zip(idx, values, strict=True):
                (self.floor_emd if floor else emd)[i] = v

        futures: dict[Future, list[tuple[bool, int]]] = {}
        done = 0
        for idx, job in self.pending:
            if isinstance(job, Future) and not job.done():
                futures[job] = idx
                continue
            put(idx, job.result() if isinstance(job, Future) else job)
            done += len(idx)
        if not futures:
            return
        bar = progress(total=done + sum(len(i) for i in futures.values()), initial=done,
                       desc="EMD", unit="frame")
        try:
            for job in as_completed(futures):
                idx = futures[job]
                put(idx, job.result())
                bar.update(len(idx))
        finally:
            bar.close()


def emd_frames(spans: Sequence[tuple[int, int]], emd_every: int) -> int:
    """Frames of one method that get an EMD: every ``emd_every``-th frame of each span.

    >>> emd_frames([(0, 10), (3, 4)], 3)
    5
    """
    if emd_every <= 0:
        return 0
    return sum(-(-(b - a) // emd_every) for a, b in spans)


def emd_seconds(n_frames: int, emd_points: int, workers: int) -> float:
    """Rough wall time of ``n_frames`` exact EMDs on ``emd_points`` points over ``workers``
    processes (0: in this process), from :data:`EMD_SECONDS_1024`.

    >>> round(emd_seconds(100, 1024, 2), 1)
    22.5
    """
    return n_frames * EMD_SECONDS_1024 * (emd_points / 1024) ** 3 / max(1, workers)


def _announce_emd(tracks: Sequence[Track], spans: Sequence[tuple[int, int]], n_methods: int,
                  emd_every: int, emd_points: int, workers: int) -> None:
    """Say once, before the work, how much exact EMD is coming and how to skip it."""
    with_ref = [s for tr, s in zip(tracks, spans, strict=True) if tr.complete is not None]
    n = emd_frames(with_ref, emd_every) * n_methods
    if not n:
        return
    seconds = emd_seconds(n, emd_points, workers)
    took = f"{seconds / 60:.0f} min" if seconds >= 90 else f"{seconds:.0f} s"
    log.info("exact EMD on %d frames (%d-point clouds, %d tracks, %d method(s)): about %s on "
             "%s; --emd-every 0 skips it, --emd-every K scores every K-th frame", n,
             emd_points, len(with_ref), n_methods, took,
             f"{workers} worker(s)" if workers else "this process")


def estimate_extents(est) -> np.ndarray:
    """``(length, width)`` of an estimate, metres.

    An estimate carrying a ``size`` (the box fit) gives its box; otherwise the extents of the
    complete cloud in its own canonical frame (the estimated pose's centre and yaw): the spread
    between the :data:`EXTENT_PERCENTILES` (1st and 99th) of its canonical x and y, robust to a
    few stray points. On a box's surface sampled by area, more than 1 % of the points lie on each
    end face and side, so these percentiles fall on the faces: exact for a box-like cloud.
    NaN without points or pose.
    """
    size = getattr(est, "size", None)
    if size is not None:
        return np.asarray(size, dtype=np.float64)[:2]
    pred = np.asarray(est.complete, dtype=np.float64)
    if not len(pred) or not np.all(np.isfinite(est.pose)):
        return np.full(2, np.nan)
    local = sensor_to_canonical(pred, est.pose)[:, :2]
    lo, hi = np.percentile(local, EXTENT_PERCENTILES, axis=0)
    return hi - lo


def footprint(est) -> tuple[np.ndarray, np.ndarray] | None:
    """The bird's-eye box of an estimate in its own canonical frame: ``(lo, hi)`` (2,) each;
    the box fit's ``size`` centred on its pose, else the :data:`EXTENT_PERCENTILES` of the
    complete cloud (as :func:`estimate_extents`); None without points or pose."""
    size = getattr(est, "size", None)
    if size is not None:
        half = np.asarray(size, dtype=np.float64)[:2] / 2
        return -half, half
    pred = np.asarray(est.complete, dtype=np.float64)
    if not len(pred) or not np.all(np.isfinite(est.pose)):
        return None
    local = sensor_to_canonical(pred, est.pose)[:, :2]
    lo, hi = np.percentile(local, EXTENT_PERCENTILES, axis=0)
    return lo, hi


def outside_shares(points: np.ndarray, pose, box) -> tuple[float, float]:
    """``(near, far)``: the shares of ``points`` (N, 3, sensor frame) outside the bird's-eye
    ``box`` ``(lo, hi)`` (canonical frame of ``pose``) on the sensor's side of the box centre
    and beyond it (split by the sign of the point's offset from the box centre along the
    direction from the centre to the sensor). NaN without points, pose or box."""
    pts = np.asarray(points, dtype=np.float64)
    if box is None or not len(pts) or not np.all(np.isfinite(pose)):
        return np.nan, np.nan
    lo, hi = (np.asarray(b, dtype=np.float64) for b in box)
    q = sensor_to_canonical(pts[:, :3], pose)[:, :2].astype(np.float64)
    out = np.any((q < lo) | (q > hi), axis=1)
    centre = (lo + hi) / 2
    yaw = float(pose[3])
    rot = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    box_xy = np.asarray(pose[:2], dtype=np.float64) + rot.T @ centre
    to_sensor = rot @ -box_xy  # the direction to the sensor in the canonical frame
    near = (q - centre) @ to_sensor > 0
    return float(np.mean(out & near)), float(np.mean(out & ~near))


#: Points a frame needs for :func:`face_gaps`' 98th percentile to mean something.
FACE_GAP_MIN_POINTS = 10
#: Quantile of the points toward a face taken as where they end (a stray return does not count).
FACE_GAP_QUANTILE = 0.98


def face_gaps(points: np.ndarray, pose, size) -> np.ndarray:
    """Per box axis (length, width), the distance from the box face that the sensor sees within
    60 degrees of head-on (the unit direction from the box centre to the sensor has a component
    of at least 0.5 along that axis) to the :data:`FACE_GAP_QUANTILE` of the points toward it:
    positive when the face lies in front of the points (m), NaN for a face not seen so
    squarely. ``points`` (N, 3) sensor frame, ``pose`` the box, ``size`` its (length, width,
    ...). At least one face is always seen (the two components cannot both be under 0.5)."""
    pose = np.asarray(pose, dtype=np.float64)
    q = sensor_to_canonical(np.asarray(points, dtype=np.float64)[:, :3], pose)[:, :2]
    half = np.asarray(size, dtype=np.float64)[:2] / 2
    yaw = pose[3]
    to_box = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    view = to_box @ (-pose[:2] / max(float(np.hypot(*pose[:2])), 1e-9))
    return np.array([half[a] - np.quantile(q[:, a] * np.sign(view[a]), FACE_GAP_QUANTILE)
                     if abs(view[a]) >= 0.5 else np.nan for a in (0, 1)])


def _ref_face_gap(points: np.ndarray, pose, size) -> float:
    """The ``ref_face_gap_m`` of a frame (module doc)."""
    if len(points) < FACE_GAP_MIN_POINTS or not np.all(np.isfinite(pose)):
        return np.nan
    return float(np.nanmax(face_gaps(points, pose, size)))


def world_travel(track: Track) -> float:
    """The track's travel (m): the diagonal of the planar box holding its true centres (frames
    with a known pose) in the fixed frame of its ego poses (:meth:`Track.ego_pose`,
    :func:`~seqshape.model.smooth.world_centres`); NaN when a frame's ego pose is unknown or
    no pose is."""
    known = [t for t in range(len(track)) if np.all(np.isfinite(track.poses[t]))]
    c = world_centres(np.asarray(track.poses)[known], [track.ego_pose(t) for t in known])
    if c is None or not len(c):
        return np.nan
    return float(np.linalg.norm(c.max(0) - c.min(0)))


def radial_tangential(pose_pred, pose_gt) -> tuple[float, float]:
    """The planar translation error split into ``(radial, tangential)`` metres (module doc).

    Radial: along the unit vector from the sensor to the true centre (positive: too far);
    tangential: along its left-hand normal. NaN when the true centre is at the sensor.
    """
    g = np.asarray(pose_gt, dtype=np.float64)[:2]
    d = np.asarray(pose_pred, dtype=np.float64)[:2] - g
    r = float(np.hypot(*g))
    if r == 0.0:
        return np.nan, np.nan
    u = g / r
    return float(d @ u), float(d @ np.array([-u[1], u[0]]))


def _relative(err: float, true: float) -> float:
    """``err / true``; NaN when the true value is not a positive number."""
    return float(err) / float(true) if np.isfinite(true) and true > 0 else np.nan


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    return float(nearest_distances(a, b).mean() + nearest_distances(b, a).mean())


def _score_frame(col: _Collector, method: str, track: Track, t: int, n_det: int, est,
                 emd_points: int, do_emd: bool) -> None:
    gt_pose = track.poses[t]
    known = bool(np.all(np.isfinite(gt_pose)))
    trans, rot = pose_errors(est.pose, gt_pose) if known else (np.nan, np.nan)
    radial, tangential = radial_tangential(est.pose, gt_pose) if known else (np.nan, np.nan)
    length_err, width_err = estimate_extents(est) - track.size[:2]
    pts = track.points[t]
    est_out = outside_shares(pts, est.pose, footprint(est))
    half = np.asarray(track.size, dtype=np.float64)[:2] / 2
    ref_out = outside_shares(pts, gt_pose, (-half, half)) if known else (np.nan, np.nan)
    cd = cd_tp = ref_to_est = np.nan
    gt = None
    pred = np.asarray(est.complete)
    if known and track.complete is not None and len(pred):
        gt = track.complete_in_frame(t)
        ref_to_est = float(nearest_distances(gt, pred).mean())
        cd = float(nearest_distances(pred, gt).mean()) + ref_to_est  # = chamfer_distance
        if np.all(np.isfinite(est.pose)):
            cd_tp = _chamfer(
                canonical_to_sensor(sensor_to_canonical(pred, est.pose), gt_pose), gt)
    row = col.add(method=method, track_id=track.track_id, frame=t, n_det=n_det,
                  n_points=len(track.points[t]), distance_m=float(np.hypot(*gt_pose[:2])),
                  cd_m=cd, emd_m=np.nan, trans_m=trans, rot_rad=rot, cd_true_pose_m=cd_tp,
                  **{"class": str(track.meta.get("class") or "")}, radial_m=radial,
                  tangential_m=tangential, rot_axis_rad=min(rot, np.pi - rot),
                  length_err_m=length_err, width_err_m=width_err, ref_to_est_m=ref_to_est,
                  est_near_out=est_out[0], est_far_out=est_out[1], ref_near_out=ref_out[0],
                  ref_far_out=ref_out[1], length_rel_err=_relative(length_err, track.size[0]),
                  ref_face_gap_m=_ref_face_gap(pts, gt_pose, track.size) if known else np.nan,
                  world_travel_m=col.travel(track))
    if do_emd and gt is not None:
        col.add_emd(row, subsample_pair(pred, gt, emd_points, stable_seed(track.track_id, t)))


def _run_chunk(col: _Collector, name: str, est: EstimatorLike, tracks: list[Track],
               spans: list[tuple[int, int]], emd_points: int, emd_every: int, bar,
               hints: bool = True) -> int:
    """Step all tracks of a chunk together, frame index by frame index (a whole-track
    estimator takes them one track at a time); returns K."""
    if is_whole_track(est):
        return _run_tracks(col, name, est, tracks, spans, emd_points, emd_every, bar, hints)
    length = max(stop - start for start, stop in spans)
    n_det = [0] * len(tracks)
    k_pred = 0
    for tr in tracks:
        est.reset(tr.track_id)
    for i in range(length):
        active = [j for j, (a, b) in enumerate(spans) if a + i < b]
        ids = [tracks[j].track_id for j in active]
        pts = [tracks[j].points[spans[j][0] + i] for j in active]
        kw = step_kwargs(est, [tracks[j] for j in active], [spans[j][0] + i for j in active],
                         hints)
        estimates = est.step(ids, pts, **kw)
        if len(estimates) != len(active):
            raise SeqshapeError(f"estimator {name!r} returned {len(estimates)} estimates for "
                                f"{len(active)} tracks")
        for j, e in zip(active, estimates, strict=True):
            t = spans[j][0] + i
            n_det[j] += int(len(tracks[j].points[t]) > 0)
            k_pred = k_pred or len(e.complete)
            _score_frame(col, name, tracks[j], t, n_det[j], e, emd_points,
                         emd_every > 0 and i % emd_every == 0)
            if t == spans[j][1] - 1:
                est.reset(tracks[j].track_id)
        bar.update(len(active))
    return k_pred


def _run_tracks(col: _Collector, name: str, est, tracks: list[Track],
                spans: list[tuple[int, int]], emd_points: int, emd_every: int, bar,
                hints: bool) -> int:
    """Score a whole-track estimator (:func:`is_whole_track`) on each track of a chunk."""
    k_pred = 0
    for tr, span in zip(tracks, spans, strict=True):
        frames = range(*span)
        estimates = est.estimate_track([tr.points[t] for t in frames],
                                       **track_kwargs(est, tr, frames, hints))
        if len(estimates) != len(frames):
            raise SeqshapeError(f"estimator {name!r} returned {len(estimates)} estimates for "
                                f"{len(frames)} frames of track {tr.track_id}")
        n_det = 0
        for i, (t, e) in enumerate(zip(frames, estimates, strict=True)):
            n_det += int(len(tr.points[t]) > 0)
            k_pred = k_pred or len(e.complete)
            _score_frame(col, name, tr, t, n_det, e, emd_points,
                         emd_every > 0 and i % emd_every == 0)
        bar.update(len(frames))
    return k_pred


def _floors(tracks: list[Track], n_preds: set[int], floor: str, seed: int,
            col: _Collector | None = None, emd_points: int = 0) -> list[tuple]:
    """Per track with a reference and point count ``k`` of ``n_preds``: ``(track_id, CD floor,
    k, method, EMD factor)``; with ``col`` and ``emd_points`` the EMD floor's pair
    (:func:`~seqshape.evaluation.metrics.emd_floor_pair`, the frames' EMD subset size) goes to
    ``col`` as ``floor_emd[i]``, ``i`` the entry's index (factor NaN without)."""
    out = []
    for tr in tracks:
        if tr.complete is None:
            continue
        resample = surface_resampler(tr) if floor in ("auto", "resample") else None
        if floor == "resample" and resample is None:
            raise ConfigError(f"track {tr.track_id}: cannot re-sample its surface (no mesh "
                              f"source in its meta or seqshape.vehicles unavailable)")
        for k in sorted(n_preds):
            value, how = cd_floor(tr.complete, k, stable_seed(seed, tr.track_id), resample)
            factor = np.nan
            if col is not None and emd_points > 0 and len(tr.complete) >= 8:
                a, b, factor, _ = emd_floor_pair(tr.complete, min(k, emd_points),
                                                 stable_seed(seed, tr.track_id, "emd"), resample)
                col.add_emd(len(out), (a, b), floor=True)
            out.append((tr.track_id, value, k, how, factor))
    return out


def _mode(est) -> str:
    """``"offline"`` for a whole-track estimator of a recurrent model, else ``"online"``;
    ``" + placement refiner"`` after it when the estimator refines its placements, and
    ``" + causal smoothing"`` when an online one smooths its track (``Estimator.smoothing``)."""
    mode = "offline" if is_whole_track(est) and getattr(est, "recurrent", False) else "online"
    inner = getattr(est, "estimator", est)
    smoothed = mode == "online" and getattr(inner, "smoothing", "none") == "causal"
    return mode + (" + placement refiner" if getattr(inner, "refiner", None) is not None
                   else "") + (" + causal smoothing" if smoothed else "")


def is_real(tracks: Sequence[Track]) -> bool:
    """Whether any track comes from a real log (``meta["source"] == "real"``)."""
    return any(tr.meta.get("source") == "real" for tr in tracks)


def evaluate_tracks(estimators: Mapping[str, EstimatorLike], dataset,
                    max_tracks: int | None = None, emd_points: int = 1024, emd_every: int = 1,
                    batch_tracks: int = 64, workers: int = 2, floor: str = "auto",
                    seed: int = 0, hints: bool = True) -> EvalResult:
    """Run each estimator over every track of ``dataset`` and score each frame.

    Args:
        estimators: method name -> estimator (``step``/``reset``/``recurrent``), e.g.
            ``{"sequential": ..., "baseline": ...}``.
        dataset: a sequence of :class:`~seqshape.data.Track` (e.g. ``TrackDataset.split("val")``).
        max_tracks: evaluate only the first N tracks.
        hints: give the networks each track's class and ego poses (:func:`track_hints`), as a
            user's pipeline would; False feeds the points alone (the protocol before the
            heading and scale options existed; with the shipped defaults both are the same
            except for the heading step, which needs the ego poses).
        emd_points: EMD subsample size (both clouds); ``emd_every``: EMD on every k-th scored
            frame of each track (0 disables EMD).
        batch_tracks: tracks stepped together per ``step`` call.
        workers: processes computing EMD (0: in this process).
        floor: CD floor method: ``"auto"`` (re-sample the mesh when possible, else split the
            stored sampling), ``"resample"`` or ``"split"`` (see :func:`metrics.cd_floor`).
    """
    if emd_points < 1 or emd_every < 0 or batch_tracks < 1 or workers < 0:
        raise ConfigError("emd_points and batch_tracks must be >= 1, emd_every and workers >= 0")
    if floor not in ("auto", "resample", "split"):
        raise ConfigError(f"unknown CD floor method {floor!r}")
    n = len(dataset) if max_tracks is None else min(len(dataset), max_tracks)
    tracks, spans = [], []
    for i in range(n):
        tr = dataset[i]
        span = detection_span(tr)
        if span is None:
            log.warning("track %s has no detections; skipped", tr.track_id)
            continue
        tracks.append(tr)
        spans.append(span)
    if not tracks:
        raise SeqshapeError("no track with detections to evaluate")
    _announce_emd(tracks, spans, len(estimators), emd_every, emd_points, workers)
    col = _Collector(workers if emd_every > 0 else 0)
    k_of: dict[str, int] = {}
    total = sum(b - a for a, b in spans) * len(estimators)
    bar = progress(total=total, desc="evaluate", unit="frame")
    try:
        for c in range(0, len(tracks), batch_tracks):
            for name, est in estimators.items():
                k = _run_chunk(col, name, est, tracks[c:c + batch_tracks],
                               spans[c:c + batch_tracks], emd_points, emd_every, bar, hints)
                k_of[name] = k_of.get(name) or k
        bar.close()
        fl = _floors(tracks, {k for k in k_of.values() if k}, floor, seed, col,
                     emd_points if emd_every > 0 else 0)
        records = col.finish()
    except BaseException:
        if col.pool:
            col.pool.shutdown(cancel_futures=True)
        raise
    floors = {"track_id": np.array([f[0] for f in fl], dtype=str),
              "floor_m": np.array([f[1] for f in fl], dtype=np.float64),
              "n_pred": np.array([f[2] for f in fl], dtype=np.int64),
              "method": np.array([f[3] for f in fl], dtype=str),
              "emd_floor_m": np.array([f[4] * col.floor_emd.get(i, np.nan)
                                       for i, f in enumerate(fl)], dtype=np.float64)}
    settings = dict(n_tracks=len(tracks), emd_points=emd_points, emd_every=emd_every,
                    floor=floor, seed=seed, methods=list(estimators), hints=hints,
                    modes={name: _mode(est) for name, est in estimators.items()},
                    n_pred_points=k_of, real=is_real(tracks),
                    n_reference_tracks=sum(tr.complete is not None for tr in tracks))
    return EvalResult(records, floors, settings)
