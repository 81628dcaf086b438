"""Offline (whole-track) estimation: every frame's estimate may use the track's future frames.

Auto-labelling runs after the drive with the whole track at hand. :func:`estimate_track` runs
a trained :class:`~seqshape.model.Estimator`'s network over one whole track (one batched
forward pass per pass, not one call per frame) and adds no trained parameters, so it works
with the shipped weights and with any later checkpoint. An :class:`OfflineConfig` picks the
pieces (docs/model.md, section "Offline mode", has their measured figures):

* ``shape``: where each frame's complete shape comes from. ``"online"``: the frame's own
  estimate after frames ``0..t`` (the paper). ``"final"``: the shape after the track's last
  frame with points (its state has seen every frame), carried to every frame.
  ``"two-pass"``: the network is run over the track a second time starting from that final
  state, so every frame's estimate has seen all frames (frames from the last detection on
  keep the first pass: it had seen everything there). ``"bidirectional"``: the network is
  also run over the reversed track; each frame takes the direction that has seen more
  detections. ``"average"``: the online shapes averaged slot by slot in their canonical
  frames over the whole track, past and future, weighted by each frame's points and
  ``shape_decay ** |t - j|`` (:func:`seqshape.model.smooth.average_shapes`).
* ``pose``: ``"online"``, ``"two-pass"`` (as above) or ``"bidirectional"`` (the two
  directions' centres, and their yaws when they agree within 90 degrees, averaged with
  weights the detections each has seen).
* ``smooth``: the poses smoothed along the whole track in the fixed frame of the ego poses
  (:func:`seqshape.model.smooth.smooth_track_poses`: robust local quadratic fit of the
  centres, a whole-track line or constant for a parked or creeping one that follows it;
  heading from the motion of a moving vehicle less its centre's sideslip in a turn, else
  the track's axial mean yaw).
* ``heading``: make the yaw consistent along the whole track in a fixed frame (needs ego
  poses, or a static sensor): the motion direction over a window centred on each frame (both
  directions in time) where the vehicle moves steadily, else a vote over the whole track
  weighted by closeness in time (:func:`consistent_flips`). Without it the online causal
  heading step of the estimator (:mod:`seqshape.model.heading`) is applied.

A shape moved to a pose other than the one it was estimated with is taken into its canonical
frame with its own pose (turned by pi when that is nearer the new yaw, so that it stays where
it was estimated) and placed with the new pose; a heading flip turns the yaw only (as the
online heading step does). The default, the measured best, is the track's average shape
with the online pose, smoothed, with the whole-track heading.

``mode="online"`` reproduces :meth:`Estimator.step` called frame by frame (same resampling of
large frames, same input scale, same heading step). With the estimator's track memory
(:mod:`seqshape.model.track_memory`, the sequential model's default) a track with ego poses
that the memory would feed (:func:`~seqshape.model.track_memory.memory_would_feed`, replayed
on the batched pass) is run through :meth:`Estimator.step` itself, on the estimator's
backend: online those are its estimates; offline its positions (smoothed as the others) come
from them and its shape from the batched pass. On a track of one frame every offline
configuration equals the online estimate. The per-frame baseline has no state to share
between frames: for it offline equals online.

>>> from seqshape.model import Estimator
>>> from seqshape.testing import box_surface
>>> est = Estimator.from_pretrained("sequential")
>>> frames = [box_surface(200, t, pose=(12.0 + 0.5 * t, -3.0, -0.9, 0.0), dtype=np.float32)
...           for t in range(3)]  # a car driving along x, static sensor
>>> out = estimate_track(est, frames, ego_poses=[np.eye(4)] * 3)
>>> len(out), out[0].complete.shape, out[0].pose.shape
(3, (1024, 3), (4,))
"""

from __future__ import annotations

import copy
import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from seqshape.data.windows import points_lengths, resample_frame
from seqshape.errors import ConfigError
from seqshape.model.estimator import Estimate, _class_floor, _length_hint, check_points
from seqshape.model.extents import bound_extents
from seqshape.model.heading import (
    HeadingConfig,
    HeadingFilter,
    motion_direction,
    pose_yaw,
    wrap_angle,
)
from seqshape.model.size_scale import scale_ego, scale_of, scale_size, unscale_estimate
from seqshape.model.smooth import (
    MAX_GAP,
    SHAPE_DECAY,
    CausalSmoother,
    average_shapes,
    check_decay,
    check_weighting,
    frame_numbers,
    frame_weights,
    limit_shift,
    place_shapes,
    smooth_track_poses,
    track_segments,
    world_centres,
)
from seqshape.model.track_memory import memory_would_feed

MODES = ("online", "offline")
SHAPE_SOURCES = ("online", "final", "two-pass", "bidirectional", "average")
POSE_SOURCES = ("online", "two-pass", "bidirectional")
EXTENTS = ("none", "bound", "anchor")


