"""Filled alpha shapes of 2D point sets, rasterised as boolean image masks.

The amodal mask of a vehicle is the region covered by its completed point cloud projected into
the image. The projected points are a dense but irregular sample of the silhouette; the alpha
shape (the union of the triangles of the alpha complex) follows concavities that the convex
hull would fill, and it does not bridge gaps wider than the chosen radius.

Construction: the Delaunay triangulation of the points (OpenCV's ``Subdiv2D``, faster than
``scipy.spatial.Delaunay`` here: docs/results.md, "Figures behind defaults in the code"; its
bounding triangle is placed far outside the points so that only huge hull slivers, which the
alpha test rejects anyway, can differ); a triangle is kept when its circumradius is below
``1 / alpha`` pixels; the kept triangles are filled with ``cv2.fillPoly`` at 1/16-pixel
precision. Pixel ``(row v, column u)`` is the one whose centre is
at image coordinates ``(u, v)`` (the KITTI projection convention).

Fill: ``cv2.fillPoly`` fills each scanline between the 1st and 2nd, the 3rd and 4th... crossings
of all its polygons' edges (even-odd), and draws every edge as a line too. An edge shared by
two kept triangles crosses a scanline twice at the same place and fills nothing, so the loops
of the union's boundary edges (each met by one kept triangle only; about a tenth of all
edges) fill what the triangles fill; the lines of the shared edges that touch the boundary
are drawn as well (:func:`_fill_polygons`). The shared edges deeper inside, and OpenCV's
clipping at the image border, still leave a few pixels unlike the triangles' fill: 12 pixels
in 10 of 1,942 kitti-like masks (docs/history/amodal.md, "Speed (issue 17)";
tests/test_amodal_alpha.py bounds it), for 2.5 ms less per vehicle.

Automatic alpha (``alpha=None``): radius
``r = max(NN_FACTOR * s_nn, TRI_FACTOR * r_med, MIN_RADIUS_PX)`` where ``s_nn`` is the 90th
percentile of the nearest-neighbour distances of the (deduplicated) points and ``r_med`` the
median circumradius of the Delaunay triangles. The nearest-neighbour distances are read off
the triangulation (a point's nearest neighbour is a Delaunay neighbour), bit for bit what a
KD-tree returns; where Subdiv2D left out hull slivers, the points on the triangles' boundary
ask a KD-tree (:func:`_nn_from_triangles`). For a roughly uniform sample the circumradii of
interior triangles are about the local spacing, so a few spacings keep every interior triangle
while rejecting the long slivers that bridge concavities or gaps. The 90th percentile (rather
than the median) tolerates the uneven density of projected surfaces (grazing surfaces project
densely); the circumradius term handles anisotropic samples such as LiDAR scan lines, dense
along a ring but several pixels apart across rings (there the nearest-neighbour distance is
the along-ring spacing, but most triangles span two rings and the median circumradius is about
half the ring gap).
"""

from __future__ import annotations

import logging
import threading

import cv2
import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

log = logging.getLogger(__name__)
_BUFFERS = threading.local()  # per-thread scratch arrays (:func:`_lookup_buffer`)

NN_FACTOR = 3.0
TRI_FACTOR = 3.0
MIN_RADIUS_PX = 1.5
GRID_PX = 0.25  # projected points are snapped to this lattice (px) before triangulating
_SHIFT = 4  # cv2 fixed-point bits: vertices at 1/16 px
_FAR = 4.0  # coordinates clipped to [-_FAR * size, (1 + _FAR) * size] before rasterising
_PAD = 10.0  # Subdiv2D rectangle: the points' box grown by this many times its extent
_LUT_MAX = 1 << 22  # lattice cells of the vertex lookup of _nn_from_triangles (else KD-tree)


def _subdiv_triangles(pts: np.ndarray) -> np.ndarray:
    """The Delaunay triangles of distinct points ``pts (N, 2)`` as rows ``(T, 6)`` float32
    ``(x0, y0, x1, y1, x2, y2)`` (module doc: Subdiv2D, virtual outer vertices dropped)."""
    lo0, hi0 = np.floor(pts.min(0)) - 2, np.ceil(pts.max(0)) + 2
    pad = _PAD * float(np.max(hi0 - lo0))
    lo, hi = lo0 - pad, hi0 + pad
    sub = cv2.Subdiv2D((int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1])))
    sub.insert(pts.astype(np.float32))
    tri = np.asarray(sub.getTriangleList(), dtype=np.float32).reshape(-1, 6)  # (T, 6)
    # lo0, hi0: integers within float32's exact range (module doc), so the same comparisons;
    # the six columns one by one (a reduction along rows of six is slow)
    inside = (tri >= np.tile(lo0, 3).astype(np.float32)) & (tri <= np.tile(hi0, 3).astype(
        np.float32))
    ok = inside[:, 0] & inside[:, 1] & inside[:, 2] & inside[:, 3] & inside[:, 4] & inside[:, 5]
    return tri[ok]


