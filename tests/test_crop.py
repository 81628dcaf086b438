"""The one crop function (seqshape.data.crop) on hand-made sweeps with known ground, and the
fast crop against the former implementation (kept below as the slow exact reference)."""

import numpy as np
import pytest

from seqshape.data.crop import (
    CropConfig,
    SweepIndex,
    _FreshRng,
    _yaw_matrix,
    crop_vehicle,
    crop_vehicles,
    local_ground,
)
from seqshape.data.ground import _triples
from seqshape.errors import ConfigError
from seqshape.geometry import canonical_to_sensor, sensor_to_canonical, yaw_to_rotmat

POSE = np.array([10.0, 3.0, -1.0, 0.4])  # box centre; bottom at z = -1.75 on flat ground
SIZE = np.array([4.5, 1.8, 1.5])


def _ground(slope: float = 0.0, height: float = -1.75, seed: int = 0) -> np.ndarray:
    """A grid of road returns z = height + slope * (x - 10) (+- 1 cm noise) around the box."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(2.0, 18.0, 0.15), np.arange(-5.0, 11.0, 0.15)), -1)
    g = g.reshape(-1, 2)
    z = height + slope * (g[:, 0] - 10.0) + rng.normal(0, 0.01, len(g))
    return np.c_[g, z]


def _body(seed: int = 1) -> np.ndarray:
    """Vehicle returns in the canonical frame: a broadside of dense sills/wheels near the
    bottom (a flat, horizontal-ish band that a naive plane fit takes for the road) and the
    upper body."""
    rng = np.random.default_rng(seed)
    sills = np.c_[rng.uniform(-2.2, 2.2, 400), rng.uniform(-0.9, 0.9, 400),
                  rng.uniform(-0.52, -0.48, 400)]
    upper = np.c_[rng.uniform(-2.2, 2.2, 300), np.full(300, -0.9), rng.uniform(-0.4, 0.7, 300)]
    return np.vstack([sills, upper])


def test_flat_ground_is_removed_and_the_vehicle_kept():
    body = canonical_to_sensor(_body(), POSE)
    sweep = np.vstack([_ground(), body]).astype(np.float32)
    out = crop_vehicle(sweep, POSE, SIZE)
    assert len(out) == len(body)  # every body point (>= 0.2 m above the road) and no road point
    np.testing.assert_allclose(np.sort(out[:, 0]), np.sort(body[:, 0].astype(np.float32)))


def test_the_local_plane_ignores_the_vehicles_own_lower_body():
    sweep = np.vstack([_ground(), canonical_to_sensor(_body(), POSE)])
    n, d = local_ground(sweep, POSE, SIZE)
    height_at_box = float(n @ POSE[:3] + d) - SIZE[2] / 2  # box bottom above the plane
    assert abs(height_at_box) < 0.02
    assert n[2] > 0.999


def test_a_slope_is_followed_where_a_box_bottom_cut_is_not():
    slope = 0.08  # 8 % grade: the road is 18 cm higher at the front of the box than at the centre
    ground = _ground(slope=slope)
    body = canonical_to_sensor(_body(), POSE)
    body[:, 2] += slope * (body[:, 0] - 10.0)  # the car stands on the slope
    sweep = np.vstack([ground, body]).astype(np.float32)
    # the box covers the road under the car: road points reach into the box
    plane = crop_vehicle(sweep, POSE, SIZE + [0, 0, 0.4])
    box = crop_vehicle(sweep, POSE, SIZE + [0, 0, 0.4], CropConfig(ground="box"))
    road_in = lambda pts: int(np.sum(np.abs(  # noqa: E731
        pts[:, 2] - (-1.75 + slope * (pts[:, 0] - 10.0))) < 0.05))
    assert road_in(plane) == 0
    assert road_in(box) > 20


def test_fallbacks_and_modes():
    body = canonical_to_sensor(_body(), POSE)
    # no road returns around the box: the sweep plane given by the caller is used, lazily
    calls = []

    def sweep_plane():
        calls.append(1)
        return np.array([0.0, 0.0, 1.0]), 1.75

    out = crop_vehicle(body.astype(np.float32), POSE, SIZE, sweep_plane=sweep_plane)
    assert calls == [1] and len(out) == len(body)
    # no plane at all: cut at the box bottom + box_ground (0.15): the sills 0.23-0.27 m up stay
    out = crop_vehicle(body.astype(np.float32), POSE, SIZE)
    assert len(out) == len(body)
    sweep = np.vstack([_ground(), body]).astype(np.float32)
    assert len(crop_vehicle(sweep, POSE, SIZE, CropConfig(ground="none"))) > len(body)
    empty = crop_vehicle(np.zeros((0, 4), np.float32), POSE, SIZE)
    assert empty.shape == (0, 3) and empty.dtype == np.float32
    with pytest.raises(ConfigError):
        CropConfig(ground="flat")


def test_margin_is_per_side_and_deterministic():
    pts = canonical_to_sensor(np.array([[2.25 + 0.15, 0.0, 0.0], [2.25 + 0.25, 0.0, 0.0],
                                        [0.0, 0.0, 0.75 + 0.05], [0.0, 0.0, 0.75 + 0.15]]), POSE)
    sweep = np.vstack([_ground(), pts]).astype(np.float32)
    out = crop_vehicle(sweep, POSE, SIZE)  # margin 0.2 in x/y, 0.1 in z
    assert len(out) == 2
    np.testing.assert_array_equal(out, crop_vehicle(sweep, POSE, SIZE))


def _street(seed: int, n_boxes: int = 12):
    """A float32 (N, 4) sweep of a road with ``n_boxes`` vehicles, their poses and sizes
    (some far from every point, some overlapping), plus points exactly on the squares the
    crop scans (``|x - cx| == reach``)."""
    rng = np.random.default_rng(seed)
    poses = np.c_[rng.uniform(-30, 30, (n_boxes, 2)), rng.uniform(-1.2, -0.8, n_boxes),
                  rng.uniform(-np.pi, np.pi, n_boxes)]
    poses[0, :2] = [500.0, -500.0]  # nothing near it
    poses[1] = poses[2] + [1.0, 0.5, 0.0, 0.3]  # overlapping boxes
    sizes = np.c_[rng.uniform(3.5, 12, n_boxes), rng.uniform(1.6, 2.6, n_boxes),
                  rng.uniform(1.4, 3.5, n_boxes)]
    parts = [np.c_[rng.uniform(-45, 45, (20000, 2)), -1.75 + rng.normal(0, 0.02, 20000)]]
    for pose, size in zip(poses, sizes, strict=True):
        body = rng.uniform(-0.55, 0.55, (300, 3)) * size
        parts.append(canonical_to_sensor(body, pose))
        reach = float(np.hypot(size[0] / 2, size[1] / 2)) + 2.0
        parts.append(np.c_[pose[0] + reach * np.array([1, -1, 1, -1]),
                           pose[1] + reach * np.array([1, 1, -1, -1]), np.full(4, -1.0)])
    pts = np.vstack(parts)
    return np.c_[pts, rng.random(len(pts))].astype(np.float32), poses, sizes


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_crop_vehicles_equals_crop_vehicle_box_by_box(seed):
    sweep, poses, sizes = _street(seed)
    plane = (np.array([0.0, 0.0, 1.0]), 1.75)
    for cfg in (CropConfig(), CropConfig(ground="box"), CropConfig(ground="none", margin=0.5),
                CropConfig(context=0.0, min_ground_points=5)):
        got = crop_vehicles(sweep, poses, sizes, cfg, sweep_plane=plane)
        assert len(got) == len(poses)
        for out, pose, size in zip(got, poses, sizes, strict=True):
            want = crop_vehicle(sweep, pose, size, cfg, sweep_plane=plane)
            assert out.dtype == np.float32 and out.shape == want.shape
            np.testing.assert_array_equal(out, want)  # the same points in the same order
    assert sum(len(c) for c in got) > 1000


def test_crop_vehicles_other_dtypes_non_finite_points_and_empty_input():
    sweep, poses, sizes = _street(4, n_boxes=6)
    bad = sweep.copy()
    bad[::97, 0] = np.nan
    bad[::89, 1] = np.inf
    for pts in (sweep.astype(np.float64), bad, np.round(sweep * 10).astype(np.int32)):
        got = crop_vehicles(pts, poses, sizes)
        for out, pose, size in zip(got, poses, sizes, strict=True):
            np.testing.assert_array_equal(out, crop_vehicle(pts, pose, size))
    assert crop_vehicles(sweep, np.zeros((0, 4)), np.zeros((0, 3))) == []
    empty = crop_vehicles(np.zeros((0, 4), np.float32), poses, sizes)
    assert [c.shape for c in empty] == [(0, 3)] * len(poses)
    nowhere = np.full((5, 4), np.nan, np.float32)
    assert all(len(c) == 0 for c in crop_vehicles(nowhere, poses, sizes))


def test_sweep_index_rows_hold_every_point_of_the_squares():
    rng = np.random.default_rng(7)
    pts = rng.uniform(-80, 80, (30000, 3)).astype(np.float32)
    index = SweepIndex(pts, cell=3.0)
    centres, reaches = rng.uniform(-90, 90, (40, 2)), rng.uniform(0.5, 9.0, 40)
    rows = index.rows(centres, reaches)
    assert np.all(np.diff(rows) > 0) and len(rows) < len(pts)
    inside = np.zeros(len(pts), dtype=bool)
    for c, r in zip(centres, reaches, strict=True):
        inside |= np.all(np.abs(pts[:, :2] - c) <= r, axis=1)
    assert set(np.flatnonzero(inside)) <= set(rows)
    wide = SweepIndex(np.array([[0.0, 0.0, 0.0], [1e5, 1e5, 0.0]]), max_cells=100)
    assert wide.cell == 1000.0 and list(wide.rows([[1e5, 1e5]], [1.0])) == [1]


# --- The former implementation, kept as the slow exact reference --------------------------
# crop_vehicle as it was before the crop got faster (one box, the whole sweep scanned and
# transformed with sensor_to_canonical, boolean row selections, np.all over rows of three, a
# new generator per box) with the RANSAC of seqshape.data.ground as it was then (np.cross,
# the column sums of each block's mask, the broadcast differences in _fit_plane). The former
# crop_vehicles gave crop_vehicle's crops (test above), so the new crop_vehicles and
# crop_vehicle must give these, bit for bit.


def _ref_inlier_counts(cand, n, offs, threshold, block=512):
    nt = np.ascontiguousarray(n.T)
    counts = np.zeros(len(offs), dtype=np.int64)
    dist = np.empty((min(block, len(cand)), len(offs)))
    inl = np.empty(dist.shape, dtype=bool)
    for start in range(0, len(cand), block):
        rows = cand[start:start + block]
        d, m = dist[:len(rows)], inl[:len(rows)]
        np.matmul(rows, nt, out=d)
        d -= offs
        np.abs(d, out=d)
        np.less(d, threshold, out=m)
        counts += np.add.reduce(m.view(np.uint8), axis=0, dtype=np.int64)
    return counts


def _ref_ransac_plane(cand, rng, iterations, threshold, max_tilt_deg):
    if len(cand) < 3 or iterations < 1:
        return None, 0
    tri = cand[_triples(rng, len(cand), iterations)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = (norm >= 1e-9) & (np.abs(n[:, 2]) >= np.cos(np.radians(max_tilt_deg)) * norm)
    if not ok.any():
        return None, 0
    n, tri = n[ok] / norm[ok, None] * np.sign(n[ok, 2])[:, None], tri[ok]
    offs = np.einsum("ij,ij->i", n, tri[:, 0])
    counts = _ref_inlier_counts(cand, n, offs, threshold)
    i = int(np.argmax(counts))
    if counts[i] <= 0:
        return None, 0
    return (n[i], float(-offs[i])), int(counts[i])


def _ref_fit_plane(p):
    c = p.mean(0)
    n = np.linalg.svd(p - c, full_matrices=False)[2][-1]
    n = n if n[2] >= 0 else -n
    return n, float(-n @ c)


def _ref_surroundings(points, pose, size, reach_extra):
    reach = float(np.hypot(size[0] / 2, size[1] / 2)) + reach_extra
    idx = np.flatnonzero((np.abs(points[:, 0] - pose[0]) <= reach)
                         & (np.abs(points[:, 1] - pose[1]) <= reach))
    near = points[idx].astype(np.float64)
    return near, sensor_to_canonical(near, pose)


def _ref_ground_from(near, local, size, cfg):
    if len(near) < cfg.min_ground_points:
        return None
    bottom = -size[2] / 2
    ax, ay = np.abs(local[:, 0]), np.abs(local[:, 1])
    keep = ((ax <= size[0] / 2 + cfg.context) & (ay <= size[1] / 2 + cfg.context)
            & ((ax > size[0] / 2) | (ay > size[1] / 2))
            & (local[:, 2] >= bottom - cfg.band_below) & (local[:, 2] <= bottom + cfg.band_above))
    cand = near[keep]
    if len(cand) < cfg.min_ground_points:
        return None
    rng = np.random.default_rng(cfg.seed)
    best, count = _ref_ransac_plane(cand, rng, cfg.iterations, 0.08, cfg.max_tilt_deg)
    if best is None or count < cfg.min_ground_points:
        return None
    n, d = best
    inl = cand[np.abs(cand @ n + d) < 0.08]
    n2, d2 = _ref_fit_plane(inl)
    if n2[2] >= np.cos(np.radians(cfg.max_tilt_deg)):
        n, d = n2, d2
    return n, float(d)


def _ref_local_ground(points, pose, size, cfg):
    pose, size = np.asarray(pose, dtype=np.float64), np.asarray(size, dtype=np.float64)
    near, local = _ref_surroundings(np.asarray(points)[:, :3], pose, size, cfg.context)
    return _ref_ground_from(near, local, size, cfg)


def _ref_crop_vehicle(points, pose, size, cfg, sweep_plane=None):
    pts = np.asarray(points)[:, :3]
    pose, size = np.asarray(pose, dtype=np.float64), np.asarray(size, dtype=np.float64)
    extra = max(cfg.margin, cfg.context) if cfg.ground == "plane" else cfg.margin
    near, local = _ref_surroundings(pts, pose, size, extra)
    half = size / 2 + [cfg.margin, cfg.margin, cfg.margin_z]
    inbox = np.all(np.abs(local) <= half, axis=1)
    cand = near[inbox]
    if cfg.ground == "none" or len(cand) == 0:
        return np.ascontiguousarray(cand, dtype=np.float32)
    plane = _ref_ground_from(near, local, size, cfg) if cfg.ground == "plane" else None
    if plane is None and cfg.ground == "plane":
        plane = sweep_plane() if callable(sweep_plane) else sweep_plane
    if plane is not None:
        n, d = plane
        above = cand @ np.asarray(n, dtype=np.float64) + d >= cfg.ground_threshold
    else:
        above = local[inbox, 2] >= -size[2] / 2 + cfg.box_ground
    return np.ascontiguousarray(cand[above], dtype=np.float32)


# --- The fast crop against the reference ----------------------------------------------------

_SETTINGS = (CropConfig(), CropConfig(ground="box"), CropConfig(ground="none", margin=0.5),
             CropConfig(context=0.0, min_ground_points=5), CropConfig(seed=3, iterations=17),
             CropConfig(max_tilt_deg=2.0, band_above=0.6, min_ground_points=3))


def _assert_same_crops(sweep, poses, sizes, cfg, plane=None):
    """crop_vehicles, crop_vehicle and local_ground equal the reference, bit for bit."""
    got = crop_vehicles(sweep, poses, sizes, cfg, sweep_plane=plane)
    assert len(got) == len(poses)
    for out, pose, size in zip(got, poses, sizes, strict=True):
        want = _ref_crop_vehicle(sweep, pose, size, cfg, sweep_plane=plane)
        for crop in (out, crop_vehicle(sweep, pose, size, cfg, sweep_plane=plane)):
            assert crop.dtype == np.float32 and crop.shape == want.shape
            assert crop.tobytes() == want.tobytes()  # the same points, order and bits
        lg, rg = local_ground(sweep, pose, size, cfg), _ref_local_ground(sweep, pose, size, cfg)
        assert (lg is None) == (rg is None)
        if rg is not None:
            assert lg[0].tobytes() == rg[0].tobytes() and lg[1] == rg[1]
    return got


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_crops_equal_the_former_implementation_on_random_streets(seed):
    sweep, poses, sizes = _street(seed)
    if seed == 3:  # a road at 6 % and vehicles on it
        sweep[:, 2] += np.float32(0.06) * sweep[:, 0]
    for cfg in _SETTINGS:
        for plane in (None, (np.array([0.0, 0.0, 1.0]), 1.75)):
            got = _assert_same_crops(sweep, poses, sizes, cfg, plane)
    assert sum(len(c) for c in got) > 1000


def _scene(seed: int, ground: str = "flat", n_ground: int = 6000):
    """A hand-made float32 sweep around a few boxes: ``ground`` flat, tilted (12 degrees,
    more than the 10 a plane may tilt), none, or sparse (a few returns only)."""
    rng = np.random.default_rng(seed)
    poses = np.array([[10.0, 3.0, -1.0, 0.4], [14.0, 1.0, -1.05, -2.9], [4.0, -6.0, -0.25, 1.2]])
    sizes = np.array([[4.5, 1.8, 1.5], [4.2, 1.7, 1.4], [9.0, 2.5, 3.0]])
    parts = [canonical_to_sensor(rng.uniform(-0.5, 0.5, (400, 3)) * s, p)
             for p, s in zip(poses, sizes, strict=True)]
    xy = rng.uniform(-5, 25, (n_ground if ground != "sparse" else 12, 2))
    slope = np.tan(np.radians(12.0)) if ground == "tilted" else 0.0
    if ground != "none":
        parts.append(np.c_[xy, -1.75 + slope * (xy[:, 0] - 10) + rng.normal(0, 0.01, len(xy))])
    return np.vstack(parts).astype(np.float32), poses, sizes


@pytest.mark.parametrize("ground", ["flat", "tilted", "none", "sparse"])
def test_crops_equal_the_former_implementation_on_hand_made_grounds(ground):
    sweep, poses, sizes = _scene(4, ground)
    calls = []

    def plane():
        calls.append(1)
        return np.array([0.0, 0.0, 1.0]), 1.75

    _assert_same_crops(sweep, poses, sizes, CropConfig(), plane)
    assert (len(calls) > 0) == (ground != "flat")  # the sweep plane only where the fit fails
    for cfg in _SETTINGS[1:]:
        _assert_same_crops(sweep, poses, sizes, cfg, plane)


def test_crops_equal_the_former_implementation_on_few_points():
    sweep, poses, sizes = _scene(5)
    for n in (0, 1, 2, 3, 5, 29, 30, 31, 60):
        few = sweep[np.random.default_rng(n).permutation(len(sweep))[:n]]
        for cfg in _SETTINGS:
            _assert_same_crops(few, poses, sizes, cfg, (np.array([0.0, 0.0, 1.0]), 1.75))
    one = np.repeat(sweep[:1], 50, axis=0)  # 50 times the same point: degenerate triples only
    for cfg in _SETTINGS:
        _assert_same_crops(one, poses, sizes, cfg)


def test_crops_equal_the_former_implementation_at_the_sweep_edges():
    sweep, _, _ = _scene(6)
    rng = np.random.default_rng(6)  # and clutter above the road everywhere
    clutter = np.c_[rng.uniform(-5, 25, (3000, 2)), rng.uniform(-1.4, 0.5, 3000)]
    sweep = np.vstack([sweep, clutter.astype(np.float32)])
    lo, hi = sweep[:, :2].min(0), sweep[:, :2].max(0)
    mid = (lo + hi) / 2
    centres = [  # on the edges and corners, just beyond them, beyond in one axis only
        [lo[0], mid[1]], [hi[0], mid[1]], [mid[0], lo[1]], [mid[0], hi[1]], [lo[0], lo[1]],
        [hi[0], hi[1]], [lo[0] - 3.0, mid[1]], [mid[0], hi[1] + 3.0], [mid[0], lo[1] - 6.5],
        [hi[0] + 6.5, mid[1]], [mid[0], hi[1] + 40.0], [hi[0] + 40.0, mid[1]],
        [mid[0], lo[1] - 40.0]]
    poses = np.array([[x, y, -1.0, yaw] for (x, y), yaw
                      in zip(centres, np.linspace(-3, 3, len(centres)), strict=True)])
    sizes = np.tile([4.5, 1.8, 1.5], (len(poses), 1))
    for cfg in _SETTINGS:
        got = _assert_same_crops(sweep, poses, sizes, cfg)
        assert len(got[-1]) == len(got[-2]) == 0 and len(got[0]) > 0


def test_crops_equal_the_former_implementation_with_non_finite_rows_and_other_dtypes():
    sweep, poses, sizes = _scene(7)
    bad = sweep.copy()
    bad[::17, 0] = np.nan
    bad[::19, 1] = np.inf
    bad[::23, 2] = np.nan
    bad[::29, 1] = -np.inf
    bad[::31] = np.nan  # whole rows
    for pts in (bad, bad.astype(np.float64), sweep.astype(np.float64),
                np.round(sweep * 10).astype(np.int32), np.c_[sweep, sweep[:, :1]]):
        for cfg in _SETTINGS[:4]:
            _assert_same_crops(pts, poses, sizes, cfg)
    nowhere = np.full((40, 3), np.nan, np.float32)
    assert all(len(c) == 0 for c in _assert_same_crops(nowhere, poses, sizes, CropConfig()))


def test_near_boxes_find_the_points_of_each_square_in_sweep_order():
    rng = np.random.default_rng(8)
    pts = rng.uniform(-60, 60, (20000, 3)).astype(np.float32)
    pts[::101, 0] = np.nan
    index = SweepIndex(pts, cell=3.0)
    centres, reaches = rng.uniform(-70, 70, (30, 2)), rng.uniform(0.3, 9.0, 30)
    centres[0] = [65.0, 0.0]  # beyond the sweep in x only
    centres[1] = [0.0, -68.0]  # ... in y only
    near = index.near(centres, reaches)
    assert np.all(np.diff(near.rows) > 0)
    for b, (c, r) in enumerate(zip(centres, reaches, strict=True)):
        pose = np.array([c[0], c[1], 0.0, 0.0])
        want = np.flatnonzero((np.abs(pts[:, 0] - pose[0]) <= r)
                              & (np.abs(pts[:, 1] - pose[1]) <= r))
        np.testing.assert_array_equal(near.rows[near.square(b, pose, float(r))], want)


@pytest.mark.parametrize("yaw", [0.0, -0.0, 0.4, -2.9, np.pi, -np.pi, 1e-300, 123.456])
def test_yaw_matrix_is_yaw_to_rotmat(yaw):
    for y in (yaw, np.float64(yaw), np.float32(yaw)):
        assert _yaw_matrix(y).tobytes() == yaw_to_rotmat(y).tobytes()
        assert _yaw_matrix(y).flags.c_contiguous and _yaw_matrix(y).dtype == np.float64


def test_fresh_rng_draws_as_a_new_default_rng():
    fresh = _FreshRng(11)
    for _ in range(3):
        rng = fresh()
        want = np.random.default_rng(11)
        np.testing.assert_array_equal(rng.integers(0, 1000, 50), want.integers(0, 1000, 50))
        assert rng.random() == want.random()
        assert rng.bit_generator.state == want.bit_generator.state
