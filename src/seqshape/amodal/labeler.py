"""Automatic amodal mask labels for one driving log and camera (the paper's Section IV).

The input is any :class:`~seqshape.data.sequence.DrivingLog` with cameras (KITTI tracking,
nuScenes, Argoverse 2): its LiDAR sweeps (``log.points``), boxes (``log.vehicle_boxes``), ego
poses, and one camera (``log.camera(name, frame)``, a PinholeCamera); :func:`label_log` is the
entry point (:func:`label_sequence` opens a KITTI sequence for it).

Modes:

* ``gt-accumulation``: points cropped by the ground-truth boxes
  (:func:`seqshape.data.extract.extract_tracks`, :func:`seqshape.data.crop.crop_vehicle`),
  accumulated in the canonical frame with the ground-truth poses, mirrored about the heading
  axis and placed back in every frame (:mod:`seqshape.amodal.accumulate`).
* ``sc-gt``: the same crops, completed by the sequential estimator (:mod:`.refine`).
* ``sc-seg``: no 3D labels. Each frame's LiDAR points (ground removed) are labelled from the
  2D instance masks of a COCO file (default ``ROOT/instances_2d/<log name>.json``, images
  matched by ``log.image_file_name(frame, camera)``) by graph diffusion (:mod:`.diffusion`),
  associated across frames into tracks (:mod:`.association`, with the log's ego motion when
  it has one) and completed by the estimator.

The sc-* modes estimate each track offline by default (``LabelConfig.online`` False,
:mod:`seqshape.model.offline`: the sequence is finished, so every estimate uses all the
track's frames) and refine those estimates (:mod:`.refine`); ``online=True`` (``seqshape label
--online``) steps the estimator frame by frame as the paper does.

Then per frame the completed clouds are projected into the camera, their alpha shapes filled
as amodal masks, and ordered by depth for the visible masks (:mod:`.masks`); the result is KINS
JSON, one file per camera. Category ids of the gt modes come from
:data:`seqshape.data.categories.CLASS_TO_KINS` (car 4, van 7, truck 6, bus 9, trailer 10).
"""

from __future__ import annotations

import hashlib
import json
import logging
import pickle
import threading
import time
import uuid
import weakref
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from seqshape._io import contained_path
from seqshape._progress import progress
from seqshape._version import __version__
from seqshape.amodal.accumulate import gt_accumulation_clouds
from seqshape.amodal.align import AlignConfig
from seqshape.amodal.association import (
    FrameSegments,
    instance_masks_by_frame,
    segment_frames,
    segment_sequence,
    tracks_from_segments,
)
from seqshape.amodal.fallback import mask_instance
from seqshape.amodal.masks import ORDERS, InstanceMask, frame_masks
from seqshape.amodal.overlay import draw_overlay, write_overlays  # noqa: F401 (re-exported)
from seqshape.amodal.refine import REFINE_MODES, TrackInput, complete_tracks
from seqshape.camera import KITTI_IMAGE_SIZE
from seqshape.data.categories import CLASS_TO_KINS
from seqshape.data.crop import CropConfig
from seqshape.data.extract import crop_frames, extract_tracks, tracks_from_crops
from seqshape.data.kins import (
    image_entry,
    kins_annotation,
    occlusion_order,
    rle_to_mask,
    write_kins,
)
from seqshape.data.kitti import KittiTrackingSequence, calib_path
from seqshape.data.sequence import parse_classes
from seqshape.errors import ConfigError, DataError, SeqshapeError

if TYPE_CHECKING:
    from seqshape.model.offline import OfflineConfig

log = logging.getLogger(__name__)

MODES = ("gt-accumulation", "sc-gt", "sc-seg")
DEFAULT_REFINE = "smooth"  # measured best for sc-seg, equal to backfill for sc-gt (docs/amodal.md)


@dataclass
class LabelConfig:
    """Options of :func:`label_log`.

    mode: gt-accumulation (3D boxes, accumulated LiDAR points), sc-gt (3D boxes, completed
        shapes) or sc-seg (no boxes: 2D instance masks and completed shapes).
    checkpoint: estimator weights (path), or "pretrained" for the shipped ones (sc-* modes).
    backend: sc-* modes: the estimator's inference backend, one of
        seqshape.model.engine.BACKENDS ('auto-float': the fastest float32 one that passes its
        check against PyTorch on this machine; 'auto' may take int8, which does not speed up
        labelling's passes of 10-20 vehicles; docs/model.md).
    refine: offline refinement, one of ``REFINE_MODES`` (sc-* modes).
    order: occlusion rule of :func:`seqshape.amodal.masks.resolve_occlusion`.
    alpha: alpha of the alpha shapes (None = automatic).
    classes: seqshape vehicle classes labelled in the gt modes (None: all of
        :data:`~seqshape.data.categories.VEHICLE_CLASSES`; KITTI Car, Van and Truck).
    instances: COCO instance masks for sc-seg (default ``ROOT/instances_2d/<log>.json``).
    crop: how the gt modes cut each vehicle out of its sweeps
        (:class:`~seqshape.data.crop.CropConfig`; default: box + 0.2 m margin, minus what lies
        less than 0.2 m above a locally fitted ground plane).
    polygons: write the segmentations as polygons (outer contours,
        :func:`~seqshape.data.kins.mask_to_polygons`) instead of RLE.
    min_points: sc-seg instances with fewer segmented points are dropped.
    gate: sc-seg association gate (m).
    min_visible_area: instances whose predicted visible mask is smaller (pixels) are not
        labelled (KINS annotates what can be seen). The scene generator keeps instances with
        at least 20 visible pixels of the exact masks; the predicted visible area is itself an
        estimate (a slightly small or misplaced shape of a heavily occluded car loses most of
        its few visible pixels), so the labeler keeps a margin below that rule (measured:
        docs/results.md, "Amodal labels").
    fit_box: sc-gt only: stretch each estimated shape to its ground-truth box and place it at
        the box pose (:func:`seqshape.amodal.refine.fit_to_box`).
    fit_box_below: sc-gt: tracks whose best estimate fused fewer than this many LiDAR points
        are fitted to their ground-truth box (0 disables; ``fit_box`` fits every track).
    observed: sc-* modes: add (up to ``observed_max`` of) the frame's own segmented points to
        its completed cloud before the alpha shape. They are measured vehicle surface, so they
        belong inside the amodal mask wherever the completion is misplaced or too small.
    max_gap: sc-seg with refinement ``"smooth"``: a track missing from at most this many
        consecutive frames (a missed 2D mask, too few points) is labelled there too, at its
        smoothed pose (0 disables).
    mask_fallback: sc-seg: a 2D instance with fewer than ``min_points`` LiDAR points (a far
        vehicle) is labelled with its own mask when it is a plausible vehicle on the ground
        (:mod:`seqshape.amodal.fallback`).
    trim: sc-* modes: drop the points of each completed shape outside its robust box (per
        axis the ``trim`` and ``100 - trim`` percentiles, in its own canonical frame; 0 keeps
        all). The estimator's output carries a sparse fringe of stray points, worst for far
        vehicles with few returns, and the alpha shape of a small projection takes them in.
    align: sc-seg: move each completed vehicle in the image so that its predicted visible mask
        best matches the 2D instance mask its points came from (:mod:`seqshape.amodal.align`,
        with ``align_config``); frames filled in a gap have no mask and are not moved.
    online: sc-* modes: run the estimator online (frame t's estimate has seen frames 0..t
        only, the paper). Default False: the sequence is finished, so every track is first
        estimated offline with all its frames (:mod:`seqshape.model.offline`, ``offline``
        options) and the refinement works on those estimates. Only a
        :class:`~seqshape.model.Estimator` runs offline; other estimators are stepped.
    offline: the :class:`~seqshape.model.offline.OfflineConfig` of the offline estimates
        (None: its defaults, the measured best).
    placement: sc-* modes: the estimator's placement refiner
        (:mod:`seqshape.model.placement`): 'pretrained' (the shipped one), a refiner file, or
        'none'. It moves sc-seg's shapes (sc-gt places them at the ground-truth boxes).
    max_points: sc-* modes: the most points of a frame fed to the estimator (None: its
        model's num_points; fewer is faster and less accurate, docs/model.md "Fewer points
        per frame").
    """

    mode: str = "sc-gt"
    checkpoint: str | None = "pretrained"
    backend: str = "auto-float"
    refine: str = DEFAULT_REFINE
    order: str = "pixel"
    alpha: float | None = None
    classes: tuple[str, ...] | None = None
    instances: str | None = None
    crop: CropConfig = field(default_factory=CropConfig)
    polygons: bool = False
    min_points: int = 5
    gate: float = 3.0
    min_visible_area: int = 10
    fit_box: bool = False
    fit_box_below: int = 50
    observed: bool = True
    observed_max: int = 4096
    max_gap: int = 5
    mask_fallback: bool = True
    trim: float = 1.0
    align: bool = True
    align_config: AlignConfig = field(default_factory=AlignConfig)
    online: bool = False
    offline: OfflineConfig | None = None
    placement: str = "pretrained"
    max_points: int | None = None

    def __post_init__(self):
        if self.max_points is not None and self.max_points < 1:
            raise ConfigError(f"max_points must be >= 1 or None, got {self.max_points!r}")
        if self.mode not in MODES:
            raise ConfigError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.refine not in REFINE_MODES:
            raise ConfigError(f"refine must be one of {REFINE_MODES}, got {self.refine!r}")
        if self.order not in ORDERS:
            raise ConfigError(f"order must be one of {ORDERS}, got {self.order!r}")
        if self.fit_box and self.mode != "sc-gt":
            raise ConfigError(f"fit_box needs ground-truth 3D boxes: only mode sc-gt, not "
                              f"{self.mode}")
        if not 0.0 <= self.trim < 50.0:
            raise ConfigError(f"trim must be a percentage in [0, 50), got {self.trim}")
        if self.fit_box_below < 0:
            raise ConfigError(f"fit_box_below must be >= 0, got {self.fit_box_below}")
        if self.classes is not None:
            self.classes = parse_classes(self.classes)