def delaunay_triangles(pts: np.ndarray) -> np.ndarray:
    """Delaunay triangles of distinct points ``pts (N, 2)`` as vertices ``(T, 3, 2)`` float64.

    OpenCV ``Subdiv2D`` (float32 coordinates: exact for points on the :data:`GRID_PX`
    lattice within +-2**21 px); triangles touching its virtual outer vertices are dropped.
    Empty ``(0, 3, 2)`` for collinear points.
    """
    return _subdiv_triangles(pts).astype(np.float64).reshape(-1, 3, 2)


def delaunay_triangles_scipy(pts: np.ndarray) -> np.ndarray:
    """Reference of :func:`delaunay_triangles` with ``scipy.spatial.Delaunay`` (slower)."""
    try:
        return pts[Delaunay(pts).simplices]
    except QhullError:  # collinear (or numerically so)
        return np.zeros((0, 3, 2))


def _dedup(uv: np.ndarray, grid: float) -> np.ndarray:
    """Points snapped to a ``grid``-pixel lattice, one per occupied cell (``grid`` 0: exact)."""
    if len(uv) == 0:
        return uv
    if grid <= 0:
        return np.unique(uv, axis=0)
    q = np.round(uv / grid).astype(np.int64)
    q -= q.min(0)
    span = int(q[:, 1].max()) + 1
    key = np.sort(q[:, 0] * span + q[:, 1])  # x major, y minor
    key = key[np.r_[True, key[1:] != key[:-1]]]  # each cell once
    q = np.empty((len(key), 2), dtype=np.int64)
    np.divmod(key, span, out=(q[:, 0], q[:, 1]))
    return q.astype(np.float64) * grid + np.round(uv.min(0) / grid) * grid