@dataclass(frozen=True)
class OfflineConfig:
    """What offline estimation uses (module doc). The defaults are the measured best on the
    paper-preset val split and the traffic set (docs/model.md, "Offline mode")."""

    shape: str = "average"
    """Source of each frame's complete shape: ``"online"``, ``"final"``, ``"two-pass"``,
    ``"bidirectional"`` or ``"average"`` (the online shapes averaged slot by slot in their
    canonical frames over the whole track, :func:`seqshape.model.smooth.average_shapes`
    with ``shape_decay`` and the frames' :func:`~seqshape.model.smooth.frame_weights`)."""
    pose: str = "online"
    """Source of each frame's pose: ``"online"`` or ``"two-pass"``."""
    smooth: bool = True
    """Smooth the poses along the track in the fixed frame of the ego poses (the sensor frame
    without them) with :func:`seqshape.model.smooth.smooth_track_poses` (a robust local
    quadratic fit of the centres; headings from the motion or the track's axial mean)."""
    heading: bool = True
    """Whole-track heading consistency (:func:`consistent_flips`) instead of the online
    causal heading step."""
    vote_decay: float = 0.95
    """Whole-track heading vote: weight ``vote_decay ** |t - j|`` of frame j's yaw at frame
    t (1 = a plain majority over the whole track)."""
    full_points: float | None = None
    """The smoothing's frame weights (:func:`seqshape.model.smooth.frame_weights`): points
    at which a frame's estimate counts fully (None: no weighting by points). Off by default:
    the causal smoother gains from it, the whole-track smoother loses (docs/model.md,
    "Causal pose smoothing (online)")."""
    ramp: float | None = None
    """The smoothing's frame weights: detections over which a track's first online estimates
    weigh less (None: no ramp; off by default, as ``full_points``)."""
    shape_decay: float = SHAPE_DECAY
    """``shape="average"``: frame j's shape weighs ``shape_decay ** |t - j|`` at frame t."""
    extents: str = "none"
    """Bound each segment's length and width by the track's observed points
    (:func:`seqshape.model.extents.bound_extents`): ``"none"``, ``"bound"`` (never short of
    what was seen; the observed span where both faces were seen) or ``"anchor"`` (also a
    single seen face placed where it was observed)."""

    def __post_init__(self):
        if self.shape not in SHAPE_SOURCES:
            raise ConfigError(f"OfflineConfig.shape must be one of {SHAPE_SOURCES}, got "
                              f"{self.shape!r}")
        if self.pose not in POSE_SOURCES:
            raise ConfigError(f"OfflineConfig.pose must be one of {POSE_SOURCES}, got "
                              f"{self.pose!r}")
        if not 0.0 < float(self.vote_decay) <= 1.0:
            raise ConfigError(f"OfflineConfig.vote_decay must be in (0, 1], got "
                              f"{self.vote_decay}")
        check_weighting("OfflineConfig", self.full_points, self.ramp)
        check_decay("OfflineConfig", self.shape_decay)
        if self.extents not in EXTENTS:
            raise ConfigError(f"OfflineConfig.extents must be one of {EXTENTS}, got "
                              f"{self.extents!r}")

    @property
    def two_pass(self) -> bool:
        """Whether the second pass is needed."""
        return self.shape == "two-pass" or self.pose == "two-pass"

    @property
    def name(self) -> str:
        """A short label, e.g. ``shape=final,pose=online,heading``."""
        return (f"shape={self.shape},pose={self.pose}" + (",smooth" if self.smooth else "")
                + (",heading" if self.heading else ""))


def estimate_track(estimator, points: Sequence[np.ndarray], timestamps=None, size=None,
                   cls: str | None = None, ego_poses: Sequence | None = None,
                   mode: str = "offline", config: OfflineConfig | None = None,
                   track_id: str = "track") -> list[Estimate]:
    """Estimate shape and pose in every frame of one track; one :class:`Estimate` per frame.

    Args:
        estimator: a :class:`~seqshape.model.Estimator` (its network, seed and heading
            options are used; its live track states are neither read nor changed).
        points: per frame an (N_t, 3) array in that frame's sensor frame (N_t may be 0; rows
            with NaN/inf are dropped).
        timestamps: (T,) seconds (any origin), or None: the time steps of a
            ``motion_input`` network (without them, the estimator's ``frame_period``).
        size: a box (l, w, h) or a length (m) hint for the input scale, as in
            :meth:`Estimator.step` (only a ``scale_norm="length"`` model uses it).
        cls: vehicle class hint (car, van, truck, bus, trailer), as in :meth:`Estimator.step`.
        ego_poses: per frame a (4, 4) sensor frame -> fixed frame (entries may be None), or
            None: the heading evidence from motion.
        mode: ``"offline"`` (uses every frame for every estimate) or ``"online"`` (frame t
            sees frames 0..t only: equals :meth:`Estimator.step` frame by frame).
        config: the offline pieces (:class:`OfflineConfig`; default: the measured best).
        track_id: the id written into the estimates; it also seeds the random subsets of frames
            with more points than the network takes, as :meth:`Estimator.step` does.

    Returns:
        list of :class:`~seqshape.model.Estimate`, in each frame's sensor frame.

    Many tracks at once: :func:`estimate_tracks` (the same estimates, fewer passes).
    """
    track = {"points": points, "timestamps": timestamps, "size": size, "cls": cls,
             "ego_poses": ego_poses, "track_id": track_id}
    return estimate_tracks(estimator, [track], mode, config)[0]


#: The keys of a track of :func:`estimate_tracks` (the arguments of :func:`estimate_track`).
TRACK_KEYS = ("points", "timestamps", "size", "cls", "ego_poses", "track_id")
#: Padded frames (tracks x longest track) of one batched pass of :func:`estimate_tracks`.
#: Measured (docs/history/model.md, "Inference backends (issue 17)"): one track's pass is already a
#: batch of its frames, and larger passes were slower per frame (the encoder's per-point
#: features of more frames leave the caches: 512 frames cost 1.2-1.3x the CPU time of one
#: pass per track), so only short tracks share a pass.
CHUNK_FRAMES = 64