@dataclass
class LabelResult:
    """KINS ``images`` and ``annotations`` of one camera, the masks per frame, and timings
    (s)."""

    images: list[dict]
    annotations: list[dict]
    masks: dict[int, list[InstanceMask]] = field(repr=False)
    timings: dict[str, float] = field(default_factory=dict)
    camera: str | None = None


@dataclass(frozen=True)
class EstimatorSpec:
    """How :func:`load_estimator` made an estimator: what a worker process needs to load the
    same one (:func:`complete_chunk`). ``backend`` is the backend it resolved to (``"auto"``
    and ``"auto-float"`` decided once, in the process that loaded it), so that every process
    runs the same arithmetic."""

    checkpoint: str | None
    backend: str
    placement: str = "pretrained"
    max_points: int | None = None


_SPECS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # estimator -> EstimatorSpec
_WORKER_ESTIMATOR: dict = {}  # a worker's estimator (:func:`complete_chunk`), by its spec


def load_estimator(checkpoint: str | None, backend: str = "auto-float",
                   placement: str = "pretrained", max_points: int | None = None,
                   threads: int | None = None):
    """The estimator of ``checkpoint`` (a path, or "pretrained"/None for the shipped sequential
    one): :meth:`seqshape.model.estimator.Estimator.load`, with the placement refiner
    ``placement`` (:func:`seqshape.model.placement.load_refiner`), ``max_points`` and
    ``threads`` (:class:`~seqshape.model.estimator.Estimator`'s). Its
    :class:`EstimatorSpec` is kept (:func:`estimator_spec`): with a pool, a log's tracks are
    then estimated by the pool's workers, each with the same estimator."""
    from seqshape.model.estimator import Estimator  # lazy: torch (modes without a network)

    est = Estimator.load("pretrained" if checkpoint is None else checkpoint, backend=backend,
                         refiner=placement, max_points=max_points, threads=threads)
    _SPECS[est] = EstimatorSpec(checkpoint, est.backend, placement, max_points)
    return est


def estimator_spec(estimator) -> EstimatorSpec | None:
    """The :class:`EstimatorSpec` of an estimator made by :func:`load_estimator` (None for any
    other: it is run in this process only)."""
    try:
        return _SPECS.get(estimator)
    except TypeError:  # not weakly referable: not one of ours
        return None


def _worker_load(spec: EstimatorSpec):
    """Load ``spec``'s estimator in this process (one thread: a pool runs a process per core)
    and keep it as the process's estimator, under ``spec`` and under the spec of the backend
    it resolved to."""
    import torch  # lazy: only workers that estimate import it

    torch.set_num_threads(1)
    est = load_estimator(spec.checkpoint, spec.backend, spec.placement, spec.max_points,
                         threads=1)
    _WORKER_ESTIMATOR.clear()
    _WORKER_ESTIMATOR[spec] = _WORKER_ESTIMATOR[estimator_spec(est)] = est
    return est


def preload_estimator(spec: EstimatorSpec) -> None:
    """Start loading ``spec``'s estimator in this worker process, in a background thread, so
    that the tasks the worker takes meanwhile (crops, segmentation) overlap with the load and
    its first :func:`complete_chunk` finds it ready (``backend`` may be ``"auto"`` or
    ``"auto-float"``: it is resolved in the worker; a task whose spec names another backend
    loads its own). A failed load is left to that first task, which loads again and raises."""
    def run():
        try:
            _worker_load(spec)
        except Exception:  # noqa: BLE001 (reported by the task that needs the estimator)
            log.debug("preloading the estimator failed", exc_info=True)

    _PRELOAD["thread"] = thread = threading.Thread(target=run, name="seqshape-preload",
                                                   daemon=True)
    thread.start()


_PRELOAD: dict = {}  # this worker's preloading thread (:func:`preload_estimator`)


def _worker_estimator(spec: EstimatorSpec):
    """This process's estimator of ``spec`` (preloaded or loaded before, else loaded now)."""
    thread = _PRELOAD.pop("thread", None)
    if thread is not None:
        thread.join()
    est = _WORKER_ESTIMATOR.get(spec)
    return est if est is not None else _worker_load(spec)


