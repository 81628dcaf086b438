"""Vehicle tracks from any driving log: per annotated vehicle, its points in every frame.

:func:`extract_tracks` takes a :class:`~seqshape.data.sequence.DrivingLog` and returns one
:class:`~seqshape.data.Track` per annotated vehicle track, its frames in log order, cut out
of each sweep by :func:`seqshape.data.crop.crop_vehicle` (all boxes of a sweep at once,
:func:`~seqshape.data.crop.crop_vehicles`). The ``meta`` schema of such a track
(docs/data-format.md, "Real tracks"):

====================  ==========================================================
key                   value
====================  ==========================================================
source                ``"real"``
dataset               ``"kitti"``, ``"av2"``, ``"nuscenes"`` (the reader's name)
log                   the log's name (KITTI sequence, AV2 log id, nuScenes scene)
root                  the dataset folder it was read from
object_id             the dataset's id of the object (KITTI track id, AV2 track
                      uuid, nuScenes instance token)
category              the dataset's category name (of the first frame)
class                 seqshape's vehicle class (car, van, truck, bus, trailer)
sensor                the LiDAR model (``log.sensor``)
frames                the log's frame numbers of the track's frames
dataset_num_points    per frame, the dataset's count of points in the box, or null
visibility            per frame, the dataset's visibility value, or null
ego_poses             per frame, (4, 4) sensor frame -> log reference frame
                      (absent when the log has no ego motion)
ego_pose_source       ``"given"`` (the log's own) or ``"lidar"`` (LiDAR odometry,
                      :mod:`seqshape.data.odometry`); absent without ego poses
crop                  the :class:`~seqshape.data.crop.CropConfig` used
duplicates            absent, or the object ids of the log's duplicate annotations
                      of this vehicle, left out (:func:`duplicate_objects`)
reference             absent, or how ``complete`` was made (accumulated reference)
====================  ==========================================================

**Duplicate annotations.** Real logs now and then annotate one vehicle twice: two object ids
whose boxes coincide in every frame (one such pair in Argoverse 2 log
7fab2350-7eaf-3b7e-a39d-6937a4c1bede: centres within 3.3 cm of each other in all 156 annotated
sweeps; argoverse/argoverse-api issue 40 reports others in Argoverse 1).
Both would be one vehicle counted twice by ``evaluate`` and labelled twice by ``label``. Two
boxes of one class whose centres are within :data:`DUPLICATE_DISTANCE` in at least
:data:`DUPLICATE_SHARE` of the frames they share are one vehicle (two real vehicles cannot be
that close: their bodies would overlap); the track with more frames is kept (the smaller id on
a tie), the other left out with a warning and named in the kept track's ``duplicates``.
``keep_duplicates=True`` keeps every annotation as it is.

Track ids are ``LOG_OBJECT`` (KITTI ``SSSS_TTTT`` as before), with characters that are not
safe in file names replaced by ``-``.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable

import numpy as np

from seqshape.data.crop import CropConfig, crop_vehicles
from seqshape.data.ground import ground_plane
from seqshape.data.sequence import VEHICLE_CLASSES, DrivingLog
from seqshape.data.track import Track

_log = logging.getLogger(__name__)

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def track_name(log_name: str, object_id: str) -> str:
    """The Track id of object ``object_id`` of log ``log_name`` (file-name safe)."""
    return _UNSAFE.sub("-", f"{log_name}_{object_id}")


class _SweepPlane:
    """The sweep's ground plane, fitted only when a local fit needs it (``.get``)."""

    def __init__(self, points: np.ndarray):
        self.points = points
        self._plane = None

    def get(self):
        if self._plane is None:
            self._plane = ground_plane(self.points[:, :3])
        return self._plane


DUPLICATE_DISTANCE = 0.5  # m between two boxes' centres (3D): one vehicle annotated twice
DUPLICATE_SHARE = 0.9  # of the frames two tracks share, the part where they must coincide


def duplicate_objects(boxes_by_frame: Iterable[Iterable]) -> dict[str, str]:
    """The duplicate annotations among a log's boxes (module doc): ``{dropped id: kept id}``.

    ``boxes_by_frame``: per frame, its :class:`~seqshape.data.sequence.Box3D` boxes. A chain
    (A duplicates B duplicates C) keeps one of the three."""
    seen: dict[str, set[int]] = {}
    near: dict[tuple[str, str], int] = {}
    for f, boxes in enumerate(boxes_by_frame):
        boxes = list(boxes)
        for b in boxes:
            seen.setdefault(b.track_id, set()).add(f)
        if len(boxes) < 2:
            continue
        centres = np.array([b.centre for b in boxes])
        d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
        for i, j in zip(*np.nonzero(np.triu(d < DUPLICATE_DISTANCE, 1)), strict=True):
            a, b = boxes[i], boxes[j]
            if a.cls == b.cls and a.track_id != b.track_id:
                key = tuple(sorted((a.track_id, b.track_id)))
                near[key] = near.get(key, 0) + 1
    same = sorted(p for p, k in near.items()
                  if k >= DUPLICATE_SHARE * len(seen[p[0]] & seen[p[1]]))
    frames = {t: len(v) for t, v in seen.items()}
    keep_of: dict[str, str] = {}

    def root(x: str) -> str:
        while x in keep_of:
            x = keep_of[x]
        return x

    for a, b in same:
        ra, rb = root(a), root(b)
        if ra == rb:
            continue
        kept, dropped = sorted((ra, rb), key=lambda t: (-frames[t], t))
        keep_of[dropped] = kept
    return {d: root(d) for d in keep_of}


