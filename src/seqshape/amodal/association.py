"""Associating per-frame instances (segmented LiDAR points + 2D masks) into tracks.

Frame by frame, live tracks are matched to the frame's detections by the Hungarian algorithm
(``scipy.optimize.linear_sum_assignment``) on the cost

    cost = |c_pred - c_det| / gate + iou_weight * (1 - IoU(mask_last, mask_det)),

where ``c`` are 3D centroids (the median of the instance's points) in a common frame (the
log's reference frame when ego poses are given, else each frame's sensor frame),
``c_pred`` is the track's last centroid extrapolated at constant velocity, and ``mask_last`` the
track's last 2D mask. Pairs farther apart than ``gate`` metres are forbidden. Unmatched
detections start new tracks; a track unmatched for more than ``max_age`` frames ends.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from seqshape._progress import progress
from seqshape.amodal.diffusion import diffuse_labels, ground_mask, ground_plane, grow_instances
from seqshape.amodal.refine import TrackInput
from seqshape.camera import as_camera
from seqshape.data.kins import read_coco_instances, rle_to_mask
from seqshape.errors import DataError

_FORBIDDEN = 1e6


@dataclass
class Detection:
    """One instance of one frame: ``centroid (3,)`` in the common frame, ``mask (h, w)`` bool
    (or its :class:`BoxMask`, as a worker process sends it)."""

    frame: int
    centroid: np.ndarray
    mask: np.ndarray | BoxMask
    index: int = 0  # position in its frame's detection list


@dataclass
class _Live:
    track: int
    frames: list[int] = field(default_factory=list)
    centroids: list[np.ndarray] = field(default_factory=list)
    mask: np.ndarray | None = None

    def predict(self, frame: int) -> np.ndarray:
        c = self.centroids[-1]
        if len(self.centroids) < 2:
            return c
        dt = self.frames[-1] - self.frames[-2]
        vel = (self.centroids[-1] - self.centroids[-2]) / max(dt, 1)
        return c + vel * (frame - self.frames[-1])


@dataclass
class BoxMask:
    """A 2D bool mask of ``shape`` kept as its pixels' bounding box ``(y0, y1, x0, x1)`` (end
    exclusive) and the mask within it: what a detection's mask becomes when a worker process
    sends it (:class:`FrameSegments`), a small part of the full image, all that the
    association's overlap test (:func:`_mask_iou`) needs."""

    shape: tuple[int, int]
    box: tuple[int, int, int, int]
    crop: np.ndarray

    @classmethod
    def of(cls, mask: np.ndarray) -> BoxMask:
        """The :class:`BoxMask` of a full bool mask."""
        if isinstance(mask, BoxMask):
            return mask
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if len(rows) == 0:
            return cls(mask.shape, (0, 0, 0, 0), np.zeros((0, 0), dtype=bool))
        box = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        return cls(mask.shape, box, np.ascontiguousarray(mask[box[0]:box[1], box[2]:box[3]]))

    def full(self) -> np.ndarray:
        """The full ``shape`` bool mask."""
        out = np.zeros(self.shape, dtype=bool)
        y0, y1, x0, x1 = self.box
        out[y0:y1, x0:x1] = self.crop
        return out

    def count(self) -> int:
        return int(np.count_nonzero(self.crop))


def _mask_iou(a, b) -> float:
    """Intersection over union of two masks (full bool arrays or :class:`BoxMask`)."""
    if not isinstance(a, BoxMask) and not isinstance(b, BoxMask):
        inter = np.logical_and(a, b).sum()
        union = np.logical_or(a, b).sum()
        return float(inter / union) if union else 0.0
    a, b = BoxMask.of(a), BoxMask.of(b)
    y0, y1 = max(a.box[0], b.box[0]), min(a.box[1], b.box[1])
    x0, x1 = max(a.box[2], b.box[2]), min(a.box[3], b.box[3])
    inter = 0
    if y1 > y0 and x1 > x0:
        inter = int(np.count_nonzero(
            a.crop[y0 - a.box[0]:y1 - a.box[0], x0 - a.box[2]:x1 - a.box[2]]
            & b.crop[y0 - b.box[0]:y1 - b.box[0], x0 - b.box[2]:x1 - b.box[2]]))
    union = a.count() + b.count() - inter
    return float(inter / union) if union else 0.0


def to_common_frame(centroid, ego_pose) -> np.ndarray:
    """A sensor-frame point ``(3,)`` mapped by a ``(4, 4)`` ego pose (frame t -> frame 0)."""
    c = np.asarray(centroid, dtype=np.float64)
    if ego_pose is None:
        return c
    e = np.asarray(ego_pose, dtype=np.float64)
    return e[:3, :3] @ c + e[:3, 3]


