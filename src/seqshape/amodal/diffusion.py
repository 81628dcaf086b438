"""Segmenting a LiDAR frame with 2D instance masks: ground removal and LDLS-style diffusion.

Ground removal (:func:`ground_mask`): planes are fitted by RANSAC (``iterations`` random
triples) to the low points (z below the ``low_quantile`` of the cloud plus 0.5 m; at most
``max_candidates`` of them, drawn at random, score the hypotheses); only nearly
horizontal planes (normal within ``max_tilt_deg`` of +z) count; the plane with most inliers is
refitted by least squares to them, and every point less than ``threshold`` metres above it (or
below it) is ground. When no plane is found (too few points) the fallback is the height rule
``z < -sensor_height + threshold`` (KITTI's HDL-64E is 1.73 m above the road).

Label diffusion (:func:`diffuse_labels`), after LDLS (Wang et al. 2019), on the CPU with
scipy.sparse: nodes are the points projecting into the image (in front of the camera); each
point is linked to the pixel it projects to, which carries a fixed label (one of the masks, or
background when no mask covers it); points are linked to their ``k`` nearest neighbours in 3D
with weights ``exp(-d^2 / (2 sigma^2))`` (zero beyond ``max_edge`` metres), each row
normalised to sum 1 (as LDLS's transition matrix: sparse and dense regions alike). Label scores
``L (N, C)`` iterate ``L <- rownorm(W L + lam * Y)`` from ``L = Y`` (``Y`` the pixel labels),
so a point keeps its pixel's label only when its 3D neighbourhood agrees: background points seen
through a mask (a wall behind a car, or the ground inside a dilated mask) are pulled back to
background by their neighbours. The sweeps run per block of connected components on the label
columns present there, bit for bit the full-width iteration (:func:`propagate_labels`). A point's label is the argmax; then each instance keeps only
its main cluster (:func:`vehicle_cluster`: the largest connected component of its points and
the components that fit one vehicle with it), which drops the remaining strays.
The link distance of that filter grows with range, ``max(cluster_gap, cluster_gap_per_m *
range)`` (``cluster_gap_per_m`` = 0.025: 1.25 m at 50 m): the gap between two scan lines on
one vehicle is range times the vertical angular step (0.4 degrees on the HDL-64E, 0.7 m at
100 m), larger still where a line passes from the boot lid to the roof of a vehicle seen
from behind (docs/results.md, "Figures behind defaults in the code"), and a fixed 0.5 m kept
only the nearest face.

Growing outside the image (:func:`grow_instances`): the camera sees about 90 degrees of the
360-degree scan, so a vehicle cut by the image border (one being passed, or entering the view)
keeps only its in-image points, and its completion is then placed too far into the image.
Each instance is therefore grown into the points that do not project into the image, through
chains of links no longer than its cluster gap, at most ``max_grow`` metres from its in-image
points (a vehicle's length); a point reached by two instances goes to the nearer one.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from seqshape.data.ground import _fit_plane, _ransac_plane, ground_plane  # noqa: F401

try:  # the kernel of ``csr_matrix @ ndarray`` (2-D), called without its Python dispatch
    from scipy.sparse._sparsetools import csr_matvecs as _csr_matvecs
except ImportError:  # pragma: no cover - a SciPy without it: the public product
    _csr_matvecs = None

log = logging.getLogger(__name__)

BACKGROUND = -1

_GRID_MIN_QUERIES = 1024  # grow_instances: fewer outside points in reach go to the tree
_GRID_CELLS = 16  # ... else a grid of cubes of max_grow / 16 settles most of them
_GRID_MAX_CELLS = 1 << 18  # ... unless it would be this large (and sparse)


def ground_mask(points, threshold: float = 0.2, sensor_height: float = 1.73,
                plane: tuple[np.ndarray, float] | None = None, **plane_kwargs) -> np.ndarray:
    """Boolean ``(N,)``: which of the ``(N, 3)`` sensor-frame points are ground (module doc):
    less than ``threshold`` above ``plane`` (or below it), by default :func:`ground_plane`."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    n, d = plane if plane is not None else ground_plane(points, threshold, sensor_height,
                                                        **plane_kwargs)
    return points @ n + d < threshold


