"""The label diffusion's fast sweeps against the plain full-width loop, bit for bit (issue 17).

``propagate_labels`` sweeps each block of connected components on its own label columns and
sums the rows in numpy's order; every test here compares it, and ``pixel_labels``, with a
slow, obviously right reference written out below (full-width loop, per-point loop).
"""

import numpy as np
import pytest
import scipy.sparse as sp

from seqshape.amodal import diffusion as D


def _loop_reference(w, y, lam, iterations):
    """The former sweeps: the whole ``(N, C+1)`` label matrix every time."""
    lab, pull = y.copy(), lam * y
    for _ in range(iterations):
        lab = w @ lab
        lab += pull
        lab /= lab.sum(1, keepdims=True)
    return lab


def _pixel_labels_reference(uv, masks):
    """One point at a time."""
    n, c = len(uv), len(masks)
    y = np.zeros((n, c + 1))
    for i in range(n):
        if c:
            h, w = masks[0].shape
            col = min(max(int(np.round(uv[i, 0])), 0), w - 1)
            row = min(max(int(np.round(uv[i, 1])), 0), h - 1)
            for m in range(c):
                y[i, m] = float(masks[m][row, col])
        if y[i, :c].sum() == 0:
            y[i, c] = 1.0
        y[i] /= y[i].sum()
    return y


def _scene(seed, n_blobs=6, n_masks=5, size=(80, 120)):
    """Random blobs of points (some big, some small, one big background-only blob), a fake
    projection and random rectangular masks, some overlapping (points split between them)."""
    rng = np.random.default_rng(seed)
    parts = []
    for b in range(n_blobs):
        n = int(rng.integers(300, 700)) if b % 2 == 0 else int(rng.integers(5, 60))
        parts.append(rng.normal(rng.uniform(-30, 30, 3), rng.uniform(0.3, 1.0), (n, 3)))
    parts.append(rng.normal([100.0, 100.0, 0.0], 0.5, (400, 3)))  # far from every mask
    pts = np.vstack(parts)
    uv = np.c_[60 + 1.5 * pts[:, 1], 40 + 1.2 * pts[:, 2] + 0.3 * pts[:, 0]]
    uv[-400:] = [500.0, 500.0]  # outside the image: background label
    masks = []
    for _ in range(n_masks):
        m = np.zeros(size, dtype=bool)
        r0, c0 = rng.integers(0, size[0] - 20), rng.integers(0, size[1] - 30)
        m[r0:r0 + rng.integers(10, 40), c0:c0 + rng.integers(10, 60)] = True
        masks.append(m)
    return pts, uv, masks


@pytest.mark.parametrize("seed", range(5))
def test_propagation_equals_the_full_width_loop_bit_for_bit(seed):
    pts, uv, masks = _scene(seed)
    y = D.pixel_labels(uv, masks)
    w = D._knn_graph(pts, 10, 0.3, 1.0)
    blocks = D._blocks(w, y)
    assert len(blocks) >= 2 and any(len(cols) == 1 for _, _, cols in blocks)
    for lam, iterations in ((0.2, 30), (0.5, 3), (0.2, 0), (1e-3, 1)):
        ref = _loop_reference(w, y, lam, iterations)
        got = D.propagate_labels(w, y, lam, iterations)
        assert got.dtype == ref.dtype and np.array_equal(got, ref)


def test_propagation_hand_made_graph():
    # two components: a chain 0-1-2 (labels 0 and 1 meet) and an isolated pair 3-4 (background)
    # and an isolated point 5 (no edges at all)
    rows = [0, 1, 1, 2, 3, 4]
    cols = [1, 0, 2, 1, 4, 3]
    g = sp.csr_matrix((np.ones(6), (rows, cols)), shape=(6, 6))
    deg = np.asarray(g.sum(1)).ravel()
    w = (sp.diags(np.divide(1.0, deg, out=np.zeros(6), where=deg > 0)) @ g).tocsr()
    y = np.array([[1, 0, 0], [0.5, 0.5, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0]], float)
    got = D.propagate_labels(w, y, 0.2, 10)
    assert np.array_equal(got, _loop_reference(w, y, 0.2, 10))
    assert np.array_equal(got[3:], y[3:])  # one-label components keep exact one-hot rows
    assert got[1, 0] == got[1, 1]  # the symmetric middle of the chain