class TrackReplay:
    """Plays precomputed whole-track estimates back through the ``step``/``reset`` interface
    that :func:`seqshape.amodal.refine.complete_tracks` drives: its forward pass steps the
    ids ``"<track id>/fwd"`` through each track's frames in order, its backward pass
    ``"<track id>/bwd"`` in reverse order; each step returns that frame's estimate. A step whose
    points do not match the expected frame is an error (the passes changed)."""

    recurrent = True

    def __init__(self, inputs, estimates: dict[str, list]):
        self.inputs = {inp.track_id: inp for inp in inputs}
        self.estimates = estimates
        self.cursor: dict[str, int] = {}

    def reset(self, track_id: str | None = None) -> None:
        if track_id is None:
            self.cursor.clear()
        else:
            self.cursor.pop(track_id, None)

    def step(self, track_ids, point_lists, **_hints) -> list:
        out = []
        for sid, pts in zip(track_ids, point_lists, strict=True):
            base, _, tag = str(sid).rpartition("/")
            if base not in self.inputs:
                raise SeqshapeError(f"offline replay: unknown track {sid!r}")
            n = len(self.inputs[base].frames)
            k = self.cursor.get(sid, 0)
            i = n - 1 - k if tag == "bwd" else k
            if k >= n or len(pts) != len(self.inputs[base].points[i]):
                raise SeqshapeError(f"offline replay: step {k} of {sid!r} does not match frame "
                                    f"{i} of the track")
            self.cursor[sid] = k + 1
            out.append(self.estimates[base][i])
        return out


def _has_network(estimator) -> bool:
    """Whether ``estimator`` is a :class:`~seqshape.model.Estimator` (offline estimation runs
    its network; anything else, e.g. a test double, is stepped online)."""
    from seqshape.model.estimator import Estimator  # lazy: torch (modes without a network)

    return isinstance(estimator, Estimator)


def offline_replay(estimator, inputs, log=None, config=None) -> TrackReplay:
    """Every track of ``inputs`` estimated offline (:func:`seqshape.model.offline
    .estimate_track`, with the tracks' ego poses and the log's timestamps when known), ready
    to be replayed by :func:`seqshape.amodal.refine.complete_tracks`."""
    from seqshape.model.offline import estimate_track  # lazy: torch (modes without a network)

    estimates = {}
    for inp in inputs:
        times = None
        if log is not None:
            times = [log.timestamp(f) for f in inp.frames]
        egos = None if inp.ego is None else list(np.asarray(inp.ego, dtype=np.float64))
        estimates[inp.track_id] = estimate_track(estimator, inp.points, timestamps=times,
                                                 ego_poses=egos, config=config,
                                                 track_id=inp.track_id)
    return TrackReplay(inputs, estimates)


def label_ids(object_ids) -> dict[str, int]:
    """The integer KINS ``track_id`` of each dataset object id: the id itself when it is an
    integer (KITTI), else its 1-based rank among the log's sorted object ids."""
    ids = sorted(set(object_ids))
    if all(i.isdigit() for i in ids):
        return {i: int(i) for i in ids}
    return {i: k + 1 for k, i in enumerate(ids)}


def gt_track_inputs(log, classes=None, crop: CropConfig | None = None):
    """The log's vehicle tracks (:func:`seqshape.data.extract.extract_tracks`, ``classes``
    default all, ``crop`` default :class:`CropConfig`) and the matching :class:`TrackInput`
    list (with the tracks' ego poses when the log has them: the offline estimates use them)."""
    tracks = extract_tracks(log, classes=classes, crop=crop)
    return tracks, _track_inputs(tracks)


def _track_inputs(tracks) -> list[TrackInput]:
    """The :class:`TrackInput` of each extracted track (:func:`gt_track_inputs`)."""
    ids = label_ids(t.meta["object_id"] for t in tracks)
    return [TrackInput(t.track_id, list(t.meta["frames"]), t.points, t.poses,
                       CLASS_TO_KINS[t.meta["class"]], ids[t.meta["object_id"]],
                       np.asarray(t.size, dtype=np.float64), _track_ego(t))
            for t in tracks]


def _track_ego(track) -> np.ndarray | None:
    """A track's ``meta["ego_poses"]`` as (T, 4, 4) (sensor -> log frame), or None."""
    ego = track.meta.get("ego_poses")
    if not ego:
        return None
    ego = np.asarray(ego, dtype=np.float64)
    return ego if ego.shape == (len(track), 4, 4) else None


def add_observed(inp, clouds: list, max_points: int) -> list:
    """Each frame's completed cloud with up to ``max_points`` of its own input points added
    (an even subset, the same on every run)."""
    out = []
    for pts, cloud in zip(inp.points, clouds, strict=True):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        if cloud is None or len(pts) == 0:
            out.append(cloud)
            continue
        if len(pts) > max_points:
            pts = pts[np.linspace(0, len(pts) - 1, max_points).astype(np.int64)]
        out.append(np.vstack([np.asarray(cloud, dtype=np.float64), pts]))
    return out


def clouds_by_frame(inputs, clouds_per_track) -> dict[int, dict[str, tuple]]:
    """``{frame: {track_id: (cloud, input)}}``."""
    out: dict[int, dict[str, tuple]] = {}
    for inp, clouds in zip(inputs, clouds_per_track, strict=True):
        for f, c in zip(inp.frames, clouds, strict=True):
            if c is not None and len(c):
                out.setdefault(f, {})[inp.track_id] = (c, inp)
    return out


def open_sequence(root, sequence, max_frames: int | None = None):
    """The KITTI :class:`~seqshape.data.kitti.KittiTrackingSequence`, restricted to its first
    ``max_frames`` frames (:meth:`~seqshape.data.sequence.DrivingLog.restrict`): everything
    downstream (track extraction, segmentation, masks) sees a shorter sequence, so a track is
    estimated from its first frame within the subset."""
    return KittiTrackingSequence(root, sequence).restrict(max_frames)


#: Where each dataset's camera model comes from (:func:`check_camera` names it when missing).
CAMERA_SOURCES = {
    "kitti": "the calibration file {calib}",
    "av2": "the cameras' intrinsics (calibration/intrinsics.feather in the log folder)",
    "nuscenes": "camera sample_data (CAM_FRONT, ...) in the scene's keyframes",
}

#: The image size (width, height) of a camera whose log has no image to read it from, per
#: dataset (``seqshape label --image-size W H`` gives another). Argoverse 2 and nuScenes
#: record each camera's size in their tables (intrinsics.feather; sample_data width/height).
DEFAULT_IMAGE_SIZES = {"kitti": KITTI_IMAGE_SIZE}


def check_camera(log, camera: str | None) -> str:
    """``camera`` (default: the log's default camera), checked against the log's cameras; a
    log without cameras is an error that names what is missing (:data:`CAMERA_SOURCES`).

    The modes gt-accumulation and sc-gt need only the camera model and the image size, not the
    images: a KITTI log with its calibration file and no image_02 is labelled at the size of
    :data:`DEFAULT_IMAGE_SIZES` (or ``--image-size``)."""
    if not log.camera_names:
        calib = (calib_path(log.root, log.name) if isinstance(log, KittiTrackingSequence)
                 else None)
        source = CAMERA_SOURCES.get(log.dataset, "its camera calibration").format(calib=calib)
        hint = "" if getattr(log, "frames", None) else (
            "; no frames of it were found either: is --root the folder that holds the "
            "dataset's folders (KITTI: calib/, velodyne/, label_02/, e.g. .../training)?")
        raise ConfigError(f"{log.dataset} log {log.name} has no cameras: amodal labels need "
                          f"the camera model, from {source}, which is missing{hint}")
    camera = camera or log.default_camera or log.camera_names[0]
    if camera not in log.camera_names:
        raise ConfigError(f"{log.dataset} log {log.name} has no camera {camera!r} (cameras: "
                          f"{', '.join(log.camera_names)})")
    return camera


