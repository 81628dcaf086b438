"""``alpha_shape_mask`` against an independent, slow reference: scipy's Delaunay (Qhull), the
circumradius from the circumcentre, and a per-pixel test of which pixel centres lie inside the
kept triangles.

Tolerances (docs/history/amodal.md, "Alpha shape within the label budget"): the mask is filled from
the union's boundary loops with ``cv2.fillPoly`` at 1/16 px, which also draws the loops as
1-pixel lines. So a pixel may differ from the reference only along the union's boundary:

* a pixel the reference has and the mask lacks: its centre within ``MISS_PX`` of a boundary
  edge (fillPoly rounds each scanline's ends to pixels and draws the edge's line between its
  rounded ends: a centre just inside a long edge can fall out);
* a pixel the mask has and the reference lacks: its centre within ``EXTRA_PX`` of a boundary
  edge (fillPoly draws each edge as an 8-connected line between its end points rounded to
  pixels: half a pixel from that line, whose ends move by up to sqrt(2) / 2);
* every vertex's pixel is set (both sides).

Nothing else may differ: interiors, holes wider than the radius and gaps between clusters
are exact.
"""

import numpy as np
import pytest
from scipy.spatial import Delaunay, QhullError, cKDTree

from seqshape.amodal.alpha import GRID_PX, alpha_shape_mask

MISS_PX = 0.5
EXTRA_PX = 1.25
EPS = 1e-9  # barycentric slack: a centre on a shared edge belongs to both triangles


def _lattice(uv, grid=GRID_PX):
    """The distinct points snapped to the ``grid`` lattice (an independent implementation)."""
    uv = np.asarray(uv, float)
    return np.unique(np.round(uv / grid), axis=0) * grid


def _circumradius(t):
    """Circumradius of triangles ``t (T, 3, 2)`` from their circumcentres; inf if degenerate."""
    (ax, ay), (bx, by), (cx, cy) = (t[:, i].T for i in range(3))
    d = 2.0 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = ((ax**2 + ay**2) * (by - cy) + (bx**2 + by**2) * (cy - ay)
              + (cx**2 + cy**2) * (ay - by)) / d
        uy = ((ax**2 + ay**2) * (cx - bx) + (bx**2 + by**2) * (ax - cx)
              + (cx**2 + cy**2) * (bx - ax)) / d
    r = np.hypot(ax - ux, ay - uy)
    return np.where(np.abs(d) > 1e-12, r, np.inf)


def _reference(uv, size, alpha=None):
    """``(mask, boundary edges (E, 2, 2), vertices)`` of the filled alpha shape, by brute force;
    None when the points are collinear or fewer than three."""
    pts = _lattice(uv)
    if len(pts) < 3:
        return None
    try:
        tri = pts[Delaunay(pts).simplices]
    except QhullError:
        return None
    radii = _circumradius(tri)
    if alpha is None:
        nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
        radius = max(3.0 * np.quantile(nn, 0.9), 3.0 * np.median(radii[np.isfinite(radii)]), 1.5)
    else:
        radius = np.inf if alpha == 0 else 1.0 / alpha
    kept = tri[radii < radius]
    h, w = size
    vv, uu = np.mgrid[0:h, 0:w]
    centres = np.c_[uu.ravel(), vv.ravel()].astype(float)
    inside = np.zeros(h * w, bool)
    for a, b, c in kept:  # barycentric test of every pixel centre (edges included)
        m = np.array([b - a, c - a]).T
        lam = np.linalg.solve(m, (centres - a).T)
        inside |= (lam[0] >= -EPS) & (lam[1] >= -EPS) & (lam[0] + lam[1] <= 1 + EPS)
    mask = inside.reshape(h, w)
    px = np.floor(pts + 0.5).astype(int)  # the vertex's pixel: halves up
    ok = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    mask[px[ok, 1], px[ok, 0]] = True
    # the union's boundary: the edges met by one kept triangle
    count = {}
    for t in np.round(kept / GRID_PX).astype(np.int64).tolist():
        for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):
            key = tuple(sorted((tuple(e[0]), tuple(e[1]))))
            count[key] = count.get(key, 0) + 1
    edges = np.array([k for k, n in count.items() if n == 1], float).reshape(-1, 2, 2) * GRID_PX
    return mask, edges, pts


