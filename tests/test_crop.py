"""The one crop function (seqshape.data.crop) on hand-made sweeps with known ground."""

import numpy as np
import pytest

from seqshape.data.crop import CropConfig, crop_vehicle, local_ground
from seqshape.errors import ConfigError
from seqshape.geometry import canonical_to_sensor

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