def test_full_width_sums_fallback_is_the_same(monkeypatch):
    pts, uv, masks = _scene(11)
    y = D.pixel_labels(uv, masks)
    w = D._knn_graph(pts, 10, 0.3, 1.0)
    monkeypatch.setitem(D._SUM_ORDER_OK, y.shape[1], False)
    assert np.array_equal(D.propagate_labels(w, y, 0.2, 30), _loop_reference(w, y, 0.2, 30))


@pytest.mark.parametrize("width", [1, 2, 3, 7, 8, 9, 15, 16, 17, 24, 33, 60])
def test_pairwise_sum_is_numpys_row_sum(width):
    rng = np.random.default_rng(width)
    a = rng.random((500, width)) * 10.0 ** rng.integers(-9, 3, (500, width))
    zero = rng.random(width) < 0.4
    a[:, zero] = 0.0
    got = D._pairwise_sum([None if z else a[:, j] for j, z in enumerate(zero)])
    got = np.zeros(500) if got is None else got
    assert np.array_equal(got, a.sum(1))
    assert D._sum_order_ok(width)


@pytest.mark.parametrize("order", ["C", "F", "strided"])
def test_pixel_labels_equal_the_per_point_loop(order):
    pts, uv, masks = _scene(3)
    uv = np.vstack([uv, [[-5.0, 3.0], [200.0, 90.0], [10.49, 20.5], [10.5, 20.51]]])
    masks[0][10:70, 20:100] = True
    masks[1] = masks[1] | masks[0]  # points inside two masks split their weight
    if order == "F":
        masks = [np.asfortranarray(m) for m in masks]
    elif order == "strided":
        masks = [np.repeat(np.repeat(m, 2, 0), 2, 1)[::2, ::2] for m in masks]
    assert all(m.flags.f_contiguous == (order == "F") for m in masks)
    got = D.pixel_labels(uv, masks)
    assert np.array_equal(got, _pixel_labels_reference(uv, masks))
    assert (got[:, :-1].sum(1) > 0).any() and (got[:, :-1] == 0.5).any()


def _diffuse_reference(points, uv, masks, k=10, sigma=0.3, max_edge=1.0, lam=0.2,
                       iterations=30, cluster_gap=0.5, cluster_gap_per_m=0.025):
    """``diffuse_labels`` as it was: per-point pixel labels and the full-width loop."""
    c = len(masks)
    y = _pixel_labels_reference(uv, masks)
    lab = _loop_reference(D._knn_graph(points, k, sigma, max_edge), y, lam, iterations)
    best = lab.argmax(1)
    labels = np.where(best == c, D.BACKGROUND, best)
    for m in range(c):
        idx = np.flatnonzero(labels == m)
        if cluster_gap > 0 and len(idx) > 1:
            gap = D.cluster_gap_for(points[idx], cluster_gap, cluster_gap_per_m)
            labels[idx[~D.vehicle_cluster(points[idx], gap)]] = D.BACKGROUND
    return labels


@pytest.mark.parametrize("seed", range(4))
def test_diffuse_labels_equal_the_former_pipeline(seed):
    pts, uv, masks = _scene(100 + seed)
    masks[0][:, :60] = True  # half the image: some blobs surely labelled
    got = D.diffuse_labels(pts, uv, masks)
    assert np.array_equal(got, _diffuse_reference(pts, uv, masks))
    assert (got >= 0).any() and (got == D.BACKGROUND).any()


@pytest.mark.parametrize("kernel", [True, False])
def test_product_equals_the_sparse_product(monkeypatch, kernel):
    rng = np.random.default_rng(7)
    sub = sp.random(300, 300, density=0.03, random_state=8, format="csr")
    x = rng.random((300, 3))
    if not kernel:
        monkeypatch.setattr(D, "_csr_matvecs", None)
    out = np.full((300, 3), np.nan)
    assert np.array_equal(D._product(sub, x, out), sub @ x)
    x1 = np.ascontiguousarray(x[:, :1])
    assert np.array_equal(D._product(sub, x1, np.empty((300, 1))), sub @ x1)
