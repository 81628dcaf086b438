"""Completing tracks with the sequential estimator, online (the paper) and offline (refined).

A :class:`TrackInput` is one vehicle's segmented points over the frames where it is labelled.
All tracks of a sequence go through the :class:`~seqshape.Estimator` together, one batched
``step`` per frame (each track's state advances only on its own frames).

Strategies (``refine=``), all returning one completed cloud ``(K, 3)`` per track and frame in
that frame's sensor frame:

* ``"none"`` (forward, the paper): frame t gets the estimate after frames ``0..t``.
* ``"bidirectional"``: the sequence is also run backwards (a separate state); frame t takes the
  forward or backward estimate, whichever has fused more points (cumulative input points up to
  t forwards, from t to the end backwards). Early frames of a track, where the forward estimate
  has seen little, profit from everything that comes after.
* ``"backfill"``: the best fused shape (the estimate with the most accumulated points over
  both passes) is taken into the canonical frame with its own estimated pose and carried to
  every frame: with the ground-truth pose when known (sc-gt), else with that frame's
  bidirectional pose estimate or its 180-degree flip, whichever places it closer (Chamfer) to
  the frame's own completed cloud.
* ``"smooth"``: as ``"backfill"``, but without ground-truth poses the best shape is placed
  with the track's smoothed poses (:mod:`seqshape.model.smooth`: a robust local fit of the
  bidirectional pose estimates in the world frame given by the ego poses, heading from the
  motion of moving vehicles; frames without points are not fitted but get the fit's pose at
  their time). With ground-truth poses it equals ``"backfill"``.

Box fitting (``fit_box=True``, sc-gt only: it needs the ground-truth boxes): every frame's
estimated shape is taken into the canonical frame with its own estimated pose, stretched per
axis so that its robust extent (1st-99th percentile) fills the box ``(l, w, h)``, and placed
at the ground-truth pose. The estimator then supplies only what the box cannot: the vehicle's
outline inside it (bonnet, roof line, wheel arches). ``fit_box_below=N`` fits only the tracks
whose best estimate fused fewer than N points: a vehicle with no or a handful of LiDAR returns
(far away, hidden) gets the estimator's prior shape, which knows nothing of its size, so the
box is then the better source of the extent.

Frames with no points (a labelled box with no LiDAR return) do not advance the estimate; with
ground-truth poses the previous shape is carried to the new pose, else the estimate is the
state's prediction.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from seqshape.geometry import canonical_to_sensor, sensor_to_canonical
from seqshape.model.smooth import smooth_track_poses

REFINE_MODES = ("none", "bidirectional", "backfill", "smooth")


@dataclass
class TrackInput:
    """One track to complete: ``points[i]`` ``(N_i, 3)`` sensor frame of frame ``frames[i]``.

    ``poses`` ``(T, 4)`` ground-truth poses per listed frame, or None when unknown.
    """

    track_id: str
    frames: list[int]
    points: list[np.ndarray]
    poses: np.ndarray | None = None
    category_id: int = 4
    label_id: int = 0  # the integer track id written to the labels
    size: np.ndarray | None = None  # (3,) ground-truth box (l, w, h), or None when unknown
    ego: np.ndarray | None = None  # (T, 4, 4) sensor -> common frame per listed frame
    masks: list | None = None  # sc-seg: per listed frame the COCO RLE of its 2D mask, or None


@dataclass
class Completion:
    """Per listed frame: ``clouds[i] (K, 3)`` and ``poses[i] (4,)`` sensor frame; ``fused[i]``
    the number of input points fused into that estimate."""

    clouds: list[np.ndarray]
    poses: np.ndarray
    fused: np.ndarray


def _run(estimator, tracks: Sequence[TrackInput], reverse: bool, tag: str) -> list[Completion]:
    """One pass (forward or backward) over all tracks, batched per frame."""
    order = sorted({f for t in tracks for f in t.frames}, reverse=reverse)
    pos = [{f: i for i, f in enumerate(t.frames)} for t in tracks]
    out = [Completion([None] * len(t.frames), np.zeros((len(t.frames), 4)),
                      np.zeros(len(t.frames), np.int64)) for t in tracks]
    fused = [0] * len(tracks)
    last_seen = [None] * len(tracks)  # (canonical shape) for carrying over empty frames
    remaining = [len(t.frames) for t in tracks]
    for f in order:
        live = [k for k, p in enumerate(pos) if f in p]
        ids = [f"{tracks[k].track_id}/{tag}" for k in live]
        pts = [tracks[k].points[pos[k][f]] for k in live]
        for k, est, p in zip(live, estimator.step(ids, pts), pts, strict=True):
            i = pos[k][f]
            fused[k] += len(p)
            cloud, pose = est.complete, est.pose
            gt = tracks[k].poses
            if len(p) == 0 and gt is not None and (last_seen[k] is not None or not est.valid):
                # an empty frame of a known box: the last shape seen, or before the track's
                # first points (an estimate from nothing, placed around the sensor origin) the
                # network's prior shape, at the true pose
                shape = last_seen[k] if last_seen[k] is not None else \
                    sensor_to_canonical(est.complete, est.pose)
                cloud, pose = canonical_to_sensor(shape, gt[i]), gt[i]
            elif len(p):
                last_seen[k] = sensor_to_canonical(est.complete, est.pose)
            out[k].clouds[i], out[k].poses[i], out[k].fused[i] = cloud, pose, fused[k]
            remaining[k] -= 1
            if remaining[k] == 0:
                estimator.reset(ids[live.index(k)])
    return out


def complete_forward(estimator, tracks: Sequence[TrackInput]) -> list[Completion]:
    """The paper's online completion of every track (strategy ``"none"``)."""
    return _run(estimator, tracks, reverse=False, tag="fwd")


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) == 0 or len(b) == 0:
        return np.inf
    return float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def _pick(fwd: Completion, bwd: Completion) -> Completion:
    """Per frame, the estimate of the pass that fused more points (bidirectional)."""
    use_fwd = fwd.fused >= bwd.fused
    return Completion([a if u else b for a, b, u in zip(fwd.clouds, bwd.clouds, use_fwd,
                                                        strict=True)],
                      np.where(use_fwd[:, None], fwd.poses, bwd.poses),
                      np.maximum(fwd.fused, bwd.fused))


