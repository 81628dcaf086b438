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
crop                  the :class:`~seqshape.data.crop.CropConfig` used
reference             absent, or how ``complete`` was made (accumulated reference)
====================  ==========================================================

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


def extract_tracks(log: DrivingLog, classes: Iterable[str] | None = None,
                   crop: CropConfig | None = None, min_points: int = 0,
                   frames: Iterable[int] | None = None) -> list[Track]:
    """The vehicle tracks of ``log`` (module doc).

    ``classes``: seqshape vehicle classes to keep (default all); ``min_points``: a track is
    kept when at least one of its frames has that many points after the crop; ``frames``: only
    these frames of the log (default all).
    """
    wanted = set(VEHICLE_CLASSES if classes is None else classes)
    crop = crop or CropConfig()
    rows: dict[str, list[tuple]] = {}
    for frame in (log.frames if frames is None else frames):
        boxes = [b for b in log.boxes(frame) if b.cls in wanted]
        if not boxes:
            continue
        sweep = np.asarray(log.points(frame))
        plane = _SweepPlane(sweep)
        cuts = crop_vehicles(sweep, [b.pose for b in boxes], [b.size for b in boxes], crop,
                             sweep_plane=plane.get)
        for b, pts in zip(boxes, cuts, strict=True):
            rows.setdefault(b.track_id, []).append((frame, pts, b))
    tracks = []
    for oid in sorted(rows):
        r = rows[oid]
        if max(len(x[1]) for x in r) < min_points:
            continue
        frs = [x[0] for x in r]
        first = r[0][2]
        meta = {"source": "real", "dataset": log.dataset, "log": log.name,
                "root": str(log.root), "object_id": oid, "category": first.category,
                "class": first.cls, "sensor": log.sensor, "frames": frs,
                "dataset_num_points": [x[2].num_points for x in r],
                "visibility": [x[2].visibility for x in r], "crop": crop.to_dict()}
        ego = [log.ego_pose(f) for f in frs]
        if all(e is not None for e in ego):
            meta["ego_poses"] = [np.asarray(e, dtype=np.float64).tolist() for e in ego]
        tracks.append(Track(
            track_id=track_name(log.name, oid), points=[x[1] for x in r],
            poses=np.stack([x[2].pose for x in r]), complete=None,
            size=np.median(np.stack([x[2].size for x in r]), axis=0),
            timestamps=log.timestamps(frs), meta=meta))
    _log.info("%s %s: %d tracks extracted", log.dataset, log.name, len(tracks))
    return tracks
