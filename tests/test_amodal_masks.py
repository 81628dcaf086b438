"""Masks and occlusion order of a hand-built two-vehicle frame."""

import cv2
import numpy as np
import pytest

from seqshape.amodal.masks import frame_masks, instance_from_projection, resolve_occlusion
from seqshape.camera import kitti_default_calib, project_points
from seqshape.geometry import box_corners, canonical_to_sensor

SIZE = (375, 1242)  # (h, w)


def box_surface(size, pose, n=6000, seed=0):
    """Points sampled uniformly on the surface of a posed box (sensor frame)."""
    rng = np.random.default_rng(seed)
    half = np.asarray(size) / 2
    p = rng.uniform(-half, half, size=(n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * half[axis]
    return canonical_to_sensor(p.astype(np.float32), pose)


def hull_mask(size, pose, calib):
    uv, _ = project_points(box_corners(size, pose), calib)
    m = np.zeros(SIZE, np.uint8)
    cv2.fillConvexPoly(m, cv2.convexHull(np.round(uv * 16).astype(np.int32)), 1, shift=4)
    return m.astype(bool)


def iou(a, b):
    return (a & b).sum() / (a | b).sum()


@pytest.fixture(scope="module")
def scene():
    calib = kitti_default_calib()
    size = np.array([4.5, 1.8, 1.5])
    near = np.array([10.0, 1.0, -0.98, 0.3])  # front, left of centre
    far = np.array([18.0, -1.6, -0.98, -0.2])  # behind it, partly hidden
    clouds = {"near": box_surface(size, near), "far": box_surface(size, far, seed=1)}
    refs = {"near": hull_mask(size, near, calib), "far": hull_mask(size, far, calib)}
    return calib, clouds, refs


@pytest.mark.parametrize("order", ["pixel", "median"])
def test_two_vehicle_frame(scene, order):
    calib, clouds, refs = scene
    insts = {m.track_id: m for m in frame_masks(clouds, calib, SIZE, order=order)}
    assert set(insts) == {"near", "far"}
    for tid in insts:
        assert iou(insts[tid].amodal, refs[tid]) > 0.95
    assert insts["near"].order == 0 and insts["far"].order == 1
    overlap = refs["near"] & refs["far"]
    assert overlap.sum() > 500  # the test is meaningful: they do overlap
    exp_far_visible = refs["far"] & ~refs["near"]
    assert iou(insts["far"].visible, exp_far_visible) > 0.9
    assert iou(insts["near"].visible, refs["near"]) > 0.95
    assert not (insts["near"].visible & insts["far"].visible).any()
    for m in insts.values():
        assert not (m.visible & ~m.amodal).any()


def test_pixel_order_beats_median_when_median_is_wrong():
    # a long bus beside the camera whose median depth is larger than that of a small car
    # which it nevertheless hides: per-pixel depth gets it right, the median does not.
    h, w = 100, 200
    rng = np.random.default_rng(0)
    bus_uv = rng.uniform([0, 20], [200, 80], size=(20000, 2))
    bus_z = 5.0 + 30.0 * bus_uv[:, 0] / 200  # depth grows along the bus: median 20 m
    car_uv = rng.uniform([20, 40], [60, 70], size=(3000, 2))
    car_z = np.full(len(car_uv), 15.0)  # behind the bus's near end (5-14 m there)
    for order, bus_front in (("pixel", True), ("median", False)):
        insts = [instance_from_projection("bus", bus_uv, bus_z, (h, w)),
                 instance_from_projection("car", car_uv, car_z, (h, w))]
        resolve_occlusion(insts, order=order)
        bus, car = insts
        assert (bus.order == 0) == bus_front
        assert (car.visible.sum() < 0.05 * car.amodal.sum()) == bus_front


def test_instances_behind_camera_are_dropped(scene):
    calib, clouds, _ = scene
    behind = canonical_to_sensor(clouds["near"], np.array([-20.0, 0, 0, 0]))
    insts = frame_masks({"behind": behind}, calib, SIZE)
    assert insts == []


def test_mask_guided_placement_moves_a_misplaced_far_car(scene):
    """The far car's completion is 0.4 m off sideways; its 2D mask (the true visible part)
    pulls it back: the amodal IoU with the truth rises, the near car is left alone, and the
    guide of a car given its own LiDAR returns cannot drag it off them."""
    from seqshape.amodal.align import AlignConfig

    calib, clouds, refs = scene
    size = np.array([4.5, 1.8, 1.5])
    off = dict(clouds, far=box_surface(size, np.array([18.0, -1.2, -0.98, -0.2]), seed=1))
    truth = {m.track_id: m for m in frame_masks(clouds, calib, SIZE)}
    guides = {k: m.visible for k, m in truth.items()}
    plain = {m.track_id: m for m in frame_masks(off, calib, SIZE)}
    moved = {m.track_id: m for m in frame_masks(off, calib, SIZE, guides=guides,
                                                 align=AlignConfig())}
    assert iou(plain["far"].amodal, refs["far"]) < 0.85
    assert iou(moved["far"].amodal, refs["far"]) > iou(plain["far"].amodal, refs["far"]) + 0.08
    assert np.array_equal(moved["near"].amodal, plain["near"].amodal)
    assert moved["near"].order == 0 and moved["far"].order == 1
    # its own returns (the misplaced cloud's visible side) keep it where it is
    pinned = {m.track_id: m for m in frame_masks(
        off, calib, SIZE, guides=guides, align=AlignConfig(min_inside=1.0),
        guide_points={"far": off["far"][::10]})}
    assert np.array_equal(pinned["far"].amodal, plain["far"].amodal)


def _resolve_pixel_reference(insts):
    """The former per-pixel ownership (every mask stacked over the whole image, the wins
    counted pair by pair): the slow, obviously right reference of ``_resolve_pixel``."""
    from seqshape.amodal.masks import _local_depth

    n = len(insts)
    wins = np.zeros((n, n), dtype=np.int64)
    stack = np.stack([m.amodal for m in insts])
    rows, cols = np.nonzero(stack.sum(0) >= 2)
    if len(rows) == 0:
        return wins
    pix = np.c_[cols, rows].astype(np.float64)
    cover = stack[:, rows, cols]
    depth = np.full(cover.shape, np.inf)
    for i in range(n):
        if cover[i].any():
            depth[i, cover[i]] = _local_depth(insts[i], pix[cover[i]])
    owner = np.argmin(depth, axis=0)
    for i in range(n):
        lose = cover[i] & (owner != i)
        insts[i].visible[rows[lose], cols[lose]] = False
        for j in range(n):
            if i != j:
                wins[i, j] = int(np.sum(cover[i] & cover[j] & (owner == i)))
    return wins


def _random_instances(seed, n, size=(60, 90)):
    """``n`` overlapping random instances (blobs of projected points at random depths), one of
    them without depth samples (a mask with no points: it never owns a pixel)."""
    rng = np.random.default_rng(seed)
    insts = []
    for k in range(n):
        centre = rng.uniform([10, 10], [size[1] - 10, size[0] - 10])
        uv = centre + rng.normal(0, rng.uniform(4, 15), (300, 2))
        z = rng.uniform(5, 40) + rng.normal(0, 1, 300)
        insts.append(instance_from_projection(f"t{k}", uv, z, size))
    insts[-1].z, insts[-1].uv = np.zeros(0), np.zeros((0, 2))
    return insts


@pytest.mark.parametrize("seed", range(6))
def test_fast_pixel_ownership_equals_the_reference(seed):
    from seqshape.amodal.masks import _resolve_pixel

    n = 2 + seed
    fast, slow = _random_instances(seed, n), _random_instances(seed, n)
    wins = _resolve_pixel(fast)
    assert np.array_equal(wins, _resolve_pixel_reference(slow))
    assert wins.sum() > 0  # the blobs do overlap
    for a, b in zip(fast, slow, strict=True):
        assert np.array_equal(a.visible, b.visible)
    assert _resolve_pixel(_random_instances(seed, 1)).sum() == 0  # one mask: no overlap


def test_projection_of_all_clouds_at_once_equals_one_by_one(scene):
    from seqshape.amodal.masks import project_cloud, project_clouds

    calib, clouds = scene[0], dict(scene[1])
    clouds["behind"] = np.array([[-5.0, 0.0, 0.0], [0.3, 0.0, 0.0]])  # dropped (min depth)
    clouds["empty"] = np.zeros((0, 3))
    together = project_clouds(clouds, calib)
    assert list(together) == list(clouds)
    for tid, pts in clouds.items():
        uv, depth = project_cloud(pts, calib)
        assert np.array_equal(together[tid][0], uv) and np.array_equal(together[tid][1], depth)
    assert len(together["behind"][0]) == 0 and len(together["empty"][0]) == 0
