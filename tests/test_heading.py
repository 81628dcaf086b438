"""The heading step's shape evidence (issues 15, 19): the front of a parked vehicle from the
front/back asymmetry of its observed side silhouette (seqshape.model.heading)."""

from __future__ import annotations

import numpy as np
import pytest

from seqshape.geometry import canonical_to_sensor
from seqshape.model.heading import (
    EndProfile,
    HeadingConfig,
    HeadingFilter,
    shape_flips,
    wrap_angle,
)

LENGTH, WIDTH = 4.6, 1.8


def _hood_car(x: np.ndarray) -> np.ndarray:
    """Roof line of a hatchback whose front is +x: a 0.9 m hood over the front 1.1 m, a
    windscreen rising to the 1.5 m roof, a near-vertical tall tail (1.3 m) at the rear."""
    front = LENGTH / 2 - x  # distance from the nose
    return np.select([front < 1.1, front < 1.9, front < 4.3],
                     [0.9, 0.9 + 0.6 * (front - 1.1) / 0.8, 1.5], 1.3)


def _box(x: np.ndarray) -> np.ndarray:
    """A symmetric box, 1.5 m tall."""
    return np.full_like(x, 1.5)


def _side_view(roof, n: int, rng: np.random.Generator, x_range=(-LENGTH / 2, LENGTH / 2)
               ) -> np.ndarray:
    """Canonical points the sensor sees of a vehicle with roof line ``roof``: its +y side
    (uniform in x and in height up to the roof) and its roof. z from the box centre, the box
    being 1.5 m tall."""
    x = rng.uniform(*x_range, n)
    top = roof(x)
    on_side = rng.random(n) < 0.7
    y = np.where(on_side, WIDTH / 2, rng.uniform(-WIDTH / 2, WIDTH / 2, n))
    z = np.where(on_side, rng.uniform(0.0, 1.0, n) * top, top)
    return np.stack([x, y, z - 0.75], axis=1)


def _track(roof, true_yaw: float, frames: int = 6, n: int = 300, centre=(9.0, 4.0),
           speed: float = 0.0, seed: int = 0, x_range=(-LENGTH / 2, LENGTH / 2)):
    """Sensor-frame points and true poses of a vehicle at rest (or driving along its heading
    at ``speed`` m per frame) in front of a static sensor."""
    rng = np.random.default_rng(seed)
    pts, poses = [], []
    for t in range(frames):
        pose = np.array([centre[0] + speed * t * np.cos(true_yaw),
                         centre[1] + speed * t * np.sin(true_yaw), -0.9, true_yaw])
        pts.append(canonical_to_sensor(_side_view(roof, n, rng, x_range), pose))
        poses.append(pose)
    return pts, np.array(poses)


def _run(pts, poses, yaw_offset: float, cfg: HeadingConfig, cls=None) -> list[bool]:
    """The online filter's flips for estimates at the true poses with yaw + ``yaw_offset``."""
    filt = HeadingFilter(cfg)
    out = []
    for p, pose in zip(pts, poses, strict=True):
        est = pose.copy()
        est[3] = wrap_angle(est[3] + yaw_offset)
        out.append(filt.update(est, None, True, p, cls))
    return out


STATIC = HeadingConfig(static_sensor=True, shape=True)


def test_profile_score_sign_follows_the_front():
    rng = np.random.default_rng(1)
    local = _side_view(_hood_car, 2000, rng)
    fwd, back = EndProfile(), EndProfile()
    fwd.add(local)
    back.add(local * [-1.0, -1.0, 1.0])  # the same car seen in a box frame turned by pi
    one = HeadingConfig(shape=True, shape_min_frames=1)
    s = fwd.score(one)
    assert s > 2 * one.shape_margin
    assert back.score(one) == pytest.approx(-s, abs=0.1)
    assert fwd.score(STATIC) is None  # one frame: too few


def test_reversed_parked_track_is_turned_after_min_frames():
    pts, poses = _track(_hood_car, 0.4, frames=8)
    wait = STATIC.shape_min_frames - 1
    assert _run(pts, poses, np.pi, STATIC) == [False] * wait + [True] * (8 - wait)
    assert _run(pts, poses, 0.05, STATIC) == [False] * 8
    quick = HeadingConfig(static_sensor=True, shape=True, shape_min_frames=1)
    assert _run(pts, poses, np.pi, quick) == [True] * 8


def test_reversed_parked_track_with_ego_poses():
    """The same with a moving ego: points in each frame's sensor frame, ego poses given."""
    pts, poses = _track(_hood_car, 0.4, frames=8)
    filt = HeadingFilter(HeadingConfig(shape=True))
    flips = []
    for t, (p, pose) in enumerate(zip(pts, poses, strict=True)):
        ego = np.eye(4)
        ego[:3, 3] = [0.8 * t, 0.0, 0.0]  # the ego drives along x; the car is at rest
        est = pose.copy()
        est[0] -= 0.8 * t
        est[3] += np.pi
        flips.append(filt.update(est, ego, True, p - [0.8 * t, 0.0, 0.0]))
    assert flips == [False] * 4 + [True] * 4


def test_symmetric_box_abstains():
    pts, poses = _track(_box, 0.4)
    assert _run(pts, poses, np.pi, STATIC) == [False] * 6
    assert shape_flips(pts, poses, None, STATIC) is None