def set_image_size(log, size) -> None:
    """Give ``log``'s cameras the image size ``size`` (width, height): ``--image-size W H`` for
    a KITTI log, whose calibration does not record it (default: the first image's size, or
    :data:`DEFAULT_IMAGE_SIZES` without images). Other datasets record each camera's size,
    and asking to change it is an error."""
    try:
        width, height = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ConfigError(f"--image-size takes two whole numbers W H, not {size!r}") from None
    if width <= 0 or height <= 0:
        raise ConfigError(f"--image-size {width} {height}: the width and height must be positive")
    if not isinstance(log, KittiTrackingSequence):
        raise ConfigError(f"--image-size is for KITTI logs, whose calibration has no image "
                          f"size; a {log.dataset} log records each camera's size")
    log.calib.image_size = (width, height)


def label_sequence(root, sequence, cfg: LabelConfig, estimator=None,
                   max_frames: int | None = None) -> LabelResult:
    """:func:`label_log` of KITTI sequence ``ROOT/.../SSSS``, camera ``image_02``;
    ``max_frames``: label only the first that many frames (:func:`open_sequence`)."""
    return label_log(open_sequence(root, sequence, max_frames), cfg, estimator=estimator)


@dataclass
class Prepared:
    """One log's tracks before estimation (:func:`prepare_tracks`): the
    :class:`~seqshape.amodal.refine.TrackInput` list, the extracted tracks (gt modes), the 2D
    instances without LiDAR support (sc-seg's mask fallback: ``{frame: [(mask or None,
    COCO annotation, ground plane)]}``; None: the mask is the annotation's own segmentation)
    and the seconds it took."""

    inputs: list
    tracks: list | None = None
    unsupported: dict | None = None
    seconds: float = 0.0


def prepare_tracks(log, cfg: LabelConfig, camera: str) -> Prepared:
    """The part of a log's labelling that needs no estimator, done once per log (per camera
    in sc-seg): sc-seg segments every frame and associates the segments into tracks
    (:func:`~seqshape.amodal.association.segment_sequence`), the gt modes crop the
    ground-truth boxes (:func:`gt_track_inputs`)."""
    t0 = time.perf_counter()
    if cfg.mode == "sc-seg":
        unsupported: dict | None = {} if cfg.mask_fallback else None
        inputs = segment_sequence(log, instances_path(log, cfg), min_points=cfg.min_points,
                                  gate=cfg.gate, max_gap=_max_gap(cfg),
                                  unsupported=unsupported, camera=camera)
        return Prepared(inputs, None, unsupported, time.perf_counter() - t0)
    tracks, inputs = gt_track_inputs(log, cfg.classes, cfg.crop)
    return Prepared(inputs, tracks, None, time.perf_counter() - t0)


def instances_path(log, cfg: LabelConfig) -> Path:
    """sc-seg's COCO instance file of ``log``: ``cfg.instances``, else
    ``ROOT/instances_2d/<log name>.json``."""
    if cfg.instances:
        return Path(cfg.instances)
    return contained_path(Path(log.root) / "instances_2d", f"{log.name}.json",
                          what="instance-mask file")


def _max_gap(cfg: LabelConfig) -> int:
    """The gaps sc-seg's tracks fill (only the refinement ``"smooth"`` poses those frames)."""
    return cfg.max_gap if cfg.refine == "smooth" else 0


def segment_chunk(job: tuple) -> tuple[list[FrameSegments], float]:
    """sc-seg's per-frame part (:func:`~seqshape.amodal.association.segment_frames`) of a run
    of frames, in a worker process of :class:`PreparingSegments` (``job``: log, camera,
    ``{frame: COCO annotations}``, the frames, ``min_points``); ``(segments, seconds)``."""
    log, camera, annotations, frames, min_points = job
    log = worker_log(log)
    t0 = time.perf_counter()
    segments = segment_frames(log, camera, annotations, frames, min_points)
    for seg in segments:  # their masks are their annotations' (MaskOnly decodes them again)
        seg.unsupported = [(None, ann, plane) for _, ann, plane in seg.unsupported]
    return segments, time.perf_counter() - t0


class PreparingSegments:
    """sc-seg's :func:`prepare_tracks` of one log and camera with its frames segmented by a
    pool's workers: the instance file is read here, runs of consecutive frames are segmented
    as tasks of the pool (:func:`segment_chunk`), and :meth:`get` associates them into tracks
    here, in frame order (:func:`~seqshape.amodal.association.tracks_from_segments`): the
    same :class:`Prepared` as :func:`prepare_tracks` (tested), whatever the chunks."""

    def __init__(self, pool, log, cfg: LabelConfig, camera: str):
        t0 = time.perf_counter()
        self.log, self.cfg = log, cfg
        annotations = instance_masks_by_frame(log, camera, instances_path(log, cfg))
        frames = list(log.frames)
        size = _chunk_size(len(frames), pool.workers)
        shared = shared_log(log)
        self.tasks = [pool.submit(segment_chunk, (
            shared, camera, {f: annotations[f] for f in frames[k:k + size]}, frames[k:k + size],
            cfg.min_points)) for k in range(0, len(frames), size)]
        self.seconds = time.perf_counter() - t0

    def ready(self) -> bool:
        return all(t.ready() for t in self.tasks)

    def get(self) -> Prepared:
        """Wait for the frames and associate them (:func:`prepare_tracks`' result)."""
        segments, seconds = [], self.seconds
        for task in self.tasks:
            part, secs = task.get()
            segments.extend(part)
            seconds += secs
        t0 = time.perf_counter()
        unsupported: dict | None = {} if self.cfg.mask_fallback else None
        inputs = tracks_from_segments(self.log, segments, self.cfg.gate, _max_gap(self.cfg),
                                      unsupported)
        return Prepared(inputs, None, unsupported, seconds + time.perf_counter() - t0)


class SharedLog:
    """A log as it goes to a pool's tasks (:func:`shared_log`): pickled once in this process,
    unpickled once per worker process (:func:`worker_log`). A log's annotations are many small
    objects, about 40 ms to pickle and as much to unpickle: for every task of a dense log
    that was seconds of the parent's time, which no worker can take over."""

    def __init__(self, log):
        self.key = uuid.uuid4().hex
        self.blob = pickle.dumps(log, protocol=pickle.HIGHEST_PROTOCOL)

    def get(self):
        """The log (in a worker: unpickled at the first task that needs it)."""
        log = _WORKER_LOGS.get(self.key)
        if log is None:
            log = _WORKER_LOGS[self.key] = pickle.loads(self.blob)
            while len(_WORKER_LOGS) > _LOGS_KEPT:
                _WORKER_LOGS.pop(next(iter(_WORKER_LOGS)))
        return log


_LOGS_KEPT = 8  # logs a process keeps (:class:`SharedLog`): a pool works on a few at a time
_WORKER_LOGS: dict = {}  # key -> log, in insertion order
_SHARED: dict = {}  # id(log) -> (log, SharedLog) of this process's last logs


def shared_log(log) -> SharedLog:
    """The :class:`SharedLog` of ``log`` (made once per log: its tasks share one pickle)."""
    hit = _SHARED.get(id(log))
    if hit is not None and hit[0] is log:
        return hit[1]
    ref = SharedLog(log)
    _SHARED[id(log)] = (log, ref)  # the log held: its id stays its own while cached
    while len(_SHARED) > _LOGS_KEPT:
        _SHARED.pop(next(iter(_SHARED)))
    return ref


def worker_log(log):
    """The log a task was given: a :class:`SharedLog`'s, or ``log`` itself."""
    return log.get() if isinstance(log, SharedLog) else log


