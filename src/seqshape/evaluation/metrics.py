"""Shape and pose metrics (numpy/scipy), one definition used everywhere.

Units are metres and radians; reports convert to cm and degrees. All clouds are ``(N, 3)``
arrays in one common frame (the evaluation uses each frame's sensor frame).

* :func:`chamfer_distance` -- the paper's Eq. 1: mean nearest-neighbour distance from ``a`` to
  ``b`` plus the same from ``b`` to ``a`` (Euclidean, **not** squared).
* :func:`earth_movers_distance` -- mean distance under the optimal one-to-one matching of two
  equal-size clouds, solved exactly with :func:`scipy.optimize.linear_sum_assignment`.
  :func:`subsample_pair` brings two clouds to a common size first, deterministically.
* :func:`translation_error` -- planar ``(x, y)`` distance between poses; :func:`rotation_error`
  -- ``|wrap(yaw_pred - yaw_true)|`` in ``[0, pi]``.
* :func:`cd_floor` -- the Chamfer distance an ideal estimator still pays: CD between a fresh
  sampling of the ground-truth surface and the stored ground-truth sampling;
  :func:`emd_floor` the same for the EMD (:func:`emd_floor_pair`: its two clouds).

>>> import numpy as np
>>> a = np.array([[0.0, 0, 0], [1, 0, 0]])
>>> chamfer_distance(a, a + [0, 0.1, 0])
0.2
>>> round(earth_movers_distance(a, a[::-1] + [0, 0, 0.5]), 6)
0.5
>>> round(float(np.degrees(rotation_error(np.radians(359.0), np.radians(1.0)))), 6)
2.0
"""

from __future__ import annotations

import zlib
from collections.abc import Callable

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from seqshape.geometry import wrap_angle

#: Largest cloud :func:`earth_movers_distance` accepts (the solver is O(n^3) time, O(n^2) memory).
EMD_MAX_POINTS = 8192


def _validate_cloud(x, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) point array, got shape {x.shape}")
    if len(x) == 0:
        raise ValueError(f"{name} is empty: a distance between point clouds needs points")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} holds NaN or infinite coordinates")
    return x


def nearest_distances(a, b) -> np.ndarray:
    """For each point of ``a (N, 3)``, the Euclidean distance to its nearest point of ``b (M, 3)``.

    Returns ``(N,)`` float64 (metres).

    >>> nearest_distances([[0.0, 0, 0], [3, 0, 0]], [[0.0, 1, 0], [3, 0, 2]])
    array([1., 2.])
    """
    a = _validate_cloud(a, "a")
    b = _validate_cloud(b, "b")
    d, _ = cKDTree(b).query(a, k=1)  # (N,)
    return d


def chamfer_distance(a, b) -> float:
    """Symmetric Chamfer distance of the paper's Eq. 1 between ``a (N, 3)`` and ``b (M, 3)``.

    ``mean_i min_j |a_i - b_j| + mean_j min_i |b_j - a_i|`` (Euclidean, not squared), metres.
    Both clouds must be non-empty and in the same frame.
    """
    return float(nearest_distances(a, b).mean() + nearest_distances(b, a).mean())


def earth_movers_distance(a, b) -> float:
    """Exact Earth Mover's distance between equal-size clouds ``a (N, 3)`` and ``b (N, 3)``.

    The mean Euclidean distance between matched points under the optimal one-to-one matching
    (a bijection), metres. Raises ``ValueError`` when the sizes differ: bring the clouds to a
    common size with :func:`subsample_pair`. Cost: O(N^2) memory, about O(N^3) time.
    """
    a = _validate_cloud(a, "a")
    b = _validate_cloud(b, "b")
    if len(a) != len(b):
        raise ValueError(
            f"EMD needs equal-size clouds, got {len(a)} and {len(b)} points; "
            f"subsample both to a common size first (seqshape.evaluation.subsample_pair)")
    if len(a) > EMD_MAX_POINTS:
        raise ValueError(f"EMD on {len(a)} points is too costly (limit {EMD_MAX_POINTS}); "
                         f"subsample first")
    cost = cdist(a, b)  # (N, N)
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].mean())


def stable_seed(*keys) -> int:
    """A seed derived deterministically from strings and integers (stable across processes)."""
    return zlib.crc32("\x1f".join(str(k) for k in keys).encode()) & 0x7FFFFFFF


def subsample(points, n: int, seed: int = 0) -> np.ndarray:
    """``n`` distinct points of ``points (N, 3)`` chosen uniformly at random (``n <= N``).

    Deterministic for a given ``seed``; returns all points (in their order) when ``n == N``.
    """
    points = np.asarray(points)
    if n > len(points):
        raise ValueError(f"cannot subsample {n} points from a cloud of {len(points)}")
    if n == len(points):
        return points
    idx = np.random.default_rng(seed).choice(len(points), size=n, replace=False)
    return points[np.sort(idx)]