def _backfill(track: TrackInput, fwd: Completion, bwd: Completion, bi: Completion,
              smooth: bool = False) -> Completion:
    """Carry the best fused shape to every frame (module doc)."""
    best_f, best_b = int(np.argmax(fwd.fused)), int(np.argmax(bwd.fused))
    src = fwd if fwd.fused[best_f] >= bwd.fused[best_b] else bwd
    i = best_f if src is fwd else best_b
    shape = sensor_to_canonical(src.clouds[i], src.poses[i])  # (K, 3) canonical
    clouds, poses = [], np.zeros_like(bi.poses)
    smoothed = None
    if smooth and (track.poses is None or not np.all(np.isfinite(track.poses))):
        valid = np.array([len(p) > 0 for p in track.points])
        smoothed = smooth_track_poses(bi.poses, track.frames, track.ego, valid=valid)
    for t in range(len(track.frames)):
        if track.poses is not None and np.all(np.isfinite(track.poses[t])):
            cands = [track.poses[t]]
        elif smoothed is not None:
            cands = [smoothed[t]]
        else:
            flip = bi.poses[t] + np.array([0.0, 0.0, 0.0, np.pi])
            cands = [bi.poses[t], flip]
        placed = [canonical_to_sensor(shape, p) for p in cands]
        j = 0 if len(cands) == 1 else int(np.argmin([_chamfer(c, bi.clouds[t]) for c in placed]))
        clouds.append(placed[j])
        poses[t] = cands[j]
    return Completion(clouds, poses, np.full(len(track.frames), src.fused[i]))


