"""seqshape.sim: sensors, raycasting against hand-computed hits, trajectories, CSV logs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from seqshape.errors import ConfigError, DataError
from seqshape.sim import raycast
from seqshape.sim import trajectories as tj
from seqshape.sim.sensors import LidarConfig, get_sensor, ray_directions


def _sensor(elev=(0.0,), step=1.0, **kw):
    base = dict(max_range=100.0, min_range=0.5, height=2.0, range_noise_std=0.0, dropout=0.0,
                rate_hz=10.0)
    base.update(kw)
    return LidarConfig("test", tuple(elev), step, **base)


def _box(extents=(4.0, 2.0, 1.5)):
    return trimesh.creation.box(extents=extents)


@pytest.fixture(scope="module")
def car():
    from seqshape.vehicles import procedural_vehicle

    return procedural_vehicle("pickup", 3).mesh


# ----------------------------------------------------------------------------------- sensors

def test_presets():
    v = get_sensor()
    assert v.name == "vlp16" and v.elevations_deg == tuple(range(-15, 16, 2))
    assert v.azimuth_step_deg == 0.2 and v.max_range == 100 and v.height == 2.0
    assert v.rays_per_sweep == 16 * 1800
    h32, h64 = get_sensor("hdl32"), get_sensor("hdl64")
    assert len(h32.elevations_deg) == 32
    assert min(h32.elevations_deg) == pytest.approx(-30.67) and max(h32.elevations_deg) == \
        pytest.approx(10.67)
    assert len(h64.elevations_deg) == 64 and h64.height == 1.73 and h64.max_range == 120
    assert max(h64.elevations_deg) == 2.0 and min(h64.elevations_deg) == pytest.approx(-24.33)
    with pytest.raises(ConfigError, match="unknown sensor"):
        get_sensor("vlp17")
    with pytest.raises(ConfigError):
        _sensor(dropout=1.0)


def test_ray_directions_unit_and_windowed():
    cfg = get_sensor("vlp16")
    d = ray_directions(cfg)
    assert d.shape == (cfg.rays_per_sweep, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    # a window across the +-pi seam: 170 .. -170 deg holds 20 deg / 0.2 + 1 azimuths
    w = ray_directions(cfg, (math.radians(170), math.radians(-170)))
    assert len(w) == 16 * 101
    az = np.degrees(np.arctan2(w[:, 1], w[:, 0]))
    assert np.all(np.abs(az) >= 170 - 1e-9)


# ---------------------------------------------------------------------------------- raycast

def test_box_hits_hand_computed():
    """A 4 x 2 x 1.5 box at x = 10: the front face x = 8 is hit at (8, 8 tan a, 8 tan e / cos a)."""
    cfg = _sensor(elev=(-5.0, 0.0, 3.0), step=1.0)
    pts = raycast.scan_vehicle(_box(), (10.0, 0.0, 0.0, 0.0), cfg, np.random.default_rng(0))
    assert pts.dtype == np.float32 and pts.shape[1] == 3
    expected = []
    for e in (-5.0, 0.0, 3.0):
        for a in range(-7, 8):  # 8 tan(7 deg) = 0.98 < 1 = half width; 8 deg misses
            ar, er = math.radians(a), math.radians(e)
            expected.append((8.0, 8 * math.tan(ar), 8 * math.tan(er) / math.cos(ar)))
    expected = np.array(expected)
    assert len(pts) == len(expected)
    got = pts[np.lexsort(pts.T)]
    np.testing.assert_allclose(got, expected[np.lexsort(expected.T)], atol=1e-5)


def test_box_rotated_and_nothing_hit():
    cfg = _sensor(elev=(0.0,), step=1.0)
    # rotated by 90 deg: the 2 m side faces the sensor at x = 9, half width 2 -> |a| <= 12 deg
    pts = raycast.scan_vehicle(_box(), (10.0, 0.0, 0.0, math.pi / 2), cfg,
                               np.random.default_rng(0))
    a = np.radians(np.arange(-12, 13))
    np.testing.assert_allclose(np.sort(pts[:, 1]), np.sort(9 * np.tan(a)), atol=1e-5)
    np.testing.assert_allclose(pts[:, 0], 9.0, atol=1e-5)
    # a box entirely above the only channel and one beyond max range: empty (0, 3) frames
    for pose in [(10.0, 0.0, 5.0, 0.0), (150.0, 0.0, 0.0, 0.0)]:
        empty = raycast.scan_vehicle(_box(), pose, cfg, np.random.default_rng(0))
        assert empty.shape == (0, 3) and empty.dtype == np.float32


def test_ground_and_vehicle_occluders_block():
    cfg = _sensor(elev=(-15.0, -10.0, 0.0), step=1.0, height=2.0)
    rng = np.random.default_rng(0)
    # box spanning z in [-3, -1] at x = 10: the ground (z = -2) hides its lower half
    low = (10.0, 0.0, -2.0, 0.0)
    free = raycast.scan_vehicle(_box((4, 2, 2)), low, cfg, rng)
    blocked = raycast.scan_vehicle(_box((4, 2, 2)), low, cfg, rng, ground=True)
    assert (free[:, 2] < -2.0).sum() > 0
    assert np.all(blocked[:, 2] >= -2.0 - 1e-4)
    assert len(blocked) == (free[:, 2] >= -2.0).sum()
    # a 1 m cube at x = 5 (front face x = 4.5) hides the target where 4.5 tan a <= 0.5
    cfg0 = _sensor(elev=(0.0,), step=1.0)
    pts = raycast.scan_vehicle(_box(), (10.0, 0.0, 0.0, 0.0), cfg0, rng,
                               occluders=[(_box((1, 1, 1)), (5.0, 0.0, 0.0, 0.0))])
    np.testing.assert_allclose(np.sort(pts[:, 1]), 8 * np.tan(np.radians([-7, 7])), atol=1e-5)


def test_matches_slow_full_sweep_reference(car):
    """Culling + ray transforms give exactly the hits of casting every ray at the moved mesh."""
    cfg = get_sensor("vlp16").without_noise()
    rng = np.random.default_rng(1)
    for pose in [(6.0, 2.0, -1.1, 0.3), (-15.0, -9.0, -1.1, 2.5), (-30.0, 0.01, -1.0, -1.2),
                 (3.5, -4.0, -1.1, 1.57), (45.0, 30.0, -1.1, 0.0)]:
        ours = raycast.scan_vehicle(car, pose, cfg, rng)
        ref = raycast.full_sweep_points(car, pose, cfg)
        assert len(ours) == len(ref) > 0
        np.testing.assert_allclose(ours[np.lexsort(ours.T)], ref[np.lexsort(ref.T)], atol=2e-5)


def test_track_batch_equals_per_frame(car):
    cfg = get_sensor("hdl32").without_noise()
    poses = np.array([[8.0, 3.0, -1.0, 0.1], [12.0, -5.0, -1.0, 1.0], [20.0, 20.0, -1.0, 2.0]])
    batch = raycast.scan_track(car, poses, cfg, np.random.default_rng(0))
    for p, pts in zip(poses, batch, strict=False):
        np.testing.assert_array_equal(
            pts, raycast.scan_vehicle(car, p, cfg, np.random.default_rng(0)))


def test_elevations_match_channels_and_points_on_surface(car):
    for name in ("vlp16", "hdl64"):
        cfg = get_sensor(name).without_noise()
        pts = raycast.scan_track(car, [(7.0, -3.0, -0.8, 0.5), (-12.0, 6.0, -0.8, 2.0)], cfg,
                                 np.random.default_rng(0))
        all_pts = np.concatenate(pts).astype(np.float64)
        elev = np.degrees(np.arcsin(all_pts[:, 2] / np.linalg.norm(all_pts, axis=1)))
        gap = np.abs(elev[:, None] - np.array(cfg.elevations_deg)[None]).min(1)
        assert gap.max() < 1e-3
    from seqshape.geometry import sensor_to_canonical

    _, dist, _ = trimesh.proximity.closest_point(
        car, sensor_to_canonical(pts[0], (7.0, -3.0, -0.8, 0.5)).astype(np.float64))
    assert dist.max() < 1e-4


def test_noise_and_dropout_statistics():
    base = _sensor(elev=tuple(np.linspace(-4, 4, 41)), step=0.2)
    pose = (10.0, 0.0, 0.0, 0.0)
    exact = raycast.scan_vehicle(_box(), pose, base, np.random.default_rng(0))
    noisy_cfg = _sensor(elev=base.elevations_deg, step=0.2, range_noise_std=0.05)
    noisy = raycast.scan_vehicle(_box(), pose, noisy_cfg, np.random.default_rng(0))
    assert len(noisy) == len(exact) > 1000
    # each noisy return lies on its exact ray: compare ranges along the same direction
    dr = np.linalg.norm(noisy, axis=1) - np.linalg.norm(exact, axis=1)
    assert abs(dr.std() - 0.05) < 0.005 and abs(dr.mean()) < 0.005
    drop_cfg = _sensor(elev=base.elevations_deg, step=0.2, dropout=0.3)
    kept = raycast.scan_vehicle(_box(), pose, drop_cfg, np.random.default_rng(0))
    assert abs(len(kept) / len(exact) - 0.7) < 0.04


def test_sensor_noise_and_dropout_draw_nothing_when_off():
    r = np.array([3.0, 7.5, 12.25])
    quiet = _sensor()
    rng = np.random.default_rng(1)
    assert quiet.noisy_ranges(r, rng) is r
    assert quiet.kept_returns(3, rng).all()
    assert rng.random() == np.random.default_rng(1).random()  # no draw was taken
    noisy = _sensor(range_noise_std=0.1, dropout=0.25)
    a, b = np.random.default_rng(2), np.random.default_rng(2)
    np.testing.assert_array_equal(noisy.noisy_ranges(r, a), r + b.normal(0.0, 0.1, 3))
    np.testing.assert_array_equal(noisy.kept_returns(1000, a), b.random(1000) >= 0.25)
    np.testing.assert_array_equal(quiet.in_range(np.array([0.4, 0.5, 100.0, 100.1, np.inf])),
                                  [False, True, True, False, False])


def test_window_grid_enumerates_windows_in_order():
    from seqshape.sim.sensors import window_grid

    cfg = _sensor(elev=(-6.0, -3.0, 0.0, 3.0), step=30.0)  # 12 azimuths
    c0, c1 = np.array([1, 0, 2, 3]), np.array([3, 1, 2, 4])  # frame 2: no channel
    k0, k1 = np.array([-2, 5, 0, 0]), np.array([1, 5, 11, 11])
    g = window_grid(cfg, c0, c1, k0, k1)
    want = [(f, c, k % 12) for f in range(4) for c in range(c0[f], c1[f])
            for k in range(k0[f], k1[f] + 1)]
    got = list(zip(g.row_frame[g.ray_row], g.row_ch[g.ray_row], g.col_k[g.ray_col],
                   strict=True))
    assert got == want
    np.testing.assert_array_equal(g.frame_rays, [8, 1, 0, 12])
    np.testing.assert_array_equal(g.col_frame, [0] * 4 + [1] + [3] * 12)  # frame 2 has none


def test_one_sensor_drives_both_simulators(car):
    """A sensor that is no preset, defined once, scans a track (generate's path) and renders a
    scene sweep (the scenes' path): the same returns of the same car."""
    from seqshape.sim.render import render_lidar

    cfg = _sensor(elev=(-9.0, -4.0, -1.5, 2.5), step=0.5, max_range=40.0)
    pose = np.array([9.0, 4.0, -1.2, 0.4])
    track = raycast.scan_vehicle(car, pose, cfg, np.random.default_rng(0))
    pts, owner = render_lidar([car], pose[None], np.array([[0.5, 0.5, 0.5]]), cfg,
                              np.random.default_rng(0), ground_z=-1000.0)
    scene = pts[owner == 0, :3]
    assert len(track) > 20 and abs(len(scene) - len(track)) <= 2
    gap = np.linalg.norm(track[:, None] - scene[None], axis=2)
    assert gap.min(1).max() < 1e-3 and gap.min(0).max() < 1e-3


def test_intersector_cached(car):
    assert raycast.mesh_raycaster(car) is raycast.mesh_raycaster(car)
    assert raycast.mesh_raycaster(_box()) is not raycast.mesh_raycaster(car)


def test_raycaster_freed_with_its_mesh():
    import gc

    box = _box()
    key = id(box)
    rt = raycast.mesh_raycaster(box)
    assert rt.first_faces([[-9.0, 0.0, 0.0]], [[1.0, 0.0, 0.0]])[0] >= 0
    del rt
    del box
    gc.collect()
    assert key not in raycast._CACHE


def test_first_hits_distance_semantics():
    """Embree's t is the ray parameter (distance for unit dirs); misses give face -1."""
    rt = raycast.mesh_raycaster(_box())  # x in [-2, 2]
    o = np.array([[-10.0, 0.0, 0.0], [-10.0, 0.0, 0.0], [-10.0, 5.0, 0.0], [-10.0, 0.3, 0.2]])
    d = np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    tri, t = rt.first_hits(o, d)
    assert list(tri >= 0) == [True, True, False, True]
    np.testing.assert_allclose(t[[0, 1, 3]], [8.0, 4.0, 8.0], atol=1e-5)
    np.testing.assert_array_equal(rt.first_faces(o, d), tri)
    unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    hit, rng = rt.cast(o, unit)
    assert list(hit) == [True, True, False, True]
    np.testing.assert_allclose(rng[hit], 8.0, atol=1e-12)  # exact plane ranges
    assert rt.first_faces(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def test_cast_matches_trimesh_locations(car):
    """Random rays from around the car: same hits and ranges as trimesh's own first-hit path."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    rng = np.random.default_rng(5)
    n = 4000
    o = rng.uniform(-1, 1, (n, 3)) * [12.0, 12.0, 1.0]
    o[:, :2] += np.sign(o[:, :2]) * 3.0  # outside the car's footprint
    target = rng.uniform(-1, 1, (n, 3)) * car.extents / 2
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hit, r = raycast.mesh_raycaster(car).cast(o, d)
    loc, ray_idx, _ = RayMeshIntersector(car).intersects_location(o, d, multiple_hits=False)
    ref = np.full(n, np.inf)
    ref[ray_idx] = np.linalg.norm(loc - o[ray_idx], axis=1)
    both = hit & np.isfinite(ref)
    assert both.sum() > n // 2
    assert (hit != np.isfinite(ref)).sum() <= 2  # only rays through an edge may differ
    np.testing.assert_allclose(r[both], ref[both], atol=1e-5)


def test_track_rays_are_rotated_sensor_rays(car):
    """Canonical float32 rays = the sensor's (channel, azimuth) directions rotated by -yaw,
    origins = the sensor in the canonical frame; frame-major, ascending elevation, azimuth."""
    from seqshape.geometry import sensor_to_canonical

    cfg = get_sensor("vlp16")
    poses = np.array([[9.0, 4.0, -1.0, 0.4], [-20.0, 0.5, -1.0, 3.0], [-6.0, -0.01, -1.0, -2.0]])
    rt = raycast.mesh_raycaster(car)
    rays = raycast.track_rays(rt.bounds, poses, cfg)
    idx = np.arange(len(rays))
    frame = rays.frames(idx)
    assert np.all(np.diff(frame) >= 0) and set(frame) == {0, 1, 2}
    table = ray_directions(cfg).reshape(len(cfg.elevations_deg), cfg.n_azimuths, 3)
    table = table[np.argsort(cfg.elevations_deg)]
    ch, k = rays.row_ch[rays.ray_row], rays.col_k[rays.ray_col]
    canon, sensor = rays.exact_dirs(idx, cfg)
    np.testing.assert_allclose(sensor, table[ch, k], atol=1e-12)
    for f, pose in enumerate(poses):
        m = frame == f
        want = sensor_to_canonical(sensor[m], (0.0, 0.0, 0.0, pose[3]))
        np.testing.assert_allclose(canon[m], want, atol=1e-12)
        np.testing.assert_allclose(rays.dirs[m], want, atol=1e-6)
        np.testing.assert_allclose(rays.origins[m], sensor_to_canonical(np.zeros((1, 3)), pose)
                                   .repeat(m.sum(), 0), atol=1e-5)
        order = ch[m] * cfg.n_azimuths + (k[m] - k[m][0]) % cfg.n_azimuths
        assert np.all(np.diff(order) > 0)


def test_track_with_empty_frames_first_middle_last(car):
    cfg = get_sensor("vlp16").without_noise()
    away, above = (150.0, 0.0, -1.0, 0.0), (8.0, 3.0, 30.0, 0.0)
    seen = (8.0, 3.0, -1.1, 0.2)
    out = raycast.scan_track(car, [away, seen, above, seen, away], cfg, np.random.default_rng(0))
    assert [len(p) > 0 for p in out] == [False, True, False, True, False]
    assert all(p.shape[1:] == (3,) and p.dtype == np.float32 for p in out)
    np.testing.assert_array_equal(out[1], out[3])
    assert raycast.scan_track(car, [away], cfg, np.random.default_rng(0))[0].shape == (0, 3)


# ----------------------------------------------------------------------------- trajectories

def test_track_length_distribution():
    rng = np.random.default_rng(0)
    n = np.array([tj.sample_track_length(rng) for _ in range(4000)])
    assert n.min() >= 10 and n.max() <= 200
    assert abs(n.mean() - 70) < 4
    with pytest.raises(ConfigError):
        tj.sample_track_length(rng, 10, 200, 300)


@pytest.mark.parametrize("manoeuvre", sorted(tj.MANOEUVRES))
def test_sampled_trajectories_are_kinematic_and_clear(manoeuvre):
    rng = np.random.default_rng(sorted(tj.MANOEUVRES).index(manoeuvre))
    L, W = 4.6, 1.85
    for _ in range(15):
        tr = tj.sample_trajectory(rng, manoeuvre=manoeuvre, length=L, width=W)
        assert tr.manoeuvre == manoeuvre and 10 <= len(tr) <= 200
        np.testing.assert_allclose(np.diff(tr.t), 0.1, atol=1e-12)
        assert tj.footprint_distance(tr.x, tr.y, tr.yaw, L, W).min() >= 1.5 - 1e-9
        r = np.hypot(tr.x, tr.y)
        assert r.min() >= 3.0 and r.max() <= 60.0 + 1e-6
        step = np.hypot(np.diff(tr.x), np.diff(tr.y))
        assert step.max() <= 2.0  # < 20 m/s
        # non-holonomic constraint: the rear axle moves along the heading
        wb = 0.6 * L
        rx, ry = tr.x - wb / 2 * np.cos(tr.yaw), tr.y - wb / 2 * np.sin(tr.yaw)
        moving = np.hypot(np.diff(rx), np.diff(ry)) > 0.2
        if moving.any():
            heading = np.arctan2(np.diff(ry), np.diff(rx))
            mid = tr.yaw[:-1] + tj_wrap(np.diff(tr.yaw)) / 2
            assert np.abs(tj_wrap(heading - mid))[moving].max() < 0.05
        if manoeuvre == "parked":
            assert np.ptp(tr.x) == 0 and np.ptp(tr.y) == 0
        if manoeuvre == "stop_and_go" and len(tr) > 60:
            assert step.min() < 0.05


def tj_wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_footprints_overlap():
    a = np.array([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    b = np.array([[4.0, 0.0, 0.0, 0.0], [0.0, 2.5, 0.0, 0.0]])
    assert footprints(a, b).tolist() == [True, False]
    c = np.array([[4.0, 4.0, 0.0, np.pi / 4], [0.0, 1.5, 0.0, np.pi / 2]])
    assert footprints(a, c).tolist() == [False, True]


def footprints(a, b):
    return tj.footprints_overlap(a, (4.5, 1.8, 1.5), b, (4.5, 1.8, 1.5), margin=0.0)


# ------------------------------------------------------------------------------------- CSV

def test_read_csv_roundtrip(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("yaw,t,x,y,extra\n0.1,0.0,10,5,a\n7.0,0.1,11,5,b\n\n0.3,0.25,12,5.5,c\n")
    tr = tj.read_trajectory_csv(p)
    np.testing.assert_allclose(tr.t, [0.0, 0.1, 0.25])
    np.testing.assert_allclose(tr.x, [10, 11, 12])
    np.testing.assert_allclose(tr.yaw, [0.1, 7.0 - 2 * np.pi, 0.3])
    assert tr.manoeuvre == "csv" and tr.source == str(p)


@pytest.mark.parametrize("text, line, message", [
    ("", 1, "empty file"),
    ("t,x,yaw\n0,1,2\n", 1, r"missing column\(s\) \['y'\]"),
    ("t,x,y,yaw\n0,1,2,0\n0.1,1,oops,0\n", 3, "not a number"),
    ("t,x,y,yaw\n0,1,2,0\n0.1,nan,2,0\n", 3, "non-finite"),
    ("t,x,y,yaw\n0,1,2,0\n0.1,1,2,0\n0.1,1,2,0\n", 4, "does not increase"),
    ("t,x,y,yaw\n0,1,2\n", 2, "expected 4 fields"),
    ("t,x,y,yaw\n", None, "no data rows"),
])
def test_read_csv_errors(tmp_path, text, line, message):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(DataError, match=message) as info:
        tj.read_trajectory_csv(p)
    assert info.value.path == str(p) and info.value.line == line


def test_read_csv_missing_file(tmp_path):
    with pytest.raises(DataError, match="not found"):
        tj.read_trajectory_csv(tmp_path / "nope.csv")