def subsample_pair(a, b, n: int | None = None, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Subsample ``a (N, 3)`` and ``b (M, 3)`` to a common size, deterministically.

    The size is ``min(N, M, n)`` (``n=None``: ``min(N, M)``); each cloud gets its own random
    subset without replacement drawn from ``seed``. Returns ``(a', b')`` of equal length.
    """
    k = min(len(a), len(b)) if n is None else min(len(a), len(b), int(n))
    if k <= 0:
        raise ValueError(f"cannot subsample clouds of {len(a)} and {len(b)} points to {n}")
    rng = np.random.default_rng(seed)
    sa, sb = rng.integers(0, 2**31, size=2)
    return subsample(a, k, int(sa)), subsample(b, k, int(sb))


def emd_subsampled(a, b, n: int = 1024, seed: int = 0) -> float:
    """EMD between ``a`` and ``b`` after :func:`subsample_pair` to ``min(len(a), len(b), n)``."""
    return earth_movers_distance(*subsample_pair(a, b, n, seed))


def emd_batch(pairs: list[tuple[np.ndarray, np.ndarray]]) -> list[float]:
    """EMD of each equal-size pair (a process-pool task: picklable, numpy/scipy only)."""
    return [earth_movers_distance(a, b) for a, b in pairs]


def translation_error(pose_pred, pose_gt) -> np.ndarray | float:
    """Planar distance ``|(x, y)_pred - (x, y)_gt|`` in metres; poses ``(..., 4)`` -> ``(...)``.

    The height and the yaw do not count:

    >>> translation_error([3.0, 4.0, 9.0, 1.0], [0.0, 0.0, 0.0, 0.0])
    5.0
    """
    p = np.asarray(pose_pred, dtype=np.float64)
    g = np.asarray(pose_gt, dtype=np.float64)
    d = np.hypot(p[..., 0] - g[..., 0], p[..., 1] - g[..., 1])
    return float(d) if d.ndim == 0 else d


def rotation_error(yaw_pred, yaw_gt) -> np.ndarray | float:
    """Absolute wrapped yaw difference ``|wrap(yaw_pred - yaw_gt)|`` in radians, in ``[0, pi]``.

    Takes yaws (scalars or arrays). For poses pass ``pose[..., 3]``.
    """
    d = np.abs(wrap_angle(np.asarray(yaw_pred, dtype=np.float64)
                          - np.asarray(yaw_gt, dtype=np.float64)))
    return float(d) if d.ndim == 0 else d


def pose_errors(pose_pred, pose_gt) -> tuple[np.ndarray | float, np.ndarray | float]:
    """``(translation_error, rotation_error)`` of poses ``(..., 4)`` (metres, radians)."""
    p = np.asarray(pose_pred, dtype=np.float64)
    g = np.asarray(pose_gt, dtype=np.float64)
    return translation_error(p, g), rotation_error(p[..., 3], g[..., 3])


# --------------------------------------------------------------------------------------------
# CD floor

def cd_floor(complete, n_pred: int, seed: int = 0,
             resample: Callable[[int, int], np.ndarray] | None = None) -> tuple[float, str]:
    """Chamfer distance an ideal ``n_pred``-point estimate still scores against ``complete``.

    ``complete (M, 3)`` is the stored ground-truth sampling of a surface. Returns
    ``(floor_m, method)``:

    * ``method == "resample"`` (when ``resample(n, seed)`` is given, returning a fresh ``(n, 3)``
      sampling of the same surface in the same frame): ``CD(resample(n_pred, seed), complete)``,
      exactly the paper's "two independent samplings of the same surface".
    * ``method == "split"`` (only the stored sampling is known): the points are split at random
      into two disjoint halves ``A, B`` of ``M // 2`` points, ``CD(A, B)`` is measured and
      rescaled to the densities of an ``n_pred``-point estimate against ``M`` points. For
      uniform samples of a surface the mean nearest-neighbour distance into a cloud of ``m``
      points is ``c / sqrt(m)`` (2-D Poisson process), so
      ``floor = CD(A, B) * (1/sqrt(M) + 1/sqrt(n_pred)) / (2 / sqrt(M/2))``.
      tests/test_metrics.py checks this estimate against true resampling on a box surface.
    """
    complete = _validate_cloud(complete, "complete")
    if resample is not None:
        fresh = np.asarray(resample(int(n_pred), int(seed)))
        return chamfer_distance(fresh, complete), "resample"
    m = len(complete)
    if m < 8:
        raise ValueError(f"complete shape has only {m} points: too few to estimate a CD floor")
    perm = np.random.default_rng(seed).permutation(m)
    half = m // 2
    cd_split = chamfer_distance(complete[perm[:half]], complete[perm[half:2 * half]])
    scale = (1.0 / np.sqrt(m) + 1.0 / np.sqrt(n_pred)) / (2.0 / np.sqrt(half))
    return float(cd_split * scale), "split"


def emd_sampling_law(n: int) -> float:
    """How the EMD between two independent uniform ``n``-point samplings of one surface scales
    with ``n``: ``sqrt(log n / n)`` (Ajtai, Komlos and Tusnady, "On optimal matchings", 1984;
    for 2-D samples). Measured on a car-sized box surface, the 128-, 256- and 512-point EMDs
    predicted from the 1024-point one this way were within 9 % (tests/test_metrics.py)."""
    n = max(int(n), 2)
    return float(np.sqrt(np.log(n) / n))


def emd_floor_pair(complete, n_points: int, seed: int = 0,
                   resample: Callable[[int, int], np.ndarray] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, float, str]:
    """The two clouds of :func:`emd_floor` and the factor of their EMD: ``(a, b, factor,
    method)``, the floor being ``factor * earth_movers_distance(a, b)``. ``n_points`` is the
    size of the evaluation's EMD subsets (``min(K, M, emd_points)``; capped at ``M``).

    * ``"resample"``: a fresh ``n``-point sampling of the surface (``resample(n, seed)``)
      against an ``n``-point subset of ``complete``; factor 1.
    * ``"split"``: two disjoint random subsets of ``h = min(n, M // 2)`` stored points; factor
      ``emd_sampling_law(n) / emd_sampling_law(h)`` (1 when the stored sampling has at least
      ``2 n`` points, as the generator's 2048 against 1024: then the halves are exactly two
      independent ``n``-point samplings).
    """
    complete = _validate_cloud(complete, "complete")
    m = len(complete)
    n = min(int(n_points), m)
    rng = np.random.default_rng(seed)
    sa, sb = (int(v) for v in rng.integers(0, 2**31, size=2))
    if resample is not None:
        fresh = np.asarray(resample(n, sa), dtype=np.float64).reshape(-1, 3)
        return fresh[:n], subsample(complete, n, sb), 1.0, "resample"
    h = min(n, m // 2)
    if h < 4:
        raise ValueError(f"complete shape has only {m} points: too few to estimate an EMD floor")
    perm = rng.permutation(m)
    return (complete[perm[:h]], complete[perm[h:2 * h]],
            emd_sampling_law(n) / emd_sampling_law(h), "split")


def emd_floor(complete, n_points: int, seed: int = 0,
              resample: Callable[[int, int], np.ndarray] | None = None) -> tuple[float, str]:
    """EMD an ideal estimate still scores against ``complete`` when both are subsampled to
    ``n_points``: the EMD of two independent samplings of the same surface
    (:func:`emd_floor_pair`; ``(floor_m, method)`` as :func:`cd_floor`). On a car-sized surface
    at 1024 points it is about 17 cm, most of the EMD of a good estimate
    (docs/evaluation.md, "The EMD floor")."""
    a, b, factor, how = emd_floor_pair(complete, n_points, seed, resample)
    return factor * earth_movers_distance(a, b), how


# --------------------------------------------------------------------------------------------
# 180-degree flips per track

def flip_stats(rot_rad, track_ids, flip_deg: float) -> dict[str, float | int | None]:
    """How often and on how many tracks the heading is reversed.

    A frame is flipped when its rotation error (``rot_rad (N,)``, radians, NaN where the pose
    is unknown) exceeds ``flip_deg`` degrees; ``track_ids (N,)`` names each frame's track.
    Frames with an unknown pose are left out, and so are tracks without a known frame.
    Returns ``n_frames`` and ``n_tracks`` (known), ``flipped_frames``, ``flipped_tracks`` (with
    at least one flipped frame), ``flip_pct`` (% of frames), ``tracks_with_flip_pct`` (% of
    tracks) and ``track_flip_median_pct`` (the median over tracks of each track's share of
    flipped frames, %); the percentages are None without a known frame.

    >>> s = flip_stats(np.radians([3.0, 179.0, 5.0, 2.0]), np.array(list("aabb")), 150.0)
    >>> s["flip_pct"], s["tracks_with_flip_pct"], s["track_flip_median_pct"]
    (25.0, 50.0, 25.0)
    """
    rot = np.degrees(np.asarray(rot_rad, dtype=np.float64))
    tracks = np.asarray(track_ids)
    if rot.shape != tracks.shape or rot.ndim != 1:
        raise ValueError(f"rot_rad and track_ids must be equal-length 1-D arrays, got "
                         f"{rot.shape} and {tracks.shape}")
    known = np.isfinite(rot)
    rot, tracks = rot[known], tracks[known]
    flip = rot > flip_deg
    names, which = np.unique(tracks, return_inverse=True)
    per_track = (np.bincount(which, weights=flip, minlength=len(names))
                 / np.maximum(np.bincount(which, minlength=len(names)), 1))  # (n_tracks,)
    some = len(rot) > 0
    return {"n_frames": int(len(rot)), "n_tracks": int(len(names)),
            "flipped_frames": int(flip.sum()), "flipped_tracks": int((per_track > 0).sum()),
            "flip_pct": float(100.0 * flip.mean()) if some else None,
            "tracks_with_flip_pct": float(100.0 * (per_track > 0).mean()) if some else None,
            "track_flip_median_pct": float(100.0 * np.median(per_track)) if some else None}
