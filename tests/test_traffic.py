"""The traffic placement (seqshape.sim.traffic): seeded, hand-checked views, clearance rules,
the ego's motion in the tracks, the real preset's meta and a world-static scene."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from seqshape.errors import ConfigError
from seqshape.sim import traffic
from seqshape.sim import trajectories as tj
from seqshape.sim.generate import PRESETS, config_dict, preset_config

L, W = 4.6, 1.85
BINS = (0, 20, 45, 70, 110, 135, 160, 180.01)


def _traffic(rng, **kw):
    return tj.sample_trajectory(rng, placement="traffic", length=L, width=W, **kw)


def _forced(rng, manoeuvre, situation, n=60):
    t = np.arange(n) / 10.0
    return traffic.sample_traffic(rng, t, manoeuvre, L, W, 3.0, 60.0, 1.5, situation=situation)


def _digest(tr) -> str:
    h = hashlib.sha1()
    for a in (tr.t, tr.x, tr.y, tr.yaw, tr.ego_x):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(f"{tr.manoeuvre}/{tr.situation}".encode())
    return h.hexdigest()


def test_view_angle_hand_computed():
    # car 20 m ahead heading away: the sensor sees its tail; heading toward us: its nose
    assert tj.view_angle(20.0, 0.0, 0.0) == pytest.approx(180.0)
    assert tj.view_angle(20.0, 0.0, math.pi) == pytest.approx(0.0)
    # beside us, heading +x: the sensor (at -y of the car) sees its right side
    assert tj.view_angle(0.0, 5.0, 0.0) == pytest.approx(90.0)
    # 10 m ahead in the next lane (3.5 m left), oncoming: 180 - atan2(3.5, 10) from the tail
    assert tj.view_angle(10.0, 3.5, math.pi) == pytest.approx(math.degrees(math.atan2(3.5, 10)))


def test_seeded_and_deterministic():
    a = [_digest(_traffic(np.random.default_rng(s))) for s in range(5)]
    b = [_digest(_traffic(np.random.default_rng(s))) for s in range(5)]
    assert a == b and len(set(a)) == 5


# SHA-1 of eight crossing-placement tracks (t, x, y, yaw, manoeuvre) from the code before the
# traffic placement existed (git HEAD of 2026-12-02 10:40 UTC)
CROSSING_DIGEST = "e28c435a01ae5fe15e98eaed9eb686199c5c46f9"


def test_crossing_placement_unchanged():
    h = hashlib.sha1()
    rng = np.random.default_rng(123)
    for m in [None, "straight", "turn", "lane_change", "stop_and_go", "u_turn", "parked", None]:
        tr = tj.sample_trajectory(rng, manoeuvre=m, length=4.4, width=1.8, max_frames=60,
                                  mean_frames=30.0)
        assert tr.ego_x is None and tr.situation == ""
        for a in (tr.t, tr.x, tr.y, tr.yaw):
            h.update(a.tobytes())
        h.update(tr.manoeuvre.encode())
    assert h.hexdigest() == CROSSING_DIGEST


def test_same_lane_ahead_seen_from_the_rear_oncoming_from_the_front():
    rng = np.random.default_rng(7)
    rear, front = [], []
    for _ in range(40):
        tr = _forced(rng, "straight", "same_direction")
        ahead = (tr.x > 10) & (np.abs(tr.y) < 1.0)  # in the ego's lane, ahead
        rear.append(tj.view_angle(tr.x, tr.y, tr.yaw)[ahead])
        tr = _forced(rng, "straight", "oncoming")
        if tr.situation == "same_direction":  # a one-way street: no oncoming lanes
            continue
        ahead = (tr.x > 20) & (np.abs(tr.y) < 6.0)  # the nearest oncoming lanes, ahead
        front.append(tj.view_angle(tr.x, tr.y, tr.yaw)[ahead])
        assert np.all(np.abs(tj_wrap(tr.yaw - math.pi)) < 0.2)
    rear, front = np.concatenate(rear), np.concatenate(front)
    assert len(rear) > 50 and len(front) > 50
    assert rear.min() > 160 and front.max() < 20


def tj_wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


@pytest.mark.parametrize("manoeuvre", sorted(traffic.TRAFFIC_MANOEUVRES))
def test_clearance_distance_and_kinematics(manoeuvre):
    rng = np.random.default_rng(sorted(traffic.TRAFFIC_MANOEUVRES).index(manoeuvre))
    ego_fp = np.zeros((1, 4))
    for _ in range(12):
        tr = _traffic(rng, manoeuvre=manoeuvre, min_clearance=1.5, max_distance=60.0)
        assert tr.manoeuvre == manoeuvre and 10 <= len(tr) <= 200
        assert tj.footprint_distance(tr.x, tr.y, tr.yaw, L, W).min() >= 1.5 - 1e-9
        r = np.hypot(tr.x, tr.y)
        assert r.min() >= 3.0 and r.max() <= 60.0 + 1e-6
        poses = np.stack([tr.x, tr.y, np.zeros(len(tr)), tr.yaw], 1)
        ego = np.repeat(ego_fp, len(tr), 0)
        assert not tj.footprints_overlap(poses, (L, W), ego, traffic.EGO_SIZE,
                                         traffic.EGO_MARGIN - 1e-6).any()
        # in the road frame (ego motion added back) the rear axle moves along the heading
        wx = tr.x + tr.ego_x
        wb = 0.6 * L
        rx, ry = wx - wb / 2 * np.cos(tr.yaw), tr.y - wb / 2 * np.sin(tr.yaw)
        moving = np.hypot(np.diff(rx), np.diff(ry)) > 0.2
        if moving.any():
            heading = np.arctan2(np.diff(ry), np.diff(rx))
            mid = tr.yaw[:-1] + tj_wrap(np.diff(tr.yaw)) / 2
            assert np.abs(tj_wrap(heading - mid))[moving].max() < 0.05
        assert np.all(np.diff(tr.ego_x) >= 0) and tr.ego_x[0] == 0
        if manoeuvre == "parked":  # static in the road frame
            assert np.ptp(wx) < 1e-9 and np.ptp(tr.y) == 0


def test_rules_hold_for_cars_to_buses():
    rng = np.random.default_rng(5)
    for _ in range(300):
        length, width = rng.uniform(3.5, 12.0), rng.uniform(1.6, 2.6)
        tr = tj.sample_trajectory(rng, placement="traffic", length=length, width=width,
                                  max_frames=80, mean_frames=40.0)
        r = np.hypot(tr.x, tr.y)
        assert r.min() >= 3.0 and r.max() <= 60.0 + 1e-6
        assert tj.footprint_distance(tr.x, tr.y, tr.yaw, length, width).min() >= 1.5 - 1e-9
        poses = np.stack([tr.x, tr.y, np.zeros(len(tr)), tr.yaw], 1)
        assert not tj.footprints_overlap(poses, (length, width), np.zeros_like(poses),
                                         traffic.EGO_SIZE, traffic.EGO_MARGIN - 1e-6).any()


def test_parked_car_static_under_a_given_ego_motion():
    t = np.arange(40) / 10.0
    ego_x = 8.0 * t
    tr = traffic.sample_traffic(np.random.default_rng(3), t, "parked", L, W, 3.0, 60.0, 1.5,
                                ego_x=ego_x)
    np.testing.assert_array_equal(tr.ego_x, ego_x)
    np.testing.assert_allclose(tr.x + ego_x, tr.x[0], atol=1e-9)  # moves by -ego in the sensor
    assert np.ptp(tj.view_angle(tr.x, tr.y, tr.yaw)) > 5  # seen from changing views
    poses = tr.ego_poses(slope_x=0.02)
    assert poses.shape == (40, 4, 4)
    np.testing.assert_allclose(poses[:, 0, 3], ego_x)
    np.testing.assert_allclose(poses[:, 2, 3], 0.02 * ego_x)
    with pytest.raises(ConfigError, match="ego_x"):
        traffic.sample_traffic(np.random.default_rng(3), t, "parked", L, W, 3.0, 60.0, 1.5,
                               ego_x=ego_x[:5])


def test_situation_shares_and_lanes():
    rng = np.random.default_rng(11)
    seen = {k: 0 for k in [*traffic.SITUATIONS, "parked"]}
    for _ in range(400):
        seen[_traffic(rng, max_frames=20, mean_frames=12.0).situation] += 1
    assert abs(seen["parked"] / 400 - traffic.TRAFFIC_MANOEUVRES["parked"]) < 0.08
    moving = 400 - seen["parked"]
    # oncoming loses one-way streets (15 %) to same_direction
    assert abs(seen["crossing"] / moving - traffic.SITUATIONS["crossing"]) < 0.08
    assert seen["oncoming"] < seen["same_direction"]
    road = traffic.sample_road(np.random.default_rng(0))
    lanes = np.array(road.same + road.opposite)
    assert 0.0 in road.same and np.allclose(np.diff(np.sort(np.abs(road.same))) % 3.5, 0)
    assert (np.abs(lanes) < max(abs(road.near_kerb), abs(road.far_kerb))).all()


def test_bad_arguments():
    rng = np.random.default_rng(0)
    with pytest.raises(ConfigError, match="placement"):
        tj.sample_trajectory(rng, placement="highway")
    with pytest.raises(ConfigError, match="situation"):
        _forced(rng, "straight", "merging")
    with pytest.raises(ConfigError, match="placement"):
        preset_config("real", placement="side")


def test_presets_and_saved_config():
    assert PRESETS["real"].placement == "traffic"
    for name in ("tiny", "paper", "realistic"):
        assert PRESETS[name].placement == "crossing"
        assert "placement" not in config_dict(PRESETS[name])  # older datasets stay identical
    assert config_dict(PRESETS["real"])["placement"] == "traffic"


# --------------------------------------------------------------- the real preset, end to end

SMALL = dict(n_vehicles=8, n_val_vehicles=1, tracks_per_vehicle=2, min_frames=8, max_frames=16,
             mean_frames=12.0, num_points=64, sensor="vlp16")


@pytest.fixture(scope="module")
def real_small():
    from seqshape.sim.generate import _load_vehicles, _splits

    cfg = preset_config("real", **SMALL)
    vehicles = _load_vehicles(cfg)
    return cfg, vehicles, _splits(len(vehicles), cfg)


def test_real_track_carries_ego_poses(real_small):
    from seqshape.sim.generate import make_track_in_process

    cfg, vehicles, splits = real_small
    found = False
    for i in range(16):
        tr = make_track_in_process(cfg, vehicles, splits, i)
        ego = np.asarray(tr.meta["ego_poses"])
        assert ego.shape == (len(tr), 4, 4) and tr.meta["placement"] == "traffic"
        np.testing.assert_allclose(ego[0], np.eye(4))
        if tr.meta["manoeuvre"] != "parked" or np.ptp(ego[:, 0, 3]) == 0:
            continue
        found = True
        # a parked car mapped into the first frame's sensor frame stands still
        centres = np.einsum("tij,tj->ti", ego[:, :3, :3], tr.poses[:, :3]) + ego[:, :3, 3]
        np.testing.assert_allclose(centres - centres[0], 0.0, atol=1e-6)
        break
    assert found, "no parked track with a moving ego among the first 16"


def test_clutter_stays_still_in_the_world():
    """Clutter sampled for a moving ego: every return, moved by its frame's ego pose, lies on
    the clutter's surface in the first frame's sensor frame (and the ranges change)."""
    import trimesh

    from seqshape.sim import _worker, real

    rc = real.RealConfig(max_clutter=6)
    t = np.arange(12) / 10.0
    ego_x = 10.0 * t
    sx = 0.02
    n, d = real.ground_plane(1.8, sx, 0.0)
    poses = np.stack([20.0 - ego_x, np.full(12, -4.0), np.zeros(12), np.zeros(12)], 1)  # parked
    for seed in range(20):
        clutter, objs = _worker._static_clutter(np.random.default_rng(seed), poses, (L, W, 1.5),
                                                [], ego_x, sx, (n, d), rc)
        if objs:
            break
    assert objs, "no clutter drawn in 20 seeds"
    obj = objs[0]
    np.testing.assert_allclose(obj.poses[:, 0], -ego_x)
    np.testing.assert_allclose(obj.poses[:, 2], -sx * ego_x)
    world = trimesh.util.concatenate([m for m, _, _ in clutter])
    # rays from every frame's sensor toward the clutter's vertices
    targets = world.vertices[::max(1, len(world.vertices) // 40)]
    frames = np.repeat(np.arange(12), len(targets))
    shift = np.stack([ego_x, np.zeros(12), sx * ego_x], 1)
    rel = np.tile(targets, (12, 1)) - shift[frames]
    dirs = rel / np.linalg.norm(rel, axis=1, keepdims=True)
    scene = real.Scene([obj], n, d, 0.1)
    rng_, which, _ = real.cast_scene(scene, np.zeros_like(dirs), dirs, frames)
    hit = which == 0
    assert hit.sum() > 20
    pts = dirs[hit] * rng_[hit, None] + shift[frames[hit]]  # back into the first frame
    _, dist, _ = trimesh.proximity.closest_point(world, pts)
    assert dist.max() < 1e-6
    assert np.ptp(rng_[hit]) > 5.0
