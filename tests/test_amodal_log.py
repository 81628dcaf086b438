"""The labeller on any DrivingLog: a tiny synthetic log (not KITTI), cameras, the CLI."""

import argparse
import json

import cv2
import numpy as np
import pytest

from seqshape.amodal.association import instance_masks_by_frame
from seqshape.amodal.labeler import LabelConfig, label_log, label_log_cameras, write_labels
from seqshape.camera import PinholeCamera, kitti_default_calib, write_calib
from seqshape.data.kins import coco_annotation, mask_to_polygons, read_kins, segm_to_mask
from seqshape.data.kitti import KittiLabel, pose_to_label_fields, write_velodyne
from seqshape.data.kitti import write_labels as write_kitti
from seqshape.data.sequence import Box3D, DrivingLog
from seqshape.errors import ConfigError
from seqshape.geometry import box_corners, canonical_to_sensor
from seqshape.scripts.label import add_arguments, open_args_log
from seqshape.testing import box_surface

GROUND = -1.7
W, H = 320, 200
K = np.array([[200.0, 0, 160], [0, 200, 100], [0, 0, 1]])
# sensor (x forward, y left, z up) -> camera (x right, y down, z forward), camera 0.3 m below
# and 0.5 m ahead of the LiDAR
R_FRONT = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])
VEHICLES = {  # object id -> (class, size, pose at frame f)
    "b7f": ("car", np.array([4.4, 1.8, 1.5]), lambda f: [12.0 + 0.6 * f, 2.0, 0.0, 0.1]),
    "a03": ("bus", np.array([11.0, 2.5, 3.0]), lambda f: [25.0 + 0.3 * f, -3.5, 0.0, -0.05]),
}
CLEARANCE = 0.3  # m between the road and each box bottom (a vehicle's ground clearance)


def _pose(oid, f):
    _, size, fn = VEHICLES[oid]
    pose = np.array(fn(f), dtype=np.float64)
    pose[2] = GROUND + CLEARANCE + size[2] / 2
    return pose


def _transform(rot, position):
    """(4, 4) sensor -> camera for a camera at ``position`` (sensor frame) with ``rot``."""
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = -rot @ np.asarray(position, dtype=np.float64)
    return t


class SyntheticLog(DrivingLog):
    """Two box vehicles driving ahead over a flat road; a front and a rear camera."""

    dataset = "synthetic"
    sensor = "test"

    def __init__(self, root, name="syn", cameras=True):
        self.root = root
        self.name = name
        self.frames = [0, 1, 2, 3]
        self.camera_names = ("front", "rear") if cameras else ()
        self.default_camera = "front" if cameras else None

    def timestamp(self, frame):
        return 0.1 * frame

    def points(self, frame):
        rng = np.random.default_rng(frame)
        road = np.c_[rng.uniform(-10, 50, 8000), rng.uniform(-15, 15, 8000), np.full(8000, GROUND)]
        parts = [road]
        for k, oid in enumerate(VEHICLES):
            size = VEHICLES[oid][1]
            parts.append(canonical_to_sensor(box_surface(3000, 10 * frame + k, size),
                                             _pose(oid, frame)))
        pts = np.vstack(parts)
        return np.c_[pts, np.zeros(len(pts))].astype(np.float32)

    def boxes(self, frame):
        out = [Box3D(oid, f"vehicle.{cls}", cls, _pose(oid, frame)[:3], size,
                     _pose(oid, frame)[3]) for oid, (cls, size, _) in VEHICLES.items()]
        return out + [Box3D("p1", "pedestrian", None, [8.0, -1.0, -0.8], [0.6, 0.6, 1.7], 0.0)]

    def ego_pose(self, frame):
        return np.eye(4)

    def camera(self, name=None, frame=None):
        name = name or self.default_camera
        if name not in self.camera_names:
            raise ConfigError(f"no camera {name}")
        if name == "front":
            return PinholeCamera.from_intrinsics(K, _transform(R_FRONT, [0.5, 0, -0.3]), (W, H),
                                                 name)
        back = R_FRONT @ np.diag([-1.0, -1.0, 1.0])  # looking along -x
        return PinholeCamera.from_intrinsics(K, _transform(back, [-0.5, 0, -0.3]), (W, H), name)


def _box_hull(camera, oid, frame):
    """The filled projection of the vehicle's box: its exact amodal mask."""
    uv, _ = camera.project(box_corners(VEHICLES[oid][1], _pose(oid, frame)))
    m = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(m, cv2.convexHull(np.round(uv * 16).astype(np.int32)), 1, shift=4)
    return m.astype(bool)


def test_label_log_masks_land_where_the_boxes_project(tmp_path):
    log = SyntheticLog(tmp_path)
    result = label_log(log, LabelConfig(mode="gt-accumulation"))
    assert result.camera == "front" and len(result.images) == 4
    assert result.images[2]["file_name"] == "syn/front/000002"
    assert (result.images[0]["width"], result.images[0]["height"]) == (W, H)
    # the pedestrian (no vehicle class) is not labelled; ids: object ids in sorted order
    ids = {"a03": 1, "b7f": 2}
    assert len(result.annotations) == 8
    for ann in result.annotations:
        frame = result.images[ann["image_id"]]["frame"]
        oid = next(o for o, i in ids.items() if i == ann["track_id"])
        assert ann["category_id"] == {"car": 4, "bus": 9}[VEHICLES[oid][0]]
        truth = _box_hull(log.camera(), oid, frame)
        got = segm_to_mask(ann["a_segm"], H, W)
        iou = (got & truth).sum() / (got | truth).sum()
        assert iou > 0.9, (frame, oid, iou)
        # the car (left, near) hides part of the bus (right, far) in no frame: no overlap,
        # so both are in no occlusion cluster
        assert (ann["oco_id"], ann["ico_id"]) == (0, 0)
    write_labels(tmp_path / "l.json", result)
    doc = read_kins(tmp_path / "l.json")
    assert {c["name"] for c in doc["categories"]} >= {"car", "bus", "trailer"}


