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