def crop_chunk(job: tuple) -> tuple[list[tuple], float]:
    """The gt modes' per-frame part (:func:`seqshape.data.extract.crop_frames`) of a run of
    frames, in a worker process of :class:`PreparingCrops` (``job``: log, the frames, classes,
    :class:`~seqshape.data.crop.CropConfig`); ``(crops, seconds)``."""
    log, frames, classes, crop = job
    log = worker_log(log)
    t0 = time.perf_counter()
    cuts = crop_frames(log, frames, classes, crop)
    return cuts, time.perf_counter() - t0


class PreparingCrops:
    """The gt modes' :func:`prepare_tracks` of one log with its frames cropped by a pool's
    workers, runs of consecutive frames as tasks (:func:`crop_chunk`); :meth:`get` joins them
    into tracks here (:func:`seqshape.data.extract.tracks_from_crops`): the same
    :class:`Prepared` as :func:`prepare_tracks` (tested), whatever the runs."""

    def __init__(self, pool, log, cfg: LabelConfig):
        self.log, self.cfg = log, cfg
        frames = list(log.frames)
        size = _chunk_size(len(frames), pool.workers)
        shared = shared_log(log)
        self.tasks = [pool.submit(crop_chunk, (shared, frames[k:k + size], cfg.classes,
                                               cfg.crop))
                      for k in range(0, len(frames), size)]

    def ready(self) -> bool:
        return all(t.ready() for t in self.tasks)

    def get(self) -> Prepared:
        """Wait for the frames and join them into tracks (:func:`prepare_tracks`' result)."""
        cuts, seconds = [], 0.0
        for task in self.tasks:
            part, secs = task.get()
            cuts.extend(part)
            seconds += secs
        t0 = time.perf_counter()
        tracks = tracks_from_crops(self.log, cuts, self.cfg.crop)
        return Prepared(_track_inputs(tracks), tracks, None, seconds + time.perf_counter() - t0)


def submit_prepare(pool, log, cfg: LabelConfig, camera: str):
    """Start :func:`prepare_tracks` of ``log`` and ``camera`` in ``pool`` (a
    :class:`seqshape._runner.WorkerPool`): sc-seg's frames in runs across the workers
    (:class:`PreparingSegments`), the gt modes' crops likewise (:class:`PreparingCrops`).
    Returns an object whose ``get()`` gives the :class:`Prepared`."""
    if cfg.mode == "sc-seg":
        return PreparingSegments(pool, log, cfg, camera)
    return PreparingCrops(pool, log, cfg)


def preparations(log, cfg: LabelConfig, cameras) -> list[str]:
    """The cameras for which :func:`start_labels` needs a :func:`prepare_tracks` of ``log``
    (sc-seg: each camera's own 2D masks; the others: the tracks once, by the first)."""
    return list(cameras) if cfg.mode == "sc-seg" else list(cameras)[:1]


def _complete(log, cfg: LabelConfig, camera: str, estimator, timings: dict,
              prepared: Prepared | None = None, pool=None):
    """``(by_frame clouds, extra mask-only instances)`` of the log (module doc), from its
    :func:`prepare_tracks` (made here when not given). ``estimator``: an estimator, an
    :class:`EstimatorSpec` (loaded where it runs, once per process) or None (``cfg``'s); with
    ``pool`` and a spec or an estimator of :func:`load_estimator`, the offline estimation runs
    in the pool's workers (:func:`complete_chunk`)."""
    prepared = prepared if prepared is not None else prepare_tracks(log, cfg, camera)
    inputs, tracks = prepared.inputs, prepared.tracks
    t0 = time.perf_counter()
    extra = None
    if cfg.mode == "sc-seg" and pool is not None:  # made by the workers that draw the frames
        extra = mask_only_specs(log, prepared.unsupported or {})
    elif cfg.mode == "sc-seg":
        extra = mask_only_labels(log, prepared.unsupported or {}, camera)
    timings["segment"] = prepared.seconds + time.perf_counter() - t0
    t0 = time.perf_counter()
    if cfg.mode == "gt-accumulation":
        clouds = [gt_accumulation_clouds(t) for t in tracks]
    else:
        if isinstance(estimator, EstimatorSpec):
            spec, est = estimator, None
        else:
            est = estimator if estimator is not None else load_estimator(
                cfg.checkpoint, cfg.backend, cfg.placement, cfg.max_points)
            spec = estimator_spec(est)
        if pool is not None and spec is not None and not cfg.online and inputs:
            clouds = _complete_in_pool(pool, log, cfg, spec, inputs)
        else:
            clouds = complete_clouds(log, cfg, est if est is not None
                                     else _worker_estimator(spec), inputs)
    timings["complete"] = time.perf_counter() - t0
    return clouds_by_frame(inputs, clouds), extra


def complete_clouds(log, cfg: LabelConfig, estimator, inputs) -> list[list]:
    """Per track of ``inputs`` (:class:`~seqshape.amodal.refine.TrackInput`), its completed
    cloud in each frame (None where there is none): estimated offline unless ``cfg.online``
    (:func:`offline_replay`), completed and refined (:func:`~seqshape.amodal.refine
    .complete_tracks`), with the frame's own points added (``cfg.observed``). Offline, each
    track's clouds depend on that track alone."""
    estimator.reset()
    if not cfg.online and _has_network(estimator):
        estimator = offline_replay(estimator, inputs, log, cfg.offline)
    clouds = [c.clouds for c in complete_tracks(
        estimator, inputs, cfg.refine, cfg.fit_box, cfg.fit_box_below, cfg.trim)]
    if cfg.observed:
        clouds = [add_observed(inp, cl, cfg.observed_max) for inp, cl in
                  zip(inputs, clouds, strict=True)]
    return clouds


def complete_chunk(job: tuple) -> tuple[list[list], float]:
    """:func:`complete_clouds` of some of a log's tracks in a worker process (``job``: log,
    :class:`EstimatorSpec`, config, the tracks), with the estimator the spec loads there
    (once per process); ``(clouds per track, seconds)``."""
    log, spec, cfg, inputs = job
    log = worker_log(log)
    t0 = time.perf_counter()
    clouds = complete_clouds(log, cfg, _worker_estimator(spec), inputs)
    return clouds, time.perf_counter() - t0


def track_chunks(frames: list[int], workers: int) -> list[list[int]]:
    """The tracks (indices; ``frames``: each one's length) in about
    :data:`CHUNKS_PER_WORKER` x ``workers`` groups of similar work, for :func:`complete_chunk`
    tasks: longest first, each to the group with the least so far (a track's cost is about
    its frames plus a fixed part); each group in track order, the heaviest group first."""
    n = min(len(frames), CHUNKS_PER_WORKER * max(1, workers))
    loads, groups = [0] * n, [[] for _ in range(n)]
    for i in sorted(range(len(frames)), key=lambda i: (-frames[i], i)):
        k = loads.index(min(loads))
        groups[k].append(i)
        loads[k] += frames[i] + _TRACK_COST_FRAMES
    order = sorted(range(n), key=lambda k: (-loads[k], k))
    return [sorted(groups[k]) for k in order if groups[k]]


#: the fixed part of a track's estimation cost, in frames (:func:`track_chunks`)
_TRACK_COST_FRAMES = 4


def _complete_in_pool(pool, log, cfg: LabelConfig, spec: EstimatorSpec, inputs) -> list[list]:
    """:func:`complete_clouds` of every track, its tracks spread over ``pool``'s workers
    (:func:`track_chunks`); the same clouds as in one process (each track's depend on it
    alone, and every worker loads the same estimator: tested)."""
    chunks = track_chunks([len(inp.frames) for inp in inputs], pool.workers)
    shared = shared_log(log)
    tasks = [pool.submit(complete_chunk, (shared, spec, cfg, [inputs[i] for i in idx]))
             for idx in chunks]
    clouds: list = [None] * len(inputs)
    for idx, task in zip(chunks, tasks, strict=True):
        part, _ = task.get()
        for i, c in zip(idx, part, strict=True):
            clouds[i] = c
    return clouds


