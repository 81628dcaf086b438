"""Label diffusion and ground removal on hand-built point sets; frame association."""

import numpy as np

from seqshape.amodal.association import Detection, associate
from seqshape.amodal.diffusion import (
    BACKGROUND,
    components,
    diffuse_labels,
    ground_mask,
    grow_instances,
    largest_cluster,
)
from seqshape.testing import box_shell


def blob(centre, n, rng, spread=(1.0, 0.5, 0.4)):
    """Points filling a box of half-extents 2 * spread around centre (a vehicle-sized blob)."""
    return rng.uniform(np.subtract(centre, 2 * np.asarray(spread)),
                       np.add(centre, 2 * np.asarray(spread)), size=(n, 3))


def test_diffusion_two_separated_objects_with_sloppy_masks():
    rng = np.random.default_rng(0)
    a, b = blob([10, 2, 0], 400, rng), blob([15, -3, 0], 400, rng)
    wall = rng.uniform([30, -10, -1], [31, 10, 2], size=(600, 3))  # background behind
    pts = np.vstack([a, b, wall])
    truth = np.r_[np.zeros(400), np.ones(400), np.full(600, BACKGROUND)]
    # a fake "projection": u from y, v from z; masks are the objects' boxes dilated so that
    # wall points fall inside them too, and 15% of each object's points fall outside
    uv = np.c_[100 - 10 * pts[:, 1], 50 - 10 * pts[:, 2]]
    masks = []
    for obj in (a, b):
        ouv = np.c_[100 - 10 * obj[:, 1], 50 - 10 * obj[:, 2]]
        lo, hi = np.quantile(ouv, 0.08, axis=0), np.quantile(ouv, 0.92, axis=0)
        m = np.zeros((100, 200), bool)
        m[int(lo[1]) - 3:int(hi[1]) + 3, int(lo[0]) - 3:int(hi[0]) + 3] = True
        masks.append(m)
    col = np.clip(np.round(uv[:, 0]).astype(int), 0, 199)
    row = np.clip(np.round(uv[:, 1]).astype(int), 0, 99)
    inside = masks[0][row, col] | masks[1][row, col]
    assert inside[800:].sum() > 50  # the masks do cover wall points: diffusion must fix them
    labels = diffuse_labels(pts, uv, masks)
    assert np.array_equal(labels, truth)


def test_diffusion_edge_cases():
    assert diffuse_labels(np.zeros((0, 3)), np.zeros((0, 2)), [np.ones((5, 5), bool)]).size == 0
    assert (diffuse_labels(np.zeros((3, 3)), np.zeros((3, 2)), []) == BACKGROUND).all()


def test_ground_mask_plane_and_objects():
    rng = np.random.default_rng(1)
    ground = np.c_[rng.uniform(0, 40, 3000), rng.uniform(-10, 10, 3000), np.zeros(3000)]
    ground[:, 2] = -1.73 + 0.02 * ground[:, 0] / 40 + rng.normal(0, 0.02, 3000)  # slight slope
    car = blob([12, 0, -1.0], 500, rng, (1.0, 0.5, 0.3))
    car = car[car[:, 2] > -1.73 + 0.3]
    g = ground_mask(np.vstack([ground, car]))
    assert g[:3000].mean() > 0.99 and not g[3000:].any()


def test_largest_cluster():
    pts = np.array([[0, 0, 0], [0.3, 0, 0], [0.6, 0, 0], [5, 5, 5]], float)
    assert largest_cluster(pts, 0.5).tolist() == [True, True, True, False]


def test_association_crossing_tracks():
    # two vehicles at constant velocity, detections shuffled per frame
    masks = np.zeros((2, 10, 10), bool)
    frames = []
    for f in range(6):
        c0, c1 = np.array([f * 1.5, 0.0, 0.0]), np.array([20 - f * 1.5, 3.5, 0.0])
        dets = [Detection(f, c0, masks[0]), Detection(f, c1, masks[1])]
        frames.append(dets[::-1] if f % 2 else dets)
    ids = associate(frames, gate=3.0)
    first = {0: ids[0][0], 1: ids[0][1]}
    for f, row in enumerate(ids):
        want = [first[1], first[0]] if f % 2 else [first[0], first[1]]
        assert row == want
    # a gap longer than max_age starts a new track
    late = [[Detection(0, np.zeros(3), masks[0])], [], [], [], [], [],
            [Detection(6, np.zeros(3), masks[0])]]
    assert associate(late, max_age=2) == [[0], [], [], [], [], [], [1]]


