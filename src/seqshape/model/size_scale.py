"""The world scale of :attr:`Estimator.size_scale <seqshape.model.Estimator.size_scale>`: inputs
times ``k`` before the networks, estimates over ``k`` after (cars and tracks without a class
hint only); :mod:`seqshape.model.calibration` finds ``k`` for a log."""

from __future__ import annotations

import numpy as np

from seqshape.errors import ConfigError

#: The classes a size scale applies to (with tracks without a class hint): the calibration's
#: statistic is the cars' (:mod:`seqshape.model.calibration`).
CAR_CLASSES = ("car",)
#: The widest scales :attr:`Estimator.size_scale` accepts.
SIZE_SCALE_RANGE = (0.5, 2.0)


def check_size_scale(value, name: str = "size_scale") -> float:
    """``value`` as a float within :data:`SIZE_SCALE_RANGE`, else :class:`ConfigError`."""
    try:
        k = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    lo, hi = SIZE_SCALE_RANGE
    if isinstance(value, bool) or not (np.isfinite(k) and lo <= k <= hi):
        raise ConfigError(f"{name} must be a number in [{lo}, {hi}], got {value!r}")
    return k


def scale_of(k: float, cls) -> float:
    """The scale a track of class ``cls`` gets from a size scale ``k``: ``k`` for a car
    (:data:`CAR_CLASSES`) or a track without a class hint, 1 for the other classes (the
    statistic is the cars'; vans, trucks, buses and trailers keep their learned sizes)."""
    return k if not cls or str(cls) in CAR_CLASSES else 1.0


def scale_ego(ego, k: float):
    """An ego pose (4, 4) of a world scaled by ``k``: the translation times ``k`` (None stays
    None)."""
    if ego is None:
        return None
    out = np.array(ego, dtype=np.float64)
    out[:3, 3] *= k
    return out


def scale_size(size, k: float):
    """A size hint (a length or a box) times ``k`` (None stays None)."""
    return None if size is None else np.asarray(size, dtype=np.float64) * k


def unscale_estimate(est, k: float):
    """A copy of an :class:`~seqshape.model.Estimate` of a world scaled by ``k``, back in
    metres: the complete shape and the pose centre over ``k`` (the yaw and the flags kept)."""
    out = type(est)(est.track_id, (np.asarray(est.complete) / np.float32(k)).astype(np.float32),
                    np.asarray(est.pose, dtype=np.float64).copy(), est.num_points)
    out.pose[:3] /= k
    out.flipped, out.scale, out.valid = est.flipped, est.scale, est.valid
    return out