def _render_timed(log, by_frame, cfg, extra, camera, timings, pool=None,
                  keep_masks: bool = True) -> PendingLabels:
    return PendingLabels(start_render(log, by_frame, cfg, extra, camera, pool, keep_masks),
                         timings, len(log.frames))


def label_log(log, cfg: LabelConfig, camera: str | None = None,
              estimator=None, pool=None, keep_masks: bool = True) -> LabelResult:
    """Amodal labels of every frame of ``log`` (a DrivingLog) in ``camera`` (default: the log's
    default camera) (module doc); nothing is written. A log without cameras is a
    :class:`~seqshape.errors.ConfigError`. ``pool`` and ``keep_masks``: :func:`render_labels`
    (the labels do not depend on the pool)."""
    camera = check_camera(log, camera)
    return start_labels(log, cfg, [camera], estimator, pool, keep_masks)[camera].result()


def label_log_cameras(log, cfg: LabelConfig, cameras=None, estimator=None, pool=None,
                      keep_masks: bool = True) -> dict[str, LabelResult]:
    """:func:`label_log` for several cameras (default: all of the log's); the gt and sc-gt
    modes complete the tracks once and project them into every camera (sc-seg segments each
    camera's own 2D masks)."""
    pending = start_labels(log, cfg, cameras, estimator, pool, keep_masks)
    return {c: p.result() for c, p in pending.items()}


def start_labels(log, cfg: LabelConfig, cameras=None, estimator=None, pool=None,
                 keep_masks: bool = True, prepared: dict | None = None
                 ) -> dict[str, PendingLabels]:
    """:func:`label_log_cameras` in parts: ``prepared`` ``{camera: Prepared}`` (the cameras
    of :func:`preparations`, e.g. made by :func:`submit_prepare`'s tasks; made here when
    None: sc-seg with a pool segments runs of frames in its workers, :class:`PreparingSegments`),
    then the estimation (here, or with a pool and an :class:`EstimatorSpec` or an estimator
    of :func:`load_estimator` in the pool's workers, tracks spread over them:
    :func:`complete_chunk`; this returns when it is done), then the frames' masks handed to
    ``pool`` (:func:`start_render`); the
    :class:`PendingLabels` of each camera gives
    its :class:`LabelResult` when the pool has rendered every frame. Without a pool everything
    is done before this returns."""
    cameras = [check_camera(log, c) for c in (cameras or log.camera_names)]
    if not log.frames:
        raise DataError(Path(log.root), f"{log.dataset} log {log.name}: no frames found")
    prepared = dict(prepared or {})
    if cfg.mode == "sc-seg":  # each camera's own 2D masks
        if pool is not None:  # every camera's frames to the pool at once
            jobs = {c: PreparingSegments(pool, log, cfg, c) for c in cameras
                    if c not in prepared}
            prepared.update({c: job.get() for c, job in jobs.items()})
        out = {}
        for c in cameras:
            timings: dict[str, float] = {}
            by_frame, extra = _complete(log, cfg, c, estimator, timings, prepared.get(c), pool)
            out[c] = _render_timed(log, by_frame, cfg, extra, c, timings, pool, keep_masks)
        return out
    timings = {}
    by_frame, _ = _complete(log, cfg, cameras[0], estimator, timings,
                            prepared.get(cameras[0]), pool)
    return {c: _render_timed(log, by_frame, cfg, None, c, dict(timings), pool, keep_masks)
            for c in cameras}


def mask_only_labels(log, unsupported: dict, camera: str | None = None
                     ) -> dict[int, list[tuple[InstanceMask, int]]]:
    """``{frame: [(instance, category_id)]}``: the mask-only labels
    (:mod:`seqshape.amodal.fallback`) of the 2D instances without LiDAR support
    (``{frame: [(mask, coco annotation, ground plane)]}``, from
    :func:`~seqshape.amodal.association.segment_sequence`) seen by ``camera``."""
    out: dict[int, list[tuple[InstanceMask, int]]] = {}
    for frame in sorted(unsupported):
        made = _mask_only(log, frame, camera, [(
            MaskOnly(f"{log.name}_mask{frame:06d}_{k}", ann, plane, mask), int(ann["category_id"]))
            for k, (mask, ann, plane) in enumerate(unsupported[frame])])
        if made:
            out[frame] = made
    return out


@dataclass
class MaskOnly:
    """A mask-only label still to be made (:func:`mask_only_labels`), as it goes to a worker
    process: the instance's name, its COCO annotation, the sweep's ground plane, and its mask
    when already decoded (None: decoded from the annotation where it is made)."""

    name: str
    annotation: dict
    plane: object
    mask: np.ndarray | None = None


def mask_only_specs(log, unsupported: dict) -> dict[int, list[tuple[MaskOnly, int]]]:
    """:func:`mask_only_labels` left to be made where the frame is drawn (:func:`render_frame`:
    by the pool's workers), the same labels: ``{frame: [(MaskOnly, category_id)]}``."""
    return {frame: [(MaskOnly(f"{log.name}_mask{frame:06d}_{k}", ann, plane),
                     int(ann["category_id"])) for k, (_, ann, plane) in enumerate(rows)]
            for frame, rows in sorted(unsupported.items())}


def _mask_only(log, frame: int, camera: str | None, items: list) -> list[tuple]:
    """``items`` ``[(InstanceMask or MaskOnly, category_id)]`` of one frame with each
    :class:`MaskOnly` made (:func:`~seqshape.amodal.fallback.mask_instance`; left out when it
    gives none)."""
    if not any(isinstance(m, MaskOnly) for m, _ in items):
        return list(items)
    cam = log.camera(camera, frame)
    out = []
    for m, cat in items:
        if isinstance(m, MaskOnly):
            mask = rle_to_mask(m.annotation["segmentation"]) if m.mask is None else m.mask
            m = mask_instance(m.name, mask, float(m.annotation.get("score", 1.0)), m.plane, cam)
        if m is not None:
            out.append((m, cat))
    return out


@dataclass
class FrameInput:
    """What :func:`render_frame` needs of one frame, and no more (it goes to a worker process):
    the completed clouds ``{track_id: (K, 3)}``, ``{track_id: (category_id, label_id)}``, per
    track with a 2D instance mask (sc-seg) ``(its COCO RLE, the track's own points of the
    frame (M, 3))``, and the instances made otherwise with their category ids
    (:func:`mask_only_labels`; a :class:`MaskOnly` is made by :func:`render_frame`)."""

    clouds: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, tuple[int, int | None]] = field(default_factory=dict)
    guides: dict[str, tuple[dict, np.ndarray]] = field(default_factory=dict)
    extra: list[tuple[InstanceMask | MaskOnly, int]] = field(default_factory=list)