def estimate_tracks(estimator, tracks: Sequence[Mapping], mode: str = "offline",
                    config: OfflineConfig | None = None,
                    chunk_frames: int = CHUNK_FRAMES) -> list[list[Estimate]]:
    """:func:`estimate_track` of many tracks: the network runs over chunks of tracks in one
    batched pass each, not one pass per track.

    Args:
        estimator, mode, config: as in :func:`estimate_track`.
        tracks: per track a mapping of :func:`estimate_track`'s per-track arguments
            (:data:`TRACK_KEYS`: ``points`` required; ``timestamps``, ``size``, ``cls``,
            ``ego_poses``, ``track_id`` optional, with its defaults).
        chunk_frames: at most this many padded frames (tracks times the chunk's longest
            track) per pass, a longer track alone; tracks are chunked longest first, so
            tracks of similar lengths share a pass.

    Returns:
        per track, in order, what :func:`estimate_track` returns for it (equal within float
        rounding: the batched matrix products may sum in another order).
    """
    if mode not in MODES:
        raise ConfigError(f"mode must be one of {MODES}, got {mode!r}")
    if int(chunk_frames) < 1:
        raise ConfigError(f"chunk_frames must be >= 1, got {chunk_frames!r}")
    cfg = config or OfflineConfig()
    k = float(getattr(estimator, "size_scale", 1.0))
    args = [_track_args(track, i) for i, track in enumerate(tracks)]
    ks = [scale_of(k, a["cls"]) for a in args]  # cars only (Estimator.size_scale)
    preps = [_prepare(estimator, a, kt) for a, kt in zip(args, ks, strict=True)]
    live = [p for p in preps if p.frames]
    model = estimator.model
    for p, first in zip(live, _run_many(model, [_Pass(p.frames, p.scales, p.motion)
                                                for p in live], chunk_frames), strict=True):
        p.passes["online"] = _refined(estimator, p.frames, first)
    # a track the memory feeds: its input depends on its own estimates, so it runs step by
    # step (Estimator.step, on the estimator's backend), the first pass of the offline mode
    fed = _memory_fed(estimator, cfg, mode, preps)
    stepped = dict(zip(fed, _stepped(estimator, [preps[i] for i in fed], mode == "online"),
                       strict=True))
    for i, ests in stepped.items():  # offline: its positions; the shapes stay the first pass's
        preps[i].passes["memory"] = _unflipped(ests)
    offline = [p for p in live if mode == "offline" and model.recurrent and p.counts.any()]
    jobs, owners = [], []
    for p in offline:
        if cfg.two_pass:
            last = int(np.flatnonzero(p.counts)[-1])
            final = None if p.scales is None else np.full(len(p.frames), p.scales[last])
            first = p.passes["online"]
            jobs.append(_Pass(p.frames, final, p.motion, first["hidden"], first["gap"]))
            owners.append((p, "two-pass"))
        if "bidirectional" in (cfg.shape, cfg.pose):
            jobs.append(_backward_pass(estimator, p))
            owners.append((p, "backward"))
    for (p, key), job, out in zip(owners, jobs, _run_many(model, jobs, chunk_frames),
                                  strict=True):
        p.passes[key] = _refined(estimator, job.frames, out)
    out = [stepped[i] if i in stepped and mode == "online"
           else _assemble(estimator, p, cfg, p in offline) if p.frames else []
           for i, p in enumerate(preps)]
    if k != 1.0:  # the networks saw cars at the fleet's sizes (Estimator.size_scale)
        out = [[unscale_estimate(e, kt) for e in ests] for ests, kt in zip(out, ks, strict=True)]
    return out


def _memory_fed(estimator, cfg: OfflineConfig, mode: str, preps: list) -> list[int]:
    """The tracks (indices of ``preps``) whose estimates the track memory would change
    (``estimator.track_memory`` on, a recurrent model, ego poses): those in which it would
    feed a frame given the first pass (:func:`~seqshape.model.track_memory.memory_would_feed`;
    until it feeds one the stream's estimates are the first pass's). Online, or offline with
    a configuration that takes the first pass alone (no ``two-pass`` or ``bidirectional``
    network passes); with ``smoothing="causal"`` online every track with ego poses (the
    memory then sees the smoothed positions)."""
    if getattr(estimator, "track_memory", "none") == "none" or not estimator.model.recurrent \
            or (mode == "offline" and (cfg.two_pass or "bidirectional" in (cfg.shape,
                                                                           cfg.pose))):
        return []
    smoothed = mode == "online" and getattr(estimator, "smoothing", "none") != "none"
    return [i for i, p in enumerate(preps) if p.frames and p.egos is not None and (
        smoothed or memory_would_feed(p.passes["online"]["pose"], p.egos, p.counts > 0))]


def _unflipped(estimates: list[Estimate]) -> dict:
    """The first-pass arrays of :func:`estimate_tracks` from a stream's estimates: their
    shapes and poses before the heading step (a flip turned the yaw only)."""
    pose = np.stack([e.pose for e in estimates]).astype(np.float64)
    flipped = np.array([e.flipped for e in estimates])
    pose[flipped, 3] = wrap_angle(pose[flipped, 3] - math.pi)
    return {"complete": np.stack([e.complete for e in estimates]), "pose": pose}


