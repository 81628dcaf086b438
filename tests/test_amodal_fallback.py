"""Mask-only labels of 2D instances without LiDAR support (seqshape.amodal.fallback)."""

import numpy as np
import pytest
from test_amodal_labeler import SIZE, H, hull

from seqshape.amodal.fallback import FallbackConfig, convex_fill, ground_depth, mask_instance
from seqshape.camera import kitti_default_calib, project_points

FLAT = (np.array([0.0, 0.0, 1.0]), H)  # the road, z = -1.73 m in the velodyne frame


@pytest.mark.parametrize("point", [(30.0, 2.0), (8.0, -3.0), (150.0, 5.0)])
def test_ground_depth_round_trip(point):
    calib = kitti_default_calib()
    p = np.array([[point[0], point[1], -H]])
    uv, depth = project_points(p, calib)
    hit = ground_depth(*uv[0], FLAT, calib)
    assert hit is not None
    assert hit[0] == pytest.approx(depth[0], rel=1e-9)
    np.testing.assert_allclose(hit[1], p[0], atol=1e-6)


def test_ray_above_the_horizon_misses_the_ground():
    calib = kitti_default_calib()
    assert ground_depth(600.0, 20.0, FLAT, calib) is None  # pixel in the sky


@pytest.mark.parametrize("x", [40.0, 120.0])
def test_far_vehicle_mask_becomes_a_label_at_its_depth(x):
    calib = kitti_default_calib()
    pose = np.array([x, 1.0, -H + SIZE[2] / 2, 0.3])
    mask = hull(pose, calib)
    inst = mask_instance("far", mask, 0.9, FLAT, calib)
    assert inst is not None and np.array_equal(inst.amodal, convex_fill(mask))
    # the bottom edge is the nearest bottom corner's row (2.4 m in front of the centre), to
    # within a pixel row, which spans D^2 / (f H) metres of depth on the road
    _, d_centre = project_points(pose[None, :3], calib)
    d_corner = d_centre[0] - 2.4
    one_px = d_corner**2 / (calib.P(2)[1, 1] * H)
    assert abs(inst.depth - d_corner) < max(one_px, 0.5), (inst.depth, d_corner, one_px)
    assert np.all(inst.z == inst.depth) and len(inst.uv) > 0


def test_implausible_masks_are_rejected():
    calib = kitti_default_calib()
    pose = np.array([60.0, 1.0, -H + SIZE[2] / 2, 0.0])
    mask = hull(pose, calib)
    cfg = FallbackConfig()
    assert mask_instance("low score", mask, cfg.min_score - 0.01, FLAT, calib) is None
    sky = np.zeros_like(mask)
    sky[5:30, 600:640] = True
    assert mask_instance("sky", sky, 1.0, FLAT, calib) is None
    rows, cols = np.nonzero(mask)
    tall = np.zeros_like(mask)  # same bottom edge, 10x the height: a 15 m "vehicle"
    tall[max(0, rows.max() - 10 * (rows.max() - rows.min())):rows.max() + 1,
         cols.min():cols.max() + 1] = True
    assert mask_instance("tall", tall, 1.0, FLAT, calib) is None
    cut = hull(np.array([3.5, 0.0, -H + SIZE[2] / 2, 0.0]), calib)
    assert cut[-1].any()  # cut by the bottom border: no ground contact in the image
    assert mask_instance("cut", cut, 1.0, FLAT, calib) is None
    near = hull(np.array([10.0, 0.0, -H + SIZE[2] / 2, 0.0]), calib)
    assert not near[-1].any() and mask_instance("near", near, 1.0, FLAT, calib) is not None
    assert mask_instance("near", near, 1.0, FLAT, calib, FallbackConfig(min_distance=9.0)) is None
    assert mask_instance("empty", np.zeros_like(mask), 1.0, FLAT, calib) is None


def test_convex_fill_closes_notches_and_keeps_convex_masks():
    m = np.zeros((40, 60), bool)
    m[10:30, 10:50] = True
    assert np.array_equal(convex_fill(m), m)  # a rectangle is its own hull
    notched = m.copy()
    notched[10:20, 25:30] = False  # a notch from the top edge
    notched[22, 40] = False  # a hole
    assert np.array_equal(convex_fill(notched), m)
    tiny = np.zeros((5, 5), bool)
    tiny[2, 2] = True
    assert np.array_equal(convex_fill(tiny), tiny)