def frame_inputs(by_frame: dict[int, dict[str, tuple]],
                 extra: dict[int, list[tuple[InstanceMask, int]]] | None = None
                 ) -> dict[int, FrameInput]:
    """The :class:`FrameInput` of every frame with a cloud or an extra instance."""
    extra = extra or {}
    # track id -> frame -> (RLE of its 2D mask, position of the frame in the track)
    mask_index: dict[str, dict[int, tuple[dict, int]]] = {}
    for items in by_frame.values():
        for tid, (_, inp) in items.items():
            if inp.masks is not None and tid not in mask_index:
                mask_index[tid] = {f: (r, i) for i, (f, r) in
                                   enumerate(zip(inp.frames, inp.masks, strict=True))
                                   if r is not None}
    out = {}
    for frame in set(by_frame) | set(extra):
        items = by_frame.get(frame, {})
        guides = {}
        for tid, (_, inp) in items.items():
            hit = mask_index.get(tid, {}).get(frame)
            if hit is not None:
                guides[tid] = (hit[0], inp.points[hit[1]])
        out[frame] = FrameInput({tid: c for tid, (c, _) in items.items()},
                                {tid: (inp.category_id, inp.label_id)
                                 for tid, (_, inp) in items.items()},
                                guides, list(extra.get(frame, [])))
    return out


def render_frame(log, frame: int, image_id: int, camera: str, cfg: LabelConfig,
                 inputs: FrameInput | None = None
                 ) -> tuple[dict, list[dict], list[InstanceMask]]:
    """One frame's KINS image entry, annotations (``id`` 0: numbered when the log's frames are
    joined, :class:`PendingLabels`) and instance masks (module doc)."""
    cam = log.camera(camera, frame)
    size = (cam.height, cam.width)
    image = image_entry(image_id, log.name, frame, *size,
                        file_name=log.image_file_name(frame, camera))
    inputs = inputs or FrameInput()
    extra = _mask_only(log, frame, camera, inputs.extra)
    meta = dict(inputs.meta)
    meta.update({m.track_id: (cat, None) for m, cat in extra})
    guides = own = None
    if cfg.align:
        guides = {tid: rle_to_mask(rle) for tid, (rle, _) in inputs.guides.items()}
        own = {tid: pts for tid, (_, pts) in inputs.guides.items()}
    insts = frame_masks(inputs.clouds, cam, size, alpha=cfg.alpha, order=cfg.order,
                        extra=[m for m, _ in extra], guides=guides,
                        align=cfg.align_config if cfg.align else None, guide_points=own)
    insts = [m for m in insts if np.count_nonzero(m.visible) >= cfg.min_visible_area]
    oco, ico = occlusion_order([m.order for m in insts], [m.amodal for m in insts])
    anns = []
    for m, o, i in zip(insts, oco, ico, strict=True):
        cat, label_id = meta[m.track_id]
        ann = kins_annotation(0, image_id, cat, m.amodal, m.visible, o, i, track_id=label_id,
                              polygons=cfg.polygons)
        ann["depth"] = round(float(m.depth), 3)
        anns.append(ann)
    return image, anns, insts


def _pack(m: InstanceMask) -> tuple:
    """An instance mask cut to its amodal box (the visible mask lies inside), without its
    projected points: what a worker sends back (:func:`_unpack` restores the masks)."""
    y0, y1, x0, x1 = _mask_box(m.amodal)
    return (m.track_id, m.amodal.shape, (y0, x0), m.amodal[y0:y1, x0:x1].copy(),
            m.visible[y0:y1, x0:x1].copy(), m.depth, m.order)


def _unpack(packed: tuple) -> InstanceMask:
    tid, shape, (y0, x0), amodal, visible, depth, order = packed
    full_a, full_v = np.zeros(shape, dtype=bool), np.zeros(shape, dtype=bool)
    full_a[y0:y0 + amodal.shape[0], x0:x0 + amodal.shape[1]] = amodal
    full_v[y0:y0 + visible.shape[0], x0:x0 + visible.shape[1]] = visible
    return InstanceMask(tid, full_a, full_v, depth, order)


def _mask_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)`` (end exclusive) of a mask's pixels (empty box when none)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return 0, 0, 0, 0
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def render_chunk(job: tuple) -> tuple[list[tuple], float]:
    """:func:`render_frame` of a run of frames, in a worker process of :func:`start_render`
    (``job``: log, camera, config, ``[(image_id, frame, FrameInput | None)]``, whether the
    masks go back); ``([(image, annotations, packed masks or None)], seconds)``."""
    log, camera, cfg, frames, keep_masks = job
    log = worker_log(log)
    t0 = time.perf_counter()
    out = []
    for image_id, frame, inputs in frames:
        image, anns, insts = render_frame(log, frame, image_id, camera, cfg, inputs)
        out.append((image, anns, [_pack(m) for m in insts] if keep_masks else None))
    return out, time.perf_counter() - t0


#: frames per task of :func:`start_render` and :class:`PreparingSegments` in a pool: at
#: least this many...
CHUNK_FRAMES = 4
#: ... and about this many tasks per worker and log (balance against the cost of a task)
CHUNKS_PER_WORKER = 3