def fit_to_box(shape: np.ndarray, size, lo: float = 1.0, hi: float = 99.0) -> np.ndarray:
    """Stretch a canonical shape ``(K, 3)`` per axis so its ``lo``-``hi`` percentile extent
    becomes the box ``size = (l, w, h)`` centred on the origin (the box centre)."""
    shape = np.asarray(shape, dtype=np.float64)
    size = np.asarray(size, dtype=np.float64).reshape(3)
    if len(shape) == 0:
        return shape
    a, b = np.percentile(shape, [lo, hi], axis=0)  # (3,), (3,)
    extent = b - a
    scale = np.where(extent > 1e-6, size / np.maximum(extent, 1e-6), 1.0)
    return (shape - (a + b) / 2) * scale


def _fit_boxes(track: TrackInput, comp: Completion) -> Completion:
    """Re-place every frame's estimated shape in the track's ground-truth box (module doc)."""
    if track.poses is None or track.size is None:
        raise ValueError(f"track {track.track_id}: box fitting needs ground-truth poses and a "
                         f"box size")
    clouds, poses = [], comp.poses.copy()
    for t, (cloud, pose) in enumerate(zip(comp.clouds, comp.poses, strict=True)):
        gt = track.poses[t]
        if cloud is None or not np.all(np.isfinite(gt)):
            clouds.append(cloud)
            continue
        clouds.append(canonical_to_sensor(fit_to_box(sensor_to_canonical(cloud, pose),
                                                     track.size), gt))
        poses[t] = gt
    return Completion(clouds, poses, comp.fused)


def trim_to_extent(shape: np.ndarray, percent: float) -> np.ndarray:
    """The points of a canonical shape ``(K, 3)`` inside its robust box: per axis between the
    ``percent`` and ``100 - percent`` percentiles (0 keeps every point)."""
    shape = np.asarray(shape)
    if percent <= 0 or len(shape) == 0:
        return shape
    a, b = np.percentile(shape, [percent, 100.0 - percent], axis=0)
    return shape[np.all((shape >= a) & (shape <= b), axis=1)]


def _trim(comp: Completion, percent: float) -> Completion:
    """Every frame's cloud trimmed to its robust box in its own canonical frame."""
    clouds = [c if c is None or len(c) == 0 else canonical_to_sensor(
        trim_to_extent(sensor_to_canonical(c, p), percent), p).astype(np.float32)
        for c, p in zip(comp.clouds, comp.poses, strict=True)]
    return Completion(clouds, comp.poses, comp.fused)


def complete_tracks(estimator, tracks: Sequence[TrackInput], refine: str = "none",
                    fit_box: bool = False, fit_box_below: int = 0,
                    trim: float = 0.0) -> list[Completion]:
    """Complete every track with one of :data:`REFINE_MODES`, optionally fitted to its
    ground-truth box (module doc): every track with ``fit_box``, else the tracks with a known
    box whose best estimate fused fewer than ``fit_box_below`` points. ``trim`` > 0 drops the
    points outside each shape's robust box (:func:`trim_to_extent`, in percent per side)."""
    if refine not in REFINE_MODES:
        raise ValueError(f"refine must be one of {REFINE_MODES}, got {refine!r}")
    fwd = complete_forward(estimator, tracks)
    if refine == "none":
        out = fwd
    else:
        bwd = _run(estimator, tracks, reverse=True, tag="bwd")  # fused: points from t to end
        out = [_pick(f, b) for f, b in zip(fwd, bwd, strict=True)]
        if refine in ("backfill", "smooth"):
            out = [_backfill(t, f, b, c, refine == "smooth")
                   for t, f, b, c in zip(tracks, fwd, bwd, out, strict=True)]
    out = [_fit_boxes(t, c) if fit_box or (
        fit_box_below > 0 and t.poses is not None and t.size is not None
        and int(c.fused.max(initial=0)) < fit_box_below) else c
        for t, c in zip(tracks, out, strict=True)]
    return [_trim(c, trim) for c in out] if trim > 0 else out