def auto_alpha_radius(uv: np.ndarray, radii: np.ndarray | None = None,
                     distinct: bool = False) -> float:
    """The automatic circumradius threshold (pixels) for points ``uv (N, 2)`` (module doc).

    ``radii`` are the circumradii of the points' Delaunay triangles when already known;
    ``distinct``: the points are known to be pairwise distinct (skips deduplication).
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if not distinct:
        uv = _dedup(uv, 0.0)
    if len(uv) < 2:
        return MIN_RADIUS_PX
    d, _ = cKDTree(uv, balanced_tree=False).query(uv, k=2)  # (N, 2); col 0: the point itself
    r = max(NN_FACTOR * np.quantile(d[:, 1], 0.9), MIN_RADIUS_PX)
    if radii is None and len(uv) >= 3:
        tri = delaunay_triangles(uv)
        radii = circumradii(tri) if len(tri) else None
    if radii is not None and np.isfinite(radii).any():
        r = max(r, TRI_FACTOR * float(np.median(radii[np.isfinite(radii)])))
    return float(r)


def circumradii(vertices: np.ndarray) -> np.ndarray:
    """Circumradius of each triangle, ``vertices (T, 3, 2) -> (T,)``; inf for degenerate ones."""
    return _radii(*_sides(vertices))


def _radii(a, b, c, area2) -> np.ndarray:
    """:func:`circumradii` from :func:`_sides`."""
    with np.errstate(divide="ignore", invalid="ignore"):
        r = a * b * c / (2.0 * area2)
    return np.where(area2 > 1e-12, r, np.inf)


def _sides(vertices: np.ndarray):
    """Side lengths ``(a, b, c)`` (opposite vertices 0, 1, 2) and twice the area of each
    triangle ``vertices (T, 3, 2)``, as :func:`circumradii` computes them."""
    x0, y0, x1, y1, x2, y2 = (vertices[:, i, j] for i in range(3) for j in range(2))
    # sqrt(dx * dx + dy * dy): what np.linalg.norm(..., axis=1) computes, bit for bit
    a = np.sqrt((x1 - x2) ** 2 + (y1 - y2) ** 2)
    b = np.sqrt((x0 - x2) ** 2 + (y0 - y2) ** 2)
    c = np.sqrt((x0 - x1) ** 2 + (y0 - y1) ** 2)
    return a, b, c, np.abs((x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0))


def _lookup_buffer(size: int) -> np.ndarray:
    """An int32 array of at least ``size`` entries (contents undefined), kept per thread: a fresh
    megabyte-sized array per call costs more in page faults than the lookups themselves."""
    buf = getattr(_BUFFERS, "lut", None)
    if buf is None or len(buf) < size:
        buf = _BUFFERS.lut = np.empty(max(size, 1 << 16), dtype=np.int32)
    return buf


def _vertex_ids(pts: np.ndarray, vertices: np.ndarray, grid: float) -> np.ndarray | None:
    """``(T, 3)`` int32: the row of ``pts (N, 2)`` (distinct, on the ``grid`` lattice) at each
    vertex of the triangles ``vertices (T, 3, 2)``, looked up by lattice cell: in a table of
    the cells when the points span at most :data:`_LUT_MAX` of them, else by binary search in
    the sorted cell keys (a vehicle beside the camera projects thousands of pixels wide);
    None when the points are not on the lattice (or a vertex is none of them)."""
    if grid <= 0 or len(pts) > 1 << 22:
        return None
    q = np.rint(pts / grid)
    if not np.array_equal(q * grid, pts) or np.abs(q).max() > 1 << 20:
        return None
    q = q.astype(np.int64)
    lo = q.min(0)
    span = q.max(0) - lo + 1
    qv = np.rint(vertices.reshape(-1, 2) / grid).astype(np.int64) - lo  # (3T, 2)
    keys = (q[:, 0] - lo[0]) * span[1] + (q[:, 1] - lo[1])  # distinct: one point per cell
    wanted = qv[:, 0] * span[1] + qv[:, 1]
    if span[0] * span[1] <= _LUT_MAX:
        lut = _lookup_buffer(int(span[0] * span[1]))
        lut[keys] = np.arange(len(q), dtype=np.int32)
        return lut[wanted].reshape(-1, 3)
    order = np.argsort(keys, kind="stable")
    at = np.minimum(np.searchsorted(keys[order], wanted), len(keys) - 1)
    if not np.array_equal(keys[order[at]], wanted):
        return None
    return order[at].astype(np.int32).reshape(-1, 3)


def _nn_from_triangles(pts: np.ndarray, ids: np.ndarray | None, sides) -> np.ndarray | None:
    """Nearest-neighbour distance of each point ``pts (N, 2)`` (distinct, on a lattice) from
    its Delaunay triangles (``ids``: :func:`_vertex_ids`, ``sides``: :func:`_sides`), bit for
    bit what a KD-tree gives; None without ``ids`` (then the caller asks a KD-tree).

    A point's nearest neighbour q is a Delaunay neighbour: the closed disk with diameter pq
    holds no other point (one on its circle would be nearer than q), so pq is an edge of every
    Delaunay triangulation. When the triangles triangulate the points' convex hull (their
    areas sum to the hull's, exactly: lattice coordinates), every point's nearest neighbour is
    the shortest side of its triangles, and the distance is computed as a KD-tree computes it
    (the same two squares, summed, square root). Subdiv2D leaves out a few hull slivers of some
    clouds (the areas then differ): a point all of whose edges are shared by two of the
    triangles still has its whole star of triangles, so its nearest neighbour is still among
    their sides; only the points on the triangles' boundary (and any in no triangle) ask the
    KD-tree.
    """
    if ids is None:
        return None
    a, b, c, area2 = sides
    nn = np.full(len(pts), np.inf)
    for side, (i, j) in ((a, (1, 2)), (b, (0, 2)), (c, (0, 1))):
        np.minimum.at(nn, ids[:, i], side)
        np.minimum.at(nn, ids[:, j], side)
    hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    hull2 = abs(float(np.sum(hull[:, 0] * np.roll(hull[:, 1], -1)
                             - hull[:, 1] * np.roll(hull[:, 0], -1))))
    if float(area2.sum()) != hull2:
        ask = ~np.isfinite(nn)  # in no triangle
        ask[_boundary_vertices(ids, len(pts))] = True
        d, _ = cKDTree(pts, balanced_tree=False).query(pts[ask], k=2)  # col 0: the point
        nn[ask] = d[:, 1]
    return nn if np.isfinite(nn).all() else None


def _boundary_vertices(ids: np.ndarray, n: int) -> np.ndarray:
    """The vertices of the edges met by one triangle only of ``ids (T, 3)`` (points ``< n``)."""
    i = ids.astype(np.int64)
    a, b = i.ravel(), i[:, [1, 2, 0]].ravel()
    key = np.sort(np.minimum(a, b) * n + np.maximum(a, b))
    key = key[_unique_entries(key)]
    return np.unique(np.concatenate([key // n, key % n]))


def _unique_entries(key: np.ndarray) -> np.ndarray:
    """Which entries of the sorted ``key`` equal neither neighbour (the edges met once)."""
    single = np.ones(len(key), dtype=bool)
    single[1:] &= key[1:] != key[:-1]
    single[:-1] &= key[:-1] != key[1:]
    return single


def _auto_radius_fast(pts: np.ndarray, ids: np.ndarray | None, sides, radii: np.ndarray
                      ) -> float:
    """:func:`auto_alpha_radius` of distinct lattice points with their Delaunay triangles,
    equal to it (the nearest-neighbour distances from the triangles, :func:`_nn_from_triangles`,
    else the KD-tree)."""
    nn = _nn_from_triangles(pts, ids, sides)
    if nn is None:
        return auto_alpha_radius(pts, radii, distinct=True)
    r = max(NN_FACTOR * np.quantile(nn, 0.9), MIN_RADIUS_PX)
    if np.isfinite(radii).any():
        r = max(r, TRI_FACTOR * float(np.median(radii[np.isfinite(radii)])))
    return float(r)


def _to_fixed(uv: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    h, w = image_size
    lo = np.array([-_FAR * w, -_FAR * h])
    hi = np.array([(1 + _FAR) * w, (1 + _FAR) * h])
    # np.clip's value for finite input, without its wrapper's overhead
    return np.round(np.minimum(np.maximum(uv, lo), hi) * (1 << _SHIFT)).astype(np.int32)


def _fill_polygons(pts: np.ndarray, tri: np.ndarray, ids: np.ndarray | None, image_size):
    """``(polygons, lines)`` that draw the union of the triangles ``tri (K, 3, 2)`` (vertices:
    the rows ``ids (K, 3)`` of ``pts``, :func:`_vertex_ids`; interiors pairwise disjoint):
    the loops of the union's boundary in fixed point for ``cv2.fillPoly``, and the pixel end
    points ``(L, 2, 2)`` of the shared edges at the boundary for ``cv2.polylines`` (module doc,
    "Fill"); the triangles themselves and None when ``ids`` is None."""
    if ids is None:
        return _to_fixed(tri.reshape(-1, 2), image_size).reshape(-1, 3, 2), None
    n = np.int64(len(pts))
    x, y = tri[:, :, 0], tri[:, :, 1]
    cw = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (y[:, 1] - y[:, 0]) * (x[:, 2] - x[:, 0]) < 0
    ids = ids.astype(np.int64)
    ids[cw] = ids[cw][:, ::-1]  # counter-clockwise: a shared edge is met once each way
    a = ids.ravel()
    b = ids[:, [1, 2, 0]].ravel()
    # an edge met once is a boundary edge: sort the undirected edges (direction in the lowest
    # bit) and keep those unequal to both neighbours
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = np.sort((lo * n + hi) * 2 + (a > b))
    und = key >> 1
    single = _unique_entries(und)
    shared = und[~single][::2]  # each shared edge once (its two copies are neighbours)
    key = key[single]
    lo, hi, flip = (key >> 1) // n, (key >> 1) % n, (key & 1).astype(bool)
    a, b = np.where(flip, hi, lo), np.where(flip, lo, hi)
    # each vertex has as many boundary edges in as out: pair them off into closed loops
    nxt = np.empty(len(a), dtype=np.int64)
    nxt[np.argsort(b, kind="stable")] = np.argsort(a, kind="stable")
    fixed = _to_fixed(pts[a], image_size)  # (E, 2): the start of each boundary edge
    loops = [fixed[loop] for loop in _cycles(nxt.tolist())]
    # the lines fillPoly draws of the shared edges at the boundary (module doc, "Fill")
    on_boundary = np.zeros(len(pts), dtype=bool)
    on_boundary[a] = True
    slo, shi = shared // n, shared % n
    near = on_boundary[slo] | on_boundary[shi]
    ends = _line_ends(_to_fixed(pts[np.c_[slo[near], shi[near]].ravel()], image_size))
    ends = ends.reshape(-1, 2, 2)
    return loops, np.ascontiguousarray(np.concatenate([ends, ends[:, ::-1]]))


def _line_ends(fixed: np.ndarray) -> np.ndarray:
    """Fixed-point vertices rounded to the pixels between which ``cv2.fillPoly`` draws a
    polygon's edge lines (x to nearest, halves up; y likewise)."""
    half = 1 << (_SHIFT - 1)
    return ((fixed + half) >> _SHIFT).astype(np.int32)