def _distance_to_edges(p, edges):
    """Distance of points ``p (P, 2)`` to the nearest segment of ``edges (E, 2, 2)``."""
    if len(edges) == 0:
        return np.full(len(p), np.inf)
    a, b = edges[:, 0], edges[:, 1]
    ab = b - a
    t = np.clip(((p[:, None] - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
    return np.linalg.norm(p[:, None] - (a + t[..., None] * ab), axis=-1).min(1)


def _check(uv, size, alpha=None, expect_area=None):
    got = alpha_shape_mask(uv, size, alpha=alpha)
    ref = _reference(uv, size, alpha)
    assert ref is not None
    want, edges, pts = ref
    miss = np.argwhere(want & ~got)[:, ::-1].astype(float)  # (u, v)
    extra = np.argwhere(got & ~want)[:, ::-1].astype(float)
    assert (_distance_to_edges(miss, edges) <= MISS_PX).all(), f"{len(miss)} pixels missing"
    assert (_distance_to_edges(extra, edges) <= EXTRA_PX).all(), f"{len(extra)} pixels extra"
    px = np.floor(pts + 0.5).astype(int)
    ok = (px[:, 0] >= 0) & (px[:, 0] < size[1]) & (px[:, 1] >= 0) & (px[:, 1] < size[0])
    assert got[px[ok, 1], px[ok, 0]].all()
    if expect_area is not None:
        assert abs(int(got.sum()) - expect_area) <= 0.2 * expect_area
    return got, want


@pytest.mark.parametrize("seed", range(6))
def test_random_clouds_match_the_brute_force_reference(seed):
    rng = np.random.default_rng(100 + seed)
    size = (70, 110)
    n = int(rng.integers(30, 600))
    kind = seed % 3
    if kind == 0:
        uv = rng.normal([55, 35], [18, 10], (n, 2))  # partly off the image
    elif kind == 1:
        uv = np.c_[rng.uniform(5, 105, n), rng.integers(0, 7, n) * 5.0 + 8]  # scan lines
    else:
        ang, rad = rng.uniform(0, 2 * np.pi, n), rng.uniform(12, 28, n)  # annulus
        uv = np.c_[55 + rad * np.cos(ang), 35 + rad * np.sin(ang)]
    for alpha in (None, 0.25, 0):
        _check(uv, size, alpha)


def test_square_lattice_of_cocircular_points():
    """Every cell of a square lattice is four cocircular points: the triangulation is not
    unique, the union of the kept triangles is."""
    g = np.stack(np.meshgrid(np.arange(10, 50, 2.0), np.arange(8, 40, 2.0)), -1).reshape(-1, 2)
    got, want = _check(g, (50, 60), expect_area=39 * 31)  # x 10..48, y 8..38
    assert got[8:39, 10:49].all() and not got[:7].any() and not got[:, :9].any()
    # radius below the cells' circumradius (sqrt 2): no triangle kept, the points alone
    few = alpha_shape_mask(g, (50, 60), alpha=1 / 1.4)
    assert few.sum() == len(g)


def test_two_far_clusters_stay_apart():
    rng = np.random.default_rng(7)
    uv = np.r_[rng.normal([20, 25], 4, (300, 2)), rng.normal([90, 30], 4, (300, 2))]
    got, _ = _check(uv, (60, 120))
    assert got[:, 35:75].sum() == 0  # no triangle bridges the 70 px gap
    assert got[20:30, 15:25].all() and got[25:35, 85:95].all()


def test_single_point_and_collinear_points():
    size = (20, 30)
    one = alpha_shape_mask([[5.2, 7.0]], size)
    assert one.sum() == 1 and one[7, 5]
    line = alpha_shape_mask(np.c_[np.arange(3.0, 25.0), np.full(22, 11.0)], size)
    assert line[11, 3:25].all() and line.sum() == 22
    assert _reference(np.c_[np.arange(3.0, 25.0), np.full(22, 11.0)], size) is None
    diag = alpha_shape_mask(np.c_[np.arange(2.0, 15.0), np.arange(2.0, 15.0)], size)
    assert all(diag[i, i] for i in range(2, 15)) and diag.sum() == 13


def _former_dedup(uv, grid):
    """The lattice snapping as it was written before (``np.unique`` with first indices)."""
    q = np.round(uv / grid).astype(np.int64)
    q -= q.min(0)
    key = q[:, 0] * (int(q[:, 1].max()) + 1) + q[:, 1]
    _, first = np.unique(key, return_index=True)
    return q[first].astype(np.float64) * grid + np.round(uv.min(0) / grid) * grid


def test_lattice_snapping_equals_the_former_bit_for_bit():
    from seqshape.amodal.alpha import _dedup

    rng = np.random.default_rng(12)
    for k in range(60):
        n = int(rng.integers(1, 3000))
        uv = rng.normal(rng.uniform(-2000, 2000, 2), rng.uniform(0.05, 400), (n, 2))
        if k % 3 == 0:
            uv = np.round(uv)  # many points per cell
        for grid in (0.25, 0.1, 1.0):
            want, got = _former_dedup(uv, grid), _dedup(uv, grid)
            assert got.dtype == want.dtype and np.array_equal(got, want), (k, grid)
            # the independent snapping: the same cells (bit for bit on power-of-two lattices)
            np.testing.assert_allclose(got, _lattice(uv, grid), rtol=0, atol=1e-9)
            if grid != 0.1:
                np.testing.assert_array_equal(got, _lattice(uv, grid))