def _stepped(estimator, tracks: list[_Track], smoothing: bool = True) -> list[list[Estimate]]:
    """Prepared tracks run through :meth:`Estimator.step <seqshape.model.Estimator.step>`
    frame by frame (``track_memory``: a frame's input depends on the track's estimates before
    it), on a copy of ``estimator`` with states of its own, in the world of
    :attr:`~seqshape.model.Estimator.size_scale` the tracks were prepared in (the estimates
    stay there); tracks whose ids differ share each step. Without ``smoothing`` the copy does
    not smooth (an offline first pass)."""
    twin = copy.copy(estimator)
    twin.size_scale = 1.0
    if not smoothing:
        twin.smoothing = "none"
    out: list[list[Estimate]] = [[] for _ in tracks]
    pending = list(range(len(tracks)))
    while pending:
        group, ids = [], set()
        for i in pending:
            if str(tracks[i].track_id) not in ids:
                group.append(i)
                ids.add(str(tracks[i].track_id))
        pending = [i for i in pending if i not in set(group)]
        twin._states = {}
        for t in range(max(len(tracks[i].given) for i in group)):
            live = [tracks[i] for i in group if t < len(tracks[i].given)]
            res = twin.step([str(p.track_id) for p in live],
                            [p.given[t] * np.float32(p.world) for p in live],
                            sizes=[p.size for p in live], classes=[p.cls for p in live],
                            ego_poses=[p.egos[t] for p in live],
                            timestamps=[None if p.times is None else float(p.times[t])
                                        for p in live])
            for i, e in zip([i for i in group if t < len(tracks[i].given)], res, strict=True):
                out[i].append(e)
    return out


@dataclass(eq=False)
class _Track:
    """One track of :func:`estimate_tracks` as the network gets it, and its passes."""

    track_id: str
    frames: list[np.ndarray]  # at most N finite points per frame
    raw: np.ndarray  # (T,) finite points per frame before the subsets
    egos: list | None
    times: np.ndarray | None
    counts: np.ndarray  # (T,) points per frame the network gets
    scales: np.ndarray | None  # (T,) input scales of a scale_norm="length" model
    motion: dict  # (1, T) motion inputs of a motion_input model
    size: object
    cls: str | None
    given: list[np.ndarray]  # the checked frames before the subsets (the track memory's input)
    world: float  # the world scale of frames, egos and size (Estimator.size_scale; not given)
    passes: dict = field(default_factory=dict)


@dataclass(eq=False)
class _Pass:
    """One pass of the network over one track: its frames, scales, motion inputs and the
    state it starts from (None: a fresh track)."""

    frames: list[np.ndarray]
    scales: np.ndarray | None
    motion: dict
    hidden: torch.Tensor | None = None  # (1, S)
    gap: torch.Tensor | None = None  # (1,)


def _track_args(track: Mapping, i: int) -> dict:
    if not isinstance(track, Mapping) or "points" not in track:
        raise ConfigError(f"tracks[{i}] must be a mapping with 'points' (and optionally "
                          f"{', '.join(TRACK_KEYS[1:])})")
    unknown = sorted(set(track) - set(TRACK_KEYS))
    if unknown:
        raise ConfigError(f"tracks[{i}]: unknown keys {unknown}; expected {TRACK_KEYS}")
    return {"timestamps": None, "size": None, "cls": None, "ego_poses": None,
            "track_id": "track", **track}


def _prepare(estimator, args: dict, k: float = 1.0) -> _Track:
    """The checked inputs of one track (:func:`estimate_track`'s arguments), in a world
    scaled by ``k`` (:attr:`Estimator.size_scale <seqshape.model.Estimator.size_scale>`)."""
    track_id = args["track_id"]
    frames, given = _frames(estimator, args["points"], track_id)
    raw = np.array([len(f) for f in given], dtype=np.int64)
    n = len(frames)
    egos = _ego_list(args["ego_poses"], n) if n else None
    times = _times(args["timestamps"], n) if n else None
    model = estimator.model
    size = args["size"]
    if k != 1.0:
        frames = [f * np.float32(k) for f in frames]
        egos = None if egos is None else [scale_ego(e, k) for e in egos]
        _length_hint([size], 0)  # its error before it is scaled
        size = scale_size(size, k)
    scales = _scales(model, frames, size, args["cls"]) if n else None
    return _Track(track_id, frames, raw, egos, times,
                  np.array([len(f) for f in frames], dtype=np.int64), scales,
                  _motion(estimator, raw, times) if n else {}, size, args["cls"], given, k)


def _backward_pass(estimator, p: _Track) -> _Pass:
    """The network's pass over the reversed track (``bidirectional``)."""
    back = p.frames[::-1]
    times = None if p.times is None else p.times[-1] - p.times[::-1]
    return _Pass(back, _scales(estimator.model, back, p.size, p.cls),
                 _motion(estimator, p.raw[::-1], times))


