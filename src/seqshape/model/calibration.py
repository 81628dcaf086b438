"""Size calibration: a log's vehicles seen at the sizes the networks learned.

Where a vehicle is seen end-on at range nothing in its points says where its far end is: the
networks fill it in from the fleet they were trained on, and centre the vehicle half that
length behind the end they see. A log whose cars are shorter than the training fleet's
(KITTI's 2011 Karlsruhe cars: a median annotated length of about 3.9 m, against 4.6 m for the
synthetic fleet's 2015-2022 models) then gets centres too far from the sensor on every far
frame; its median centre error follows the fleet, not the method (docs/history/model.md,
"Size calibration").

:attr:`Estimator.size_scale <seqshape.model.Estimator.size_scale>` ``k`` scales every input
(points, ego translations, size hints) by ``k`` before the networks see it and every estimate
(complete shape, pose centre) by ``1 / k`` after: the log is seen at the fleet's sizes and the
answers come back in metres. :func:`calibrate_size` finds ``k`` from the log itself, without
labels:

1. each track is estimated online at ``k = 1``;
2. a frame *shows the whole length* when its points span at least :data:`SEEN_SHARE` of the
   estimated length along the estimated heading (both ends seen: a side view), with at least
   :data:`MIN_POINTS` points;
3. a track's length is the median estimated length over such frames, the log's the median
   over its car tracks (the class hint, or a length in :data:`CAR_LENGTHS` without one);
4. ``k = prior / length``, clipped to :data:`SCALE_LIMITS` (never below 1: scaling a log of
   longer cars down was measured to hurt), where ``prior`` is the same statistic on the
   networks' own training distribution (:func:`size_prior`: measured once per shipped weights
   on a held-out synthetic set and kept in ``pretrained/size_prior.json``).

With fewer than ``min_tracks`` such tracks the scale stays 1 and :attr:`SizeCalibration.reason`
says why. The same statistic, not the labels' lengths, sits on both sides of the ratio, so the
networks' own habit of measuring a seen car about 10 cm short cancels out.

Measured on the shared logs (``python benchmarks/bm_realdata.py --size-scale auto``): the
scale is 1.22 on KITTI 0000 and 1.10 on the Argoverse 2 log, 1 on synthetic sets (docs/results.md).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from seqshape.errors import ConfigError, DataError
from seqshape.model.size_scale import CAR_CLASSES

#: A frame shows the whole length when its points span this share of the estimated length.
SEEN_SHARE = 0.85
#: Fewest points of a frame that counts.
MIN_POINTS = 50
#: Lengths (m) of a car-like track when the track has no class hint.
CAR_LENGTHS = (2.5, 5.8)
#: Fewest tracks with a seen length for a calibration.
MIN_TRACKS = 3
#: Bounds of a calibrated scale. Up to 1.25 (a log's cars 20 % shorter than the fleet's;
#: beyond, the statistic is more likely wrong than the fleet that different). Never below 1:
#: on the paper preset, whose cars the networks were trained on and measure 4.79 m, a scale
#: of 0.95 made every figure worse (CD +2.9 %, translation +4.5 %; docs/history/model.md,
#: "Size calibration"); no log with longer cars than the fleet's has shown a gain.
SCALE_LIMITS = (1.0, 1.25)
#: The shipped weights' priors (:func:`size_prior`).
PRIORS_FILE = Path(__file__).resolve().parent.parent / "pretrained" / "size_prior.json"


@dataclass(frozen=True)
class SizeCalibration:
    """What :func:`calibrate_size` found.

    ``scale``: the :attr:`~seqshape.model.Estimator.size_scale` to use (1 when ``reason``
    says why not); ``length``: the log's median car length as the network measures it where it
    sees the whole length (m; None without such tracks); ``prior``: the same statistic on the
    network's training distribution (m); ``tracks`` / ``frames``: tracks and frames that
    showed their whole length; ``reason``: empty when calibrated, else why the scale is 1."""

    scale: float
    length: float | None
    prior: float
    tracks: int
    frames: int
    reason: str = ""

    def to_dict(self) -> dict:
        """A JSON-able dict (the lengths rounded to mm)."""
        d = asdict(self)
        d["scale"] = round(self.scale, 4)
        d["prior"] = round(self.prior, 3)
        d["length"] = None if self.length is None else round(self.length, 3)
        return d


@contextlib.contextmanager
def unit_scale(estimator) -> Iterator[None]:
    """``estimator.size_scale`` set to 1 and its track memory off for the ``with`` block
    (the prior was measured so: each frame on its own points), then restored."""
    before = getattr(estimator, "size_scale", 1.0)
    memory = getattr(estimator, "track_memory", None)
    estimator.size_scale = 1.0
    if memory is not None:
        estimator.track_memory = "none"
    try:
        yield
    finally:
        estimator.size_scale = before
        if memory is not None:
            estimator.track_memory = memory


def frame_lengths(est, points: np.ndarray) -> tuple[float, float]:
    """``(length, span)`` (m) of one estimate: the 1st-99th percentile extent of its complete
    shape along its heading, and the same extent of the frame's points along that axis."""
    c = np.asarray(est.pose[:2], dtype=np.float64)
    axis = np.array([np.cos(est.pose[3]), np.sin(est.pose[3])])
    shape = (np.asarray(est.complete[:, :2], dtype=np.float64) - c) @ axis
    seen = (np.asarray(points[:, :2], dtype=np.float64) - c) @ axis
    lo, hi = np.percentile(shape, [1, 99])
    plo, phi = np.percentile(seen, [1, 99])
    return float(hi - lo), float(phi - plo)