def test_label_log_cameras_and_polygons(tmp_path):
    log = SyntheticLog(tmp_path)
    out = label_log_cameras(log, LabelConfig(mode="gt-accumulation", polygons=True))
    assert list(out) == ["front", "rear"]
    assert out["rear"].annotations == [] and len(out["rear"].images) == 4  # nothing behind
    front = out["front"].annotations
    assert len(front) == 8 and all(isinstance(a["a_segm"], list) for a in front)
    ref = label_log(log, LabelConfig(mode="gt-accumulation"))
    for a, b in zip(front, ref.annotations, strict=True):
        np.testing.assert_array_equal(segm_to_mask(a["a_segm"], H, W),
                                      segm_to_mask(b["a_segm"], H, W))


def test_label_log_needs_a_camera(tmp_path):
    with pytest.raises(ConfigError, match="has no cameras"):
        label_log(SyntheticLog(tmp_path, cameras=False), LabelConfig(mode="gt-accumulation"))
    with pytest.raises(ConfigError, match="no camera 'side'"):
        label_log(SyntheticLog(tmp_path), LabelConfig(mode="gt-accumulation"), camera="side")


def test_instances_matched_by_image_file_name_polygons_too(tmp_path):
    log = SyntheticLog(tmp_path)
    mask = _box_hull(log.camera(), "b7f", 1)
    images = [{"id": 5, "file_name": "syn/front/000001", "height": H, "width": W},
              {"id": 6, "file_name": "other/front/000002", "height": H, "width": W}]
    ann = coco_annotation(1, 5, 4, mask)
    ann["segmentation"] = mask_to_polygons(mask)
    del ann["area"], ann["bbox"]
    path = tmp_path / "inst.json"
    path.write_text(json.dumps({"images": images, "categories": [{"id": 4, "name": "car"}],
                                "annotations": [ann, {**ann, "id": 2, "image_id": 6}]}))
    got = instance_masks_by_frame(log, "front", path)
    assert sorted(got) == log.frames and [len(got[f]) for f in log.frames] == [0, 1, 0, 0]
    np.testing.assert_array_equal(segm_to_mask(got[1][0]["segmentation"], H, W), mask)


def _kitti_root(root):
    """The synthetic log's vehicles as a KITTI tracking sequence 0004."""
    calib = kitti_default_calib()
    write_calib(root / "calib" / "0004.txt", calib)
    log = SyntheticLog(root)
    labels = []
    for f in log.frames[:2]:
        write_velodyne(root / "velodyne" / "0004" / f"{f:06d}.bin", log.points(f))
        for k, oid in enumerate(VEHICLES):
            labels.append(KittiLabel(f, k, "Car", 0, 0, bbox=[0, 0, 1, 1],
                                     **pose_to_label_fields(_pose(oid, f), VEHICLES[oid][1],
                                                            calib)))
    write_kitti(root / "label_02" / "0004.txt", labels)
    return root


def test_label_cli_cameras_folder_and_errors(tmp_path, capsys):
    from seqshape.cli import main

    root = _kitti_root(tmp_path / "kitti")
    out = tmp_path / "labels"
    assert main(["label", "--dataset", "kitti", "--root", str(root), "--sequence", "4",
                 "--camera", "all", "--mode", "gt-accumulation", "--polygons",
                 "--out", str(out)]) == 0
    left, right = read_kins(out / "image_02.json"), read_kins(out / "image_03.json")
    assert [im["file_name"] for im in left["images"]] == ["0004/000000.png", "0004/000001.png"]
    assert len(left["annotations"]) == 4 and isinstance(left["annotations"][0]["a_segm"], list)
    assert len(right["annotations"]) == 4
    # the right camera sees the vehicles shifted left (its baseline): different masks
    assert left["annotations"][0]["a_bbox"][0] > right["annotations"][0]["a_bbox"][0]
    # --kitti is the alias; one camera writes one file (RLE: the same masks)
    one = tmp_path / "one.json"
    assert main(["label", "--kitti", str(root), "--sequence", "0004", "--mode",
                 "gt-accumulation", "--out", str(one)]) == 0
    single = read_kins(one)["annotations"]
    assert isinstance(single[0]["a_segm"], dict)
    assert [a["a_bbox"] for a in single] == [a["a_bbox"] for a in left["annotations"]]
    # no calib: no cameras, a clear error
    (root / "calib" / "0004.txt").unlink()
    assert main(["label", "--kitti", str(root), "--sequence", "0004", "--mode",
                 "gt-accumulation", "--out", str(one)]) == 1
    assert "kitti log 0004 has no cameras" in capsys.readouterr().err
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    both = parser.parse_args(["--kitti", str(root), "--root", str(root), "--sequence", "4"])
    with pytest.raises(ConfigError, match="--kitti DIR is short"):
        open_args_log(both)