def _knn_graph(points: np.ndarray, k: int, sigma: float, max_edge: float) -> sp.csr_matrix:
    """Row-normalised symmetric k-NN affinity ``(N, N)`` (Gaussian weights, no self loops)."""
    n = len(points)
    k = min(k, n - 1)
    if k < 1:
        return sp.csr_matrix((n, n))
    dist, idx = cKDTree(points).query(points, k=k + 1)  # (N, k+1), first is the point itself
    dist, idx = dist[:, 1:], idx[:, 1:]
    w = np.exp(-dist ** 2 / (2 * sigma ** 2)) * (dist <= max_edge)
    rows = np.repeat(np.arange(n), k)
    g = sp.csr_matrix((w.ravel(), (rows, idx.ravel())), shape=(n, n))
    g = g.maximum(g.T).tocsr()
    deg = np.asarray(g.sum(1)).ravel()
    return (sp.diags(np.divide(1.0, deg, out=np.zeros(n), where=deg > 0)) @ g).tocsr()


def pixel_labels(uv, masks: Sequence[np.ndarray]) -> np.ndarray:
    """One-hot-ish pixel labels ``Y (N, C+1)`` of points at ``uv (N, 2)`` (last = background).

    A point inside several masks splits its weight between them.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n, c = len(uv), len(masks)
    y = np.zeros((n, c + 1))
    if c:
        h, w = masks[0].shape
        col = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, w - 1)
        row = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, h - 1)
        flat_c = row * w + col  # (N,): each point's pixel in a row-major (h, w) mask
        flat_f = col * h + row  # ... in a column-major one (decoded RLE masks are)
        for m, mask in enumerate(masks):
            mask = np.asarray(mask)
            if mask.flags.c_contiguous:
                y[:, m] = mask.reshape(-1)[flat_c]
            elif mask.flags.f_contiguous:
                y[:, m] = mask.T.reshape(-1)[flat_f]
            else:
                y[:, m] = mask[row, col]
    y[:, c] = y[:, :c].sum(1) == 0
    return y / y.sum(1, keepdims=True)


def _blocks(w: sp.csr_matrix, y: np.ndarray, min_rows: int = 256):
    """The graph ``w (N, N)`` cut into blocks of whole connected components for
    :func:`propagate_labels`: a list of ``(rows, sub, cols)``, ``rows`` the block's nodes
    (ascending), ``sub`` its square CSR block (each row's entries in ``w``'s order, so every
    product sums in the same order as ``w``'s), ``cols`` the label columns of ``y (N, C+1)``
    that are nonzero somewhere in the block (the others stay exactly 0 there at every sweep).
    Components under ``min_rows`` nodes share one block (the union of their columns)."""
    n = w.shape[0]
    _, comp = connected_components(w, directed=False)
    sizes = np.bincount(comp)
    big = sizes >= min_rows
    group = np.where(big[comp], comp, -1)  # the small components together
    out = []
    nz = y != 0  # (N, C+1)
    for g in np.unique(group):
        rows = np.flatnonzero(group == g)
        local = np.full(n, -1, dtype=np.int64)
        local[rows] = np.arange(len(rows))
        starts, ends = w.indptr[rows], w.indptr[rows + 1]
        lens = ends - starts
        indptr = np.zeros(len(rows) + 1, dtype=np.int64)
        np.cumsum(lens, out=indptr[1:])
        pos = np.repeat(starts - indptr[:-1], lens) + np.arange(indptr[-1])
        sub = sp.csr_matrix((w.data[pos], local[w.indices[pos]], indptr),
                            shape=(len(rows), len(rows)))
        cols = np.flatnonzero(nz[rows].any(axis=0))
        out.append((rows, sub, cols))
    return out


def _pairwise_sum(columns: list) -> np.ndarray | None:
    """The sum of ``columns`` (arrays, or None for a column of exact zeros) in the order of
    numpy's pairwise summation of a row (``a.sum(1)`` of a C-contiguous ``(R, W)`` array,
    ``W = len(columns)`` below 128: sequential below 8 terms, else eight running sums over
    blocks of eight, a fixed tree, then the rest in order). Adding an exact zero (the values
    are >= 0) changes nothing, so the zero columns are skipped; None when all are zero."""
    def add(x, y):
        return y if x is None else x if y is None else x + y

    n = len(columns)
    if n < 8:
        res = None
        for col in columns:
            res = add(res, col)
        return res
    r = list(columns[:8])
    i = 8
    while i < n - n % 8:
        for j in range(8):
            r[j] = add(r[j], columns[i + j])
        i += 8
    res = add(add(add(r[0], r[1]), add(r[2], r[3])), add(add(r[4], r[5]), add(r[6], r[7])))
    for col in columns[i:]:
        res = add(res, col)
    return res


_SUM_ORDER_OK: dict[int, bool] = {}


def _sum_order_ok(width: int) -> bool:
    """Whether :func:`_pairwise_sum` gives numpy's row sums bit for bit at this width
    (checked once per width on random rows with zeros; else the rows are summed at full width)."""
    if width not in _SUM_ORDER_OK:
        ok = width < 128
        if ok:
            rng = np.random.default_rng(width)
            for rows in (1, 3, 257):
                a = rng.random((rows, width)) * 10.0 ** rng.integers(-9, 3, (rows, width))
                a[rng.random(a.shape) < 0.4] = 0.0
                cols = [a[:, j].copy() if j % 3 else None for j in range(width)]
                a[:, [j for j in range(width) if not j % 3]] = 0.0
                got = _pairwise_sum(cols)
                got = np.zeros(rows) if got is None else got
                ok = ok and np.array_equal(got, a.sum(1))
        _SUM_ORDER_OK[width] = ok
    return _SUM_ORDER_OK[width]


def _product(sub: sp.csr_matrix, x: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``sub @ x`` for a C-contiguous float64 ``x (R, K)``, written to ``out (R, K)``: the
    kernel scipy's product calls for a 2-D operand (``csr_matvecs``; each row's terms added
    in order into zeros), or the product itself without it."""
    if _csr_matvecs is None:
        out[...] = sub @ x
        return out
    out.fill(0.0)
    _csr_matvecs(sub.shape[0], sub.shape[1], x.shape[1], sub.indptr, sub.indices, sub.data,
                 x.ravel(), out.ravel())
    return out