def _cycles(nxt: list[int]) -> list[list[int]]:
    """The cycles of the permutation ``nxt`` (each from its smallest index)."""
    seen = [False] * len(nxt)
    out = []
    for start in range(len(nxt)):
        if seen[start]:
            continue
        cyc = []
        e = start
        while not seen[e]:
            seen[e] = True
            cyc.append(e)
            e = nxt[e]
        out.append(cyc)
    return out


def _draw_degenerate(mask: np.ndarray, uv: np.ndarray, image_size) -> None:
    """0-2 points or collinear points: the segment between the extreme points (1 px wide)."""
    if len(uv) == 0:
        return
    centred = uv - uv.mean(0)
    direction = np.linalg.svd(centred, full_matrices=False)[2][0] if len(uv) > 1 else np.zeros(2)
    t = centred @ direction
    ends = _to_fixed(uv[[np.argmin(t), np.argmax(t)]], image_size)
    cv2.line(mask, tuple(int(v) for v in ends[0]), tuple(int(v) for v in ends[1]), 1,
             thickness=1, lineType=cv2.LINE_8, shift=_SHIFT)


def alpha_shape_mask(uv, image_size: tuple[int, int], alpha: float | None = None,
                     grid: float = GRID_PX) -> np.ndarray:
    """Rasterise the filled alpha shape of the points ``uv``.

    Args:
        uv: ``(N, 2)`` image coordinates (u = column, v = row), pixels; points may lie outside
            the image (their triangles are clipped by the rasteriser).
        image_size: ``(h, w)`` of the output mask.
        alpha: keep Delaunay triangles with circumradius ``< 1 / alpha`` (pixels); ``None`` picks
            it from the point spacing (:func:`auto_alpha_radius`); ``0`` keeps every triangle
            (the convex hull).
        grid: the points are first snapped to a lattice of this many pixels, one point per
            cell (dense clouds project many points per pixel; 0 keeps them all).

    Returns:
        ``(h, w)`` bool mask. Fewer than 3 distinct points, or collinear points, give the
        1-pixel-wide segment through them (empty for no points).
    """
    h, w = int(image_size[0]), int(image_size[1])
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    uv = uv[np.isfinite(uv[:, 0]) & np.isfinite(uv[:, 1])]
    mask = np.zeros((h, w), dtype=np.uint8)
    if alpha is not None and alpha < 0:
        raise ValueError(f"alpha must be >= 0, got {alpha}")
    pts = _dedup(uv, grid)
    if len(pts) < 3:
        _draw_degenerate(mask, pts, (h, w))
        return mask.view(bool)  # 0 / 1 only: a view, not a copy
    verts = delaunay_triangles(pts)  # (T, 3, 2)
    if len(verts) == 0:  # collinear
        _draw_degenerate(mask, pts, (h, w))
        return mask.view(bool)  # 0 / 1 only: a view, not a copy
    sides = _sides(verts)
    radii = _radii(*sides)  # (T,)
    ids = _vertex_ids(pts, verts, grid)
    if alpha is None:
        radius = _auto_radius_fast(pts, ids, sides, radii)
    else:
        radius = np.inf if alpha == 0 else 1.0 / alpha
    keep = radii < radius
    if not np.any(keep):
        log.debug("alpha shape: no triangle below radius %.2f px; drawing the points", radius)
        fixed = _to_fixed(pts, (h, w)) >> _SHIFT
        inside = (fixed[:, 0] >= 0) & (fixed[:, 0] < w) & (fixed[:, 1] >= 0) & (fixed[:, 1] < h)
        mask[fixed[inside, 1], fixed[inside, 0]] = 1
        return mask.view(bool)  # 0 / 1 only: a view, not a copy
    polys, lines = _fill_polygons(pts, verts[keep], None if ids is None else ids[keep], (h, w))
    cv2.fillPoly(mask, polys, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    if lines is not None and len(lines):
        cv2.polylines(mask, lines, False, 1, lineType=cv2.LINE_8)
    # Vertices themselves belong to the shape (thin sliver triangles may rasterise to nothing).
    fixed = (_to_fixed(pts, (h, w)) + (1 << (_SHIFT - 1))) >> _SHIFT
    inside = (fixed[:, 0] >= 0) & (fixed[:, 0] < w) & (fixed[:, 1] >= 0) & (fixed[:, 1] < h)
    mask[fixed[inside, 1], fixed[inside, 0]] = 1
    return mask.view(bool)  # 0 / 1 only: a view, not a copy