def extract_tracks(log: DrivingLog, classes: Iterable[str] | None = None,
                   crop: CropConfig | None = None, min_points: int = 0,
                   frames: Iterable[int] | None = None,
                   keep_duplicates: bool = False) -> list[Track]:
    """The vehicle tracks of ``log`` (module doc).

    ``classes``: seqshape vehicle classes to keep (default all); ``min_points``: a track is
    kept when at least one of its frames has that many points after the crop; ``frames``: only
    these frames of the log (default all); ``keep_duplicates``: keep a vehicle's duplicate
    annotations as tracks of their own (module doc, "Duplicate annotations").

    In two parts, for callers that spread the frames over processes: :func:`crop_frames`
    (each frame on its own) and :func:`tracks_from_crops` (the frames' crops joined).
    """
    crop = crop or CropConfig()
    cuts = crop_frames(log, log.frames if frames is None else frames, classes, crop)
    return tracks_from_crops(log, cuts, crop, min_points, keep_duplicates)


def crop_frames(log: DrivingLog, frames: Iterable[int], classes: Iterable[str] | None = None,
                crop: CropConfig | None = None) -> list[tuple[int, list, list]]:
    """Per frame of ``frames``, ``(frame, its boxes of the wanted classes, each box's points)``
    (:func:`~seqshape.data.crop.crop_vehicles`; no points read for a frame without boxes): the
    part of :func:`extract_tracks` that takes each frame on its own."""
    wanted = set(VEHICLE_CLASSES if classes is None else classes)
    crop = crop or CropConfig()
    out = []
    for frame in frames:
        boxes = [b for b in log.boxes(frame) if b.cls in wanted]
        if not boxes:
            out.append((frame, boxes, []))
            continue
        sweep = np.asarray(log.points(frame))
        plane = _SweepPlane(sweep)
        out.append((frame, boxes, crop_vehicles(sweep, [b.pose for b in boxes],
                                                [b.size for b in boxes], crop,
                                                sweep_plane=plane.get)))
    return out


def tracks_from_crops(log: DrivingLog, cuts: Iterable[tuple[int, list, list]],
                      crop: CropConfig | None = None, min_points: int = 0,
                      keep_duplicates: bool = False) -> list[Track]:
    """The tracks of :func:`extract_tracks` from the frames' :func:`crop_frames` (in log
    order; ``crop``: the :class:`~seqshape.data.crop.CropConfig` they were cut with)."""
    crop = crop or CropConfig()
    rows: dict[str, list[tuple]] = {}
    per_frame = []
    for frame, boxes, points in cuts:
        if not keep_duplicates:
            per_frame.append(boxes)
        for b, pts in zip(boxes, points, strict=True):
            rows.setdefault(b.track_id, []).append((frame, pts, b))
    dropped = {} if keep_duplicates else duplicate_objects(per_frame)
    for d, k in sorted(dropped.items()):
        _log.warning("%s %s: object %s is a duplicate annotation of %s (box centres within "
                     "%.1f m in %d %% or more of the frames they share): left out",
                     log.dataset, log.name, d, k, DUPLICATE_DISTANCE, round(100 * DUPLICATE_SHARE))
    tracks = []
    for oid in sorted(rows):
        r = rows[oid]
        if oid in dropped or max(len(x[1]) for x in r) < min_points:
            continue
        frs = [x[0] for x in r]
        first = r[0][2]
        meta = {"source": "real", "dataset": log.dataset, "log": log.name,
                "root": str(log.root), "object_id": oid, "category": first.category,
                "class": first.cls, "sensor": log.sensor, "frames": frs,
                "dataset_num_points": [x[2].num_points for x in r],
                "visibility": [x[2].visibility for x in r], "crop": crop.to_dict()}
        dups = sorted(d for d, k in dropped.items() if k == oid)
        if dups:
            meta["duplicates"] = dups
        ego = [log.ego_pose(f) for f in frs]
        if all(e is not None for e in ego):
            meta["ego_poses"] = [np.asarray(e, dtype=np.float64).tolist() for e in ego]
            meta["ego_pose_source"] = log.ego_pose_source
        tracks.append(Track(
            track_id=track_name(log.name, oid), points=[x[1] for x in r],
            poses=np.stack([x[2].pose for x in r]), complete=None,
            size=np.median(np.stack([x[2].size for x in r]), axis=0),
            timestamps=log.timestamps(frs), meta=meta))
    _log.info("%s %s: %d tracks extracted", log.dataset, log.name, len(tracks))
    return tracks