def associate(frames: Sequence[Sequence[Detection]], gate: float = 3.0,
              iou_weight: float = 1.0, max_age: int = 3) -> list[list[int]]:
    """Track ids (0, 1, ...) for the detections of consecutive frames.

    ``frames[i]`` lists frame i's detections (their ``frame`` fields must increase with i).
    Returns, per frame, the track id of each detection, in the same order.
    """
    live: list[_Live] = []
    next_id = 0
    out: list[list[int]] = []
    for dets in frames:
        ids = [-1] * len(dets)
        if dets:
            frame = dets[0].frame
            live = [t for t in live if frame - t.frames[-1] <= max_age + 1]
            if live:
                cost = np.full((len(live), len(dets)), _FORBIDDEN)
                for i, t in enumerate(live):
                    pred = t.predict(frame)
                    for j, d in enumerate(dets):
                        dist = float(np.linalg.norm(pred - d.centroid))
                        if dist <= gate:
                            cost[i, j] = dist / gate + iou_weight * (1 - _mask_iou(t.mask, d.mask))
                rows, cols = linear_sum_assignment(cost)
                for r, c in zip(rows, cols, strict=True):
                    if cost[r, c] < _FORBIDDEN:
                        ids[c] = live[r].track
                        live[r].frames.append(frame)
                        live[r].centroids.append(np.asarray(dets[c].centroid, np.float64))
                        live[r].mask = dets[c].mask
            for j, d in enumerate(dets):
                if ids[j] < 0:
                    ids[j] = next_id
                    live.append(_Live(next_id, [d.frame], [np.asarray(d.centroid, np.float64)],
                                      d.mask))
                    next_id += 1
        out.append(ids)
    return out


# ----------------------------------------------------------------------------- sc-seg input


def segment_frame(scan, camera, masks, min_depth: float = 1.0, grow: bool = True,
                  plane=None, **diffusion_kwargs):
    """Points of each 2D instance of one frame: a list (one per mask) of ``(N_i, 3)`` float32.

    ``scan (N, 3+)`` is in the sensor frame; ground points are removed
    (:func:`~seqshape.amodal.diffusion.ground_mask`, against ``plane`` when given), the rest
    projected with ``camera`` (a PinholeCamera of the masks' image), the
    points inside the image labelled by :func:`~seqshape.amodal.diffusion.diffuse_labels`, and
    (``grow``) each instance grown into the connected points outside the image
    (:func:`~seqshape.amodal.diffusion.grow_instances`).
    """
    camera = as_camera(camera)
    pts = np.asarray(scan)[:, :3].astype(np.float64)  # (N, 3) contiguous
    pts = pts[~ground_mask(pts, plane=plane)]
    uv, depth = camera.project(pts)
    keep = camera.in_image(uv, depth, min_depth=min_depth)
    seen = pts[keep]  # (M, 3): the points in the image
    labels = diffuse_labels(seen, uv[keep], masks, **diffusion_kwargs)
    parts = [seen[labels == m] for m in range(len(masks))]
    if grow:
        gap_kw = {k: diffusion_kwargs[k] for k in ("cluster_gap", "cluster_gap_per_m")
                  if k in diffusion_kwargs}
        parts = grow_instances(parts, pts[~keep], **gap_kw)
    return [p.astype(np.float32) for p in parts]


def fill_gaps(track, max_gap: int, ego=None):
    """``track`` with every run of at most ``max_gap`` missing frames between two of its
    frames filled by frames without points (their pose comes from the smoothed track:
    refinement ``"smooth"``); ``ego`` ``{frame: (4, 4)}`` (or an array indexed by frame) sets
    ``track.ego`` when every frame of the track has one."""
    frames, points, masks = [], [], []
    for i, f in enumerate(track.frames):
        if i and 0 < f - track.frames[i - 1] - 1 <= max_gap:
            for g in range(track.frames[i - 1] + 1, f):
                frames.append(g)
                points.append(np.zeros((0, 3), np.float32))
                masks.append(None)
        frames.append(f)
        points.append(track.points[i])
        masks.append(None if track.masks is None else track.masks[i])
    out = TrackInput(track.track_id, frames, points, None, track.category_id, track.label_id,
                     masks=None if track.masks is None else masks)
    out.ego = _ego_of(ego, frames)
    return out


def _ego_of(ego, frames) -> np.ndarray | None:
    """``(T, 4, 4)`` ego poses of ``frames`` from ``{frame: pose}``, or None if one lacks."""
    if ego is None or not frames:
        return None
    poses = [ego.get(f) if isinstance(ego, dict) else (ego[f] if f < len(ego) else None)
             for f in frames]
    if any(p is None for p in poses):
        return None
    return np.stack([np.asarray(p, dtype=np.float64) for p in poses])


