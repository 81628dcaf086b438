"""Ground planes of LiDAR sweeps, fitted by RANSAC (used by track extraction, the labeller
and the segmentation; one implementation).

:func:`ground_plane`: planes are fitted by RANSAC (``iterations`` random triples) to the low
points (z below the ``low_quantile`` of the cloud plus 0.5 m; at most ``max_candidates`` of
them, drawn at random, score the hypotheses); only nearly horizontal planes (normal within
``max_tilt_deg`` of +z) count; the plane with most inliers is refitted by least squares to
them. When no plane is found (too few points) the fallback is the flat plane
``z = -sensor_height``. A plane is ``(n, d)`` with ``n . x + d = 0``, unit ``n``, ``n_z > 0``,
so ``n . x + d`` is the height of ``x`` above it.
"""

from __future__ import annotations

import logging
import math

import numpy as np

log = logging.getLogger(__name__)

_BLOCK = 512  # rows of the RANSAC scoring per block (:func:`_inlier_counts`)


def _minus(p: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``p - v`` for ``p (M, 3)`` and ``v (3,)``: the same differences, column by column (the
    broadcast runs one loop of three per row, three times slower), into a new C-ordered array
    like the broadcast's, so a product or decomposition of it gives the same bits."""
    out = np.empty(p.shape, dtype=np.result_type(p, v))
    for j in range(3):
        np.subtract(p[:, j], v[j], out=out[:, j])
    return out


def _fit_plane(p: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane ``n . x + d = 0`` (unit n, n_z > 0) through ``p (M, 3)``."""
    c = p.mean(0)
    n = np.linalg.svd(_minus(p, c), full_matrices=False)[2][-1]
    n = n if n[2] >= 0 else -n
    return n, float(-n @ c)


def _triples(rng, m: int, iterations: int) -> np.ndarray:
    """``(iterations, 3)`` indices into ``m`` points: exactly the draws of ``iterations`` calls
    of ``rng.choice(m, 3, replace=False)`` (what this module did), made by one call.

    For three of ``m`` without replacement numpy's ``Generator.choice`` runs Floyd's algorithm
    (bounded integers in ``[0, m - 3]``, ``[0, m - 2]``, ``[0, m - 1]``; a repeat is replaced
    by the bound) and then shuffles the three (bounded integers in ``[0, 2]``, ``[0, 1]``), each
    draw one bounded integer of the same generator; ``rng.integers`` with those five bounds per
    triple draws the same integers in the same order. tests/test_ground.py checks the equality
    against the calls themselves.
    """
    bounds = np.tile(np.array([m - 3, m - 2, m - 1, 2, 1], dtype=np.int64), iterations)
    d = rng.integers(0, bounds, endpoint=True).reshape(iterations, 5)
    first = d[:, 0]
    second = np.where(d[:, 1] == first, m - 2, d[:, 1])
    third = np.where((d[:, 2] == first) | (d[:, 2] == second), m - 1, d[:, 2])
    idx = np.stack([first, second, third], axis=1)
    r = np.arange(iterations)
    for pos, col in ((2, 3), (1, 4)):  # the shuffle: swap idx[pos] with idx[draw]
        j = d[:, col]
        picked = idx[r, j]
        idx[r, j] = idx[:, pos]
        idx[:, pos] = picked
    return idx


def _inlier_counts(cand: np.ndarray, n: np.ndarray, offs: np.ndarray, threshold: float,
                   block: int = _BLOCK) -> np.ndarray:
    """``(I,)`` how many points ``cand (M, 3)`` lie within ``threshold`` of each plane
    ``n[i] . x = offs[i]``: ``|cand @ n.T - offs| < threshold`` counted per column, ``block``
    rows at a time: the (block, I) distances stay in the cache, 2.8x faster than one product
    of all rows on the kitti-like logs' candidate sets. Each distance is the same three-term
    dot product; a matrix-product kernel may round it differently by one unit in the last place
    for another row count, so only a point within ~1e-16 m of ``threshold`` could count
    differently (the counts of all 582 RANSAC runs of two kitti-like logs, and so their crops
    and planes, are unchanged; tests/test_ground.py compares with one product).

    Per block the same product is taken (the row count is part of the result, above) and
    ``|d - offs| < threshold`` tested; the counts are exact integer sums of the 0/1 masks in
    any order. With more than one block, the masks are added up as bytes, element by element,
    over up to 255 blocks (a byte holds 255) before one sum by column: the sum by column of
    each block's mask (``np.add.reduce`` over axis 0, one short loop per row) was the slowest
    step of a block.
    """
    nt = np.ascontiguousarray(n.T)
    dist = np.empty((min(block, len(cand)), len(offs)))
    inl = np.empty(dist.shape, dtype=bool)

    def mask(start: int) -> np.ndarray:
        """The (rows, I) inlier mask of the block of rows from ``start`` (in ``inl``)."""
        rows = cand[start:start + block]
        d, m = dist[:len(rows)], inl[:len(rows)]
        np.matmul(rows, nt, out=d)
        d -= offs
        np.abs(d, out=d)
        return np.less(d, threshold, out=m)

    if len(cand) <= block:  # one block (or none): its mask summed by column
        return _column_counts(mask(0).view(np.uint8))
    counts = np.zeros(len(offs), dtype=np.int64)
    tally = np.zeros(dist.shape, dtype=np.uint8)  # inliers per entry over <= 255 blocks
    for i, start in enumerate(range(0, len(cand), block)):
        m = mask(start).view(np.uint8)
        np.add(tally[:len(m)], m, out=tally[:len(m)])
        if i % 255 == 254 or start + block >= len(cand):
            counts += np.add.reduce(tally, axis=0, dtype=np.int64)
            tally[:] = 0
    return counts


def _column_counts(mask: np.ndarray) -> np.ndarray:
    """``(I,)`` int64 column sums of a ``(k, I)`` array of 0/1 bytes: ``np.einsum`` sums bytes
    in bytes, exact for up to 255 rows, so 255 rows at a time (twice as fast as
    ``np.add.reduce(mask, axis=0, dtype=np.int64)`` on a few hundred rows, the same counts)."""
    counts = np.zeros(mask.shape[1], dtype=np.int64)
    for start in range(0, len(mask), 255):
        counts += np.einsum("ij->j", mask[start:start + 255])
    return counts


def _quantile(z: np.ndarray, q) -> np.floating:
    """``np.quantile(z, q)`` of a non-empty 1-D float64 ``z``, the same float, faster.

    ``np.quantile`` (its default, linear method) partitions ``z`` at four places (the first,
    the last and the two order statistics around ``(len(z) - 1) * q``); a partition at one
    place and a minimum give the same two order statistics four to six times faster on a
    sweep. They are then interpolated by numpy's own steps (``numpy.lib._function_base_impl``
    ``_quantile`` and ``_lerp`` for a Python float ``q``): the same operations on the same
    values, so the same float (but for the sign of a zero: -0.0 and 0.0 tie, and either may
    come first out of a partition; ground_plane adds 0.5). With a NaN in ``z`` the result is
    NaN, as numpy's. Any ``q`` but a Python float in [0, 1] goes to ``np.quantile`` itself;
    tests/test_ground.py compares the two on many arrays (ties, signed zeros, infinities, NaNs,
    one or two values).
    """
    n = len(z)
    if type(q) is not float or not 0.0 <= q <= 1.0 or n == 0:
        return np.quantile(z, q)
    v = (n - 1) * q  # numpy's virtual index
    if v >= n - 1:  # numpy takes the last (largest) value twice
        a = b = np.max(z)
        t = v - (-1)
    else:
        i = math.floor(v)
        part = np.partition(z, i)
        a, b = part[i], np.min(part[i + 1:])
        t = v - i
    if np.isnan(a) or np.isnan(b):  # a NaN sorts last: it is in part[i:] or is the max
        return np.float64(np.nan)
    diff = b - a
    return b - diff * (1 - t) if t >= 0.5 else a + diff * t


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``np.cross(u, v)`` of ``(I, 3)`` arrays of one dtype, the same floats: numpy computes
    each component as one rounded product minus another (``u1 v2 - u2 v1``, ``u2 v0 - u0 v2``,
    ``u0 v1 - u1 v0``); here the same products and differences, three components at a time
    (twice as fast on 60 rows)."""
    nxt, prv = [1, 2, 0], [2, 0, 1]
    return u[:, nxt] * v[:, prv] - u[:, prv] * v[:, nxt]


def _ransac_plane(cand: np.ndarray, rng, iterations: int, threshold: float,
                  max_tilt_deg: float) -> tuple[tuple[np.ndarray, float] | None, int]:
    """The best of ``iterations`` 3-point plane hypotheses on ``cand (M, 3)``: ``((n, d), count)``.

    Hypotheses tilted more than ``max_tilt_deg`` or degenerate are skipped; the first one with
    the most points within ``threshold`` wins (``(None, 0)`` when none is valid). All triples
    are drawn first (the same draws, in the same order, as one at a time: :func:`_triples`)
    and scored at once.
    """
    if len(cand) < 3 or iterations < 1:
        return None, 0
    tri = cand[_triples(rng, len(cand), iterations)]
    n = _cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (I, 3)
    norm = np.linalg.norm(n, axis=1)
    ok = (norm >= 1e-9) & (np.abs(n[:, 2]) >= np.cos(np.radians(max_tilt_deg)) * norm)
    if not ok.any():
        return None, 0
    if not ok.all():  # (when all are valid, the selection would only copy them)
        n, norm, tri = n[ok], norm[ok], tri[ok]
    n = n / norm[:, None] * np.sign(n[:, 2])[:, None]
    offs = np.einsum("ij,ij->i", n, tri[:, 0])  # (I',)
    counts = _inlier_counts(cand, n, offs, threshold)
    i = int(np.argmax(counts))
    if counts[i] <= 0:
        return None, 0
    return (n[i], float(-offs[i])), int(counts[i])


def ground_plane(points, threshold: float = 0.2, sensor_height: float = 1.73,
                 iterations: int = 100, max_tilt_deg: float = 10.0, low_quantile: float = 0.3,
                 seed: int = 0, max_candidates: int = 5000) -> tuple[np.ndarray, float]:
    """The ground plane ``n . x + d = 0`` (unit ``n``, ``n_z > 0``) of ``(N, 3)`` sensor-frame
    points (module doc); the flat plane ``z = -sensor_height`` when none is found."""
    points = np.asarray(points).reshape(-1, 3)
    flat = (np.array([0.0, 0.0, 1.0]), float(sensor_height))
    if len(points) == 0:
        return flat
    # only the heights and the chosen candidates are converted to float64: the same values
    z = points[:, 2].astype(np.float64)
    z_lo = _quantile(z, low_quantile) + 0.5
    rows = np.flatnonzero(z <= z_lo)
    rng = np.random.default_rng(seed)
    if len(rows) > max_candidates:  # plane hypotheses are scored on a random subset
        rows = rows[rng.choice(len(rows), max_candidates, replace=False)]
    cand = points[rows].astype(np.float64)
    best, best_count = _ransac_plane(cand, rng, iterations, threshold, max_tilt_deg)
    if best is None or best_count < 3:
        log.debug("ground: no plane found, flat plane at z = %.2f", -sensor_height)
        return flat
    n, d = best
    inl = np.compress(np.abs(cand @ n + d) < threshold, cand, axis=0)
    n2, d2 = _fit_plane(inl)
    if n2[2] < np.cos(np.radians(max_tilt_deg)):
        return n, d
    return n2, d2