def propagate_labels(w: sp.csr_matrix, y: np.ndarray, lam: float, iterations: int
                     ) -> np.ndarray:
    """``iterations`` sweeps of ``L <- rownorm(w L + lam y)`` from ``L = y`` (module doc):
    ``(N, C+1)``, bit for bit the full-width loop (``lab = w @ lab; lab += lam * y;
    lab /= lab.sum(1, keepdims=True)``).

    The graph splits into connected components, and inside one only the label columns
    that its pixel labels use are ever nonzero (the others are sums of exact zeros). Each
    block of components (:func:`_blocks`) sweeps on its own columns only, with the same
    sparse product (each row's terms in the same order, so the same sums); the row sums
    add the nonzero columns in the order numpy's row sum adds the full-width row
    (:func:`_pairwise_sum`), so they are the same sums too. About a fifth of the
    full-width arithmetic on kitti-like frames.
    """
    n, width = y.shape
    if n == 0 or iterations <= 0:
        return y.copy()
    lab = np.zeros((n, width))
    exact_order = _sum_order_ok(width)
    for rows, sub, cols in _blocks(w, y):
        pull = lam * y[np.ix_(rows, cols)]  # (R, K): lam * y, elementwise as the full loop
        cur = y[np.ix_(rows, cols)]
        slot = np.full(width, -1)
        slot[cols] = np.arange(len(cols))
        full = None if exact_order else np.zeros((len(rows), width))
        spare = np.empty_like(cur)
        for _ in range(iterations):
            cur, spare = _product(sub, cur, spare), cur
            cur += pull
            if full is None:
                total = _pairwise_sum([None if k < 0 else cur[:, k] for k in slot])
            else:  # the rows at full width (the zeros in place), summed by numpy
                full[:, cols] = cur
                total = full.sum(1)
            cur /= total[:, None]
        lab[np.ix_(rows, cols)] = cur
    return lab


