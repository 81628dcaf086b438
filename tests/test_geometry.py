import numpy as np
import pytest

from seqshape import geometry as g


def test_wrap_angle_range_and_identity():
    a = np.linspace(-20, 20, 1001)
    w = g.wrap_angle(a)
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    assert np.allclose(np.cos(w), np.cos(a)) and np.allclose(np.sin(w), np.sin(a))


def test_canonical_to_sensor_hand_computed():
    # front bumper of a 4 m car heading +y (yaw 90 deg) at (10, 5, -1): ends up at (10, 7, -1)
    p = np.array([[2.0, 0.0, 0.0], [0.0, 1.0, 0.5]], dtype=np.float32)
    out = g.canonical_to_sensor(p, [10.0, 5.0, -1.0, np.pi / 2])
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, [[10, 7, -1], [9, 5, -0.5]], atol=1e-6)


def test_transform_round_trip_and_matrix_agreement():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(50, 3))
    for _ in range(10):
        pose = np.r_[rng.normal(size=3) * 10, rng.uniform(-np.pi, np.pi)]
        m = g.pose_to_matrix(pose)
        np.testing.assert_allclose(g.canonical_to_sensor(pts, pose), pts @ m[:3, :3].T + m[:3, 3])
        np.testing.assert_allclose(g.sensor_to_canonical(g.canonical_to_sensor(pts, pose), pose),
                                   pts, atol=1e-12)
        np.testing.assert_allclose(g.matrix_to_pose(m), pose, atol=1e-12)


def test_compose_and_invert():
    a = np.array([1.0, 2.0, 0.5, 0.7])
    b = np.array([-3.0, 0.5, 0.0, -2.0])
    pts = np.random.default_rng(2).normal(size=(7, 3))
    np.testing.assert_allclose(g.canonical_to_sensor(pts, g.compose(a, b)),
                               g.canonical_to_sensor(g.canonical_to_sensor(pts, b), a), atol=1e-12)
    np.testing.assert_allclose(g.compose(a, g.invert(a)), np.zeros(4), atol=1e-12)


def test_box_corners_and_points_in_box():
    size = (4.0, 2.0, 1.5)
    pose = np.array([5.0, -3.0, -1.25, np.pi / 6])
    c = g.box_corners(size, pose)
    assert c.shape == (8, 3)
    local = g.sensor_to_canonical(c, pose)
    np.testing.assert_allclose(np.abs(local), np.tile([2.0, 1.0, 0.75], (8, 1)), atol=1e-12)
    inside = g.canonical_to_sensor(np.array([[1.9, 0.9, 0.7], [0, 0, 0]]), pose)
    outside = g.canonical_to_sensor(np.array([[2.1, 0, 0], [0, 1.1, 0], [0, 0, 0.8]]), pose)
    assert g.points_in_box(inside, size, pose).all()
    assert not g.points_in_box(outside, size, pose).any()
    assert g.points_in_box(outside[:1], size, pose, margin=0.2).all()


@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_yaw_to_rotmat_batched(shape):
    yaw = np.random.default_rng(0).uniform(-4, 4, size=shape)
    r = g.yaw_to_rotmat(yaw)
    assert r.shape == shape + (3, 3)
    eye = np.broadcast_to(np.eye(3), r.shape)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0)