def instance_masks_by_frame(log, camera: str, instances_path, categories=None
                            ) -> dict[int, list[dict]]:
    """``{frame: [COCO annotation, ...]}`` of ``log``'s frames from a COCO instance file.

    Images are matched by ``file_name`` to ``log.image_file_name(frame, camera)`` (KITTI:
    ``SSSS/FFFFFF.png``); segmentations may be RLE or polygons (read as RLE). ``categories``:
    keep only these category ids (default all).
    """
    instances_path = Path(instances_path)
    if not instances_path.is_file():
        raise DataError(instances_path, "2D instance masks not found: sc-seg needs the "
                                        "camera images' instance masks (COCO instance JSON; "
                                        "pass --instances FILE); the modes gt-accumulation "
                                        "and sc-gt need no images")
    doc = read_coco_instances(instances_path)
    by_name = {img["file_name"]: img["id"] for img in doc["images"]}
    anns: dict = {}
    for a in doc["annotations"]:
        if categories is None or a["category_id"] in categories:
            anns.setdefault(a["image_id"], []).append(a)
    out = {}
    for frame in log.frames:
        image_id = by_name.get(log.image_file_name(frame, camera))
        out[frame] = anns.get(image_id, []) if image_id is not None else []
    if log.frames and not any(img in by_name for img in
                              (log.image_file_name(f, camera) for f in log.frames)):
        logging.getLogger(__name__).warning(
            "%s: no image file_name matches %s (e.g. %r): no 2D instances", instances_path,
            log.name, log.image_file_name(log.frames[0], camera))
    return out


@dataclass
class FrameSegments:
    """What one frame contributes to sc-seg's tracks (:func:`segment_frames`): its
    detections (centroids in the common frame, 2D masks), their points ``(N_i, 3)`` float32,
    category ids and COCO segmentations, and the 2D instances dropped for too few points
    ``[(mask or None, COCO annotation, ground plane)]``. Pickles with its masks bit-packed
    (a worker process sends it back; its detections' masks arrive as :class:`BoxMask`)."""

    frame: int
    detections: list[Detection] = field(default_factory=list)
    points: list[np.ndarray] = field(default_factory=list)
    categories: list[int] = field(default_factory=list)
    segmentations: list = field(default_factory=list)
    unsupported: list[tuple] = field(default_factory=list)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["detections"] = [(d.frame, d.centroid, d.index, _packed(d.mask))
                               for d in self.detections]
        state["unsupported"] = [(_packed(m), a, p) for m, a, p in self.unsupported]
        return state

    def __setstate__(self, state: dict) -> None:
        state = dict(state)
        state["detections"] = [Detection(f, c, _unpacked_box(m), i)
                               for f, c, i, m in state["detections"]]
        state["unsupported"] = [(_unpacked(m), a, p) for m, a, p in state["unsupported"]]
        self.__dict__.update(state)


def _packed(mask) -> tuple | None:
    """A 2D bool mask (array or :class:`BoxMask`) as ``(shape, (y0, y1, x0, x1), packed bits
    of that box)``: its pixels' bounding box only, an eighth of its bytes; or None."""
    if mask is None:
        return None
    m = BoxMask.of(mask)
    return m.shape, m.box, np.packbits(m.crop, axis=None)


def _unpacked_box(packed: tuple | None) -> BoxMask | None:
    """The :class:`BoxMask` of :func:`_packed`."""
    if packed is None:
        return None
    shape, (y0, y1, x0, x1), bits = packed
    crop = np.unpackbits(bits, count=(y1 - y0) * (x1 - x0)).reshape(y1 - y0, x1 - x0)
    return BoxMask(tuple(shape), (y0, y1, x0, x1), crop.view(bool))


def _unpacked(packed: tuple | None) -> np.ndarray | None:
    """The full mask of :func:`_packed`."""
    box = _unpacked_box(packed)
    return None if box is None else box.full()


def segment_frames(log, camera: str, annotations: dict[int, list[dict]], frames,
                   min_points: int = 5, desc: str | None = None) -> list[FrameSegments]:
    """The :class:`FrameSegments` of each of ``frames`` of ``log`` (in that order), seen by
    ``camera``, from their COCO annotations ``{frame: [annotation, ...]}``
    (:func:`instance_masks_by_frame`): the masks decoded, the sweep's ground plane fitted, the
    points segmented (:func:`segment_frame`); instances with fewer than ``min_points`` points
    are unsupported. Each frame depends on itself only (the ground plane is seeded per
    sweep), so frames can be segmented apart and in any grouping. ``desc``: a progress bar."""
    frames = list(frames)
    it = frames if desc is None else progress(frames, desc=desc, unit="frame")
    return [_segment_one(log, camera, annotations.get(f, []), f, min_points) for f in it]


