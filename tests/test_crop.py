"""The one crop function (seqshape.data.crop) on hand-made sweeps with known ground."""

import numpy as np
import pytest

from seqshape.data.crop import (
    CropConfig,
    SweepIndex,
    crop_vehicle,
    crop_vehicles,
    local_ground,
)
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
