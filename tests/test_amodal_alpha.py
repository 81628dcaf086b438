"""Alpha-shape masks: polygon recovery, convex hull, degenerate inputs."""

import cv2
import numpy as np
import pytest
from matplotlib.path import Path

from seqshape.amodal.alpha import alpha_shape_mask, auto_alpha_radius, circumradii

L_SHAPE = np.array([[50, 40], [350, 40], [350, 120], [180, 120], [180, 260], [50, 260]], float)


def _iou(a, b):
    return (a & b).sum() / (a | b).sum()


def _poly_mask(poly, size):
    m = np.zeros(size, np.uint8)
    cv2.fillPoly(m, [np.round(poly).astype(np.int32)], 1)
    return m.astype(bool)


def _sample_inside(poly, n, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = poly.min(0), poly.max(0)
    p = rng.uniform(lo, hi, size=(4 * n, 2))
    return p[Path(poly).contains_points(p)][:n]


def test_alpha_shape_recovers_concave_polygon():
    pts = _sample_inside(L_SHAPE, 8000)
    ref = _poly_mask(L_SHAPE, (300, 400))
    mask = alpha_shape_mask(pts, (300, 400))
    assert mask.dtype == bool and mask.shape == (300, 400)
    assert _iou(mask, ref) > 0.97
    # the convex hull fills the concavity: clearly worse, so the alpha rule does something
    hull = alpha_shape_mask(pts, (300, 400), alpha=0)
    assert _iou(hull, ref) < 0.85
    assert hull.sum() > mask.sum()


def test_alpha_shape_convex_no_holes():
    sq = np.array([[20, 20], [80, 20], [80, 60], [20, 60]], float)
    pts = _sample_inside(sq, 3000, seed=1)
    mask = alpha_shape_mask(pts, (100, 100))
    # interior fully filled (no holes from the batched fill)
    assert mask[24:57, 24:77].all()
    assert _iou(mask, _poly_mask(sq, (100, 100))) > 0.95


def test_alpha_shape_clips_outside_points():
    sq = np.array([[-50, -50], [50, -50], [50, 50], [-50, 50]], float)
    pts = _sample_inside(sq, 4000, seed=2)
    mask = alpha_shape_mask(pts, (100, 100))
    assert mask[2:45, 2:45].all() and not mask[60:, 60:].any()


def test_degenerate_inputs():
    size = (20, 30)
    assert not alpha_shape_mask(np.zeros((0, 2)), size).any()
    one = alpha_shape_mask([[5.2, 7.0]], size)
    assert one.sum() == 1 and one[7, 5]
    line = alpha_shape_mask([[2, 3], [10, 3], [6, 3], [4, 3]], size)  # collinear
    assert line[3, 2:11].all() and line.sum() == 9
    two = alpha_shape_mask([[0, 0], [0, 5]], size)
    assert two[0:6, 0].all() and two.sum() == 6
    assert not alpha_shape_mask([[np.nan, 1.0]], size).any()
    with pytest.raises(ValueError):
        alpha_shape_mask([[0, 0], [1, 1], [0, 1]], size, alpha=-1)


def test_circumradius_and_auto_radius():
    tri = np.array([[[0, 0], [2, 0], [0, 2]]], float)  # right triangle: R = hypotenuse / 2
    assert circumradii(tri)[0] == pytest.approx(np.sqrt(2))
    assert np.isinf(circumradii(np.array([[[0, 0], [1, 1], [2, 2]]], float))[0])
    grid = np.stack(np.meshgrid(np.arange(20), np.arange(20)), -1).reshape(-1, 2) * 2.0
    assert auto_alpha_radius(grid) == pytest.approx(6.0)  # 3 x spacing 2 (> 3 x R = 4.24)
    rings = np.stack(np.meshgrid(np.arange(0, 100, 0.5), np.arange(0, 50, 5.0)), -1)
    r = auto_alpha_radius(rings.reshape(-1, 2))  # scan lines: 0.5 px along, 5 px across
    assert r > 5.0 and r < 10.0


def _reference_mask(uv, size):
    """The alpha mask with scipy's Delaunay (the implementation before Subdiv2D)."""
    import cv2

    from seqshape.amodal import alpha as A

    pts = A._dedup(np.asarray(uv, float), A.GRID_PX)
    verts = A.delaunay_triangles_scipy(pts)
    radii = A.circumradii(verts)
    keep = radii < A.auto_alpha_radius(pts, radii, distinct=True)
    mask = np.zeros(size, np.uint8)
    cv2.fillPoly(mask, list(A._to_fixed(verts[keep].reshape(-1, 2), size).reshape(-1, 3, 2)), 1,
                 lineType=cv2.LINE_8, shift=A._SHIFT)
    fixed = (A._to_fixed(pts, size) + (1 << (A._SHIFT - 1))) >> A._SHIFT
    ok = (fixed[:, 0] >= 0) & (fixed[:, 0] < size[1]) & (fixed[:, 1] >= 0) & (fixed[:, 1] < size[0])
    mask[fixed[ok, 1], fixed[ok, 0]] = 1
    return mask.astype(bool)


def test_fast_triangulation_matches_scipy_reference():
    """Subdiv2D-based masks equal the scipy-Delaunay ones (random blobs, rings, off-image)."""
    from seqshape.amodal.alpha import alpha_shape_mask

    rng = np.random.default_rng(3)
    size = (120, 200)
    for trial in range(12):
        n = int(rng.integers(20, 1500))
        if trial % 3 == 0:  # annulus: concave hole
            ang, rad = rng.uniform(0, 2 * np.pi, n), rng.uniform(20, 40, n)
            uv = np.c_[100 + rad * np.cos(ang), 60 + rad * np.sin(ang)]
        elif trial % 3 == 1:  # scan-line-like rows, partly outside the image
            uv = np.c_[rng.uniform(-30, 230, n), rng.integers(0, 12, n) * 6.0 + 40]
        else:
            uv = rng.normal([100, 60], [30, 15], (n, 2))
        assert np.array_equal(alpha_shape_mask(uv, size), _reference_mask(uv, size)), trial