def _assemble(estimator, p: _Track, cfg: OfflineConfig, offline: bool) -> list[Estimate]:
    """A track's estimates from its passes (the offline pieces of ``cfg``; the first pass
    with the online heading step when not ``offline``)."""
    first = p.passes["online"]
    if not offline:
        out = _finish(estimator, p, first["complete"], first["pose"], None)
        if getattr(estimator, "smoothing", "none") == "causal":  # as Estimator.step does
            _smooth_causally(estimator, p, out)
        return out
    last = int(np.flatnonzero(p.counts)[-1])
    passes = {"online": first}
    if cfg.two_pass:
        second = p.passes["two-pass"]
        for key in ("complete", "pose"):  # from the last detection on, pass 1 saw it all
            second[key][last:] = first[key][last:]
        passes["two-pass"] = second
    if "bidirectional" in (cfg.shape, cfg.pose):
        passes["bidirectional"] = _bidirectional(p.frames, first, p.passes["backward"])
    poses = passes[cfg.pose]["pose"].copy()
    if "memory" in p.passes:  # the track memory's positions (cfg.pose is "online")
        poses = p.passes["memory"]["pose"].copy()
    # a hole longer than MAX_GAP or a jump no vehicle makes splits the track into segments
    # that no smoothing, shape average or heading vote crosses
    segments = track_segments(p.times, p.counts > 0, world_centres(poses, p.egos))
    if cfg.smooth:
        poses = _smooth(poses, frame_weights(p.counts, cfg.full_points, cfg.ramp), p.egos,
                        p.times, segments)
    if cfg.shape == "final":
        complete = np.broadcast_to(first["complete"][last], first["complete"].shape)
        own = np.broadcast_to(first["pose"][last], poses.shape)
    elif cfg.shape == "average":  # the first pass's poses are the decoder's (no flip yet)
        complete = average_shapes(first["complete"], first["pose"], frame_weights(p.counts),
                                  cfg.shape_decay, causal=False,
                                  frames=frame_numbers(p.times, len(p.counts)),
                                  segments=segments)
        own = first["pose"]
    else:
        complete, own = passes[cfg.shape]["complete"], passes[cfg.shape]["pose"]
    complete = place_shapes(complete, own, poses)
    if cfg.extents != "none":
        complete, poses = bound_extents(p.frames, complete, poses, segments,
                                        anchor=cfg.extents == "anchor")
    flips = (consistent_flips(poses, p.egos, p.counts > 0, estimator.heading, cfg.vote_decay,
                              segments) if cfg.heading else None)
    return _finish(estimator, p, complete, poses, flips)


def _smooth_causally(estimator, p: _Track, out: list[Estimate]) -> None:
    """The online estimates ``out`` of track ``p`` through a :class:`CausalSmoother`, frame
    by frame, as :meth:`Estimator.step` with ``smoothing="causal"`` gives them (in place)."""
    smoother = CausalSmoother()
    for t, est in enumerate(out):
        smoother.update_estimate(est, None if p.egos is None else p.egos[t],
                                 None if p.times is None else float(p.times[t]),
                                 1.0 / estimator.frame_period)


def _bidirectional(frames: list[np.ndarray], first: dict, back: dict) -> dict:
    """Per frame the forward (first-pass) and the backward estimate (the network run over the
    reversed track, ``back``) combined: the centres averaged with weights the detections each
    has seen (frames with points up to t forwards, from t backwards), the yaws likewise when
    they agree within 90 degrees, else the better-informed one's; the shape of the
    better-informed direction."""
    b_pose, b_complete = back["pose"][::-1], back["complete"][::-1]
    has = np.array([len(f) > 0 for f in frames], dtype=np.float64)
    w_f, w_b = np.cumsum(has), np.cumsum(has[::-1])[::-1]
    f_pose = first["pose"]
    use_b = w_b > w_f
    pose = np.where(use_b[:, None], b_pose, f_pose).copy()
    agree = np.abs(wrap_angle(b_pose[:, 3] - f_pose[:, 3])) <= math.pi / 2
    wf = w_f / np.maximum(w_f + w_b, 1e-9)
    pose[:, :3] = wf[:, None] * f_pose[:, :3] + (1.0 - wf[:, None]) * b_pose[:, :3]
    mean_yaw = np.arctan2(wf * np.sin(f_pose[:, 3]) + (1 - wf) * np.sin(b_pose[:, 3]),
                          wf * np.cos(f_pose[:, 3]) + (1 - wf) * np.cos(b_pose[:, 3]))
    pose[agree, 3] = mean_yaw[agree]
    complete = np.where(use_b[:, None, None], b_complete, first["complete"])
    own = np.where(use_b[:, None], b_pose, f_pose)
    return {"pose": pose, "complete": place_shapes(complete, own, pose)}


def _smooth(poses: np.ndarray, weights: np.ndarray, egos, times: np.ndarray | None,
            segments: np.ndarray) -> np.ndarray:
    """:func:`seqshape.model.smooth.smooth_track_poses` of the poses of each segment on its
    own, over the frame numbers of the timestamps (:func:`~seqshape.model.smooth.
    frame_numbers`: the window counts frames, holes included), with the frames' ``weights``
    (0: not fitted), at the frame rate of the timestamps (10 Hz without them); in the fixed
    frame of the ego poses when every frame has one. A frame with points whose centre the fit
    would move more than ``MAX_SHIFT`` keeps its estimate
    (:func:`~seqshape.model.smooth.limit_shift`), as does a frame without points more than
    ``MAX_GAP`` seconds from its segment's detections (nothing is carried far)."""
    rate = 10.0
    if times is not None and len(times) > 1:
        step = float(np.median(np.diff(times)))
        rate = 1.0 / step if step > 0 else rate
    ego = None
    if egos is not None and all(e is not None for e in egos):
        ego = np.stack(egos)
    frames = frame_numbers(times, len(poses))
    out = poses.copy()
    for s in np.unique(segments):
        idx = np.flatnonzero(segments == s)
        out[idx] = smooth_track_poses(poses[idx], frames[idx],
                                      None if ego is None else ego[idx], rate_hz=rate,
                                      weights=weights[idx])
    valid = weights > 0
    out = limit_shift(out, poses, valid)
    if times is not None and valid.any():  # stale frames far from any detection
        seconds = np.asarray(times, dtype=np.float64)
        for s in np.unique(segments):
            idx = np.flatnonzero(segments == s)
            hits = seconds[idx[valid[idx]]]
            if len(hits) == 0:
                out[idx] = poses[idx]
                continue
            far = np.min(np.abs(seconds[idx, None] - hits[None, :]), axis=1) > MAX_GAP
            out[idx[far]] = poses[idx[far]]
    return out