def _ransac_loop(cand, rng, iterations, threshold, max_tilt_deg):
    """The one-hypothesis-at-a-time RANSAC that _ransac_plane vectorises (reference)."""
    best, best_count = None, 0
    cos_tilt = np.cos(np.radians(max_tilt_deg))
    for _ in range(iterations):
        tri = cand[rng.choice(len(cand), 3, replace=False)]
        n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        norm = np.linalg.norm(n)
        if norm < 1e-9 or abs(n[2]) / norm < cos_tilt:
            continue
        n = n / norm * np.sign(n[2])
        count = int(np.sum(np.abs(cand @ n - n @ tri[0]) < threshold))
        if count > best_count:
            best, best_count = (n, float(-n @ tri[0])), count
    return best, best_count


def test_vectorised_ransac_equals_loop():
    from seqshape.amodal.diffusion import _ransac_plane

    gen = np.random.default_rng(5)
    for trial in range(6):
        ground = np.c_[gen.uniform(-20, 20, (400, 2)), gen.normal(-1.7, 0.05, 400)]
        clutter = gen.uniform([-20, -20, -2], [20, 20, 1], (int(gen.integers(50, 600)), 3))
        cand = np.vstack([ground, clutter])
        if trial == 5:  # only steep walls: no valid hypothesis
            cand = np.c_[gen.uniform(-1, 1, 300), np.full(300, 3.0), gen.uniform(-2, 1, 300)]
        a = _ransac_plane(cand, np.random.default_rng(trial), 60, 0.2, 10.0)
        b = _ransac_loop(cand, np.random.default_rng(trial), 60, 0.2, 10.0)
        assert a[1] == b[1]
        if b[0] is None:
            assert a[0] is None
        else:
            np.testing.assert_allclose(a[0][0], b[0][0], atol=1e-12)
            assert abs(a[0][1] - b[0][1]) < 1e-9


def test_components_link_sparse_scan_lines():
    # two dense scan lines 0.6 m apart: every point's 8 nearest neighbours lie on its own line,
    # yet the lines are one object at a 0.75 m gap (and two at 0.5 m)
    x = np.linspace(0, 4, 400)
    pts = np.r_[np.c_[x, np.zeros_like(x), np.zeros_like(x)],
                np.c_[x, np.zeros_like(x), np.full_like(x, 0.6)]]
    assert len(np.unique(components(pts, 0.75))) == 1
    assert len(np.unique(components(pts, 0.5))) == 2


def test_grow_instances_recovers_the_cut_part_only():
    car = box_shell(3000, 0, (4.0, 1.8, 1.5)) + np.array([8.0, 0.0, 0.0])
    other = box_shell(1000, 1, (4.0, 1.8, 1.5)) + np.array([8.0, 4.0, 0.0])  # 2.2 m away
    seen = car[:, 0] > 9.0  # the part inside the image
    grown = grow_instances([car[seen]], np.r_[car[~seen], other], cluster_gap=0.5)[0]
    assert len(grown) == len(car)
    assert np.all(grown[:, 1] < 1.0)  # nothing of the other car


def test_voxel_ids_equal_numpy_unique_rows():
    from seqshape.amodal.diffusion import _voxel_ids

    rng = np.random.default_rng(3)
    for keys in (rng.integers(-50, 50, (500, 3)), rng.integers(-3, 3, (200, 3)),
                 np.array([[5, -2, 7]]), np.array([[0, 0, 2**40], [0, 1, -2**40]])):
        ref = np.unique(keys, axis=0, return_inverse=True)[1].ravel()
        assert np.array_equal(_voxel_ids(keys), ref)