def components(points, gap: float) -> np.ndarray:
    """Connected-component label ``(N,)`` of ``points``, linked when closer than ``gap``.

    The points are first pooled into voxels of ``gap / 2`` (their mean stands for them), and
    voxels closer than ``gap`` are linked: every pair within ``gap`` would be quadratic in a
    dense near vehicle, and a k-nearest-neighbour graph fails on a far one, whose k nearest
    neighbours all lie on its own scan line (dense along the line, sparse across lines).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) <= 1:
        return np.zeros(len(points), dtype=np.int64)
    comp, inv = _voxel_components(points, gap)
    return comp[inv]


def _voxel_components(points: np.ndarray, gap: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`components` of float64 ``points (N, 3)`` (N >= 1) per voxel: ``(comp (V,),
    inv (N,))``, the component of each voxel and the voxel of each point (``comp[inv]``).

    The voxel sums are ``np.bincount`` with weights, one column at a time: it adds each
    voxel's points in the order of the points, from 0.0, as ``np.add.at(reps, inv, points)``
    does, so the means are the same bit for bit (and several times faster)."""
    keys = np.floor(points / (gap / 2)).astype(np.int64)  # (N, 3)
    inv = _voxel_ids(keys)
    nv = int(inv.max()) + 1
    reps = np.empty((nv, 3))
    for j in range(3):
        reps[:, j] = np.bincount(inv, weights=points[:, j], minlength=nv)
    reps /= np.bincount(inv, minlength=nv)[:, None]
    pairs = cKDTree(reps).query_pairs(gap, output_type="ndarray")  # (P, 2)
    # the graph as CSR, built directly (scipy's COO route costs more than the rest); the
    # labels of connected_components depend only on the partition (numbered in the order
    # of each component's first node), not on how the matrix was built
    order = np.argsort(pairs[:, 0], kind="stable")
    indptr = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(np.bincount(pairs[:, 0], minlength=nv), out=indptr[1:])
    g = sp.csr_matrix((np.ones(len(pairs)), pairs[order, 1], indptr), shape=(nv, nv))
    _, comp = connected_components(g, directed=False)
    return comp, inv


def _voxel_ids(keys: np.ndarray) -> np.ndarray:
    """``(N,)`` index of each integer voxel ``keys (N, 3)`` among the distinct voxels in
    lexicographic order (``np.unique(keys, axis=0, return_inverse=True)``, on one int64 key
    per voxel, which sorts the same way). When the keys span few voxels the rank of each key
    comes from a dense occupancy table (its running count) instead of a sort: the same ranks."""
    cols = [keys[:, j] - keys[:, j].min() for j in range(3)]  # column-wise: (N, 3) reductions
    span = [int(c.max()) + 1 for c in cols]                   # along axis 0 are slow
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0 ** 62:  # no room: the slow way
        return np.unique(keys, axis=0, return_inverse=True)[1].ravel()
    flat = (cols[0] * span[1] + cols[1]) * span[2] + cols[2]
    size = span[0] * span[1] * span[2]
    if size <= 8 * len(flat) + 4096:
        occupied = np.zeros(size, dtype=bool)
        occupied[flat] = True
        rank = np.cumsum(occupied, dtype=np.int64)
        return rank[flat] - 1
    return np.unique(flat, return_inverse=True)[1].ravel()


def largest_cluster(points, gap: float) -> np.ndarray:
    """Boolean ``(N,)``: the largest connected component of ``points`` (:func:`components`)."""
    comp = components(points, gap)
    if len(comp) <= 1:
        return np.ones(len(comp), dtype=bool)
    return comp == np.bincount(comp).argmax()