def _frames(estimator, points: Sequence[np.ndarray], track_id: str
            ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The frames as the network gets them: finite rows, at most N (random subsets drawn
    with the estimator's per-track generator, in frame order, as :meth:`Estimator.step`),
    and the checked frames before that subset."""
    n_max = estimator.max_points
    rng = np.random.default_rng([estimator.seed, zlib.crc32(str(track_id).encode("utf-8"))])
    out, given = [], []
    for i, pts in enumerate(points):
        pts = check_points(pts, f"points[{i}] (track {track_id!r})")  # as Estimator.step
        given.append(pts)
        out.append(pts if len(pts) <= n_max else resample_frame(pts, n_max, rng)[0])
    return out, given


def _ego_list(ego_poses: Sequence | None, n: int) -> list[np.ndarray | None] | None:
    if ego_poses is None:
        return None
    if len(ego_poses) != n:
        raise ConfigError(f"{n} frames of points but {len(ego_poses)} ego poses")
    out = []
    for i, e in enumerate(ego_poses):
        if e is None:
            out.append(None)
            continue
        e = np.asarray(e, dtype=np.float64)
        if e.shape != (4, 4) or not np.all(np.isfinite(e)):
            raise ConfigError(f"ego_poses[{i}] must be a finite (4, 4) matrix, got shape "
                              f"{e.shape}")
        out.append(e)
    return out if any(e is not None for e in out) else None


def _times(timestamps, n: int) -> np.ndarray | None:
    if timestamps is None:
        return None
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if len(t) != n or not np.all(np.isfinite(t)):
        raise ConfigError(f"timestamps must be {n} finite values (one per frame), got "
                          f"{len(t)}")
    return t


def _scales(model, frames: list[np.ndarray], size, cls) -> np.ndarray | None:
    """(T,) input scales of a ``scale_norm="length"`` model, as :meth:`Estimator.step` sets
    them frame by frame (None for other models)."""
    mcfg = model.cfg
    if mcfg.scale_norm == "none":
        return None
    # the same hint rules and errors as Estimator.step, for one track
    hint = _length_hint([size], 0)
    floor = _class_floor([cls], 0)
    length, out = 0.0, []
    for f, here in zip(frames, points_lengths(frames).tolist(), strict=True):
        if len(f):
            length = max(length, here) if model.recurrent else here
        out.append(mcfg.scale_for(hint if hint is not None else max(length, floor)))
    return np.asarray(out, dtype=np.float64)


def _motion(estimator, raw: np.ndarray, times: np.ndarray | None) -> dict:
    """The motion inputs of a ``motion_input`` network for the whole track, as
    :meth:`Estimator.step` gives them frame by frame (empty for other networks): ``counts``
    (1, T) points before resampling and ``dts`` (1, T) seconds since the previous frame (the
    first frame, and every frame without timestamps: the estimator's ``frame_period``)."""
    if not getattr(estimator.model, "motion", False):
        return {}
    period = float(getattr(estimator, "frame_period", 0.1))
    dts = np.full(len(raw), period)
    if times is not None and len(times) > 1:
        dts[1:] = np.diff(times)
    return {"counts": torch.tensor(raw.tolist(), dtype=torch.int64)[None],
            "dts": torch.as_tensor(dts, dtype=torch.float64).float()[None]}


def _run_many(model, passes: list[_Pass], chunk_frames: int) -> list[dict]:
    """:func:`_run_chunk` over chunks of ``passes`` (longest first, at most ``chunk_frames``
    padded frames each, :func:`chunk_tracks`); the outputs in the order of ``passes``."""
    out: list[dict | None] = [None] * len(passes)
    for chunk in chunk_tracks([len(p.frames) for p in passes], chunk_frames):
        for i, result in zip(chunk, _run_chunk(model, [passes[i] for i in chunk]),
                             strict=True):
            out[i] = result
    return out


def chunk_tracks(lengths: Sequence[int], chunk_frames: int) -> list[list[int]]:
    """Indices of tracks of ``lengths`` frames grouped for batched passes: longest first, a
    chunk takes tracks while (its tracks) x (its longest) <= ``chunk_frames`` (a track longer
    than that alone).

    >>> chunk_tracks([3, 10, 4, 9, 2], 20)
    [[1, 3], [2, 0, 4]]
    """
    order = sorted(range(len(lengths)), key=lambda i: -lengths[i])
    chunks: list[list[int]] = []
    for i in order:
        if chunks and (len(chunks[-1]) + 1) * lengths[chunks[-1][0]] <= chunk_frames:
            chunks[-1].append(i)
        else:
            chunks.append([i])
    return chunks


def _refined(estimator, frames: list[np.ndarray], out: dict) -> dict:
    """A pass's output with the estimator's placement refiner applied frame by frame (as
    :meth:`Estimator.step` applies it; unchanged without a refiner)."""
    refiner = getattr(estimator, "refiner", None)
    if refiner is None:
        return out
    out = dict(out)
    out["complete"], out["pose"], _ = refiner.refine_sequence(frames, out["complete"],
                                                              out["pose"])
    return out


def _run_chunk(model, passes: list[_Pass]) -> list[dict]:
    """One pass of the network over several tracks at once (padded at the end with empty
    frames, which hold the state and, with zero time steps, the time since the last
    detection): per track numpy ``complete`` (T, K, 3) float32, ``pose`` (T, 4) float64,
    and the final ``hidden`` (1, S) and ``gap`` (1,) (time since the last detection)."""
    b, w = len(passes), max(len(p.frames) for p in passes)
    n = max(1, max(len(f) for p in passes for f in p.frames))
    batch = np.zeros((b, w, n, 3), np.float32)
    lengths = np.zeros((b, w), np.int64)
    for i, p in enumerate(passes):
        for t, f in enumerate(p.frames):
            lengths[i, t] = len(f)
            if len(f):
                batch[i, t] = np.resize(f, (n, 3))
    kw: dict = {}
    if passes[0].scales is not None:
        scale = np.ones((b, w), np.float32)
        for i, p in enumerate(passes):
            scale[i, :len(p.frames)] = p.scales
        kw["scale"] = torch.from_numpy(scale)
    if passes[0].motion:
        for key in ("counts", "dts"):
            kw[key] = torch.cat([F.pad(p.motion[key], (0, w - len(p.frames)))
                                 for p in passes])
        if any(p.gap is not None for p in passes):
            kw["gap"] = torch.cat([torch.zeros(1) if p.gap is None else p.gap
                                   for p in passes])
    hidden = None
    if any(p.hidden is not None for p in passes):
        hidden = torch.cat([torch.zeros(1, model.state_size) if p.hidden is None else p.hidden
                            for p in passes])
    with torch.inference_mode():
        out = model(torch.from_numpy(batch), torch.from_numpy(lengths), hidden=hidden, **kw)
    results = []
    for i, p in enumerate(passes):
        t = len(p.frames)
        results.append({"complete": out["complete"][i, :t].numpy(),
                        "pose": out["pose"][i, :t].double().numpy(),
                        "hidden": out["hidden"][i:i + 1].clone(),
                        "gap": out["gap"][i:i + 1].clone()})
    return results


def _finish(estimator, p: _Track, complete: np.ndarray, poses: np.ndarray,
            flips: np.ndarray | None) -> list[Estimate]:
    """Track ``p``'s estimates with the heading step: ``flips`` (whole track) or the
    estimator's online causal heading filter (when ``flips`` is None), which gets each
    frame's points as :meth:`Estimator.step` gives them (the opt-in shape evidence)."""
    heading, counts, egos = estimator.heading, p.counts, p.egos
    filt = HeadingFilter(heading) if (egos is not None or heading.active_without_poses) \
        else None
    out = []
    seen = np.cumsum(counts > 0) > 0  # frames before the first detection: not valid
    for t in range(len(counts)):
        est = Estimate(str(p.track_id), np.array(complete[t], dtype=np.float32),
                       np.array(poses[t], dtype=np.float64), int(counts[t]))
        est.valid = est.valid and bool(seen[t])
        if p.scales is not None:
            est.scale = float(p.scales[t])
        ego = None if egos is None else egos[t]
        if flips is not None:
            flip = bool(flips[t])
        elif filt is not None and (ego is not None or heading.active_without_poses):
            flip = filt.update(est.pose, ego, est.num_points > 0, p.frames[t], p.cls,
                               None if p.times is None else float(p.times[t]))
        else:
            flip = False
        if flip:
            est.pose[3] = wrap_angle(est.pose[3] + math.pi)
            est.flipped = True
        out.append(est)
    return out


def consistent_flips(poses: np.ndarray, ego_poses: Sequence | None, has_points: np.ndarray,
                     cfg: HeadingConfig | None = None, vote_decay: float = 0.95,
                     segments: np.ndarray | None = None) -> np.ndarray:
    """Which frames' yaws to turn by pi so the heading is consistent along the whole track.

    In the fixed frame of ``ego_poses`` (per frame (4, 4) sensor -> fixed, or None; with
    ``cfg.static_sensor`` the sensor frame itself; with neither nothing is flipped): where the
    estimated centres of the frames with points move steadily over a window of
    ``cfg.motion_frames`` of them centred on the frame (the past and the future,
    :func:`~seqshape.model.heading.motion_direction` with ``min_travel`` and
    ``min_consistency``), the motion direction is the heading. Elsewhere the heading is the
    vote of the whole track: the unit vectors of the frames' yaws (those of moving frames
    aligned to their motion and weighted ``cfg.motion_weight``), weighted ``vote_decay **
    |t - j|``. A yaw more than 90 degrees from its frame's heading is flipped.

    Args:
        poses: (T, 4) per-frame (x, y, z, yaw) in each frame's sensor frame.
        ego_poses: per frame a (4, 4) matrix or None (that frame then takes no part), or None.
        has_points: (T,) bool, frames with points (only they are evidence).
        cfg: motion and vote options (:class:`~seqshape.model.heading.HeadingConfig`;
            ``motion=False`` leaves only the vote).
        vote_decay: temporal weight of the vote, in (0, 1].
        segments: (T,) segment numbers (:func:`~seqshape.model.smooth.track_segments`), or
            None (one): each segment is decided on its own.

    Returns:
        (T,) bool.
    """
    cfg = cfg or HeadingConfig()
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    n = len(poses)
    if segments is not None and len(np.unique(segments)) > 1:
        flips = np.zeros(n, dtype=bool)
        has_points = np.asarray(has_points, dtype=bool)
        for s in np.unique(segments):
            idx = np.flatnonzero(np.asarray(segments) == s)
            flips[idx] = consistent_flips(
                poses[idx], None if ego_poses is None else [ego_poses[i] for i in idx],
                has_points[idx], cfg, vote_decay)
        return flips
    flips = np.zeros(n, dtype=bool)
    yaw, centre, known = _fixed_frame(poses, ego_poses, cfg.static_sensor)
    if known is None:
        return flips
    evidence = np.flatnonzero(known & np.asarray(has_points, dtype=bool))
    if len(evidence) == 0:
        return flips
    motion = np.full(n, np.nan)
    if cfg.motion:
        motion = _window_motion(centre, evidence, n, cfg)
    moving = np.isfinite(motion)
    aligned = np.where(moving & (np.abs(wrap_angle(yaw - motion)) > math.pi / 2), yaw + math.pi, yaw)
    weight = np.where(moving, cfg.motion_weight, 1.0)[evidence]
    unit = np.stack([np.cos(aligned[evidence]), np.sin(aligned[evidence])], axis=1)
    for t in np.flatnonzero(known):
        if moving[t]:
            target = motion[t]
        else:
            w = weight * float(vote_decay) ** np.abs(evidence - t)
            vote = (w[:, None] * unit).sum(0)
            if not np.any(vote):
                continue
            target = math.atan2(vote[1], vote[0])
        flips[t] = abs(wrap_angle(yaw[t] - target)) > math.pi / 2
    return flips


def _fixed_frame(poses: np.ndarray, ego_poses, static: bool):
    """Yaws (T,), planar centres (T, 2) in the fixed frame and which frames have one (None
    when there is no fixed frame)."""
    n = len(poses)
    if ego_poses is None:
        if not static:
            return None, None, None
        return poses[:, 3].copy(), poses[:, :2].copy(), np.ones(n, dtype=bool)
    yaw, centre, known = np.zeros(n), np.zeros((n, 2)), np.zeros(n, dtype=bool)
    for t, ego in enumerate(ego_poses):
        if ego is None:
            continue
        ego = np.asarray(ego, dtype=np.float64)
        centre[t] = (ego[:3, :3] @ poses[t, :3] + ego[:3, 3])[:2]
        yaw[t] = poses[t, 3] + pose_yaw(ego)
        known[t] = True
    return yaw, centre, known if known.any() else None


def _window_motion(centre: np.ndarray, evidence: np.ndarray, n: int,
                   cfg: HeadingConfig) -> np.ndarray:
    """(T,) confident motion direction around each frame (NaN where none): the line through
    the ``motion_frames`` frames with points nearest in order, centred on the frame."""
    k = min(int(cfg.motion_frames), len(evidence))
    out = np.full(n, np.nan)
    if k < 3:
        return out
    for t in range(n):
        pos = int(np.searchsorted(evidence, t))
        start = min(max(pos - k // 2, 0), len(evidence) - k)
        idx = evidence[start:start + k]
        direction = motion_direction(centre[idx], cfg.min_travel, cfg.min_consistency)
        if direction is not None:
            out[t] = direction
    return out


class OfflineEstimator:
    """An :class:`~seqshape.model.Estimator` that estimates whole tracks offline
    (:func:`estimate_track`): what ``seqshape evaluate --offline`` and the labeller run.

    ``estimate_track(points, ...)`` has the arguments of :func:`estimate_track` without the
    estimator; ``estimator``, ``config``, ``recurrent`` and ``kind`` are the wrapped ones.
    ``whole_track`` tells :mod:`seqshape.evaluation.runner` to hand it whole tracks.
    """

    whole_track = True

    def __init__(self, estimator, config: OfflineConfig | None = None):
        self.estimator = estimator
        self.config = config or OfflineConfig()

    @property
    def recurrent(self) -> bool:
        return self.estimator.recurrent

    @property
    def kind(self) -> str:
        return self.estimator.kind

    @property
    def model(self):
        return self.estimator.model

    def reset(self, track_id: str | None = None) -> None:
        """Nothing to drop (whole tracks keep no state); present for the estimator protocol."""

    def estimate_track(self, points: Sequence[np.ndarray], **kwargs) -> list[Estimate]:
        """:func:`estimate_track` with this estimator and configuration (``mode`` defaults to
        ``"offline"``)."""
        kwargs.setdefault("config", self.config)
        return estimate_track(self.estimator, points, **kwargs)

    def estimate_tracks(self, tracks: Sequence[Mapping], **kwargs) -> list[list[Estimate]]:
        """:func:`estimate_tracks` with this estimator and configuration (``mode`` defaults
        to ``"offline"``)."""
        kwargs.setdefault("config", self.config)
        return estimate_tracks(self.estimator, tracks, **kwargs)