def _components_reference(points, gap):
    """The former components: voxel means by ``np.add.at``, voxel ids by ``np.unique`` of
    the key rows, the graph through scipy's COO constructor."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) <= 1:
        return np.zeros(len(points), dtype=np.int64)
    keys = np.floor(points / (gap / 2)).astype(np.int64)
    inv = np.unique(keys, axis=0, return_inverse=True)[1].ravel()
    nv = int(inv.max()) + 1
    reps = np.zeros((nv, 3))
    np.add.at(reps, inv, points)
    reps /= np.bincount(inv, minlength=nv)[:, None]
    pairs = cKDTree(reps).query_pairs(gap, output_type="ndarray")
    g = sp.csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(nv, nv))
    return connected_components(g, directed=False)[1][inv]


def _grow_reference(parts, outside, cluster_gap=0.5, cluster_gap_per_m=0.025, max_grow=5.0):
    """The former grow_instances: every outside point queried against every instance, and
    every distance compared."""
    from scipy.spatial import cKDTree

    from seqshape.amodal.diffusion import cluster_gap_for

    outside = np.asarray(outside, dtype=np.float64).reshape(-1, 3)
    parts = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in parts]
    if len(outside) == 0 or not any(len(p) for p in parts):
        return parts
    best, best_d = np.full(len(outside), -1), np.full(len(outside), np.inf)
    for m, p in enumerate(parts):
        if len(p) == 0:
            continue
        d, _ = cKDTree(p).query(outside, distance_upper_bound=max_grow)
        cand = np.flatnonzero(np.isfinite(d))
        if len(cand) == 0:
            continue
        comp = _components_reference(np.concatenate([p, outside[cand]]),
                                     cluster_gap_for(p, cluster_gap, cluster_gap_per_m))
        sel = cand[np.isin(comp[len(p):], np.unique(comp[:len(p)]))]
        closer = d[sel] < best_d[sel]
        best[sel[closer]], best_d[sel[closer]] = m, d[sel][closer]
    return [np.concatenate([p, outside[best == m]]) for m, p in enumerate(parts)]


def test_grow_instances_equals_the_unfiltered_reference():
    rng = np.random.default_rng(5)
    # two vehicles cut by the image border, a third far away, and scattered clutter
    a, b, c = blob([8, 6, 0], 300, rng), blob([9, 9.5, 0], 300, rng), blob([40, -20, 0], 50, rng)
    clutter = rng.uniform([-60, -60, -2], [60, 60, 3], (20000, 3))
    outside = np.vstack([a[150:], b[150:], clutter])
    lone = blob([200, 200, 0], 30, rng)  # nothing outside the image within its reach
    parts = [a[:150], b[:150], c[:10], np.zeros((0, 3)), lone]
    fast, ref = grow_instances(parts, outside), _grow_reference(parts, outside)
    for f, r in zip(fast, ref, strict=True):
        assert np.array_equal(f, r)
    assert len(fast[0]) > 250 and len(fast[1]) > 250  # the cut parts did come back
    assert np.array_equal(fast[4], lone)



# ------------------------------------------------ grow_instances and components: bit for bit


def _assert_grow_equal(parts, outside, **kw):
    fast, ref = grow_instances(parts, outside, **kw), _grow_reference(parts, outside, **kw)
    assert len(fast) == len(ref)
    for f, r in zip(fast, ref, strict=True):
        assert f.dtype == r.dtype == np.float64 and f.shape == r.shape
        assert np.array_equal(f, r)
    return fast


def _scene(rng, n_clutter=6000):
    """Vehicle-like blobs cut by the image border (part in ``parts``, the rest outside),
    two of them touching, one duplicated as an overlapping instance, and clutter."""
    cars = [blob(c, n, rng) for c, n in (([8, 6, 0], 1500), ([9, 9.5, 0], 900),
                                         ([20, -4, 0.5], 400), ([40, -20, 0], 80))]
    parts, rest = [], []
    for car in cars:
        seen = car[:, 0] > np.median(car[:, 0])
        parts.append(car[seen])
        rest.append(car[~seen])
    parts.append(parts[0][::7].copy())  # a second mask on the first vehicle: ties and overlaps
    clutter = rng.uniform([-10, -30, -1.5], [60, 30, 2.5], (n_clutter, 3))
    return parts, np.vstack(rest + [clutter])


def test_components_equal_the_reference():
    rng = np.random.default_rng(11)
    clouds = [rng.uniform(-5, 5, (3000, 3)), blob([10, -3, 0], 2000, rng),
              np.round(rng.uniform(0, 3, (1500, 3)), 1),  # many points on voxel borders
              np.vstack([blob([0, 0, 0], 500, rng)] * 2),  # duplicated points
              rng.uniform(-1e4, 1e4, (300, 3)),  # a sparse span: the sorting route
              np.zeros((1, 3)), np.zeros((0, 3)), np.array([[1.0, 2, 3], [1.1, 2, 3]])]
    for pts in clouds:
        for gap in (0.3, 0.5, 1.25, 4.0):
            assert np.array_equal(components(pts, gap), _components_reference(pts, gap))


def test_voxel_components_labels_follow_the_points():
    from seqshape.amodal.diffusion import _voxel_components

    rng = np.random.default_rng(12)
    pts = rng.uniform(0, 8, (4000, 3))
    comp, inv = _voxel_components(pts, 0.4)
    assert np.array_equal(comp[inv], _components_reference(pts, 0.4))


def test_surely_agrees_with_the_tree():
    """Points settled by the grid bounds get the tree's answer, with points at exactly the
    cut, just inside and just outside it, and on cube borders."""
    from scipy.spatial import cKDTree

    from seqshape.amodal.diffusion import _columns, _surely

    rng = np.random.default_rng(13)
    line = np.c_[np.zeros(41), np.arange(41) * 0.25, np.zeros(41)]  # 0..10 m along y
    offsets = np.array([[5, 0, 0], [3, 0, 4], [0, 0, 5], [-4, 0, 3], [4.999999, 0, 0],
                        [5.000001, 0, 0], [2.5, 0, 0], [7, 0, 0], [0, 0, -5]], float)
    lattice = (line[:, None, :] + offsets[None]).reshape(-1, 3)
    for p, q, max_grow in ((line, lattice, 5.0), (blob([5, 5, 0], 3000, rng),
                                                  rng.uniform(-5, 15, (20000, 3)), 5.0),
                           (blob([5, 5, 0], 800, rng),
                            rng.uniform([0, 1, -3], [10, 9, 3], (5000, 3)), 2.5),
                           (np.round(rng.uniform(0, 4, (500, 3)), 1),
                            np.round(rng.uniform(-1.5, 5.5, (8000, 3)), 1), 2.0)):
        d, _ = cKDTree(p).query(q, distance_upper_bound=max_grow)
        for cells in (4, 16, 40):  # (40: too many cubes for the line; nothing settled)
            within, beyond = _surely(_columns(p), _columns(q), max_grow, max_grow / cells)
            assert not (within & beyond).any()
            assert np.isfinite(d[within]).all() and np.isinf(d[beyond]).all()
            if cells == 16 and p is not line:  # (the line's points are mostly at the cut)
                assert (within | beyond).mean() > 0.5  # it does settle most of them



def test_surely_bounds_are_tight_at_cube_corners():
    """Where the grid bounds are tight (p and q at the corners of their cubes, on the
    diagonal), a point a hair inside (outside) max_grow is not called beyond (within)."""
    from scipy.spatial import cKDTree

    from seqshape.amodal.diffusion import _columns, _surely

    diag, eps, delta = np.ones(3), 1e-9, 1e-7
    for cell, k in ((0.25, 12), (0.3125, 9), (0.5, 3)):
        origin = np.zeros((1, 3))  # sets the grid's origin: cube 0 is [0, cell)^3
        cases = (  # (p, q, max_grow): at the lower bound, then at the upper bound
            ((cell - eps) * diag, k * cell * diag, (k - 1) * cell * np.sqrt(3) + delta),
            (eps * diag, ((k + 1) * cell - eps) * diag, (k + 1) * cell * np.sqrt(3) - delta))
        for p, q, max_grow in cases:
            q = np.vstack([origin, q, q + 1e-4])
            within, beyond = _surely(_columns(p[None]), _columns(q), max_grow, cell)
            d, _ = cKDTree(p[None]).query(q, distance_upper_bound=max_grow)
            assert np.isfinite(d[within]).all() and np.isinf(d[beyond]).all()


def test_grow_instances_equal_the_reference_on_random_scenes():
    for seed in range(4):
        rng = np.random.default_rng(100 + seed)
        parts, outside = _scene(rng)
        for kw in ({}, {"max_grow": 2.0}, {"max_grow": 0.3}, {"max_grow": 12.0},
                   {"cluster_gap": 1.0, "cluster_gap_per_m": 0.05}):
            _assert_grow_equal(parts, outside, **kw)
        _assert_grow_equal(parts[::-1], outside)  # the duplicate instance first
        _assert_grow_equal(parts, outside, max_grow=np.inf)
        _assert_grow_equal(parts, outside, max_grow=0.0)
        _assert_grow_equal([p.astype(np.float32) for p in parts], outside.astype(np.float32))


def test_grow_instances_cut_at_exactly_max_grow():
    """Outside points at exactly max_grow from an instance (3-4-5 offsets: exact squared
    distances) are not reached, points a hair closer are, on the grid route (many points in
    reach) and the tree route (few); a large cluster gap links everything within reach."""
    rng = np.random.default_rng(14)
    line = np.c_[np.zeros(81), np.arange(81) * 0.125, np.zeros(81)]
    offsets = np.array([[5, 0, 0], [3, 0, 4], [0, 0, 5], [-4, 0, 3], [-3, 0, -4],
                        [4.999999999, 0, 0], [5.000000001, 0, 0], [0, 0, 4.99999999999],
                        [2.5, 0, 0], [1, 0, 1], [6, 0, 0]], float)
    exact = (line[:, None, :] + offsets[None]).reshape(-1, 3)
    clutter = rng.uniform([-8, -3, -8], [8, 13, 8], (3000, 3))
    for outside in (exact, np.vstack([exact, clutter]), exact[::40]):
        for gap in (0.5, 20.0):
            grown = _assert_grow_equal([line], outside, cluster_gap=gap)[0]
            if gap == 20.0:
                d = np.linalg.norm(grown[len(line):, None] - line[None], axis=2).min(1)
                assert d.max() < 5.0 and len(grown) > len(line)
        _assert_grow_equal([line[:40], line[40:]], outside, cluster_gap=20.0)


def test_grow_instances_ties_go_to_the_first_instance():
    """Outside points equally near to two instances (mirror images, or the same points twice)
    go to the first of them, and a nearer later instance takes them."""
    y, z = np.meshgrid(np.arange(30) * 0.2, np.arange(10) * 0.2)
    plane = np.c_[np.zeros(y.size), y.ravel(), z.ravel()]
    left, right = plane - [1.0, 0, 0], plane + [1.0, 0, 0]
    middle = np.vstack([plane + [dx, 0, 0] for dx in (0.0, 0.5, -0.5, 0.25)])
    for parts in ([left, right], [right, left], [left, left.copy()], [left, right, left.copy()],
                  [np.zeros((0, 3)), right, left]):
        grown = _assert_grow_equal(parts, middle, cluster_gap=3.0)
        assert sum(len(g) for g in grown) == sum(len(p) for p in parts) + len(middle)
    grown = grow_instances([left, left.copy()], middle, cluster_gap=3.0)
    assert len(grown[1]) == len(left)  # every tie kept by the first
    big = np.vstack([middle, np.random.default_rng(15).uniform(-4, 4, (3000, 3))])
    for parts in ([left, right], [left, left.copy(), right]):  # the grid route
        _assert_grow_equal(parts, big, cluster_gap=3.0)


def test_grow_instances_edge_cases():
    rng = np.random.default_rng(16)
    pts = blob([5, 0, 0], 200, rng)
    empty = np.zeros((0, 3))
    for parts, outside in (([pts], empty), ([], pts), ([empty, empty], pts),
                           ([empty, pts[:1]], pts[1:]), ([pts[:100]], pts[100:101]),
                           ([pts[:100], empty], pts[100:]), ([pts[:50], pts[50:100]], pts[100:]),
                           ([pts.astype(np.float32)[:100]], pts[100:].astype(np.float32)),
                           ([pts[:100].ravel()], list(map(tuple, pts[100:])))):
        _assert_grow_equal(parts, outside)
    with_nan = pts[:100].copy()
    with_nan[3] = np.nan  # no box to reach into: nothing grown (and no tree), as before
    fast = grow_instances([with_nan, pts[100:150]], pts[150:])
    assert np.array_equal(fast[0], with_nan, equal_nan=True)
    assert np.array_equal(fast[1], _grow_reference([pts[100:150]], pts[150:])[0])