def vehicle_cluster(points, gap: float, join: float = 3.0, max_extent: float = 7.0
                    ) -> np.ndarray:
    """Boolean ``(N,)``: the largest component plus the others that fit one vehicle with it.

    Seen at a grazing angle, a far vehicle's scan lines land metres apart in depth (the rear
    face, then the roof), so it splits into several components. Components are added, largest
    first, when they lie within ``join`` metres of the kept points and the kept points still
    fit in ``max_extent`` metres (the planar diagonal of their bounding box); strays seen
    through the mask (a wall, the road far behind) fail one or the other.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    comp = components(points, gap)
    if len(comp) <= 1:
        return np.ones(len(comp), dtype=bool)
    sizes = np.bincount(comp)
    order = np.argsort(-sizes, kind="stable")
    keep = comp == order[0]
    for c in order[1:]:
        sel = comp == c
        d, _ = cKDTree(points[keep]).query(points[sel], distance_upper_bound=join)
        if not np.isfinite(d).any():
            continue
        both = points[keep | sel, :2]
        if np.linalg.norm(both.max(0) - both.min(0)) <= max_extent:
            keep |= sel
    return keep


def cluster_gap_for(points, cluster_gap: float, per_m: float) -> float:
    """Link distance (m) of the cluster filter for an instance's ``points`` (module doc)."""
    if len(points) == 0:
        return cluster_gap
    rng = float(np.median(np.linalg.norm(np.asarray(points)[:, :2], axis=1)))
    return max(cluster_gap, per_m * rng)


def diffuse_labels(points, uv, masks: Sequence[np.ndarray], k: int = 10, sigma: float = 0.3,
                   max_edge: float = 1.0, lam: float = 0.2, iterations: int = 30,
                   cluster_gap: float = 0.5, min_points: int = 1,
                   cluster_gap_per_m: float = 0.025) -> np.ndarray:
    """Instance label of every point: index into ``masks``, or :data:`BACKGROUND` (-1).

    Args:
        points: ``(N, 3)`` sensor-frame points that project into the image (filter first).
        uv: ``(N, 2)`` their pixel coordinates.
        masks: C boolean ``(h, w)`` instance masks of the image.
        k, sigma, max_edge: the point graph (neighbours, Gaussian width m, cut-off m).
        lam: weight of the pixel links against the point graph.
        iterations: label-propagation sweeps.
        cluster_gap: link distance (m) of the largest-cluster outlier filter (0 disables it).
        cluster_gap_per_m: its growth with range (module doc).
        min_points: instances left with fewer points are dropped to background.

    Returns:
        ``(N,)`` int64 labels.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n, c = len(points), len(masks)
    labels = np.full(n, BACKGROUND, dtype=np.int64)
    if n == 0 or c == 0:
        return labels
    y = pixel_labels(uv, masks)  # (N, C+1)
    w = _knn_graph(points, k, sigma, max_edge)
    lab = propagate_labels(w, y, lam, iterations)  # (N, C+1)
    best = lab.argmax(1)
    labels = np.where(best == c, BACKGROUND, best)
    for m in range(c):
        idx = np.flatnonzero(labels == m)
        if cluster_gap > 0 and len(idx) > 1:
            gap = cluster_gap_for(points[idx], cluster_gap, cluster_gap_per_m)
            labels[idx[~vehicle_cluster(points[idx], gap)]] = BACKGROUND
        if np.sum(labels == m) < min_points:
            labels[labels == m] = BACKGROUND
    return labels


def _columns(points: np.ndarray) -> list[np.ndarray]:
    """The x, y, z columns of ``points (N, 3)``, contiguous (numpy's reductions along axis 0
    of an ``(N, 3)`` array, and row tests with ``all(axis=1)``, are about ten times slower)."""
    return [np.ascontiguousarray(points[:, j]) for j in range(3)]


def _in_reach(cols: list[np.ndarray], lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Indices (ascending) of the points (columns ``cols``) inside the box ``[lo, hi]``.
    Only these can lie within ``max_grow`` of an instance whose points span
    ``[lo + max_grow, hi - max_grow]``."""
    near = np.flatnonzero((cols[0] >= lo[0]) & (cols[0] <= hi[0]))
    for j in (1, 2):
        c = cols[j][near]
        near = near[(c >= lo[j]) & (c <= hi[j])]
    return near


_SQRT3 = float(np.sqrt(3.0))


