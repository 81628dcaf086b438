"""Streaming inference: :class:`Estimator` keeps one hidden state per live track.

>>> from seqshape.testing import box_surface
>>> est = Estimator.from_pretrained("sequential")  # or .from_checkpoint("run/model.pt")
>>> points_a = box_surface(300, 0, pose=(12.0, -3.0, -0.9, 0.3), dtype=np.float32)
>>> points_b = box_surface(200, 1, pose=(20.0, 4.0, -0.9, -1.2), dtype=np.float32)
>>> out = est.step(["car7", "car9"], [points_a, points_b])
>>> out[0].track_id, out[0].complete.shape, out[0].pose.shape  # pose: (x, y, z, yaw)
('car7', (1024, 3), (4,))

Optional per-track inputs of :meth:`Estimator.step` (all default to None = unknown):
``sizes`` (a tracker's / annotator's box (l, w, h) or a length; sets the input scale of a
``scale_norm="length"`` model), ``classes`` (vehicle class: a floor on that length) and
``ego_poses`` ((4, 4) sensor frame of this frame -> a fixed frame: lets the heading
post-processing (:mod:`seqshape.model.heading`) use the track's motion) and ``timestamps``
(s; the time steps of a ``motion_input`` model, else one ``frame_period`` per step).

Until a track has had a frame with points its estimate is the network's prior (a car decoded
around the sensor origin): :attr:`Estimate.valid` is False for those steps. Points are checked
(:func:`check_points`): real numbers only (bool, complex, strings and objects are refused), no
NaN or inf, within :data:`MAX_RANGE` of the sensor; a refused step changes no track's state.

Weight files (checkpoints and exported ``model.pt``) are plain dicts read with
``torch.load(weights_only=True)``::

    {"format": "seqshape-checkpoint", "version": 1, "kind": "sequential" | "baseline",
     "model_config": {...}, "train_config": {...}, "state_dict": {...}, "metrics": {...}}

(training checkpoints add a "training" entry with the optimiser and RNG states).

One loader: :meth:`Estimator.load` takes a shipped name (``"sequential"``, ``"baseline"``, or
``"pretrained"`` with a ``kind``) or the path of a weights file; :func:`resolve_weights` is the
one place that turns such a spec into a file (training's ``--init`` uses it too).

How :meth:`Estimator.step` runs the network is its ``backend`` (:mod:`seqshape.model.engine`):
the loaders default to ``"auto"``, ONNX Runtime when installed (``seqshape[fast]``) and
matching the PyTorch reference here (int8 first, float32 next), which ``backend="torch"``
always runs; ``"auto-float"`` keeps to float32.
"""

from __future__ import annotations

import logging
import warnings
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from seqshape.data.windows import points_lengths, resample_frame
from seqshape.errors import ConfigError, DataError
from seqshape.model.causal import update_estimates
from seqshape.model.config import ModelConfig
from seqshape.model.engine import (
    AUTO_ORDERS,
    BACKENDS,
    MAX_PASS_ROWS,
    PassTooLarge,
    StepInputs,
    car_stream,
    check_stream,
    length_buckets,
    make_engine,
    pack_frames,
    refine_limits,
    select_backend,
)
from seqshape.model.heading import HeadingConfig, HeadingFilter, wrap_angle
from seqshape.model.network import DEFAULT_FRAME_PERIOD, ShapePoseNet
from seqshape.model.placement import apply_corrections, delta, load_refiner
from seqshape.model.size_scale import (
    check_size_scale,
    scale_ego,
    scale_of,
    scale_size,
    unscale_estimate,
)
from seqshape.model.smooth import CausalSmoother
from seqshape.model.track_memory import TrackMemory, check_track_memory
from seqshape.model.weights import (  # noqa: F401 (re-exported: the names' former home)
    KINDS,
    PRETRAINED,
    PRETRAINED_DIR,
    pretrained_path,
    resolve_weights,
)

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "seqshape-checkpoint"
CHECKPOINT_VERSION = 1
#: A class hint's floor on the vehicle length (m) used for the input scale when no size is
#: given: about the short end of each class (the points' running extent raises it). Only the
#: classes longer than ``ModelConfig.scale_ref`` change anything.
CLASS_MIN_LENGTH = {"car": 3.5, "van": 4.5, "truck": 6.5, "bus": 10.0, "trailer": 7.0}
#: Farthest point (m from the sensor) :meth:`Estimator.step` accepts: no LiDAR return of a
#: vehicle lies 1 km away, so such a point is a unit or frame mistake (millimetres, a world or
#: map frame) that would give a meaningless estimate.
MAX_RANGE = 1000.0