def seen_length(estimates: Sequence, points: Sequence[np.ndarray]) -> tuple[float | None, int]:
    """A track's length where its frames show all of it (median over those frames; None
    without one) and how many frames did, from its online estimates at scale 1."""
    lengths = []
    for est, pts in zip(estimates, points, strict=True):
        if len(pts) < MIN_POINTS or not est.valid:
            continue
        length, span = frame_lengths(est, np.asarray(pts))
        if span >= SEEN_SHARE * length:
            lengths.append(length)
    return (float(np.median(lengths)) if lengths else None), len(lengths)


def size_prior(estimator) -> float:
    """The calibration statistic (m) on ``estimator``'s training distribution: the weights'
    ``metrics["size_prior"]`` when they record one, else the shipped weights' value from
    :data:`PRIORS_FILE`; :class:`ConfigError` for other weights (pass ``prior`` to
    :func:`calibrate_size`: the ``length`` it reports on a synthetic set of the training
    generator)."""
    own = getattr(estimator, "metrics", {}).get("size_prior")
    if own is not None:
        return check_prior(own, "the weights' metrics['size_prior']")
    source = getattr(estimator, "weights_file", None)
    if source is not None:
        from seqshape.model.weights import KINDS, pretrained_path

        for kind in KINDS:
            try:
                shipped = pretrained_path(kind)
            except (ConfigError, DataError):
                continue
            if Path(source).resolve() == shipped.resolve():
                return shipped_prior(kind)
    raise ConfigError("these weights record no size prior: pass one (the length "
                      "`calibrate_size` reports on a synthetic set of their training data) "
                      "or a fixed size scale")


def shipped_prior(kind: str) -> float:
    """The shipped ``kind`` weights' prior from :data:`PRIORS_FILE`."""
    try:
        table = json.loads(PRIORS_FILE.read_text())
        return check_prior(table[kind]["length"], f"{PRIORS_FILE}: {kind}")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(PRIORS_FILE, f"no size prior for the shipped {kind} weights "
                                     f"({type(exc).__name__}: {exc})") from None


def check_prior(value, what: str) -> float:
    """A prior length (m) between 1 and 20, else :class:`ConfigError` naming ``what``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be a length in metres, got {value!r}") from None
    if not (np.isfinite(v) and 1.0 <= v <= 20.0):
        raise ConfigError(f"{what} must be a length between 1 and 20 m, got {value!r}")
    return v


def is_car(cls, length: float) -> bool:
    """Whether a track counts as a car: its class hint is one of :data:`CAR_CLASSES`, or it
    has none and its seen length lies in :data:`CAR_LENGTHS`."""
    if cls:
        return str(cls) in CAR_CLASSES
    return CAR_LENGTHS[0] <= length <= CAR_LENGTHS[1]


def calibrate_size(estimator, tracks: Sequence[Mapping], prior: float | None = None,
                   min_tracks: int = MIN_TRACKS) -> SizeCalibration:
    """The size scale of a log (module doc) from its tracks, without labels.

    Args:
        estimator: a :class:`~seqshape.model.Estimator` (its ``size_scale`` is left as it
            was; the statistic is taken at scale 1).
        tracks: the log's tracks as :func:`~seqshape.model.offline.estimate_tracks` takes them
            (``points`` per frame; ``timestamps``, ``cls``, ``ego_poses``, ``track_id``
            optional): the more car tracks seen from the side, the steadier the figure.
        prior: the statistic on the network's training distribution (None:
            :func:`size_prior`).
        min_tracks: fewest car tracks with a seen length; with fewer the scale is 1.

    Returns:
        a :class:`SizeCalibration` (``scale`` 1 and a ``reason`` when it cannot calibrate).
    """
    from seqshape.model.offline import estimate_tracks  # lazy: torch

    prior = size_prior(estimator) if prior is None else check_prior(prior, "prior")
    if int(min_tracks) < 1:
        raise ConfigError(f"min_tracks must be >= 1, got {min_tracks!r}")
    tracks = list(tracks)
    with unit_scale(estimator):
        estimates = estimate_tracks(estimator, tracks, "online") if tracks else []
    lengths, frames = [], 0
    for track, ests in zip(tracks, estimates, strict=True):
        length, n = seen_length(ests, [np.asarray(p, dtype=np.float64).reshape(-1, 3)
                                       for p in track["points"]])
        if length is not None and is_car(track.get("cls"), length):
            lengths.append(length)
            frames += n
    if len(lengths) < int(min_tracks):
        return SizeCalibration(1.0, float(np.median(lengths)) if lengths else None, prior,
                               len(lengths), frames,
                               f"{len(lengths)} car tracks showed their whole length, "
                               f"{int(min_tracks)} needed")
    length = float(np.median(lengths))
    lo, hi = SCALE_LIMITS
    k = prior / length
    if k >= lo:
        return SizeCalibration(float(min(k, hi)), length, prior, len(lengths), frames)
    longer = k < lo - 1e-3  # not the prior's own figure (it is kept to the millimetre)
    return SizeCalibration(lo, length, prior, len(lengths), frames,
                           f"the log's cars measure {length:.3f} m, longer than the training "
                           f"data's {prior:.3f} m: not scaled down" if longer else "")
