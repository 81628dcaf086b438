"""Pseudo-labels for self-supervised fine-tuning on a user's own unlabelled tracks.

The paper fine-tunes on real tracks whose complete shapes are the accumulated scans of each
track (its KITTI experiment). With annotations that is :func:`seqshape.data.reference.
accumulated_reference` on the annotated boxes (``seqshape tracks`` / ``export-tracks``). A
user's own log often has a tracker's boxes only, or none worth trusting. :func:`pseudo_label`
makes the labels from the models themselves, with the most each track offers:

1. the sequential model estimates the whole track **offline** (every frame's estimate uses
   the whole track, past and future, :mod:`seqshape.model.offline`; with the track's ego poses
   and timestamps and the placement refiner): a pose per frame from its first to its last
   detection (frames outside that span get no pose: NaN, and are left out of training);
2. the track's size is the median over its frames with points of the estimated extents
   (:func:`seqshape.model.placement.extents_of`, the 1st-99th percentiles of the decoded cloud
   in its box frame) and its height;
3. its complete shape is the accumulation of the track's own points in those estimated box
   frames (:func:`~seqshape.data.reference.accumulated_reference`: box and ground cuts,
   mirrored, thinned, outliers removed, resampled), so the shape target is real surface the
   sensor saw, not the network's guess.

The tracks keep their ids, points, timestamps, ego poses and split; ``meta["pseudo"]`` records
where the labels came from, ``meta["reference"]`` the accumulation. The original poses, sizes
and shapes, if any, are not used. A track with too few points inside its estimated boxes for
an accumulation (:data:`~seqshape.data.reference.MIN_POINTS`) gets no complete shape, and
``seqshape pseudo-label`` leaves it out of the dataset it writes (``seqshape train`` needs a
shape for every track), saying how many.

Fine-tuning on them (``seqshape train --data PSEUDO --init pretrained --stage-steps 0,0,N``)
adapts the shapes to the log's vehicles and distils the offline estimates into the online
network; it cannot correct what the offline estimates get wrong in every frame (a length never
seen). Measure it as ``benchmarks/bm_realdata.py --finetune-labels pseudo`` does: labels made
on the train tracks only, scored on annotated tracks held out by vehicle.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from seqshape._progress import progress
from seqshape.data import Track
from seqshape.data.reference import NoReferenceError, accumulated_reference
from seqshape.model.offline import estimate_tracks
from seqshape.model.placement import extents_of


def _track_args(tr: Track, frames: range) -> dict:
    egos = [tr.ego_pose(t) for t in frames]
    return {"points": [tr.points[t] for t in frames],
            "timestamps": np.asarray(tr.timestamps[frames.start:frames.stop]),
            "cls": tr.meta.get("class") or None,
            "ego_poses": egos if any(e is not None for e in egos) else None,
            "track_id": tr.track_id}


def pseudo_track(tr: Track, estimates: Sequence, frames: range, source: str) -> Track:
    """``tr`` with the poses, size and accumulated complete shape of its offline
    ``estimates`` over ``frames`` (module doc)."""
    n = len(tr)
    poses = np.full((n, 4), np.nan)
    extents = []
    for t, e in zip(frames, estimates, strict=True):
        if not e.valid or not np.all(np.isfinite(e.pose)):
            continue
        poses[t] = np.asarray(e.pose, dtype=np.float64)
        if len(tr.points[t]) and len(e.complete):
            extents.append(extents_of(e.complete, poses[t]))
    size = np.median(np.asarray(extents), axis=0) if extents else np.full(3, np.nan)
    meta = {k: v for k, v in tr.meta.items() if k != "reference"}
    meta["pseudo"] = {"labels": "offline estimates", "models": source,
                      "frames": int(np.isfinite(poses[:, 0]).sum())}
    base = Track(tr.track_id, tr.points, poses, None, size, tr.timestamps, meta)
    if not np.all(np.isfinite(size)):
        meta["reference"] = {"kind": None, "error": "no estimate with points"}
        return base
    try:
        complete, info = accumulated_reference(base)
    except NoReferenceError as exc:
        meta["reference"] = {"kind": None, "error": str(exc)}
        return base
    info["note"] = "observed points accumulated with the offline estimates' boxes"
    meta["reference"] = info
    return Track(tr.track_id, tr.points, poses, complete, size, tr.timestamps, meta)


def pseudo_label(tracks: Iterable[Track], estimator, source: str = "",
                 chunk: int = 16) -> list[Track]:
    """Pseudo-labelled copies of ``tracks`` (module doc), estimated with ``estimator`` (a
    sequential :class:`~seqshape.model.Estimator`, offline) ``chunk`` tracks per batched
    pass. ``source`` names the models in ``meta["pseudo"]``. A track without any point is
    returned with NaN poses and no shape."""
    tracks = list(tracks)
    out: list[Track | None] = [None] * len(tracks)
    todo = []
    for i, tr in enumerate(tracks):
        det = np.flatnonzero(tr.num_points > 0)
        if not len(det):
            out[i] = pseudo_track(tr, [], range(0), source)
        else:
            todo.append((i, range(int(det[0]), int(det[-1]) + 1)))
    bar = progress(total=sum(len(f) for _, f in todo), desc="pseudo-labels", unit="frame")
    step = max(int(chunk), 1)
    try:
        for k in range(0, len(todo), step):
            part = todo[k:k + step]
            results = estimate_tracks(estimator, [_track_args(tracks[i], f) for i, f in part],
                                      "offline")
            for (i, frames), est in zip(part, results, strict=True):
                out[i] = pseudo_track(tracks[i], est, frames, source)
                bar.update(len(frames))
    finally:
        bar.close()
    return out