def read_model_file(path: str | Path) -> dict[str, Any]:
    """Load and validate a seqshape weights file; anything else raises :class:`DataError`."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "weights file not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt/foreign files
        raise DataError(path, f"not a readable seqshape weights file "
                              f"({type(exc).__name__}: {str(exc).splitlines()[0][:200]})") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise DataError(path, f"not a seqshape checkpoint (expected a dict with format "
                              f"{CHECKPOINT_FORMAT!r})")
    if int(payload.get("version", 0)) > CHECKPOINT_VERSION:
        raise DataError(path, f"checkpoint version {payload.get('version')} is newer than this "
                              f"seqshape understands ({CHECKPOINT_VERSION}); upgrade seqshape")
    if payload.get("kind") not in KINDS:
        raise DataError(path, f"unknown model kind {payload.get('kind')!r}; expected {KINDS}")
    for key in ("model_config", "state_dict"):
        if not isinstance(payload.get(key), dict):
            raise DataError(path, f"checkpoint lacks a valid {key!r} entry")
    return payload


def build_model(payload: dict[str, Any], path: str | Path = "<memory>") -> ShapePoseNet:
    """The :class:`ShapePoseNet` described and weighted by a validated payload."""
    try:
        cfg = ModelConfig.from_dict(payload["model_config"])
        model = ShapePoseNet(cfg, recurrent=payload["kind"] == "sequential")
        model.load_state_dict(payload["state_dict"])
    except (ConfigError, RuntimeError, TypeError, ValueError) as exc:
        raise DataError(path, f"weights do not fit the model they describe ({exc})") from None
    return model


@dataclass
class Estimate:
    """One track's estimate at its latest frame.

    ``complete`` (K, 3) float32 and ``pose`` (4,) float64 = (x, y, z, yaw) are in that frame's
    sensor frame; ``num_points`` is the number of input points of the frame (0 = the estimate
    was carried forward from the state). ``flipped``: the heading post-processing turned the
    network's yaw by pi (the placed ``complete`` is unchanged); ``scale``: the input scale s
    used (1 without ``scale_norm``).

    ``valid``: whether the estimate rests on points of the track. False until the track's first
    frame with points (since its start or its last reset): :class:`Estimator` then returns the
    network's output from an empty state, a car decoded around the sensor origin, not a
    measurement; also False for an estimate whose pose is not finite. It stays True over later
    empty frames (the estimate carried forward from the state).
    """

    track_id: str
    complete: np.ndarray
    pose: np.ndarray
    num_points: int
    flipped: bool = field(default=False, init=False)
    scale: float = field(default=1.0, init=False)
    valid: bool = field(default=True, init=False)

    def __post_init__(self):
        self.valid = bool(np.isfinite(self.pose).all())


#: The values of :attr:`Estimator.smoothing`.
SMOOTHING = ("none", "causal")


@dataclass
class _TrackState:
    hidden: np.ndarray  # (S,) float32
    mean: np.ndarray  # (3,) float32, last known frame mean
    seen: bool
    rng: np.random.Generator
    length: float = 0.0  # points' length estimate: running max (sequential) or last frame's
    heading: HeadingFilter | None = None
    gap: float = 0.0  # time (s) since the last frame with points (motion inputs)
    last_time: float | None = None  # timestamp (s) of the track's last step, when given
    # fast backends: the last estimate (complete, pose, scale, refiner), returned again for an
    # empty frame at the same scale (the state does not change, so neither does the
    # estimate); refiner: the refiner whose corrections it holds (the refined graphs), or None
    last: tuple[np.ndarray, np.ndarray, float, Any] | None = None
    correction: np.ndarray | None = None  # the placement refiner's last correction (4,)
    smoother: CausalSmoother | None = None  # smoothing="causal": the track's past estimates
    memory: TrackMemory | None = None  # track_memory="parked": the track's earlier points


class Estimator:
    """The network plus one recurrent state per live track; numpy in, numpy out.

    Args:
        model: a trained :class:`ShapePoseNet` (put in eval mode).
        threads: intra-op threads of the backend. With ``backend="torch"`` this is
            ``torch.set_num_threads`` (process-wide; None leaves it alone); the fast backends
            use their own setting for their steps only. None: 1 thread (robust when other
            processes keep the cores busy), and for the ONNX backends 2 threads while a core
            is free, on passes of many tracks (at least
            :data:`~seqshape.model.engine.LARGE_PASS_ROWS` encoder rows) and of one track
            (:class:`~seqshape.model.engine.OnnxEngine`); see docs/model.md "Inference
            backends".
        seed: seeds the per-track random subsets of frames with more than N points.
        heading: the heading post-processing (:class:`HeadingConfig`; None = the defaults,
            which act only on steps given ego poses).
        frame_period: seconds between a track's consecutive steps assumed by a
            ``motion_input`` model when :meth:`step` gets no timestamp (10 Hz by default).
        backend: how :meth:`step` runs the network (:data:`~seqshape.model.engine.BACKENDS`):
            ``"torch"`` (the reference: the model's own forward pass), ``"onnx"`` (ONNX
            Runtime, ``pip install 'seqshape[fast]'``), ``"torch-lean"`` (the same step
            function in PyTorch), ``"onnx-int8"`` (ONNX Runtime with the shape decoder and,
            for many tracks a pass, the encoder's last layers in int8, quantised per track;
            1.4-1.5x the 100-track throughput of ``"onnx"``, about its single-track speed,
            estimates moved less than by 1 cm of noise on the points),
            ``"auto"``: the first of :data:`~seqshape.model.engine.AUTO_ORDER`
            (``"onnx-int8"``, ``"onnx"``, ``"torch-lean"``) installed and passing
            :func:`check_backend` here (a warning names any passed over), else ``"torch"``;
            or ``"auto-float"``: the same over the float32 ones
            (:data:`~seqshape.model.engine.FLOAT_ORDER`).
            The loaders default to ``"auto"``, this constructor to the reference.
        refiner: a :class:`~seqshape.model.placement.PlacementRefiner` applied to every
            estimate of a frame with points (the frame's points re-read in the estimated box
            frame; docs/model.md, "Placement refinement"), before the heading step; None: the
            network's estimate as it is. An attribute: set it after loading too. On the fast
            backends its first pass runs inside the engine's graphs (:class:`~seqshape.model.
            engine.RefinedStepGraph`, checked by ``"auto"`` with the network; int8 in
            ``"onnx-int8"``'s batch graph), unless frames are fed with more points than it
            reads (``max_points`` above ``RefinerConfig.points``: it then runs after the
            network, as on ``"torch"``).
        max_points: the most points of a frame fed to the network (a larger frame is cut to a
            seeded random subset of this size); None: the model's ``num_points``, what it was
            trained with. The encoder's work grows with it: 128 for the shipped weights gives
            about 1.7x the updates/s at 100 tracks, for a few per cent of accuracy on synthetic
            data and about 5 cm of median centre error on real cars (docs/model.md, "Fewer
            points per frame").
        smoothing: ``"none"`` (the default) or ``"causal"``: each track's pose is then
            replaced by a robust fit over its past estimates and its shape by the average of
            its past shapes in their canonical frames
            (:class:`~seqshape.model.smooth.CausalSmoother`, after the heading step; frames
            ``<= t`` only, so still online), all tracks of a step in one vectorised pass
            (:func:`~seqshape.model.causal.update_estimates`). It lowers the online errors
            (docs/model.md, "Causal pose smoothing (online)") and costs about 0.1-0.2 ms per
            track and step with 100 live tracks. An attribute: set it after loading too
            (before a track's first step).
        size_scale: the world scale the networks see (default 1; :attr:`size_scale`): every
            input times it, every estimate over it (cars and tracks without a class hint), for
            a log whose cars are shorter (``> 1``) than the training fleet's;
            :func:`~seqshape.model.calibration.calibrate_size` finds it from the log's own
            tracks. An attribute: set it after loading too (before a track's first step).
        track_memory: ``"parked"`` or ``"none"``; None (the default): ``"parked"`` for a
            recurrent model, ``"none"`` for the per-frame baseline (which stays per frame).
            ``"parked"``: a track that looks parked while the ego moves (steps given ego
            poses) is fed half its new frame and half its earlier frames' points, moved by
            the ego poses into the new sensor frame (:mod:`seqshape.model.track_memory`;
            docs/model.md, "Track memory"); without ego poses nothing changes. An attribute:
            set it after loading too (before a track's first step).
    """

    def __init__(self, model: ShapePoseNet, threads: int | None = None, seed: int = 0,
                 metrics: dict | None = None, heading: HeadingConfig | None = None,
                 frame_period: float = DEFAULT_FRAME_PERIOD, backend: str = "torch",
                 refiner: Any = None, max_points: int | None = None, smoothing: str = "none",
                 size_scale: float = 1.0, track_memory: str | None = None):
        self.model = model.eval()
        self.refiner = refiner
        self.smoothing = smoothing
        self.size_scale = size_scale
        self.track_memory = track_memory
        #: The weights file the estimator was loaded from (None: built from a model object);
        #: :func:`~seqshape.model.calibration.size_prior` looks the shipped ones up by it.
        self.weights_file: Path | None = None
        #: The :class:`~seqshape.model.calibration.SizeCalibration` that set
        #: :attr:`size_scale`, when one did (``seqshape evaluate --size-scale auto``).
        self.size_calibration = None
        if max_points is not None and (isinstance(max_points, bool) or not (
                isinstance(max_points, int | np.integer) and max_points >= 1)):
            raise ConfigError(f"max_points must be a whole number >= 1 or None, got "
                              f"{max_points!r}")
        self.max_points = int(model.cfg.num_points if max_points is None else max_points)
        if not (np.isfinite(frame_period) and frame_period > 0):
            raise ConfigError(f"frame_period must be a positive number of seconds, got "
                              f"{frame_period!r}")
        if backend not in BACKENDS:
            raise ConfigError(f"unknown inference backend {backend!r}; choose from {BACKENDS}")
        if threads is not None and int(threads) < 1:
            raise ConfigError(f"threads must be >= 1 or None, got {threads!r}")
        self.frame_period = float(frame_period)
        self.heading = heading or HeadingConfig()
        self.seed = int(seed)
        self.metrics = dict(metrics or {})
        self.threads = None if threads is None else int(threads)
        self._buffer = np.zeros(0, np.float32)  # reused input points of the fast backends
        self._states: dict[str, _TrackState] = {}
        self._engine = None
        self.backend = (select_backend(self.model, self._check, AUTO_ORDERS[backend],
                                       getattr(refiner, "net", None))
                        if backend in AUTO_ORDERS else backend)
        if self.backend == "torch":
            self._engine = None  # "auto" may have tried engines that did not pass
            if self.threads is not None:
                torch.set_num_threads(self.threads)
        elif getattr(self._engine, "name", None) != self.backend:
            self._engine = make_engine(self.model, self.backend, self.threads)

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str = "cpu",
                        threads: int | None = None, seed: int = 0,
                        heading: HeadingConfig | None = None,
                        frame_period: float = DEFAULT_FRAME_PERIOD,
                        backend: str = "auto", refiner: Any = "pretrained",
                        max_points: int | None = None, smoothing: str = "none",
                        size_scale: float = 1.0, track_memory: str | None = None
                        ) -> Estimator:
        """Load a training checkpoint or an exported ``model.pt`` (CPU inference).
        ``refiner``: the placement refiner, a :class:`~seqshape.model.placement.
        PlacementRefiner` or a spec of :func:`~seqshape.model.placement.load_refiner`:
        ``"pretrained"`` (the default: the shipped refiner, as ``seqshape evaluate`` and
        ``label`` use it; on real Argoverse 2 cars it takes the shipped networks' median centre
        error from 38.9 / 43.2 cm to 35.7 / 34.4, docs/model.md), a refiner file, or ``"none"``
        (the network's own placement: the fastest streaming step)."""
        if device != "cpu":
            raise ConfigError(f"Estimator runs on the CPU; got device {device!r}")
        payload = read_model_file(path)
        est = cls(build_model(payload, path), threads, seed, payload.get("metrics"), heading,
                  frame_period, backend, _refiner(refiner), max_points, smoothing, size_scale,
                  track_memory)
        est.weights_file = Path(path)
        return est

    @classmethod
    def from_pretrained(cls, kind: str = "sequential", threads: int | None = None,
                        seed: int = 0, heading: HeadingConfig | None = None,
                        frame_period: float = DEFAULT_FRAME_PERIOD,
                        backend: str = "auto", refiner: Any = "pretrained",
                        max_points: int | None = None, smoothing: str = "none",
                        size_scale: float = 1.0, track_memory: str | None = None
                        ) -> Estimator:
        """The shipped weights ``seqshape/pretrained/<kind>.pt``."""
        return cls.from_checkpoint(pretrained_path(kind), threads=threads, seed=seed,
                                   heading=heading, frame_period=frame_period, backend=backend,
                                   refiner=refiner, max_points=max_points, smoothing=smoothing,
                                   size_scale=size_scale, track_memory=track_memory)

    @classmethod
    def load(cls, spec: str | Path, *, kind: str | None = None, threads: int | None = None,
             device: str = "cpu", seed: int = 0, heading: HeadingConfig | None = None,
             frame_period: float = DEFAULT_FRAME_PERIOD, backend: str = "auto",
             refiner: Any = "pretrained", max_points: int | None = None,
             smoothing: str = "none", size_scale: float = 1.0,
             track_memory: str | None = None) -> Estimator:
        """The estimator named by ``spec``: a shipped name or a weights path.

        ``spec``: ``"sequential"`` / ``"baseline"`` (the shipped weights), ``"pretrained"``
        (the shipped weights of ``kind``, sequential by default), or the path of an exported
        ``model.pt`` or a training checkpoint (read with ``weights_only=True``: a pickle is
        refused). ``kind``, when given, must be the kind of the weights loaded
        (:class:`ConfigError` otherwise). The other arguments are those of the constructor
        (``backend`` defaults to ``"auto"`` here).

        >>> Estimator.load("pretrained", kind="baseline", backend="torch").kind
        'baseline'
        """
        path = resolve_weights(spec, kind or "sequential")
        est = cls.from_checkpoint(path, device, threads, seed, heading, frame_period, backend,
                                  refiner, max_points, smoothing, size_scale, track_memory)
        if kind is not None and est.kind != kind:
            raise ConfigError(f"{spec} holds a {est.kind} model, not a {kind} one")
        return est

    @property
    def smoothing(self) -> str:
        """``"none"`` or ``"causal"`` (the constructor's argument)."""
        return self._smoothing

    @smoothing.setter
    def smoothing(self, value: str) -> None:
        if value not in SMOOTHING:
            raise ConfigError(f"smoothing must be one of {SMOOTHING}, got {value!r}")
        self._smoothing = value

    @property
    def track_memory(self) -> str:
        """``"none"`` or ``"parked"`` (the constructor's argument; None there: ``"parked"``
        for a recurrent model, ``"none"`` for the baseline)."""
        return self._track_memory

    @track_memory.setter
    def track_memory(self, value: str | None) -> None:
        if value is None:
            value = "parked" if self.model.recurrent else "none"
        self._track_memory = check_track_memory(value)

    @property
    def size_scale(self) -> float:
        """The world scale the networks see (default 1): every input (points, ego
        translations, size hints) of a car or a track without a class hint times it before the
        networks, its estimates (shape, centre) over it after (other classes keep scale 1,
        :func:`~seqshape.model.size_scale.scale_of`), so that a log whose cars are smaller
        than the training fleet's
        (``size_scale > 1``) is seen at the fleet's sizes (:mod:`seqshape.model.calibration`;
        :func:`~seqshape.model.calibration.calibrate_size` finds it from a log's own tracks).
        An attribute: set it before a track's first step, and keep it for the track."""
        return self._size_scale

    @size_scale.setter
    def size_scale(self, value: float) -> None:
        self._size_scale = check_size_scale(value)

    @property
    def recurrent(self) -> bool:
        return self.model.recurrent

    @property
    def kind(self) -> str:
        return self.model.kind

    @property
    def config(self) -> ModelConfig:
        return self.model.cfg

    @property
    def track_ids(self) -> list[str]:
        """Tracks with a live state."""
        return list(self._states)

    def reset(self, track_id: str | None = None) -> None:
        """Drop one track's state (unknown ids are ignored), or every track's with None."""
        if track_id is None:
            self._states.clear()
        else:
            self._states.pop(track_id, None)

    def _state(self, track_id: str) -> _TrackState:
        st = self._states.get(track_id)
        if st is None:
            seed = [self.seed, zlib.crc32(track_id.encode("utf-8"))]
            st = _TrackState(np.zeros(self.model.state_size, np.float32),
                             np.zeros(3, np.float32), False, np.random.default_rng(seed))
            self._states[track_id] = st
        return st

    def _frames(self, states: list[_TrackState], point_lists: Sequence[np.ndarray]
                ) -> tuple[list[np.ndarray], list[int]]:
        """Each track's frame (checked by :func:`check_points`) fitted to at most N points (a
        random subset of a larger one), and its point count before the subset."""
        frames, counts = [], []
        n_max = self.max_points
        for st, pts in zip(states, point_lists, strict=True):
            counts.append(len(pts))
            frames.append(pts if len(pts) <= n_max else resample_frame(pts, n_max, st.rng)[0])
        return frames, counts

    def _scales(self, states: list[_TrackState], frames: list[np.ndarray],
                sizes: Sequence | None, classes: Sequence | None) -> np.ndarray | None:
        """(B,) float32 input scales of a ``scale_norm="length"`` model (None otherwise).

        L per track: the size hint's length; else the points' estimate (running maximum over
        the track for the sequential model, this frame's, or the last frame with points', for
        the baseline), raised to the class hint's floor (:data:`CLASS_MIN_LENGTH`).
        """
        cfg = self.model.cfg
        if cfg.scale_norm == "none":
            return None
        lengths, heres = [], points_lengths(frames)
        for i, (st, f) in enumerate(zip(states, frames, strict=True)):
            if len(f):
                here = float(heres[i])
                st.length = max(st.length, here) if self.recurrent else here
            hint = _length_hint(sizes, i)
            lengths.append(max(st.length, _class_floor(classes, i)) if hint is None else hint)
        return cfg.scale_for(np.asarray(lengths, dtype=np.float64)).astype(np.float32)

    def _dts(self, states: list[_TrackState], timestamps: Sequence | None) -> np.ndarray:
        """(B,) float32 time steps of a ``motion_input`` model for this step; advances each
        track's ``last_time``. dt is this step's timestamp minus the track's previous step's
        when both are known, else :attr:`frame_period`."""
        dts = []
        for i, st in enumerate(states):
            ts = _timestamp(timestamps, i)
            known = ts is not None and st.last_time is not None
            dts.append(ts - st.last_time if known else self.frame_period)
            st.last_time = ts
        return np.asarray(dts, dtype=np.float64).astype(np.float32)

    def _run_torch(self, states: list[_TrackState], frames: list[np.ndarray],
                   counts: list[int], scale: np.ndarray | None, dts: np.ndarray | None
                   ) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The reference: the model's own forward pass over every listed track."""
        n = max(1, max(len(f) for f in frames))  # pad only to the largest frame of this batch
        batch = np.zeros((len(frames), 1, n, 3), np.float32)
        for i, f in enumerate(frames):
            if len(f):
                batch[i, 0] = np.resize(f, (n, 3))
        lengths = torch.tensor([len(f) for f in frames], dtype=torch.int64)[:, None]
        extra: dict[str, Any] = {}
        if scale is not None:
            extra["scale"] = torch.from_numpy(scale)[:, None]
        if dts is not None:
            extra.update(counts=torch.tensor(counts, dtype=torch.int64)[:, None],
                         dts=torch.from_numpy(dts)[:, None],
                         gap=torch.tensor([st.gap for st in states], dtype=torch.float32))
        with torch.inference_mode():
            out = self.model(torch.from_numpy(batch), lengths,
                             torch.from_numpy(np.stack([s.hidden for s in states])),
                             torch.from_numpy(np.stack([s.mean for s in states])),
                             torch.tensor([s.seen for s in states]), **extra)
        complete = out["complete"][:, 0].numpy()
        pose = out["pose"][:, 0].double().numpy()
        hidden, mean = out["hidden"].numpy(), out["mean"].numpy()
        for i, st in enumerate(states):
            st.hidden, st.mean = hidden[i].copy(), mean[i].copy()
            st.seen = bool(out["seen"][i, 0])
            st.gap = float(out["gap"][i])
        return [c.copy() for c in complete], [p.copy() for p in pose]

    def _fused_refiner(self):
        """The refiner whose first pass runs inside the engine's graphs (the refined graphs of
        :class:`~seqshape.model.engine.RefinedStepGraph`), or None: no refiner, the reference
        backend, no pass configured, or frames fed with more points than the refiner reads
        (its seeded subset is numpy's; :meth:`_refine` then runs it after the network)."""
        ref = self.refiner
        if ref is None or self._engine is None or not hasattr(self._engine, "set_refiner") \
                or not hasattr(ref, "net") or ref.config.iterations < 1 \
                or self.max_points > ref.config.points:
            return None
        return ref

    def _run_engine(self, states: list[_TrackState], frames: list[np.ndarray],
                    counts: list[int], scale: np.ndarray | None, dts: np.ndarray | None,
                    refiner=None) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """A fast backend: one pass over the tracks whose estimate can change (a frame with
        points, a new track, a new scale); an empty frame at the same scale returns the
        track's last estimate (the network would compute the same from the same state).

        With ``refiner`` (:meth:`_fused_refiner`) the passes run the refined graphs and the
        estimates are the refined ones (:meth:`_finish_refined`). A pass holds at most
        :data:`~seqshape.model.engine.MAX_PASS_ROWS` encoder rows (tracks x padded points);
        one that finds too little memory is split in two, and a step in which one track
        alone does not fit is refused (:class:`ConfigError`). The tracks' states change only
        once every pass has run."""
        b = len(states)
        scale = np.ones(b, np.float32) if scale is None else scale
        limits = None
        if refiner is not None:
            self._engine.set_refiner(refiner.net)
            limits = refine_limits(refiner.config)
        rows = []
        for i, st in enumerate(states):
            if len(frames[i]) or st.last is None or st.last[2] != scale[i] \
                    or st.last[3] is not refiner:
                rows.append(i)
        outs: dict[int, tuple] = {}
        lengths = np.array([len(frames[i]) for i in rows] or [0])
        try:
            if rows:  # a pass per group of similar point counts: less padding to encode
                for group in length_buckets(lengths):
                    for part in _capped(group, int(lengths[group].max()), MAX_PASS_ROWS):
                        self._run_rows([rows[j] for j in part], states, frames, counts,
                                       scale, dts, limits, outs, b)
                if refiner is not None:
                    self._finish_refined(refiner, rows, outs, states, frames)
            done = [outs[i] if i in outs else states[i].last for i in range(b)]
            complete = [d[0].copy() for d in done]
            pose = [d[1].copy() for d in done]
        except MemoryError as exc:  # numpy's, between passes (the runtime's arena full)
            raise ConfigError(f"not enough memory for a step of {b} tracks ({len(rows)} "
                              f"computed, up to {int(lengths.max())} points each): "
                              f"{type(exc).__name__} {exc}; step fewer tracks at a time or "
                              "free memory") from None
        for i in rows:  # every pass ran: the states change
            st, out = states[i], outs[i]
            st.hidden, st.mean, st.seen, st.gap = out[2], out[3], bool(out[4]), float(out[5])
            st.last = (out[0], out[1], float(scale[i]), refiner)
            if refiner is not None and out[7] is not None:
                st.correction = out[7]
        if dts is not None:  # a carried state: the time since a detection grows
            computed = set(rows)
            for i, st in enumerate(states):
                if i not in computed:
                    st.gap = float(np.float32(st.gap) + dts[i])
        return complete, pose

    def _run_rows(self, rows: list[int], states: list[_TrackState], frames: list[np.ndarray],
                  counts: list[int], scale: np.ndarray, dts: np.ndarray | None,
                  limits: np.ndarray | None, outs: dict[int, tuple], step_size: int) -> None:
        """One engine pass over ``rows``; each row's outputs (the engine's, pose as float64)
        into ``outs``. Split in halves when the pass runs out of memory."""
        sub = [states[i] for i in rows]
        points, self._buffer = pack_frames([frames[i] for i in rows], self._buffer)
        if len(rows) == 1:  # one track (a single-track stream's every step): views, no copies
            i = rows[0]
            hidden, mean, picked = sub[0].hidden[None], sub[0].mean[None], slice(i, i + 1)
        else:
            hidden, mean = np.stack([st.hidden for st in sub]), np.stack([st.mean for st in sub])
            picked = rows
        inputs = StepInputs(
            points, np.array([len(frames[i]) for i in rows], np.int64), hidden, mean,
            np.array([st.seen for st in sub], bool), scale[picked],
            np.zeros(len(rows), np.float32) if dts is None else dts[picked],
            np.array([counts[i] for i in rows], np.int64),
            np.array([st.gap for st in sub], np.float32), limits)
        try:
            out = self._engine.run(inputs)
        except PassTooLarge as exc:
            if len(rows) == 1:
                n = max(len(frames[i]) for i in rows)
                raise ConfigError(
                    f"not enough memory for a step of {step_size} tracks: one track's pass "
                    f"({n} points) failed to allocate ({exc.detail}); free memory or feed "
                    f"fewer points (max_points)") from None
            log.info("%s; splitting it in two", exc)
            half = len(rows) // 2
            for part in (rows[:half], rows[half:]):
                self._run_rows(part, states, frames, counts, scale, dts, limits, outs,
                               step_size)
            return
        out = list(out)
        out[1] = out[1].astype(np.float64)
        if len(out) > 6:
            out[6:] = [a.astype(np.float64) for a in out[6:]]
        for j, i in enumerate(rows):
            outs[i] = tuple(a[j] for a in out)

    def _finish_refined(self, refiner, rows: list[int], outs: dict[int, tuple],
                        states: list[_TrackState], frames: list[np.ndarray]) -> None:
        """The refined graphs' estimates completed as :meth:`_refine` would: the further
        passes of long vehicles (``RefinerConfig.iterations``, on the engine's refiner
        session), the last correction of its track carried to a recomputed frame without
        points (a new scale); ``outs`` in place, each row's entry 7 the correction its track
        keeps (None: the track keeps its own). No state changes here."""
        cfg = refiner.config
        n = np.array([len(frames[i]) for i in rows])
        corr = np.stack([outs[i][7] for i in rows])
        ext = np.stack([outs[i][8] for i in rows])
        has = n >= max(cfg.min_points, 1)
        again = has & (ext[:, 0] >= cfg.repeat_min_length) & (n >= cfg.repeat_min_points) \
            & (np.hypot(corr[:, 0], corr[:, 1]) >= cfg.repeat_shift)
        if cfg.iterations > 1 and again.any():
            idx = np.flatnonzero(again)
            first = np.stack([outs[rows[j]][1] for j in idx])
            new, _ = refiner.refine([frames[rows[j]] for j in idx], first, ext[idx],
                                    [rows[j] for j in idx], self._refiner_run(), first=1)
            moved, _ = apply_corrections(np.stack([outs[rows[j]][0] for j in idx]), first,
                                         delta(first, new))
            for k, j in enumerate(idx):
                i = rows[j]
                out = list(outs[i])
                out[0], out[1] = moved[k], new[k]
                corr[j, :4] = delta(out[6], new[k])[0]
                outs[i] = tuple(out)
        for j, i in enumerate(rows):
            st = states[i]
            out = list(outs[i])
            if has[j]:
                out[7] = corr[j]  # the track's correction from now on (kept at the commit)
            else:
                out[7] = None
                if not len(frames[i]) and st.correction is not None:
                    c, p = apply_corrections(out[0][None], out[1][None], st.correction[None])
                    out[0], out[1] = c[0], p[0]
            outs[i] = tuple(out)

    def _refine(self, states: list[_TrackState], frames: list[np.ndarray],
                complete: list[np.ndarray], pose: list[np.ndarray]
                ) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The placement refiner over one step's tracks (one batched pass); an empty frame's
        carried estimate gets its track's last correction."""
        c, p = np.stack(complete), np.stack(pose)
        corr = self.refiner.corrections_of(frames, c, p, run=self._refiner_run())
        for i, st in enumerate(states):
            if np.isfinite(corr[i, 0]):
                st.correction = corr[i]
            elif not len(frames[i]) and st.correction is not None:
                corr[i] = st.correction
        new_c, new_p = apply_corrections(c, p, corr)
        return list(new_c), list(new_p)

    def _refiner_run(self):
        """The refiner network's forward on this estimator's engine (its threads; None:
        numpy, for the reference backend)."""
        engine = self._engine
        return None if engine is None or not hasattr(engine, "refiner") \
            else engine.refiner(self.refiner.net)

    def _check(self, name: str) -> bool:
        """``backend="auto"``'s test of backend ``name`` (its engine is kept when it passes);
        raises :class:`~seqshape.errors.MissingDependencyError` when its runtime is missing."""
        fast = Estimator(self.model, self.threads, backend=name, refiner=self.refiner)
        self._engine = fast._engine
        return check_backend(fast)

    def _fix_headings(self, result: list[Estimate], states: list[_TrackState],
                      ego_poses: Sequence | None, frames: list[np.ndarray],
                      classes: Sequence | None, timestamps: Sequence | None = None) -> None:
        """The heading post-processing (:mod:`seqshape.model.heading`), in place."""
        for i, (est, st) in enumerate(zip(result, states, strict=True)):
            ego = _ego_pose(ego_poses, i)
            if ego is None and not self.heading.active_without_poses:
                continue
            if st.heading is None:
                st.heading = HeadingFilter(self.heading)
            cls = None if classes is None or not classes[i] else str(classes[i])
            if st.heading.update(est.pose, ego, est.num_points > 0, frames[i], cls,
                                 _timestamp(timestamps, i)):
                est.pose[3] = wrap_angle(est.pose[3] + np.pi)
                est.flipped = True

    def step(self, track_ids: Sequence[str], point_lists: Sequence[np.ndarray],
             sizes: Sequence | None = None, classes: Sequence[str | None] | None = None,
             ego_poses: Sequence[np.ndarray | None] | None = None,
             timestamps: Sequence[float | None] | None = None) -> list[Estimate]:
        """Advance each listed track by one frame, all in one forward pass.

        ``point_lists[i]`` is track ``track_ids[i]``'s (N_i, 3) points in its current sensor
        frame as float or integer numbers (N_i may be 0: an empty array or list); NaN or inf,
        a point farther than :data:`MAX_RANGE` from the sensor, or a bool, complex, string or
        object array raise :class:`ConfigError` naming the track (:func:`check_points`), and
        a refused step changes no state. New ids start a fresh state.
        Optional hints, each a sequence parallel to ``track_ids`` whose entries may be None:
        ``sizes[i]`` a box (l, w, h) or a length (m) for the input scale (only a
        ``scale_norm="length"`` model uses it; it overrides the points' estimate);
        ``classes[i]`` a vehicle class (car, van, truck, bus, trailer: a floor on the points'
        length estimate, :data:`CLASS_MIN_LENGTH`; likewise only used by such a model);
        ``ego_poses[i]`` (4, 4) this frame's sensor frame -> a fixed frame (the same for all
        the track's steps), for the heading post-processing; ``timestamps[i]`` this frame's
        time (s, any origin, the same clock for all the track's steps) for the motion inputs
        of a ``motion_input`` model (a missing or NaN one, or the track's first, counts as
        :attr:`frame_period` after the previous step). Returns one :class:`Estimate` per
        track, in order; :attr:`Estimate.valid` is False while a track has had no frame with
        points yet (the estimate is then the network's prior around the sensor origin).
        """
        track_ids = [str(t) for t in track_ids]
        if len(track_ids) != len(point_lists):
            raise ConfigError(f"{len(track_ids)} track ids but {len(point_lists)} point lists")
        for name, hints in (("sizes", sizes), ("classes", classes), ("ego_poses", ego_poses),
                            ("timestamps", timestamps)):
            if hints is not None and len(hints) != len(track_ids):
                raise ConfigError(f"{len(track_ids)} track ids but {len(hints)} {name}")
        if len(set(track_ids)) != len(track_ids):
            raise ConfigError("a track id appears twice in one step")
        if not track_ids:
            return []
        points = [check_points(p, f"point_lists[{i}] (track {t!r})")
                  for i, (t, p) in enumerate(zip(track_ids, point_lists, strict=True))]
        _check_hints(len(track_ids), sizes, classes, ego_poses, timestamps)
        if self._size_scale != 1.0:  # cars seen at the fleet's sizes, the answers in metres
            ks = [scale_of(self._size_scale, None if classes is None else classes[i])
                  for i in range(len(track_ids))]
            points = [p * np.float32(k) for p, k in zip(points, ks, strict=True)]
            sizes = None if sizes is None else [scale_size(s, k) for s, k in
                                                zip(sizes, ks, strict=True)]
            ego_poses = None if ego_poses is None else [scale_ego(e, k) for e, k in
                                                        zip(ego_poses, ks, strict=True)]
            return [unscale_estimate(e, k) for e, k in zip(self._step(
                track_ids, points, sizes, classes, ego_poses, timestamps), ks, strict=True)]
        return self._step(track_ids, points, sizes, classes, ego_poses, timestamps)

    def _step(self, track_ids: list[str], points: list[np.ndarray], sizes, classes, ego_poses,
              timestamps) -> list[Estimate]:
        """:meth:`step` after its checks, in the networks' world (:attr:`size_scale`)."""
        fresh = [t for t in track_ids if t not in self._states]
        states = [self._state(t) for t in track_ids]
        kept = [(st.length, st.last_time) for st in states]
        remember = self._track_memory != "none" and ego_poses is not None
        given = points
        if remember:
            egos = [_ego_pose(ego_poses, i) for i in range(len(points))]
            drawn = [None if st.memory is None else st.memory.rng.bit_generator.state
                     for st in states]  # restored if the step is refused
            points = self._with_memory(states, points, egos)
        frames, counts = self._frames(states, points)
        scale = self._scales(states, frames, sizes, classes)
        dts = self._dts(states, timestamps) if self.model.motion else None
        fused = self._fused_refiner()
        if self._engine is None:
            complete, pose = self._run_torch(states, frames, counts, scale, dts)
        else:
            try:
                complete, pose = self._run_engine(states, frames, counts, scale, dts, fused)
            except ConfigError:  # a step too large for the memory left: refused, no change
                for st, (length, last_time) in zip(states, kept, strict=True):
                    st.length, st.last_time = length, last_time
                if remember:
                    for st, state in zip(states, drawn, strict=True):
                        if state is not None:
                            st.memory.rng.bit_generator.state = state
                for t in fresh:
                    self._states.pop(t, None)
                raise
        if self.refiner is not None and fused is None:
            complete, pose = self._refine(states, frames, complete, pose)
        result = []
        for i, tid in enumerate(track_ids):
            result.append(Estimate(tid, complete[i], pose[i], len(frames[i])))
            result[-1].valid = states[i].seen and result[-1].valid
            if scale is not None:
                result[-1].scale = float(scale[i])
        if ego_poses is not None or self.heading.active_without_poses:
            self._fix_headings(result, states, ego_poses, frames, classes, timestamps)
        if self.smoothing == "causal":
            self._smooth(result, states, ego_poses, timestamps)
        if remember:
            self._remember(track_ids, states, given, result, egos)
        return result

    def _with_memory(self, states: list[_TrackState], points: list[np.ndarray],
                     egos: list[np.ndarray | None]) -> list[np.ndarray]:
        """Each track's frame, with its memory mixed in where it applies
        (:meth:`~seqshape.model.track_memory.TrackMemory.frame_input`); ``egos[i]`` track
        i's ego pose or None."""
        out = []
        for st, pts, ego in zip(states, points, egos, strict=True):
            mixed = None if ego is None or st.memory is None else \
                st.memory.frame_input(pts, ego, self.max_points)
            out.append(pts if mixed is None else mixed)
        return out

    def _remember(self, track_ids: list[str], states: list[_TrackState],
                  given: list[np.ndarray], result: list[Estimate],
                  egos: list[np.ndarray | None]) -> None:
        """Store each track's frame as given and its estimate's position in its memory."""
        for i, (st, est, ego) in enumerate(zip(states, result, egos, strict=True)):
            if ego is None:
                continue
            if st.memory is None:
                st.memory = TrackMemory(np.random.default_rng(
                    [self.seed, zlib.crc32(track_ids[i].encode("utf-8")), 1]))
            st.memory.record(given[i], ego, est.pose if est.valid else None)

    def _smooth(self, result: list[Estimate], states: list[_TrackState],
                ego_poses: Sequence | None, timestamps: Sequence | None) -> None:
        """``smoothing="causal"``: each estimate replaced by its track's causal fit (in place;
        the complete shape moves rigidly with the pose), all tracks in one vectorised pass
        (:func:`~seqshape.model.causal.update_estimates`)."""
        for st in states:
            if st.smoother is None:
                st.smoother = CausalSmoother()
        update_estimates([st.smoother for st in states], result,
                         [_ego_pose(ego_poses, i) for i in range(len(result))],
                         [_timestamp(timestamps, i) for i in range(len(result))],
                         1.0 / self.frame_period)


def _refiner(spec: Any):
    """A refiner object as it is, or the refiner a spec names (:func:`load_refiner`)."""
    if spec is None or isinstance(spec, (str, Path)):
        return load_refiner(spec)
    return spec


def check_backend(fast: Estimator) -> bool:
    """Whether ``fast`` (an estimator on a fast backend) reproduces the reference
    ``"torch"`` for its model on this machine: a short synthetic stream (:func:`~seqshape.model.engine.check_stream`)
    within the engine's ``tolerance`` (:data:`~seqshape.model.engine.TOLERANCE`, looser for
    ``"onnx-int8"``'s shape points), estimate by estimate; and for an engine with a ``noise``
    (``"onnx-int8"``), over :func:`~seqshape.model.engine.car_stream` its estimates'
    deviations from the reference's no larger than the reference's own under that much noise
    on the points (:func:`noise_quantiles`) instead."""
    name = fast.backend
    noise = getattr(fast._engine, "noise", None)
    if noise is not None:
        mine, allowed = noise_quantiles(fast, car_stream(fast.model.cfg.num_points), noise)
        if not np.all(mine <= allowed):
            log.info("backend %s differs from the reference on this machine by more than "
                     "%g m of noise on the points would: %s against %s", name, noise,
                     mine.round(4).tolist(), allowed.round(4).tolist())
            return False
        return True
    ref = Estimator(fast.model, backend="torch", refiner=fast.refiner)
    tol_shape, tol_centre, tol_yaw = fast._engine.tolerance
    for step in check_stream(fast.model.cfg.num_points):
        for a, b in zip(fast.step(**step), ref.step(**step), strict=True):
            if not (np.allclose(a.complete, b.complete, rtol=0, atol=tol_shape)
                    and np.allclose(a.pose[:3], b.pose[:3], rtol=0, atol=tol_centre)
                    and abs(wrap_angle(a.pose[3] - b.pose[3])) <= tol_yaw):
                log.info("backend %s differs from the reference on this machine", name)
                return False
    return True


def deviations(estimates: Sequence[Estimate], reference: Sequence[Estimate]) -> np.ndarray:
    """``(E, 3)``: per pair of estimates of the same tracks, the largest deviation of a shape
    point (m, any axis), of the centre (m, any axis) and of the yaw (rad, wrapped)."""
    return np.array([(np.abs(a.complete - b.complete).max(), np.abs(a.pose[:3] - b.pose[:3]).max(),
                      abs(wrap_angle(a.pose[3] - b.pose[3])))
                     for a, b in zip(estimates, reference, strict=True)]).reshape(-1, 3)


def noise_quantiles(fast: Estimator, steps: Sequence[dict], noise: float, seed: int = 0,
                    quantiles: Sequence[float] = (0.5, 0.9)) -> tuple[np.ndarray, np.ndarray]:
    """``(mine, allowed)``, each ``(len(quantiles), 3)``: quantiles of the :func:`deviations`
    of ``fast``'s estimates over ``steps`` (:meth:`Estimator.step` keyword arguments, from a
    reset state) from the reference's (``"torch"`` on the same model), and of the reference's
    own estimates of the same steps with Gaussian noise of ``noise`` m (seeded) on every
    point."""
    ref, noisy = (Estimator(fast.model, backend="torch", refiner=fast.refiner)
                  for _ in range(2))
    fast.reset()
    rng = np.random.default_rng(seed)
    mine, allowed = [], []
    for step in steps:
        truth = ref.step(**step)
        mine.append(deviations(fast.step(**step), truth))
        jitter = [np.asarray(p, np.float32) + rng.normal(0.0, noise, np.shape(p)).astype(np.float32)
                  for p in step["point_lists"]]
        allowed.append(deviations(noisy.step(**{**step, "point_lists": jitter}), truth))
    q = np.asarray(quantiles)
    return (np.quantile(np.concatenate(mine), q, axis=0),
            np.quantile(np.concatenate(allowed), q, axis=0))


def check_points(points, name: str = "points") -> np.ndarray:
    """``points`` as the (N, 3) float32 array :meth:`Estimator.step` takes, or a
    :class:`ConfigError` naming ``name`` (e.g. the track).

    Accepts float and integer arrays (or nested lists) of shape (N, 3), and any empty input
    (``[]``, shape (0,) or (0, 3)) as zero points. Refuses bool, complex, string and object
    data (numpy would turn them into numbers silently) and points farther than
    :data:`MAX_RANGE` from the sensor (a unit or frame mistake). Rows with NaN or inf (a
    sensor's no-return points) are dropped with a warning, as the sweep readers drop them.

    >>> check_points([[1, 2, 3]]).dtype, check_points([]).shape
    (dtype('float32'), (0, 3))
    """
    try:
        raw = np.asarray(points)
    except (ValueError, TypeError) as exc:  # ragged nested lists
        raise ConfigError(f"{name}: not an (N, 3) array of numbers ({exc})") from None
    if raw.dtype.kind not in "fiu":
        raise ConfigError(f"{name}: points must be float or integer numbers, got dtype "
                          f"{raw.dtype} ({_KIND_NAMES.get(raw.dtype.kind, 'not numbers')})")
    if raw.size == 0 and (raw.ndim == 1 or raw.ndim == 2 and raw.shape[1] == 3):
        return np.zeros((0, 3), np.float32)
    if raw.ndim != 2 or raw.shape[1] != 3:
        raise ConfigError(f"{name}: points must have shape (N, 3), got {raw.shape}")
    with np.errstate(over="ignore", invalid="ignore"):  # huge values: refused just below
        pts = np.asarray(raw, dtype=np.float32)
        far = np.einsum("ij,ij->i", pts, pts)
    if far.max() <= MAX_RANGE ** 2:  # False for NaN and inf too
        return pts
    bad = ~np.isfinite(raw).all(axis=1)
    if bad.any():  # as the sweep readers do: a sensor's no-return rows, dropped with a word
        warnings.warn(f"{name}: dropped {int(bad.sum())} of {len(raw)} points that are not "
                      f"finite (NaN or inf; first at row {int(np.argmax(bad))})", stacklevel=3)
        raw, pts, far = raw[~bad], pts[~bad], far[~bad]
        if not len(pts) or far.max() <= MAX_RANGE ** 2:
            return pts
    j = int(np.argmax(far))
    raise ConfigError(f"{name}: point {j} at {tuple(float(v) for v in raw[j])} is more than "
                      f"{MAX_RANGE:g} m from the sensor; points must be in the sensor frame, "
                      f"in metres")


_KIND_NAMES = {"b": "booleans", "c": "complex numbers", "U": "strings", "S": "bytes",
               "O": "Python objects", "V": "raw records", "M": "dates", "m": "durations"}


def _check_hints(n: int, sizes, classes, ego_poses, timestamps) -> None:
    """Every per-track hint of a step checked before any state changes (the errors of
    :func:`_length_hint`, :func:`_class_floor`, :func:`_ego_pose`, :func:`_timestamp`)."""
    for i in range(n):
        _length_hint(sizes, i)
        _class_floor(classes, i)
        _ego_pose(ego_poses, i)
        _timestamp(timestamps, i)


def _length_hint(sizes: Sequence | None, i: int) -> float | None:
    """Track i's length hint (m) from ``sizes`` (a box (l, w, h) or a length), or None."""
    if sizes is None or sizes[i] is None:
        return None
    size = np.asarray(sizes[i], dtype=np.float64).reshape(-1)
    if size.size == 0 or not np.isfinite(size[0]) or size[0] <= 0:
        raise ConfigError(f"sizes[{i}] must be a positive length or a box (l, w, h), got "
                          f"{sizes[i]!r}")
    return float(size[0])


def _class_floor(classes: Sequence | None, i: int) -> float:
    if classes is None or not classes[i]:
        return 0.0
    try:
        return CLASS_MIN_LENGTH[str(classes[i])]
    except KeyError:
        raise ConfigError(f"classes[{i}]: unknown vehicle class {classes[i]!r}; expected one "
                          f"of {sorted(CLASS_MIN_LENGTH)} or None") from None


def _timestamp(timestamps: Sequence | None, i: int) -> float | None:
    if timestamps is None or timestamps[i] is None:
        return None
    try:
        ts = float(timestamps[i])
    except (TypeError, ValueError):
        raise ConfigError(f"timestamps[{i}] must be a number of seconds or None, got "
                          f"{timestamps[i]!r}") from None
    return ts if np.isfinite(ts) else None  # NaN: unknown, as in the training windows


def _ego_pose(ego_poses: Sequence | None, i: int) -> np.ndarray | None:
    if ego_poses is None or ego_poses[i] is None:
        return None
    pose = np.asarray(ego_poses[i], dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ConfigError(f"ego_poses[{i}] must be a finite (4, 4) matrix, got shape "
                          f"{pose.shape}")
    return pose


def _capped(group: np.ndarray, points: int, max_rows: int) -> list[np.ndarray]:
    """``group`` (indices of one pass of ``points`` padded points) cut into passes of at most
    ``max_rows`` encoder rows (tracks x points; at least one track a pass)."""
    per = max(1, max_rows // max(points, 1))
    return [group[k:k + per] for k in range(0, len(group), per)]