def _surely(p_cols: list[np.ndarray], q_cols: list[np.ndarray], max_grow: float,
            cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Which of the points ``q`` (columns ``q_cols``, ``(K,)`` each) are surely within
    ``max_grow`` of the points ``p`` (columns ``p_cols``), and which surely beyond: two
    boolean ``(K,)``, from bounds on the distance from each ``q`` to its nearest ``p``.

    Both sides go into a grid of cubes of side ``cell``; the Euclidean distance transform of
    the cubes holding a ``p`` gives for each cube the distance ``D`` (in cubes) from its
    centre to the nearest such cube's centre, and that cube. A point lies within ``r = cell *
    sqrt(3) / 2`` of its cube's centre ``c``, so the distance from ``q`` to its nearest ``p``
    is at least ``cell * D - |q - c| - r >= cell * (D - sqrt(3))`` and at most ``cell * (D +
    sqrt(3))``, or the distance to any one ``p``, here one in that nearest cube. The cubes
    are settled first with the coarse bounds (most points), the other points with the
    finer ones. A point is surely within (beyond) when a bound is below (above) ``max_grow``
    by more than ``margin``, far more than the rounding of these bounds and of the k-d
    tree's squared distances: the tree's ``distance_upper_bound`` test (``d < max_grow``)
    says the same of it. Neither set is filled when the grid would be large and sparse."""
    k = len(q_cols[0])
    o = [min(pc.min(), qc.min()) for pc, qc in zip(p_cols, q_cols, strict=True)]
    kp = [((c - a) / cell).astype(np.int64) for c, a in zip(p_cols, o, strict=True)]  # >= 0:
    kq = [((c - a) / cell).astype(np.int64) for c, a in zip(q_cols, o, strict=True)]  # floor
    shape = tuple(max(int(a.max()), int(b.max())) + 1 for a, b in zip(kp, kq, strict=True))
    if shape[0] * shape[1] * shape[2] > max(_GRID_MAX_CELLS, 8 * k):
        return np.zeros(k, dtype=bool), np.zeros(k, dtype=bool)
    fp = (kp[0] * shape[1] + kp[1]) * shape[2] + kp[2]
    fq = (kq[0] * shape[1] + kq[1]) * shape[2] + kq[2]
    free = np.ones(shape[0] * shape[1] * shape[2], dtype=bool)  # the cubes holding no p
    free[fp] = False
    dist, nearest = ndimage.distance_transform_edt(free.reshape(shape), return_indices=True)
    dist = dist.ravel()
    scale = max(max(abs(c).max() for c in p_cols), max(abs(c).max() for c in q_cols))
    margin = 1e-9 * (1.0 + max_grow + scale)
    state = np.zeros(dist.size, dtype=np.int8)  # per cube: 1 surely within, -1 beyond
    state[cell * (dist + _SQRT3) < max_grow - margin] = 1
    state[cell * (dist - _SQRT3) > max_grow + margin] = -1
    state = state[fq]
    within, beyond = state == 1, state == -1
    rest = np.flatnonzero(state == 0)
    if len(rest):
        rep = np.empty(dist.size, dtype=np.int64)  # a point of p in each cube holding one
        rep[fp] = np.arange(len(fp))
        n = nearest.reshape(3, -1)[:, fq[rest]].astype(np.int64)
        to = rep[(n[0] * shape[1] + n[1]) * shape[2] + n[2]]  # (R,) a p in the nearest cube
        to_p = to_c = 0.0
        for j in range(3):
            q = q_cols[j][rest]
            diff = q - p_cols[j][to]
            to_p = to_p + diff * diff
            diff = q - (o[j] + (kq[j][rest] + 0.5) * cell)
            to_c = to_c + diff * diff
        within[rest] = np.sqrt(to_p) < max_grow - margin
        low = cell * dist[fq[rest]] - np.sqrt(to_c) - cell * (_SQRT3 / 2)
        beyond[rest] = low > max_grow + margin
    return within, beyond


def grow_instances(parts: Sequence[np.ndarray], outside, cluster_gap: float = 0.5,
                   cluster_gap_per_m: float = 0.025, max_grow: float = 5.0,
                   ) -> list[np.ndarray]:
    """Each instance's points ``parts[m] (N_m, 3)`` plus the ``outside (M, 3)`` points
    connected to them (module doc). Returns new arrays (the input order, float64).

    The rule, as first written: for each instance ``m`` in turn, its candidates are the
    outside points whose distance ``d_m`` to it, by ``cKDTree(part).query(...,
    distance_upper_bound=max_grow)``, is finite; those in a component (:func:`components`,
    on the part and its candidates) that holds a point of the part are reached, and a reached
    point goes to ``m`` when ``d_m`` is below the smallest distance of the instances before
    (so the first of equally near instances keeps it). The same, with less work:

    * a point outside the box of the part grown by ``max_grow`` is not queried (its
      distance is infinite), and a point surely within or surely beyond ``max_grow``
      (:func:`_surely`, from a coarse grid) is not queried either: only the points near
      the cut need the tree's answer, whose exact test (``<``, squared) decides them;
    * a point reached by one instance only goes to it whatever its distance, so the
      distances are computed (by the same tree, so to the same bits) only for the points
      reached by several instances, and compared in the instances' order.
    """
    outside = np.asarray(outside, dtype=np.float64).reshape(-1, 3)
    parts = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in parts]
    if len(outside) == 0 or not any(len(p) for p in parts):
        return parts
    cols = _columns(outside)
    trees: dict[int, cKDTree] = {}

    def tree(m: int) -> cKDTree:
        if m not in trees:
            trees[m] = cKDTree(parts[m])
        return trees[m]

    grid = 0 < max_grow < np.inf  # a bound to cut at: the grid can settle points
    reached = []  # (m, indices into outside)
    times_reached = np.zeros(len(outside), dtype=np.int64)
    for m, p in enumerate(parts):
        if len(p) == 0:
            continue
        p_cols = _columns(p)
        lo = np.array([c.min() for c in p_cols]) - max_grow
        hi = np.array([c.max() for c in p_cols]) + max_grow
        near = _in_reach(cols, lo, hi)
        if len(near) == 0:  # nothing outside the image within reach: no tree to build
            continue
        if grid and len(near) >= _GRID_MIN_QUERIES and np.isfinite(lo).all() \
                and np.isfinite(hi).all():
            q_cols = [c[near] for c in cols]
            found, beyond = _surely(p_cols, q_cols, max_grow, max_grow / _GRID_CELLS)
            ask = np.flatnonzero(~(found | beyond))
            if len(ask):
                d, _ = tree(m).query(outside[near[ask]], distance_upper_bound=max_grow)
                found[ask] = np.isfinite(d)
        else:
            d, _ = tree(m).query(outside[near], distance_upper_bound=max_grow)  # (K,)
            found = np.isfinite(d)
        cand = near[found]
        if len(cand) == 0:
            continue
        gap = cluster_gap_for(p, cluster_gap, cluster_gap_per_m)
        comp, inv = _voxel_components(np.concatenate([p, outside[cand]]), gap)
        linked = np.zeros(int(comp.max()) + 1, dtype=bool)
        linked[comp[inv[:len(p)]]] = True  # the components holding a point of the part
        sel = cand[linked[comp[inv[len(p):]]]]
        times_reached[sel] += 1
        reached.append((m, sel))
    best = np.full(len(outside), -1)
    best_d = np.full(len(outside), np.inf)
    for m, sel in reached:
        shared = times_reached[sel] > 1
        best[sel[~shared]] = m
        sel = sel[shared]
        if len(sel):
            d, _ = tree(m).query(outside[sel], distance_upper_bound=max_grow)
            closer = d < best_d[sel]
            best[sel[closer]], best_d[sel[closer]] = m, d[closer]
    order = np.argsort(best, kind="stable")  # the points of each instance, ascending
    ends = np.cumsum(np.bincount(best + 1, minlength=len(parts) + 1))
    return [np.concatenate([p, outside[order[ends[m]:ends[m + 1]]]])
            for m, p in enumerate(parts)]