def _chunk_size(frames: int, workers: int) -> int:
    """Frames per task when ``frames`` frames of a log go to ``workers`` workers."""
    return max(CHUNK_FRAMES, -(-frames // (CHUNKS_PER_WORKER * workers)))


class _Done:
    """A finished task, with the interface of :class:`seqshape._runner.Task` (``ready``, ``get``)."""

    def __init__(self, value):
        self.value = value

    def ready(self) -> bool:
        return True

    def get(self):
        return self.value


class PendingLabels:
    """The labels of one log and camera while a pool renders its frames
    (:func:`start_labels`): :meth:`ready` tells whether every frame is done, :meth:`result`
    waits for them and joins them into a :class:`LabelResult` (annotation ids numbered in
    frame order: the same file as one process writes)."""

    def __init__(self, started: tuple, timings: dict, frames: int):
        self.camera, self.tasks, self.keep_masks = started
        self.timings = timings
        self.frames = frames

    def ready(self) -> bool:
        return all(t.ready() for t in self.tasks)

    def result(self) -> LabelResult:
        images, anns, masks, secs = [], [], {}, 0.0
        for task in self.tasks:
            rows, seconds = task.get()
            secs += seconds
            for image, frame_anns, packed in rows:
                images.append(image)
                for ann in frame_anns:
                    ann["id"] = len(anns) + 1
                    anns.append(ann)
                if packed is not None:
                    masks[image["frame"]] = [m if isinstance(m, InstanceMask) else _unpack(m)
                                             for m in packed]
        timings = dict(self.timings)
        timings["masks"] = secs
        timings["total"] = sum(v for k, v in timings.items() if k != "frames")
        timings["frames"] = self.frames
        return LabelResult(images, anns, masks, timings, camera=self.camera)


def start_render(log, by_frame: dict[int, dict[str, tuple]], cfg: LabelConfig,
                 extra: dict[int, list[tuple[InstanceMask, int]]] | None = None,
                 camera: str | None = None, pool=None, keep_masks: bool = True) -> tuple:
    """Start :func:`render_labels`: in this process (``pool`` None: done when this returns),
    or as tasks of ``pool`` (a :class:`seqshape._runner.WorkerPool`), runs of consecutive
    frames each; ``(camera, tasks, keep_masks)`` for :class:`PendingLabels`."""
    camera = check_camera(log, camera)
    inputs = frame_inputs(by_frame, extra)
    frames = [(i, f, inputs.get(f)) for i, f in enumerate(log.frames)]
    if pool is None:
        t0 = time.perf_counter()
        rows = []
        for image_id, frame, inp in progress(frames, desc=f"masks {log.name} {camera}",
                                             unit="frame"):
            image, anns, insts = render_frame(log, frame, image_id, camera, cfg, inp)
            rows.append((image, anns, insts if keep_masks else None))
        return camera, [_Done((rows, time.perf_counter() - t0))], keep_masks
    size = _chunk_size(len(frames), pool.workers)
    shared = shared_log(log)
    tasks = [pool.submit(render_chunk, (shared, camera, cfg, frames[k:k + size], keep_masks))
             for k in range(0, len(frames), size)]
    return camera, tasks, keep_masks


def render_labels(log, by_frame: dict[int, dict[str, tuple]], cfg: LabelConfig,
                  extra: dict[int, list[tuple[InstanceMask, int]]] | None = None,
                  camera: str | None = None, pool=None, keep_masks: bool = True
                  ) -> LabelResult:
    """Masks and KINS records of every frame of ``log`` in ``camera`` (default: the log's
    default) from the completed clouds, plus the ``extra`` instances made otherwise
    (:func:`mask_only_labels`; no ``track_id``).

    ``pool``: render runs of frames in its worker processes (:func:`start_render`; the
    result does not depend on it, except that the masks it sends back carry no projected
    points); ``keep_masks`` False: ``LabelResult.masks`` stays empty (only overlays need it).
    """
    return PendingLabels(start_render(log, by_frame, cfg, extra, camera, pool, keep_masks),
                         {}, len(log.frames)).result()

def write_labels(path, result: LabelResult, settings: dict | None = None) -> None:
    """Write the KINS JSON of a :class:`LabelResult` (categories: KINS's plus bus 9 and
    trailer 10, :data:`~seqshape.data.categories.KINS_CATEGORIES`), atomically.

    ``settings`` (:func:`label_settings`): recorded in the file, as its ``info`` block
    (``{"description": LABEL_INFO, "settings": ...}``, first key), for ``seqshape label
    --resume``; None: no ``info`` block (the file as before settings were recorded).
    """
    info = None if settings is None else {"description": LABEL_INFO, "settings": settings}
    write_kins(path, result.images, result.annotations, info=info)


#: ``info.description`` of a label file written with its settings (:func:`write_labels`).
LABEL_INFO = "amodal mask labels written by seqshape label"
#: LabelConfig fields that :func:`label_settings` records otherwise: the weights by their
#: digest, the backend by the arithmetic it computes in.
_NOT_RECORDED = ("checkpoint", "backend")


def inference_arithmetic(backend: str) -> str:
    """What of the estimator's backend can change labels beyond float noise: ``"int8"`` for
    ``onnx-int8`` (shape points move by up to a few cm), ``"float32"`` for the others
    (``auto-float``, ``torch``, ``onnx``, ``torch-lean``: the same float32 network, shape
    points within 2 mm of each other, :data:`seqshape.model.engine.TOLERANCE`). ``"auto"``
    may be either: resolve it first (the loaded estimator's ``backend``), else
    :class:`~seqshape.errors.ConfigError`."""
    if backend == "auto":
        raise ConfigError("backend 'auto' may run int8 or float32: record the backend the "
                          "estimator chose (Estimator.backend)")
    return "int8" if backend == "onnx-int8" else "float32"


def weights_digest(checkpoint: str | None, placement: str = "none") -> str:
    """``"sha256:<hex>"`` of the weights file that :func:`load_estimator` loads for
    ``checkpoint`` (a path, or a shipped name: "pretrained" / None is the shipped sequential
    one), followed by ``" placement sha256:<hex>"`` of the placement refiner's file unless
    ``placement`` is "none"; :class:`~seqshape.errors.DataError` when there is no such file."""
    # torch-free modules: the parent of `label --workers N` never imports PyTorch
    from seqshape.model.placement import pretrained_refiner_path
    from seqshape.model.weights import resolve_weights

    path = resolve_weights("pretrained" if checkpoint is None else checkpoint)
    if placement != "none":
        extra = Path(placement) if placement != "pretrained" else pretrained_refiner_path()
        return f"{_file_digest(path)} placement {_file_digest(extra)}"
    return _file_digest(path)


def _file_digest(path) -> str:
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
    except OSError as exc:
        raise DataError(path, f"unreadable weights file ({exc.strerror or exc})") from None
    return f"sha256:{digest.hexdigest()}"


def _flat(prefix: str, value) -> dict:
    """``{"a.b": leaf}`` of nested dicts (nested config dataclasses after ``asdict``)."""
    if not isinstance(value, dict):
        return {prefix: value}
    out: dict = {}
    for key, item in value.items():
        out.update(_flat(f"{prefix}.{key}" if prefix else str(key), item))
    return out


def label_settings(cfg: LabelConfig, log, camera: str, *, max_frames: int | None = None,
                   weights: str | None = None) -> dict:
    """Everything that decides the label file of ``log`` in ``camera`` (docs/amodal.md,
    "Resuming"): the seqshape version, the log (dataset, name, ``max_frames``), the camera,
    every :class:`LabelConfig` field (nested configs as ``crop.margin`` ...), with the
    checkpoint recorded as ``weights`` (its :func:`weights_digest`, which the caller
    passes, computed once per run) and the backend as ``inference``
    (:func:`inference_arithmetic`); both None in ``gt-accumulation`` (no network). Returns
    a JSON-normalised dict (lists, not tuples), to compare with a file's
    (:func:`settings_differences`)."""
    network = cfg.mode != "gt-accumulation"
    if network and weights is None:
        raise ConfigError(f"mode {cfg.mode}: the settings need the weights' digest")
    fields = {k: v for k, v in _flat("", asdict(cfg)).items()
              if k.split(".")[0] not in _NOT_RECORDED}
    settings = {"seqshape": __version__, "dataset": log.dataset, "log": log.name,
                "camera": camera, "max_frames": max_frames,
                "weights": weights if network else None,
                "inference": inference_arithmetic(cfg.backend) if network else None,
                **fields}
    return json.loads(json.dumps(settings, default=str))


def read_label_settings(path) -> dict | None:
    """The settings recorded in the label file ``path`` (:func:`write_labels`); None when it
    records none (written by an older seqshape or another tool). A file that is not a JSON
    object with KINS's ``images``, ``categories`` and ``annotations`` lists (cut short,
    edited) is a :class:`~seqshape.errors.DataError` naming it. The annotations themselves
    are not checked (:func:`~seqshape.data.kins.read_kins` does: 30 times as long)."""
    path = Path(path)
    hint = "not a complete label file (cut short or edited?); delete it to label its log again"
    try:
        doc = json.loads(path.read_bytes())
    except OSError as exc:
        raise DataError(path, f"unreadable file ({exc.strerror or exc})") from None
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError
        raise DataError(path, f"invalid JSON ({type(exc).__name__}: {exc}): {hint}") from None
    if not isinstance(doc, dict) or not all(
            isinstance(doc.get(k), list) for k in ("images", "categories", "annotations")):
        raise DataError(path, f"no KINS images, categories and annotations lists: {hint}")
    info = doc.get("info")
    settings = info.get("settings") if isinstance(info, dict) else None
    return settings if isinstance(settings, dict) else None


def settings_differences(recorded: dict, current: dict) -> list[str]:
    """``"key: A there vs B now"`` for every key whose value differs (or that one side
    lacks), in ``current``'s order then ``recorded``'s extra keys."""
    missing = "(not recorded)"
    keys = list(current) + [k for k in recorded if k not in current]
    return [f"{k}: {recorded.get(k, missing)!r} there vs {current.get(k, missing)!r} now"
            for k in keys if recorded.get(k, missing) != current.get(k, missing)]