def _segment_one(log, camera: str, anns: list[dict], frame: int,
                 min_points: int) -> FrameSegments:
    out = FrameSegments(frame)
    masks = [rle_to_mask(a["segmentation"]) for a in anns]
    if not masks:
        return out
    scan = np.asarray(log.points(frame))
    plane = ground_plane(scan[:, :3])
    parts = segment_frame(scan, log.camera(camera, frame), masks, plane=plane)
    ego = log.ego_pose(frame)
    for m, (a, p) in enumerate(zip(anns, parts, strict=True)):
        if len(p) < min_points:
            out.unsupported.append((masks[m], a, plane))
            continue
        c = to_common_frame(np.median(p, axis=0), ego)
        out.detections.append(Detection(frame, c, masks[m], len(out.detections)))
        out.points.append(p)
        out.categories.append(int(a["category_id"]))
        out.segmentations.append(a["segmentation"])
    return out


def tracks_from_segments(log, segments: Sequence[FrameSegments], gate: float = 3.0,
                         max_gap: int = 0, unsupported: dict | None = None) -> list:
    """sc-seg's tracks (:func:`segment_sequence`) from the :class:`FrameSegments` of the
    log's frames in frame order: the detections associated (:func:`associate`), each track a
    :class:`~seqshape.amodal.refine.TrackInput` (category: the most frequent of its masks;
    ego poses when the log has them). ``unsupported`` receives ``{frame: [(mask, annotation,
    ground plane)]}`` of the dropped instances."""
    ego = {f: log.ego_pose(f) for f in log.frames}
    ego = {f: e for f, e in ego.items() if e is not None}
    if unsupported is not None:
        for seg in segments:
            if seg.unsupported:
                unsupported.setdefault(seg.frame, []).extend(seg.unsupported)
    ids = associate([seg.detections for seg in segments], gate=gate)
    tracks: dict[int, TrackInput] = {}
    cat_votes: dict[int, list[int]] = {}
    for seg, tids in zip(segments, ids, strict=True):
        for d, p, c, r, t in zip(seg.detections, seg.points, seg.categories,
                                 seg.segmentations, tids, strict=True):
            tr = tracks.setdefault(t, TrackInput(f"{log.name}_seg{t:04d}", [], [], None,
                                                 4, t, masks=[]))
            tr.frames.append(d.frame)
            tr.points.append(p)
            tr.masks.append(r)
            cat_votes.setdefault(t, []).append(c)
    for t, tr in tracks.items():
        tr.category_id = int(np.bincount(cat_votes[t]).argmax())
        tr.ego = _ego_of(ego, tr.frames)
    out = [tracks[t] for t in sorted(tracks)]
    return [fill_gaps(t, max_gap, ego) for t in out] if max_gap > 0 else out


def segment_sequence(log, instances_path, min_points: int = 5, gate: float = 3.0,
                     categories=None, max_gap: int = 0, unsupported: dict | None = None,
                     camera: str | None = None) -> list:
    """sc-seg tracks of a :class:`~seqshape.data.sequence.DrivingLog` seen by ``camera``
    (default: the log's default camera).

    Reads the COCO instance masks (``instances_path``; :func:`instance_masks_by_frame`),
    segments every frame (:func:`segment_frames`: :func:`segment_frame`; instances with
    fewer than ``min_points`` points are dropped), associates the rest in frame order
    (:func:`tracks_from_segments`: :func:`associate`; centroids in the log's reference frame
    via its ego poses when it has them) and returns a list of
    :class:`~seqshape.amodal.refine.TrackInput` (no ground-truth poses; ``category_id`` the
    most frequent category of the track's masks). ``max_gap > 0`` fills the short gaps of
    each track with empty frames (:func:`fill_gaps`). ``unsupported``: a dict that receives,
    per frame, the ``(mask, annotation, ground plane)`` of every 2D instance dropped for too
    few points (:mod:`seqshape.amodal.fallback`). The per-frame part can run apart, in
    chunks of frames (``seqshape label --workers``), and give the same tracks.
    """
    camera = camera or log.default_camera
    by_frame = instance_masks_by_frame(log, camera, instances_path, categories)
    segments = segment_frames(log, camera, by_frame, log.frames, min_points,
                              desc=f"segment {log.name}")
    return tracks_from_segments(log, segments, gate, max_gap, unsupported)
