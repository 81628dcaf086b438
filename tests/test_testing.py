"""The shared reference clouds and tolerances of :mod:`seqshape.testing`."""

from __future__ import annotations

import numpy as np
import pytest

from seqshape.geometry import sensor_to_canonical
from seqshape.testing import (
    CAR_SIZE,
    TOLERANCES,
    assert_close,
    box_shell,
    box_surface,
    tolerance,
)

SIZE = np.array([4.0, 2.0, 1.0])


def _faces(points: np.ndarray, size) -> np.ndarray:
    """``(N, 3)`` bool: which of the coordinates lie on a face (|x| = l/2, ...)."""
    return np.isclose(np.abs(points), np.asarray(size) / 2, rtol=0, atol=1e-9)


@pytest.mark.parametrize("sampler", [box_surface, box_shell])
def test_points_lie_on_the_surface(sampler):
    p = sampler(5000, 3, SIZE)
    assert p.shape == (5000, 3) and p.dtype == np.float64
    assert np.all(np.abs(p) <= SIZE / 2 + 1e-12)
    assert _faces(p, SIZE).any(axis=1).all()


def test_box_surface_is_uniform_over_the_area():
    """Share of points per face pair = its share of the 28 m^2: x faces 2 x (2 x 1), y faces
    2 x (4 x 1), z faces 2 x (4 x 2)."""
    p = box_surface(40000, 0, SIZE)
    share = _faces(p, SIZE).mean(0)  # x faces (w x h), y faces (l x h), z faces (l x w)
    np.testing.assert_allclose(share, [4 / 28, 8 / 28, 16 / 28], atol=0.01)


def test_box_shell_puts_a_third_on_each_face_pair():
    share = _faces(box_shell(40000, 0, SIZE), SIZE).mean(0)
    np.testing.assert_allclose(share, [1 / 3, 1 / 3, 1 / 3], atol=0.01)


@pytest.mark.parametrize("sampler", [box_surface, box_shell])
def test_pose_and_dtype(sampler):
    pose = np.array([12.0, -3.0, -0.9, 2.5])
    canonical = sampler(100, 7, CAR_SIZE)
    posed = sampler(100, 7, CAR_SIZE, pose=pose, dtype=np.float32)
    assert posed.dtype == np.float32
    np.testing.assert_allclose(sensor_to_canonical(posed.astype(np.float64), pose), canonical,
                               atol=1e-5)
    assert np.linalg.norm(posed.mean(0)[:2] - pose[:2]) < 1.0


@pytest.mark.parametrize("sampler", [box_surface, box_shell])
def test_a_generator_is_drawn_from_in_turn(sampler):
    rng = np.random.default_rng(11)
    first, second = sampler(50, rng), sampler(50, rng)
    assert not np.array_equal(first, second)
    assert np.array_equal(first, sampler(50, 11))
    replay = np.random.default_rng(11)
    sampler(50, replay)
    assert np.array_equal(second, sampler(50, replay))


def test_fixed_draws():
    """The clouds the tests' expected numbers were measured on (changing them changes those)."""
    np.testing.assert_allclose(box_surface(3, 0), [
        [-2.175625640121619, 0.5638864305604904, 0.75],
        [0.4798609909523094, 0.9, 0.0654374871981343],
        [2.25, 0.5685363974187579, -0.7458922497447779]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(box_shell(3, 0), [
        [0.6163275929465444, 0.9, -0.6885397140957079],
        [-2.175625640121619, 0.5638864305604904, 0.75],
        [-2.25, 0.41309380977119714, 0.0654374871981343]], rtol=0, atol=1e-12)


def test_degenerate_box():
    p = box_surface(10, 0, (0.0, 0.0, 0.0))
    assert np.array_equal(p, np.zeros((10, 3)))
    flat = box_surface(1000, 0, (4.0, 2.0, 0.0))  # a rectangle: only its two z faces have area
    assert np.all(flat[:, 2] == 0.0)


def test_tolerances():
    assert tolerance(np.float32) == TOLERANCES[np.float32] == tolerance(np.zeros(2, np.float32))
    assert tolerance("float64") == TOLERANCES[np.float64]
    with pytest.raises(ValueError, match="no tolerance for dtype int64"):
        tolerance(np.int64)
    assert_close(np.float32([1.0]) + np.float32(5e-6), [1.0])
    with pytest.raises(AssertionError):
        assert_close(np.float32([1.0]) + np.float32(1e-4), [1.0])
    with pytest.raises(AssertionError):
        assert_close(np.array([1.0 + 1e-6]), [1.0])  # float64: 1e-9
    assert_close(np.array([1.0 + 1e-6]), [1.0], dtype=np.float32)
