"""The classical box fit: rectangles of hand-made bird's-eye point sets and heading choice."""

from __future__ import annotations

import math

import numpy as np
import pytest

from seqshape.errors import ConfigError
from seqshape.geometry import canonical_to_sensor, sensor_to_canonical
from seqshape.model.boxfit import (
    BoxFitConfig,
    BoxFitEstimator,
    Rectangle,
    _BoxTrack,
    fit_lshape,
    fit_min_area_rect,
)

L, W = 4.5, 1.8


def posed(xy: np.ndarray, centre, heading: float) -> np.ndarray:
    c, s = math.cos(heading), math.sin(heading)
    return xy @ np.array([[c, s], [-s, c]]) + centre


def l_of_two_sides(n: int, seed: int, noise: float = 0.0) -> np.ndarray:
    """Canonical (x, y) of a car's right side (y = -W/2) and rear (x = -L/2), as a LiDAR on the
    right-rear sees it."""
    rng = np.random.default_rng(seed)
    side = np.c_[rng.uniform(-L / 2, L / 2, n), np.full(n, -W / 2)]
    rear = np.c_[np.full(n // 2, -L / 2), rng.uniform(-W / 2, W / 2, n // 2)]
    return np.r_[side, rear] + rng.normal(0, noise, (n + n // 2, 2))


def heading_err(a: float, b: float, period: float = math.pi) -> float:
    d = (a - b) % period
    return math.degrees(min(d, period - d))


@pytest.mark.parametrize("criterion", ["closeness", "variance"])
@pytest.mark.parametrize("heading", [0.0, 0.52, 1.4, 2.6])
def test_lshape_of_two_sides_recovers_the_rectangle(criterion, heading):
    pts = posed(l_of_two_sides(120, 1), [12.0, -4.0], heading)
    r = fit_lshape(pts, criterion)
    assert heading_err(r.heading, heading) < 1.0
    assert 0 <= r.heading < math.pi
    np.testing.assert_allclose(r.centre, [12.0, -4.0], atol=0.05)
    assert r.length == pytest.approx(L, abs=0.06) and r.width == pytest.approx(W, abs=0.06)


def test_lshape_on_noisy_points_and_one_side_only():
    pts = posed(l_of_two_sides(200, 2, noise=0.03), [8.0, 3.0], 0.9)
    r = fit_lshape(pts)
    assert heading_err(r.heading, 0.9) < 3.0
    np.testing.assert_allclose(r.centre, [8.0, 3.0], atol=0.15)
    # one long side only: the axis and the centre along it are known, the width is not
    side = posed(np.c_[np.linspace(-L / 2, L / 2, 80), np.full(80, -W / 2)], [8.0, 3.0], 0.9)
    r = fit_lshape(side)
    assert heading_err(r.heading, 0.9) < 1.0
    assert r.length == pytest.approx(L, abs=0.1) and r.width < 0.05
    along = np.array([math.cos(0.9), math.sin(0.9)])
    assert (r.centre - [8.0, 3.0]) @ along == pytest.approx(0.0, abs=0.05)


def test_min_area_rect_of_a_closed_outline():
    rng = np.random.default_rng(4)
    u = rng.uniform(-0.5, 0.5, 400)
    outline = np.r_[np.c_[u[:100] * L, np.full(100, W / 2)],
                    np.c_[u[100:200] * L, np.full(100, -W / 2)],
                    np.c_[np.full(100, L / 2), u[200:300] * W],
                    np.c_[np.full(100, -L / 2), u[300:] * W]]
    r = fit_min_area_rect(posed(outline, [-5.0, 7.0], 2.2))
    assert heading_err(r.heading, 2.2) < 0.5
    np.testing.assert_allclose(r.centre, [-5.0, 7.0], atol=0.02)
    assert r.length == pytest.approx(L, abs=0.03) and r.width == pytest.approx(W, abs=0.03)
    est = BoxFitEstimator(method="min_area_rect")
    assert est.kind == "boxfit:min_area_rect"


def oncoming_track(n: int = 5, step: float = -0.8):
    """A car ahead of the sensor facing it (yaw pi), driving towards it by ``step`` m/frame;
    the sensor sees its front (x = +L/2 canonical) and its right side."""
    rng = np.random.default_rng(5)
    frames, poses = [], []
    for t in range(n):
        pose = np.array([20.0 + step * t, 3.0, -1.0, math.pi])
        side = np.c_[rng.uniform(-L / 2, L / 2, 60), np.full(60, -W / 2)]
        front = np.c_[np.full(30, L / 2), rng.uniform(-W / 2, W / 2, 30)]
        xy = np.r_[side, front]
        z = rng.uniform(-0.7, 0.7, (len(xy), 1))
        frames.append(canonical_to_sensor(np.c_[xy, z], pose))
        poses.append(pose)
    return frames, np.array(poses)


def test_heading_follows_motion_once_moved_else_faces_away():
    frames, poses = oncoming_track()
    est = BoxFitEstimator()
    yaws = [est.step(["a"], [f])[0].pose[3] for f in frames]
    # frames 0-1: moved at most 0.8 m, the front faces away from the sensor: flipped
    assert heading_err(yaws[0], 0.0, 2 * math.pi) < 1.0
    assert heading_err(yaws[1], 0.0, 2 * math.pi) < 1.0
    # from frame 2 the fitted centre moved 1.6 m towards -x: the heading follows the motion
    for y in yaws[2:]:
        assert heading_err(y, math.pi, 2 * math.pi) < 1.0
    # a parked vehicle keeps the previous frame's choice
    est.reset("a")
    st = _BoxTrack(first_centre=np.array([20.0, 3.0]), heading=math.pi + 0.1)
    h, ln, w = est.choose_heading(st, Rectangle(np.array([20.1, 3.0]), L, W, 0.1))
    assert h == pytest.approx(math.pi + 0.1) and (ln, w) == (L, W)


def test_motion_settles_which_side_is_the_length():
    est = BoxFitEstimator()
    st = _BoxTrack(first_centre=np.zeros(2))
    # a rectangle fitted with its long side across the motion (e.g. a truck seen from behind)
    h, ln, w = est.choose_heading(st, Rectangle(np.array([0.0, 2.0]), 2.5, 1.0, 0.0))
    assert heading_err(h, math.pi / 2, 2 * math.pi) < 1e-9 and (ln, w) == (1.0, 2.5)


def test_estimate_box_surface_size_and_empty_frames():
    frames, poses = oncoming_track(3)
    est = BoxFitEstimator(num_complete=256)
    out = est.step(["a", "b"], [frames[0], np.zeros((0, 3))])
    a, b = out
    assert a.complete.shape == (256, 3) and a.complete.dtype == np.float32
    assert a.num_points == len(frames[0])
    local = sensor_to_canonical(a.complete, a.pose)
    half = a.size / 2
    assert np.all(np.abs(local) <= half + 1e-4)
    on_face = np.isclose(np.abs(local), half, atol=1e-4).any(axis=1)
    assert on_face.all()
    np.testing.assert_allclose(a.size, [L, W, 1.4], atol=0.1)
    assert a.pose[2] == pytest.approx(-1.0, abs=0.05)
    # no points yet: NaN pose, no shape; a later empty frame repeats the last estimate
    assert np.isnan(b.pose).all() and len(b.complete) == 0
    again = est.step(["a"], [np.zeros((0, 3))])[0]
    np.testing.assert_array_equal(again.pose, a.pose)
    assert again.num_points == 0
    est.reset()
    assert est.track_ids == []


def test_bad_configuration_is_a_config_error():
    with pytest.raises(ConfigError, match="method"):
        BoxFitEstimator(method="hough")
    with pytest.raises(ConfigError, match="criterion"):
        BoxFitConfig(criterion="area")
    with pytest.raises(ConfigError, match="shape"):
        BoxFitEstimator().step(["a"], [np.zeros((4, 2))])
