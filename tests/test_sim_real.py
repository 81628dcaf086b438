"""seqshape.sim.real and the ``real`` preset: sensors, mount tilt, glass, dropout, edges, clutter,
the tracker-box crop (the shared function) and the untouched older presets."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from seqshape.errors import ConfigError
from seqshape.sim import real
from seqshape.sim.generate import (
    PRESETS,
    _load_vehicles,
    _splits,
    config_dict,
    generate_dataset,
    make_track_in_process,
    preset_config,
)
from seqshape.sim.sensors import get_sensor, mount_rotation
from seqshape.vehicles.fleet import FLEET_KINDS

GLASS, BODY, TYRE = 1, 0, 2
SMALL = dict(n_vehicles=4, n_val_vehicles=1, tracks_per_vehicle=1, min_frames=6, max_frames=10,
             mean_frames=8.0, max_distance=30.0)


def _scene(mesh, labels, rc, paint=0.5, height=50.0):
    """A scene holding ``mesh`` (static at the origin pose) and a far-away level ground."""
    ob = real.vehicle_object(mesh, np.zeros((1, 4)), labels, paint, rc, 0)
    n, d = real.ground_plane(height, 0.0, 0.0)
    return real.Scene([ob], n, d, 0.1)


def _pane_and_box():
    """A glass pane at x = 5 (y, z in [-1, 1]) in front of a body box whose face is at x = 6."""
    pane = trimesh.Trimesh([[5, -1, -1], [5, 1, -1], [5, 1, 1], [5, -1, 1]],
                           [[0, 1, 2], [0, 2, 3]], process=False)
    box = trimesh.creation.box(extents=(1.0, 2.0, 2.0))
    box.apply_translation([6.5, 0, 0])
    mesh = trimesh.util.concatenate([pane, box])
    labels = np.array([GLASS, GLASS] + [BODY] * len(box.faces), np.uint8)
    return mesh, labels


def _forward_rays(n=50):
    a = np.linspace(-0.1, 0.1, n)
    return real.head_directions(np.zeros(n), a, np.eye(3)), np.zeros(n, np.int64)


# ----------------------------------------------------------------------------- sensors


def test_sensor_presets_channels_and_elevations():
    expect = {"vlp16": (16, -15.0, 15.0), "vlp32c": (32, -25.0, 15.0),
              "hdl64": (64, -24.33, 2.0), "os128": (128, -22.5, 22.5)}
    for name, (n, lo, hi) in expect.items():
        s = get_sensor(name)
        assert len(s.elevations_deg) == n, name
        assert min(s.elevations_deg) == pytest.approx(lo) and max(s.elevations_deg) == \
            pytest.approx(hi)
        assert s.divergence_mrad > 0 and s.range_10pct > 0
    e = np.sort(get_sensor("vlp32c").elevations_deg)
    assert len(set(e)) == 32 and np.diff(e).min() == pytest.approx(1 / 3, abs=2e-3)
    assert np.diff(e).max() == pytest.approx(25 - 15.639)  # non-uniform: 9.4 deg at the bottom
    o = np.diff(get_sensor("os128").elevations_deg)
    np.testing.assert_allclose(o, 45 / 127, atol=1e-4)
    assert get_sensor("os128").n_azimuths == 1024
    # the AV2 pair: the VLP-32C table and its negation 0.1 deg up, 64 distinct channels with
    # 1/3-deg steps in both dense bands (-4.667..+1.667 upright, -1.567..+4.767 inverted)
    p = get_sensor("vlp32c_pair")
    pe = np.array(p.elevations_deg)
    assert len(pe) == 64 and len(set(np.round(pe, 4))) == 64
    np.testing.assert_allclose(np.sort(pe[32:]), np.sort(0.1 - e), atol=1e-9)
    assert min(pe) == pytest.approx(-25.0) and max(pe) == pytest.approx(25.1)
    band = np.sort(pe[(pe > -1.7) & (pe < 1.8)])
    assert len(band) == 22 and np.diff(band).max() < 0.24  # two interleaved 1/3-deg bands
    assert "vlp32c_pair" in real.RealConfig().sensors


def test_mount_rotation_by_hand():
    p, r = math.radians(2.0), math.radians(3.0)
    np.testing.assert_allclose(mount_rotation(p, 0) @ [1, 0, 0], [math.cos(p), 0, -math.sin(p)],
                               atol=1e-15)
    np.testing.assert_allclose(mount_rotation(0, r) @ [0, 1, 0], [0, math.cos(r), math.sin(r)],
                               atol=1e-15)
    np.testing.assert_allclose(mount_rotation(p, r) @ [0, 0, 1],
                               [math.cos(r) * math.sin(p), -math.sin(r),
                                math.cos(p) * math.cos(r)], atol=1e-15)
    # the head's beam at elevation 0, azimuth 0 under pitch 2 deg points 2 deg down
    d = real.head_directions(np.zeros(1), np.zeros(1), mount_rotation(p, r))[0]
    np.testing.assert_allclose(d, [math.cos(p), 0, -math.sin(p)], atol=1e-15)


def test_tilted_rays_hit_the_level_ground_at_hand_computed_points():
    rc = real.RealConfig(base_dropout=0.0)
    sensor = get_sensor("vlp16")
    n, d = real.ground_plane(2.0, 0.0, 0.0)
    scene = real.Scene([], n, d, 0.5)
    p = math.radians(1.5)
    rot = mount_rotation(p, 0.0)
    # beam at -15 deg looking forward: after a 1.5 deg nose-down pitch it meets the ground at
    # x = 2 / tan(16.5 deg), z = -2 (points stay in the level frame)
    dirs = real.head_directions(np.array([math.radians(-15)]), np.zeros(1), rot)
    r, _, src = real.trace(scene, dirs, np.zeros(1, np.int64), rc, np.random.default_rng(0))
    pt = dirs[0] * r[0]
    np.testing.assert_allclose(pt, [2 / math.tan(math.radians(16.5)), 0, -2], atol=1e-9)
    assert src[0] == real.SOURCES.index("ground")
    assert sensor.range_10pct > 0


# ------------------------------------------------------------------------------- glass


def test_glass_lets_the_ray_through_to_the_body_behind():
    mesh, labels = _pane_and_box()
    dirs, frame = _forward_rays()
    through = real.RealConfig(glass_pass=1.0, glass_return=0.0)
    r, _, src = real.trace(_scene(mesh, labels, through), dirs, frame, through,
                           np.random.default_rng(0))
    np.testing.assert_allclose(r * dirs[:, 0], 6.0, atol=1e-9)  # every return from x = 6
    assert (src == real.SOURCES.index("target_through_glass")).all()
    lost = real.RealConfig(glass_pass=0.0, glass_return=0.0)
    r, _, src = real.trace(_scene(mesh, labels, lost), dirs, frame, lost,
                           np.random.default_rng(0))
    assert np.isinf(r).all() and (src == -1).all()
    pane = real.RealConfig(glass_pass=0.0, glass_return=1.0)
    r, _, src = real.trace(_scene(mesh, labels, pane), dirs, frame, pane,
                           np.random.default_rng(0))
    np.testing.assert_allclose(r * dirs[:, 0], 5.0, atol=1e-9)
    assert (src == real.SOURCES.index("target")).all()
    # the same mesh with every face body: the pane itself returns
    r, _, _ = real.trace(_scene(mesh, None, through), dirs, frame, through,
                         np.random.default_rng(0))
    np.testing.assert_allclose(r * dirs[:, 0], 5.0, atol=1e-9)


def test_glass_shares_follow_the_probabilities():
    mesh, labels = _pane_and_box()
    dirs, frame = _forward_rays(4000)
    rc = real.RealConfig(glass_pass=0.6, glass_return=0.15)
    r, _, _ = real.trace(_scene(mesh, labels, rc), dirs, frame, rc, np.random.default_rng(1))
    x = r * dirs[:, 0]
    assert np.mean(np.isclose(x, 6.0)) == pytest.approx(0.6, abs=0.03)
    assert np.mean(np.isclose(x, 5.0)) == pytest.approx(0.15, abs=0.02)
    assert np.mean(np.isinf(r)) == pytest.approx(0.25, abs=0.03)


@pytest.mark.parametrize("label,opening,expect", [
    (8, 0.6, {6.0: 0.6, 5.0: 0.4, "lost": 0.0}),   # grille: through its openings or the bars
    (9, 0.6, {6.0: 0.0, 5.0: 0.3, "lost": 0.7}),   # headlamp: lens return or lost, never through
])
def test_grille_openings_pass_and_headlamps_lose_rays(label, opening, expect):
    # the pane of _pane_and_box relabelled: a grille (or headlamp) 1 m in front of the body
    mesh, labels = _pane_and_box()
    labels[:2] = label
    rc = real.RealConfig(grille_pass=(opening, opening), headlamp_loss=0.7)
    ob = real.vehicle_object(mesh, np.zeros((1, 4)), labels, 0.5, rc, 0,
                             real.sample_grille(np.random.default_rng(0), rc))
    scene = real.Scene([ob], *real.ground_plane(50.0, 0.0, 0.0), 0.1)
    dirs, frame = _forward_rays(4000)
    r, _, src = real.trace(scene, dirs, frame, rc, np.random.default_rng(2))
    x = r * dirs[:, 0]
    for where, share in expect.items():
        got = np.mean(np.isinf(r)) if where == "lost" else np.mean(np.isclose(x, where))
        assert got == pytest.approx(share, abs=0.03), where
    # what came through the openings is marked as seen through the target's front
    behind = np.isclose(x, 6.0)
    assert (src[behind] == real.SOURCES.index("target_through_glass")).all()


def test_faces_without_openings_or_losses_trace_as_before():
    # a body-only mesh: no face passes or loses a ray, whatever the grille and headlamp knobs
    mesh, _ = _pane_and_box()
    dirs, frame = _forward_rays(500)
    out = []
    for rc in (real.RealConfig(), real.RealConfig(grille_pass=(1.0, 1.0), headlamp_loss=1.0)):
        r, rho, src = real.trace(_scene(mesh, None, rc), dirs, frame, rc,
                                 np.random.default_rng(3))
        out.append((r, rho, src))
    for a, b in zip(*out, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(out[0][0] * dirs[:, 0], 5.0, atol=1e-9)


def test_reflectivity_of_older_configs_and_grille_validation():
    old = real.RealConfig(reflectivity=(0.5, 0.1, 0.03, 0.3, 0.05, 0.9, 0.25, 0.2))
    assert old.reflectivity == real.RealConfig().reflectivity  # the last two defaulted
    assert len(old.reflectivity) == 10
    with pytest.raises(ConfigError, match="10 positive values"):
        real.RealConfig(reflectivity=(0.5,) * 9)
    with pytest.raises(ConfigError, match="grille_pass"):
        real.RealConfig(grille_pass=(0.8, 0.2))
    with pytest.raises(ConfigError, match="probabilities"):
        real.RealConfig(headlamp_loss=1.5)
    rng = np.random.default_rng(0)
    g = [real.sample_grille(rng, real.RealConfig(grille_pass=(0.2, 0.4))) for _ in range(200)]
    assert 0.2 <= min(g) and max(g) <= 0.4 and np.std(g) > 0.04


def test_incidence_cosine_and_effective_reflectivity_by_hand():
    # a unit cube 6 m ahead turned by 30 deg: the horizontal forward ray meets its -x face at
    # 30 deg from the normal; the backward ray 10 deg down meets the level ground, whose
    # reflectivity is an effective one at every angle
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    pose = np.array([[6.0, 0.0, 0.0, math.radians(30.0)]])
    n, d = real.ground_plane(2.0, 0.0, 0.0)
    dirs = real.head_directions(np.array([0.0, math.radians(-10.0)]), np.array([0.0, math.pi]),
                                np.eye(3))
    frame = np.zeros(2, np.int64)
    for expo, expect in ((1.0, [0.5 * math.cos(math.radians(30)), 0.2]),
                         (2.0, [0.5 * 0.75, 0.2]), (0.0, [0.5, 0.2])):
        rc = real.RealConfig(incidence_exponent=expo)
        scene = real.Scene([real.vehicle_object(cube, pose, None, 0.5, rc, 0)], n, d, 0.2)
        r, rho, src = real.trace(scene, dirs, frame, rc, np.random.default_rng(0))
        np.testing.assert_allclose(rho, expect, rtol=1e-9)
        np.testing.assert_allclose(r[1], 2.0 / math.sin(math.radians(10.0)), rtol=1e-9)
        assert list(src) == [0, real.SOURCES.index("ground")]
    with pytest.raises(ConfigError, match="incidence_exponent"):
        real.RealConfig(incidence_exponent=-1.0)


@pytest.mark.parametrize("angle", [0.0, 60.0, 75.0])
def test_glass_passes_less_at_grazing_incidence(angle):
    # a vertical pane through x = 5 whose normal is turned by ``angle`` from the rays; a body
    # box behind it. Fresnel (sine / tangent forms, n = 1.52), two faces, unpolarised light
    a = math.radians(angle)
    u, w = np.array([-math.sin(a), math.cos(a), 0.0]), np.array([0.0, 0.0, 1.0])
    corners = [np.array([5.0, 0, 0]) + 3 * (su * u + sw * w)
               for su, sw in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    pane = trimesh.Trimesh(corners, [[0, 1, 2], [0, 2, 3]], process=False)
    box = trimesh.creation.box(extents=(1.0, 4.0, 4.0))
    box.apply_translation([9.5, 0, 0])
    mesh = trimesh.util.concatenate([pane, box])
    labels = np.array([GLASS, GLASS] + [BODY] * len(box.faces), np.uint8)
    dirs = real.head_directions(np.zeros(4000), np.zeros(4000), np.eye(3))
    rc = real.RealConfig(glass_pass=0.9, glass_return=0.0)
    r, _, src = real.trace(_scene(mesh, labels, rc), dirs, np.zeros(4000, np.int64), rc,
                           np.random.default_rng(2))

    def pane_t(t):
        if t == 0.0:
            return (1 - ((1.52 - 1) / (1.52 + 1)) ** 2) ** 2
        tt = math.asin(math.sin(t) / 1.52)
        rs = (math.sin(t - tt) / math.sin(t + tt)) ** 2
        rp = (math.tan(t - tt) / math.tan(t + tt)) ** 2
        return 0.5 * ((1 - rs) ** 2 + (1 - rp) ** 2)

    expect = 0.9 * pane_t(a) / pane_t(0.0)
    assert np.mean(np.isfinite(r)) == pytest.approx(expect, abs=0.025)
    np.testing.assert_allclose(r[np.isfinite(r)], 9.0, atol=1e-9)
    assert real.pane_transmission(1.0) == pytest.approx(pane_t(0.0))
    assert real.pane_transmission(math.cos(a)) == pytest.approx(pane_t(a))
    off = real.RealConfig(glass_pass=0.9, glass_return=0.0, glass_fresnel=False)
    r, _, _ = real.trace(_scene(mesh, labels, off), dirs, np.zeros(4000, np.int64), off,
                         np.random.default_rng(2))
    assert np.mean(np.isfinite(r)) == pytest.approx(0.9, abs=0.025)


# ----------------------------------------------------------------------------- dropout


def test_dropout_by_label_and_range():
    rc = real.RealConfig(base_dropout=0.0)
    s = get_sensor("vlp16")
    p = real.detection_probability
    # R50 of a 10 % target is range_10pct; a 40 % one sqrt(4) = 2x further
    assert p(s.range_10pct, 0.1, s, rc) == pytest.approx(0.5)
    assert p(2 * s.range_10pct, 0.4, s, rc) == pytest.approx(0.5)
    r = np.array([5.0, 15.0, 30.0, 60.0])
    tyre, body = p(r, rc.reflectivity[TYRE], s, rc), p(r, 0.6, s, rc)
    assert (np.diff(tyre) < 0).all() and (tyre < body).all()
    # the face labels select the reflectivity; the body's is the vehicle's paint
    box = trimesh.creation.box()
    labels = np.array([TYRE] * 6 + [BODY] * 6, np.uint8)
    ob = real.vehicle_object(box, np.zeros((1, 4)), labels, 0.05, rc, 0)
    np.testing.assert_allclose(ob.rho, [rc.reflectivity[TYRE]] * 6 + [0.05] * 6)
    with pytest.raises(ConfigError, match="face_labels"):
        real.vehicle_object(box, np.zeros((1, 4)), labels[:5], 0.5, rc, 0)


def test_tyre_half_of_a_wall_returns_less_at_range():
    # a wall 30 m ahead: upper half body (paint 0.6), lower half tyre rubber
    wall = trimesh.Trimesh([[30, -20, -3], [30, 20, -3], [30, 20, 0], [30, -20, 0],
                            [30, 20, 3], [30, -20, 3]], [[0, 1, 2], [0, 2, 3], [3, 2, 4],
                                                         [3, 4, 5]], process=False)
    labels = np.array([TYRE, TYRE, BODY, BODY], np.uint8)
    rc = real.RealConfig(base_dropout=0.0)
    s = get_sensor("vlp16")
    e, a = np.meshgrid(np.radians(np.arange(-4.5, 5, 1.0)), np.radians(np.arange(-20, 20, 0.2)))
    rays = real.Rays(e.ravel(), a.ravel(), np.zeros(e.size, np.int64),
                     np.zeros(e.size, np.int64), real.head_directions(e.ravel(), a.ravel(),
                                                                      np.eye(3)))
    (pts, _), = real.scan_scene(_scene(wall, labels, rc, paint=0.6), rays, np.eye(3), s, rc,
                                np.random.default_rng(0), 1)
    low, high = (pts[:, 2] < 0).sum(), (pts[:, 2] > 0).sum()
    n_half = e.size / 2
    assert high / n_half == pytest.approx(float(real.detection_probability(30.0, 0.6, s, rc)),
                                          abs=0.05)
    assert low / n_half == pytest.approx(
        float(real.detection_probability(30.0, rc.reflectivity[TYRE], s, rc)), abs=0.05)
    assert low / n_half < 0.2 < 0.8 < high / n_half


# ------------------------------------------------------------------------ mixed returns


def test_edge_rays_return_between_foreground_and_background():
    # a post 10 m ahead in front of a wall at 20 m; rays sweep across the post's edges
    post = trimesh.creation.box(extents=(0.2, 0.5, 4.0))
    post.apply_translation([10.1, 0, 0])
    wall = trimesh.creation.box(extents=(0.2, 40, 4.0))
    wall.apply_translation([20.1, 0, 0])
    mesh = trimesh.util.concatenate([post, wall])
    rc = real.RealConfig(base_dropout=0.0, mixed_prob=1.0)
    s = get_sensor("vlp16")  # 3 mrad: 3 cm at 10 m
    a = np.radians(np.arange(-3, 3, 0.2)) + 1e-4
    rays = real.Rays(np.zeros(len(a)), a, np.zeros(len(a), np.int64), np.zeros(len(a), np.int64),
                     real.head_directions(np.zeros(len(a)), a, np.eye(3)))
    scene = _scene(mesh, None, rc, paint=0.8)
    r, rho, src = real.trace(scene, rays.dirs, rays.frame, rc, np.random.default_rng(0))
    edge = real._edges(rays, r, rc.edge_gap)
    x = r * rays.dirs[:, 0]
    assert edge.sum() == 4 and set(np.round(x[edge])) == {10.0, 20.0}
    # the rays whose divergence cone (+-1.5 mrad) straddles the post's silhouette (|y/x| =
    # 0.025) see post and wall at once: they float between the two (mean of five samples)
    a = np.sort(np.concatenate([a, [math.atan(0.025) + 0.5e-3, -math.atan(0.025) - 0.5e-3,
                                    math.atan(0.025) + 2.5e-3]]))
    rays = real.Rays(np.zeros(len(a)), a, np.zeros(len(a), np.int64), np.zeros(len(a), np.int64),
                     real.head_directions(np.zeros(len(a)), a, np.eye(3)))
    r, rho, src = real.trace(scene, rays.dirs, rays.frame, rc, np.random.default_rng(0))
    r2, _, _ = real.mixed_returns(scene, rays, r, rho, src, np.eye(3), s, rc,
                                  np.random.default_rng(0))
    x2 = r2 * rays.dirs[:, 0]
    straddle = np.abs(np.abs(a) - math.atan(0.025)) < 1.5e-3
    mixed = np.isfinite(x2) & (x2 > 10.5) & (x2 < 19.5)
    assert straddle.sum() == 4
    np.testing.assert_array_equal(mixed, straddle)
    # outside the silhouette one sample of five is on the post, inside four of five
    expect = np.where(np.abs(a) > math.atan(0.025), 18.0, 12.0)[mixed]
    np.testing.assert_allclose(x2[mixed], expect, atol=0.05)
    assert np.all(np.isclose(x2[~mixed], 10.0, atol=0.21) | np.isclose(x2[~mixed], 20.0))


# ------------------------------------------------------------------ jitter and clutter


def test_tracker_box_jitter_is_seeded_per_frame():
    j = real.TrackerJitter()
    pose, size = np.array([10.0, 2.0, -1.0, 0.3]), np.array([4.5, 1.8, 1.5])
    a = real.tracker_box(pose, size, j, real.jitter_rng(0, 3, 7))
    b = real.tracker_box(pose, size, j, real.jitter_rng(0, 3, 7))
    c = real.tracker_box(pose, size, j, real.jitter_rng(1, 3, 7))
    d = real.tracker_box(pose, size, j, real.jitter_rng(0, 3, 8))
    np.testing.assert_array_equal(np.concatenate(a), np.concatenate(b))
    assert not np.allclose(np.concatenate(a), np.concatenate(c))
    assert not np.allclose(np.concatenate(a), np.concatenate(d))
    zero = real.TrackerJitter(0, 0, 0, 0, 0)
    p0, s0 = real.tracker_box(pose, size, zero, real.jitter_rng(0, 0, 0))
    np.testing.assert_array_equal(p0, pose)
    np.testing.assert_array_equal(s0, size)
    # statistics of many draws match the parameters
    boxes = np.array([np.concatenate(real.tracker_box(pose, size, j, real.jitter_rng(0, 0, t)))
                      for t in range(800)])
    assert np.std(boxes[:, 0] - pose[0]) == pytest.approx(j.centre_std, rel=0.15)
    assert np.degrees(np.std(boxes[:, 3] - pose[3])) == pytest.approx(j.yaw_std_deg, rel=0.15)
    assert np.median(boxes[:, 4] - size[0]) == pytest.approx(j.enlarge, abs=0.05)


def test_clutter_is_seeded_and_keeps_clear_of_the_vehicles():
    rc = real.RealConfig(max_clutter=6)
    t = np.linspace(0, 1, 20)
    poses = np.stack([10 + 0 * t, -10 + 20 * t, np.zeros_like(t), np.full_like(t, np.pi / 2)], 1)
    size = np.array([4.5, 1.8, 1.5])
    n, d = real.ground_plane(1.8, 0.01, -0.02)

    def draw(seed):
        out = []
        for k in range(6):
            cl = real.sample_clutter(np.random.default_rng([seed, k]), poses, size,
                                     [(poses, size)], n, d, rc)
            out += [(np.asarray(m.vertices), kind) for m, _, kind in cl]
        return out

    a, b, c = draw(0), draw(0), draw(1)
    assert len(a) > 3 and len(a) == len(b)
    assert all(np.array_equal(x[0], y[0]) and x[1] == y[1] for x, y in zip(a, b, strict=True))
    assert len(a) != len(c) or any(not np.array_equal(x[0], y[0])
                                   for x, y in zip(a, c, strict=True))
    for verts, _kind in a:  # beside the path (x = 10 +- 0.9), standing in the ground
        assert np.abs(verts[:, 0] - 10).min() > 0.9 + 0.2
        centre = (verts.min(0) + verts.max(0)) / 2
        zg = real.ground_height(n, d, centre[0], centre[1])
        assert verts[:, 2].min() - zg == pytest.approx(-0.05, abs=1e-9)


# ------------------------------------------------------------ the real preset, end to end


@pytest.fixture(scope="module")
def real_small():
    cfg = preset_config("real", **SMALL)
    vehicles = _load_vehicles(cfg)
    return cfg, vehicles, _splits(len(vehicles), cfg)


def _track_digest(track) -> str:
    h = hashlib.sha1()
    for p in track.points:
        h.update(np.ascontiguousarray(p).tobytes())
    h.update(track.poses.tobytes())
    return h.hexdigest()


def test_real_tracks_deterministic_and_seed_dependent(real_small):
    from dataclasses import replace

    cfg, vehicles, splits = real_small
    a = make_track_in_process(cfg, vehicles, splits, 1)
    b = make_track_in_process(cfg, vehicles, splits, 1)
    assert _track_digest(a) == _track_digest(b) and a.meta == b.meta
    c = make_track_in_process(replace(cfg, seed=5), vehicles, splits, 1)
    assert _track_digest(a) != _track_digest(c)
    assert a.meta["crop_boxes"] != c.meta["crop_boxes"]


def test_real_track_content(real_small):
    cfg, vehicles, splits = real_small
    for i in range(2):
        tr = make_track_in_process(cfg, vehicles, splits, i)
        v = vehicles[i]
        meta = tr.meta
        assert meta["sensor"] in cfg.real.sensors
        assert 1.5 <= meta["real"]["sensor_height"] <= 2.2
        assert abs(meta["real"]["pitch_deg"]) <= 1.5 and abs(meta["real"]["roll_deg"]) <= 1.5
        assert meta["jitter"] == json.loads(json.dumps(real.TrackerJitter().__dict__))
        assert meta["class"] == v.cls == FLEET_KINDS[meta["kind"]]
        boxes = np.asarray(meta["crop_boxes"])
        assert boxes.shape == (len(tr), 7)
        # exact ground-truth poses, jittered crop boxes around them
        n, d = real.ground_plane(meta["real"]["sensor_height"], *meta["real"]["ground_slope"])
        zg = real.ground_height(n, d, tr.poses[:, 0], tr.poses[:, 1])
        np.testing.assert_allclose(tr.poses[:, 2], zg - v.mesh.bounds[0, 2], atol=1e-12)
        assert np.abs(boxes[:, :2] - tr.poses[:, :2]).max() < 1.5
        assert not np.allclose(boxes[:, :4], tr.poses)
        # every point lies inside its frame's crop box (+ the crop margins)
        from seqshape.geometry import sensor_to_canonical

        for t, pts in enumerate(tr.points):
            if len(pts):
                loc = sensor_to_canonical(pts.astype(np.float64), boxes[t, :4])
                half = boxes[t, 4:] / 2 + [0.2 + 1e-4, 0.2 + 1e-4, 0.1 + 1e-4]
                assert (np.abs(loc) <= half).all()
        counts = {k: sum(x) for k, x in meta["sources"].items()}
        assert counts["target"] > 0 and sum(counts.values()) == sum(len(p) for p in tr.points)


def test_generator_uses_the_shared_crop_function(real_small, monkeypatch):
    import seqshape.data.crop
    import seqshape.data.extract

    assert real.crop_vehicle is seqshape.data.crop.crop_vehicle
    # the inference path crops all boxes of a sweep at once with the same core, crop by crop
    # equal to crop_vehicle (tests/test_crop.py)
    assert seqshape.data.extract.crop_vehicles is seqshape.data.crop.crop_vehicles
    cfg, vehicles, splits = real_small
    calls = []
    original = real.crop_vehicle

    def spy(points, pose, size, crop_cfg, sweep_plane=None):
        calls.append((np.array(pose), np.array(size)))
        return original(points, pose, size, crop_cfg, sweep_plane)

    monkeypatch.setattr(real, "crop_vehicle", spy)
    tr = make_track_in_process(cfg, vehicles, splits, 0)
    assert len(calls) == len(tr)
    np.testing.assert_allclose([np.concatenate(c) for c in calls], tr.meta["crop_boxes"],
                               atol=1e-4)


def test_real_dataset_resumes_and_records_its_config(tmp_path):
    cfg = preset_config("real", **{**SMALL, "n_vehicles": 3, "max_frames": 8, "mean_frames": 7.0})
    s = generate_dataset(cfg, tmp_path / "d")
    assert s.manifest_written and s.n_generated == 3
    saved = json.loads((tmp_path / "d" / "generate.json").read_text())
    assert saved["library"] == "fleet" and saved["real"]["sensors"] == list(cfg.real.sensors)
    again = generate_dataset(cfg, tmp_path / "d")
    assert again.n_generated == 0 and again.n_skipped == 3
    from seqshape.sim.generate import GenerateConfig

    fields = {k: v for k, v in saved.items() if k in GenerateConfig.__dataclass_fields__}
    assert GenerateConfig(**fields) == cfg


def test_one_sensor_override_and_validation():
    cfg = preset_config("real", sensor="os128")
    assert cfg.real.sensors == ("os128",) and cfg.real.sensor_weights == (1.0,)
    with pytest.raises(ConfigError, match="sensor"):
        real.RealConfig(sensors=("hdl32",), sensor_weights=(1.0,))
    with pytest.raises(ConfigError, match="glass_pass"):
        real.RealConfig(glass_pass=0.9, glass_return=0.2)
    with pytest.raises(ConfigError, match="library"):
        preset_config("tiny", library="cad")


# -------------------------------------------------------------- older presets unchanged

#: Tracks 0, 1 and 5 of a 6-vehicle tiny-sized run of the tiny and realistic presets, as
#: :func:`_fingerprint` summarises them: written by ``python tests/test_sim_real.py`` with
#: numpy's AVX-512 paths off (``NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL"``), where the
#: tracks still hashed to the SHA-1 digests of the code before the real path existed
#: (tiny b22e5a27..., realistic 83dc0a98...). Exact digests depend on the CPU: numpy's SIMD
#: sin/cos differ in the last bit with AVX-512, so the points do too; the fingerprint is
#: compared with tolerances far below any change of the generator.
OLD_FINGERPRINTS = Path(__file__).parent / "data" / "older_presets.json"
OLD_TRACKS = (0, 1, 5)


def _older_preset_tracks(name):
    cfg = preset_config(name, n_vehicles=6, n_val_vehicles=2, tracks_per_vehicle=2,
                        min_frames=10, max_frames=30, mean_frames=18.0, max_distance=40.0)
    vehicles = _load_vehicles(cfg)
    splits = _splits(len(vehicles), cfg)
    return [make_track_in_process(cfg, vehicles, splits, i) for i in OLD_TRACKS]


def _fingerprint(tr) -> dict:
    """A track's points per frame (count, coordinate sums and sums of squares), poses,
    complete shape (sums, sums of squares, bounds) and meta, as JSON values."""
    pts = [np.asarray(p, dtype=np.float64) for p in tr.points]
    shape = np.asarray(tr.complete, dtype=np.float64)
    return {"counts": [len(p) for p in pts],
            "sums": [p.sum(axis=0).tolist() for p in pts],
            "squares": [(p * p).sum(axis=0).tolist() for p in pts],
            "poses": np.asarray(tr.poses, dtype=np.float64).tolist(),
            "complete": [shape.sum(axis=0).tolist(), (shape * shape).sum(axis=0).tolist(),
                         shape.min(axis=0).tolist(), shape.max(axis=0).tolist()],
            "meta": json.loads(json.dumps(tr.meta, sort_keys=True, default=str))}


@pytest.mark.parametrize("name", ["realistic", "tiny"])
def test_older_presets_unchanged(name):
    want = json.loads(OLD_FINGERPRINTS.read_text())[name]
    got = [_fingerprint(tr) for tr in _older_preset_tracks(name)]
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g["meta"] == w["meta"]
        assert g["counts"] == w["counts"]  # every ray that hit still hits
        # float32 points of tens of metres: the last bit is ~2e-6 m; a frame's sums over
        # hundreds of points move by well under 1e-3 for that, by metres for a changed scan
        np.testing.assert_allclose(g["sums"], w["sums"], rtol=1e-6, atol=1e-3)
        np.testing.assert_allclose(g["squares"], w["squares"], rtol=1e-6, atol=1e-3)
        np.testing.assert_allclose(g["poses"], w["poses"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(g["complete"][0], w["complete"][0], rtol=1e-6, atol=1e-3)
        np.testing.assert_allclose(g["complete"][1], w["complete"][1], rtol=1e-6, atol=1e-3)
        np.testing.assert_allclose(g["complete"][2:], w["complete"][2:], rtol=0, atol=1e-5)
    saved = config_dict(PRESETS[name])
    assert "library" not in saved and "real" not in saved


def test_cli_real_preset_with_one_sensor(tmp_path, capsys):
    from seqshape.cli import main

    out = tmp_path / "cli"
    assert main(["generate", "--preset", "real", "--vehicles", "2", "--sensor", "vlp16",
                 "--out", str(out), "--shard", "2/2"]) == 0
    saved = json.loads((out / "generate.json").read_text())
    assert (saved["n_vehicles"], saved["n_val_vehicles"], saved["library"]) == (2, 1, "fleet")
    assert saved["real"]["sensors"] == ["vlp16"]
    assert len(list((out / "tracks").glob("*.npz"))) == 11
    assert "11 tracks generated" in capsys.readouterr().out


if __name__ == "__main__":  # rewrite OLD_FINGERPRINTS (see its comment for when that is right)
    OLD_FINGERPRINTS.write_text(json.dumps(
        {name: [_fingerprint(tr) for tr in _older_preset_tracks(name)]
         for name in ("realistic", "tiny")}, indent=1, sort_keys=True) + "\n")