def test_one_end_seen_abstains():
    """Only the rear half was observed: no comparison of the two ends."""
    pts, poses = _track(_hood_car, 0.4, x_range=(-LENGTH / 2, 0.0))
    assert _run(pts, poses, np.pi, STATIC) == [False] * 6


@pytest.mark.parametrize("cls", ["truck", "bus", "trailer"])
def test_other_classes_abstain(cls):
    pts, poses = _track(_hood_car, 0.4)
    assert _run(pts, poses, np.pi, STATIC, cls) == [False] * 6
    assert shape_flips(pts, poses, None, STATIC, cls) is None


def test_too_few_points_abstain_and_off_switch():
    pts, poses = _track(_hood_car, 0.4, n=20, frames=2)
    assert _run(pts, poses, np.pi, STATIC) == [False] * 2
    pts, poses = _track(_hood_car, 0.4)
    assert _run(pts, poses, np.pi, HeadingConfig(static_sensor=True)) == [False] * 6  # default
    assert shape_flips(pts, poses + [0, 0, 0, np.pi], None, HeadingConfig(static_sensor=True)) \
        is None


def test_without_points_the_filter_is_unchanged():
    pts, poses = _track(_hood_car, 0.4)
    filt = HeadingFilter(STATIC)
    assert [filt.update(p + [0, 0, 0, np.pi], None, True) for p in poses] == [False] * 6


def test_motion_wins_over_the_shape():
    """A vehicle driving along +x whose silhouette says the opposite (a reversed roof line),
    then stopping: the motion decides, and after it has, the shape is not used."""
    def reversed_car(x):
        return _hood_car(-x)

    pts, poses = _track(reversed_car, 0.0, frames=8, speed=1.0)
    still, still_poses = _track(reversed_car, 0.0, frames=12, centre=(16.0, 4.0), seed=1)
    filt = HeadingFilter(STATIC)
    flips = [filt.update(pose, None, True, p) for p, pose in
             zip(pts + still, np.concatenate([poses, still_poses]), strict=True)]
    assert flips == [False] * 20
    # the same parked stretch alone: the shape decides (here against the true heading)
    filt = HeadingFilter(STATIC)
    assert [filt.update(pose, None, True, p) for p, pose in
            zip(still, still_poses, strict=True)][-1] is True


def test_sideways_frames_are_left_out():
    """A frame whose yaw is 90 degrees off the axis does not enter the silhouette."""
    pts, poses = _track(_hood_car, 0.4, frames=8)
    filt = HeadingFilter(STATIC)
    for t, (p, pose) in enumerate(zip(pts, poses, strict=True)):
        filt.update(pose + [0, 0, 0, np.pi / 2 if t == 3 else 0.0], None, True, p)
    assert filt.profile.frames == 7


def test_whole_track_shape_flips():
    pts, poses = _track(_hood_car, -2.0)
    est = poses.copy()
    est[1::2, 3] += np.pi  # every other frame reversed
    flips = shape_flips(pts, est, [np.eye(4)] * len(est), STATIC)
    assert flips.tolist() == [False, True] * 3
    assert shape_flips(pts, est, None, HeadingConfig(shape=True)) is None  # no fixed frame
    moving, moving_poses = _track(_hood_car, -2.0, frames=8, speed=1.0)
    assert shape_flips(moving, moving_poses + [0, 0, 0, np.pi], None, STATIC) is None


def test_ego_pose_frames_without_pose_take_no_part():
    pts, poses = _track(_hood_car, 1.0)
    egos = [np.eye(4)] * 5 + [None]
    flips = shape_flips(pts, poses + [0, 0, 0, np.pi], egos, HeadingConfig(shape=True))
    assert flips.tolist() == [True] * 5 + [False]


def test_non_finite_points_are_ignored():
    pts, poses = _track(_hood_car, 0.4, frames=8)
    bad = [np.vstack([p, [[np.nan, 0.0, 0.0], [np.inf, 1.0, 1.0]]]) for p in pts]
    assert _run(bad, poses, np.pi, STATIC) == _run(pts, poses, np.pi, STATIC)


@pytest.mark.parametrize("kw", [dict(shape_min_frames=0), dict(shape_min_points=0),
                                dict(shape_min_length=7.0), dict(shape_margin=-0.1),
                                dict(shape_max_turn=2.0), dict(shape_min_heights=0)])
def test_bad_shape_options_are_refused(kw):
    from seqshape.errors import ConfigError

    with pytest.raises(ConfigError):
        HeadingConfig(**kw)


def test_a_few_scan_rings_abstain():
    """A symmetric box seen on two scan rings whose height grows with the range along the body
    (a far vehicle): the rings' slope is no outline, so the step abstains; without the height
    cells check it would take the slope for a front."""
    rng = np.random.default_rng(3)
    pose = np.array([25.0, 4.0, -0.9, 0.4])
    rings = []
    for _ in range(8):
        local = _side_view(_box, 300, rng)
        ring = np.where(local[:, 2] > 0.0, 0.3, -0.3)
        local[:, 2] = ring + 0.12 * local[:, 0]
        rings.append(canonical_to_sensor(local, pose))
    poses = np.tile(pose, (8, 1))
    assert _run(rings, poses, np.pi, STATIC) == [False] * 8
    assert shape_flips(rings, poses, None, STATIC) is None
    blind = HeadingConfig(static_sensor=True, shape=True, shape_min_heights=1)
    assert any(_run(rings, poses, np.pi, blind) + _run(rings, poses, 0.0, blind))
