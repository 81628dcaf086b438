"""nuScenes reader on fixtures written in the official v1.0 schema (tests/_nuscenes_fixture.py).

References are independent of the reader: boxes and points computed by hand, and the devkit's
own chains (get_sample_data, map_pointcloud_to_image) re-implemented with scipy rotations.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from _nuscenes_fixture import (
    CAMERAS,
    LIDAR_TOP,
    BoxSpec,
    FrameSpec,
    camera_ego_pose,
    rot_wxyz,
    token,
    write_nuscenes,
)

from seqshape.data import nuscenes as ns
from seqshape.data.nuscenes import NuScenesLog, category_to_class, read_pcd_bin
from seqshape.data.sequence import VEHICLE_CLASSES, log_names, open_log
from seqshape.errors import ConfigError, DataError
from seqshape.geometry import points_in_box

C45 = np.cos(np.pi / 4)
#: a LiDAR exactly -90 degrees about z from the ego axes (LiDAR x = ego -y), as in nuScenes.
LIDAR_M90 = {"translation": [0.94, 0.0, 1.84], "rotation": [C45, 0.0, 0.0, -C45]}
F, CX, CY = 1266.0, 816.0, 491.0
#: a camera looking straight ahead from ego (1.5, 0, 1.5): cam z = ego x, cam x = ego -y.
CAM_AHEAD = {"CAM_FRONT": {"translation": [1.5, 0.0, 1.5], "rotation": [0.5, -0.5, 0.5, -0.5],
                           "camera_intrinsic": [[F, 0, CX], [0, F, CY], [0, 0, 1]]}}


@pytest.fixture(scope="module")
def default_root(tmp_path_factory):
    return write_nuscenes(tmp_path_factory.mktemp("nuscenes"))


def _hand_scene():
    """Ego at (100, 200, 0.5) heading 30 deg; a car whose centre is at (10, 2, -0.8) in our
    sensor frame with yaw 20 deg (worked out by hand below). Frame 1: the ego 2.5 m further
    along its heading; the camera image 0.5 m after the LiDAR sweep."""
    th = np.deg2rad(30.0)
    ego = np.array([100.0, 200.0, 0.5])
    # sensor (10, 2, -0.8) -> ego: + LiDAR position (0.94, 0, 1.84) = (10.94, 2, 1.04)
    # -> global: rotate by 30 deg and add the ego position
    centre = ego + [10.94 * np.cos(th) - 2 * np.sin(th), 10.94 * np.sin(th) + 2 * np.cos(th),
                    1.04]
    car = BoxSpec("car", "vehicle.car", tuple(centre), np.deg2rad(50.0), (1.9, 4.5, 1.6),
                  n_inside=30, visibility="3")
    step = 2.5 * np.array([np.cos(th), np.sin(th), 0.0])
    return {"scene-0001": [
        FrameSpec(1_000_000, tuple(ego), th, boxes=[car],
                  camera_motion={"CAM_FRONT": (50_000, 0.5, 0.0)}),
        FrameSpec(1_500_000, tuple(ego + step), th, boxes=[car]),
    ]}


@pytest.fixture
def hand(tmp_path):
    fx = write_nuscenes(tmp_path, _hand_scene(), lidar=LIDAR_M90, cameras=CAM_AHEAD)
    return fx, NuScenesLog(tmp_path, "scene-0001")


def _table(fx, name):
    return fx.root / fx.version / f"{name}.json"


def _edit(fx, name, fn):
    path = _table(fx, name)
    records = json.loads(path.read_text())
    path.write_text(json.dumps(fn(records)))


# --- hand-computed references


def test_hand_computed_box(hand):
    fx, lg = hand
    (box,) = lg.boxes(0)
    np.testing.assert_allclose(box.centre, [10.0, 2.0, -0.8], atol=1e-9)
    assert box.yaw == pytest.approx(np.deg2rad(20.0), abs=1e-9)
    np.testing.assert_allclose(box.size, [4.5, 1.9, 1.6])  # (l, w, h) from [w, l, h]
    assert (box.track_id, box.category, box.cls) == (token("inst", "car"), "vehicle.car", "car")
    assert box.visibility == pytest.approx(0.6)
    assert box.extra["visibility_level"] == "v60-80"
    assert box.extra["attributes"] == ["vehicle.parked"]
    assert box.extra["token"] == token("ann", "scene-0001", 0, "car")
    np.testing.assert_allclose(box.extra["rotation"][:, 0], [np.cos(np.deg2rad(20)),
                                                             np.sin(np.deg2rad(20)), 0], atol=1e-12)


def test_hand_computed_points_and_count(hand):
    fx, lg = hand
    # a LiDAR point at (-2, 10, -0.8) is at (10, 2, -0.8) in the ego axes (LiDAR x = ego -y)
    raw = np.array([[-2.0, 10.0, -0.8, 7.0, 3.0], [1.0, 0.0, 0.0, 200.0, 31.0]], np.float32)
    raw.tofile(fx.lidar_files["scene-0001", 0])
    pts = lg.points(0)
    assert pts.dtype == np.float32 and pts.shape == (2, 5)
    np.testing.assert_allclose(pts[:, :3], [[10.0, 2.0, -0.8], [0.0, -1.0, 0.0]], atol=1e-6)
    np.testing.assert_array_equal(pts[:, 3:], raw[:, 3:])
    # frame 1 keeps the fixture's points: num_lidar_pts (devkit count) = our count in the box
    (box,) = lg.boxes(1)
    inside = points_in_box(lg.points(1)[:, :3], box.size, box.pose)
    assert box.num_points == fx.counts["scene-0001", 1, "car"] == inside.sum() >= 30


def test_hand_ego_pose(hand):
    _, lg = hand
    np.testing.assert_allclose(lg.ego_pose(0), np.eye(4), atol=1e-12)
    expected = np.eye(4)
    expected[0, 3] = 2.5  # straight ahead, same heading
    np.testing.assert_allclose(lg.ego_pose(1), expected, atol=1e-9)
    # the parked car seen from frame 1, brought back to frame 0
    c1 = lg.boxes(1)[0].centre
    np.testing.assert_allclose(lg.ego_pose(1)[:3, :3] @ c1 + lg.ego_pose(1)[:3, 3],
                               [10.0, 2.0, -0.8], atol=1e-9)


def test_hand_camera_projection(hand):
    _, lg = hand
    cam = lg.camera("CAM_FRONT", 0)
    assert cam.image_size == (1600, 900) and cam.name == "CAM_FRONT"
    np.testing.assert_allclose(cam.K, CAM_AHEAD["CAM_FRONT"]["camera_intrinsic"])
    # sensor (20, 1, 0.5) -> ego (20.94, 1, 2.34); the ego moved 0.5 m ahead by the image
    # time -> (20.44, 1, 2.34); minus the camera position (1.5, 0, 1.5) -> (18.94, 1, 0.84);
    # camera axes: x = -ego y, y = -ego z, z = ego x
    uv, depth = cam.project(np.array([[20.0, 1.0, 0.5]]))
    d = 18.94
    np.testing.assert_allclose(depth, [d], atol=1e-9)
    np.testing.assert_allclose(uv, [[CX - F * 1.0 / d, CY - F * 0.84 / d]], atol=1e-7)
    # frame 1 has no ego motion between sweep and image: depth 20.94 - 1.5
    uv1, depth1 = lg.camera(frame=1).project(np.array([[20.0, 1.0, 0.5]]))
    np.testing.assert_allclose(depth1, [19.44], atol=1e-9)


# --- the default fixture (tilted ego, real calibrations) against the devkit's own chains


def _lidar_to_sensor(lidar=LIDAR_TOP):
    return rot_wxyz(lidar["rotation"]).as_matrix()


def test_points_round_trip(default_root):
    fx = default_root
    lg = NuScenesLog(fx.root, "scene-0061")
    for k in lg.frames:
        raw = read_pcd_bin(fx.lidar_files["scene-0061", k])
        np.testing.assert_array_equal(raw, fx.points["scene-0061", k])
        pts = lg.points(k)
        np.testing.assert_allclose(pts[:, :3], raw[:, :3] @ _lidar_to_sensor().T, atol=2e-5)
        np.testing.assert_array_equal(pts[:, 3:], raw[:, 3:])


def test_num_lidar_pts_equals_our_count(default_root):
    """The fixture's counts are the devkit's; ours use the box's full rotation (the ego rolls
    and pitches, so the box is not upright in the sensor frame)."""
    fx = default_root
    n = 0
    for name in fx.samples:
        lg = NuScenesLog(fx.root, name)
        for k in lg.frames:
            pts = lg.points(k)[:, :3].astype(np.float64)
            for box in lg.boxes(k):
                local = (pts - box.centre) @ box.extra["rotation"]
                inside = np.all(np.abs(local) <= box.size / 2 + 1e-6, axis=1)
                assert box.num_points == inside.sum() > 0
                n += 1
    assert n == 3 * 4 + 2


def _devkit_box_in_lidar(frame: FrameSpec, box: BoxSpec, lidar=LIDAR_TOP):
    """get_sample_data: translate(-ego), rotate(ego^-1), translate(-calib), rotate(calib^-1)."""
    ego_r, cal_r = frame.ego_rot, rot_wxyz(lidar["rotation"])
    c = ego_r.inv().apply(np.asarray(box.translation) - frame.ego_translation)
    c = cal_r.inv().apply(c - lidar["translation"])
    return c, (cal_r.inv() * ego_r.inv() * box.rot).as_matrix()


def test_boxes_match_devkit_chain(default_root):
    fx = default_root
    lg = NuScenesLog(fx.root, "scene-0061")
    r = _lidar_to_sensor()
    for k, frame in enumerate(fx.specs["scene-0061"]):
        boxes = {b.extra["token"]: b for b in lg.boxes(k)}
        assert len(boxes) == len(frame.boxes)
        for spec in frame.boxes:
            box = boxes[token("ann", "scene-0061", k, spec.instance)]
            c, m = _devkit_box_in_lidar(frame, spec)
            np.testing.assert_allclose(box.centre, r @ c, atol=1e-9)
            np.testing.assert_allclose(box.extra["rotation"], r @ m, atol=1e-9)
            x_axis = r @ m[:, 0]
            assert box.yaw == pytest.approx(np.arctan2(x_axis[1], x_axis[0]), abs=1e-9)
            w, length, h = spec.size_wlh
            np.testing.assert_allclose(box.size, [length, w, h])


def _devkit_project(raw, frame: FrameSpec, channel, lidar=LIDAR_TOP, cameras=CAMERAS):
    """map_pointcloud_to_image: lidar -> ego -> global -> ego (image time) -> camera -> K."""
    cal = cameras[channel]
    p = rot_wxyz(lidar["rotation"]).apply(raw[:, :3].astype(np.float64)) + lidar["translation"]
    p = frame.ego_rot.apply(p) + frame.ego_translation
    t, rot = camera_ego_pose(frame, channel)
    p = rot.inv().apply(p - t)
    p = rot_wxyz(cal["rotation"]).inv().apply(p - cal["translation"])
    depth = p[:, 2]
    uvw = p @ np.asarray(cal["camera_intrinsic"]).T
    return uvw[:, :2] / uvw[:, 2:], depth


def test_camera_projection_matches_devkit_chain(default_root):
    fx = default_root
    lg = NuScenesLog(fx.root, "scene-0061")
    for channel in ("CAM_FRONT", "CAM_FRONT_LEFT"):
        for k, frame in enumerate(fx.specs["scene-0061"]):
            raw = read_pcd_bin(fx.lidar_files["scene-0061", k])
            uv_ref, depth_ref = _devkit_project(raw, frame, channel)
            cam = lg.camera(channel, k)
            uv, depth = cam.project(lg.points(k)[:, :3])
            np.testing.assert_allclose(depth, depth_ref, atol=1e-4)
            front = depth_ref > 1.0
            assert front.sum() > 20
            np.testing.assert_allclose(uv[front], uv_ref[front], rtol=1e-5, atol=0.05)
            assert cam.in_image(uv, depth).sum() > 0


def test_ego_pose_static_box(default_root):
    """A parked car stays put in the log's reference frame (full 3D, tilted ego)."""
    lg = NuScenesLog(default_root.root, "scene-0061")
    np.testing.assert_allclose(lg.ego_pose(0), np.eye(4), atol=1e-12)
    ref = next(b for b in lg.boxes(0) if b.category == "vehicle.car")
    for k in lg.frames[1:]:
        box = next(b for b in lg.boxes(k) if b.track_id == ref.track_id)
        T = lg.ego_pose(k)
        np.testing.assert_allclose(T[:3, :3] @ box.centre + T[:3, 3], ref.centre, atol=1e-9)
        np.testing.assert_allclose(T[:3, :3] @ box.extra["rotation"], ref.extra["rotation"],
                                   atol=1e-9)


# --- listing, frames, cameras, classes


def test_scene_listing_and_log(default_root):
    fx = default_root
    assert log_names("nuscenes", fx.root) == ["scene-0061", "scene-0103"]
    lg = open_log("nuscenes", fx.root, "scene-0061")
    assert isinstance(lg, NuScenesLog)
    assert (lg.dataset, lg.sensor, lg.version, lg.root) == ("nuscenes", "hdl32e", "v1.0-mini",
                                                            fx.root)
    assert lg.frames == [0, 1, 2]
    assert lg.camera_names == ("CAM_FRONT", "CAM_FRONT_LEFT")  # no RADAR_FRONT
    assert lg.default_camera == "CAM_FRONT"
    ts = [s.timestamp_us * 1e-6 for s in fx.specs["scene-0061"]]
    np.testing.assert_allclose(lg.timestamps(), ts, rtol=0, atol=1e-6)
    assert [lg.sample_token(k) for k in lg.frames] == fx.samples["scene-0061"]
    assert len(open_log("nuscenes", fx.root, "scene-0103")) == 2


def test_frames_follow_next_chain(tmp_path):
    fx = write_nuscenes(tmp_path)
    _edit(fx, "sample", lambda recs: recs[::-1])  # order in the file is irrelevant
    lg = NuScenesLog(tmp_path, "scene-0061")
    assert [lg.sample_token(k) for k in lg.frames] == fx.samples["scene-0061"]
    assert np.all(np.diff(lg.timestamps()) > 0)


def test_classes(default_root):
    got = {b.category: b.cls for name in ("scene-0061", "scene-0103")
           for b in NuScenesLog(default_root.root, name).boxes(0)}
    assert got == {"vehicle.car": "car", "vehicle.truck": "truck", "vehicle.bus.bendy": "bus",
                   "human.pedestrian.adult": None, "vehicle.emergency.ambulance": "van"}
    assert category_to_class("vehicle.construction") == ("truck", True)
    assert category_to_class("vehicle.emergency.police") == ("car", True)
    assert category_to_class("vehicle.trailer") == ("trailer", True)
    for name in ("vehicle.motorcycle", "animal", "movable_object.barrier",
                 "static_object.bicycle_rack", "human.pedestrian.child"):
        assert category_to_class(name) == (None, True)
    assert set(ns.CATEGORY_TO_CLASS.values()) <= set(VEHICLE_CLASSES)


def test_unknown_category_one_warning(tmp_path, caplog):
    fx = write_nuscenes(tmp_path)

    def rename(recs):
        for r in recs:
            if r["name"] == "vehicle.car":
                r["name"] = "vehicle.hovercraft"
        return recs

    _edit(fx, "category", rename)
    with caplog.at_level(logging.WARNING, logger="seqshape.data.nuscenes"):
        lg = NuScenesLog(tmp_path, "scene-0061")
        boxes = [b for k in lg.frames for b in lg.boxes(k)]
    assert lg.unknown_categories == {"vehicle.hovercraft": 3}
    assert [r.getMessage() for r in caplog.records if "unknown" in r.getMessage()] == [
        "nuScenes scene-0061: 3 boxes of unknown categories {'vehicle.hovercraft': 3} get no "
        "vehicle class"]
    assert {b.cls for b in boxes if b.category == "vehicle.hovercraft"} == {None}


def test_image_paths(tmp_path):
    write_nuscenes(tmp_path)
    lg = NuScenesLog(tmp_path, "scene-0061")
    path = lg.image_path(1)
    assert path.is_file() and path.parent.name == "CAM_FRONT"
    assert lg.image_file_name(1) == path.relative_to(tmp_path).as_posix()
    assert lg.image_path(1, "CAM_FRONT_LEFT").parent.name == "CAM_FRONT_LEFT"
    path.unlink()
    assert lg.image_path(1) is None
    with pytest.raises(ConfigError, match="no camera 'CAM_BACK'"):
        lg.camera("CAM_BACK")
    with pytest.raises(ConfigError, match="no frame 3"):
        lg.points(3)


# --- versions and the table cache


def test_version_selection(tmp_path):
    write_nuscenes(tmp_path, version="v1.0-mini")
    assert NuScenesLog(tmp_path, "scene-0061").version == "v1.0-mini"
    table_root = NuScenesLog(tmp_path / "v1.0-mini", "scene-0061")  # the table folder itself
    assert table_root.root == tmp_path and table_root.lidar_path(0).is_file()
    write_nuscenes(tmp_path, version="v1.0-trainval")
    with pytest.raises(DataError, match=r"several nuScenes table folders .*version="):
        NuScenesLog(tmp_path, "scene-0061")
    assert NuScenesLog(tmp_path, "scene-0061", version="v1.0-trainval").version == "v1.0-trainval"
    assert NuScenesLog.log_names(tmp_path, version="v1.0-mini") == ["scene-0061", "scene-0103"]
    with pytest.raises(DataError, match="no nuScenes table folder"):
        NuScenesLog(tmp_path / "samples", "scene-0061")
    with pytest.raises(DataError, match="table folder not found"):
        NuScenesLog(tmp_path, "scene-0061", version="v1.0-test")


def test_tables_read_once(tmp_path, monkeypatch):
    fx = write_nuscenes(tmp_path)
    reads = []
    real = ns._read_table
    monkeypatch.setattr(ns, "_read_table", lambda path: reads.append(path.name) or real(path))
    a = NuScenesLog(tmp_path, "scene-0061")
    b = NuScenesLog(tmp_path, "scene-0103")
    assert NuScenesLog.log_names(tmp_path) and a.tables is b.tables
    assert sorted(reads) == sorted(f"{t}.json" for t in ns.TABLES + ns.OPTIONAL_TABLES)
    _edit(fx, "scene", lambda recs: recs[:1])  # a changed table file is read again
    assert NuScenesLog.log_names(tmp_path) == ["scene-0061"]
    assert NuScenesLog(tmp_path, "scene-0061").tables is not a.tables
    ns.clear_cache()


# --- malformed and missing input


def _drop_field(field):
    def fn(recs):
        del recs[0][field]
        return recs
    return fn


@pytest.mark.parametrize("table, edit, match", [
    ("instance", None, r"instance\.json: nuScenes table not found"),
    ("sample", "truncate", r"sample\.json:1: malformed JSON"),
    ("scene", lambda recs: {"records": recs}, r"scene\.json: expected a JSON list"),
    ("sample_annotation", lambda recs: [dict(r, instance_token="nope") for r in recs],
     r"instance\.json: no record with token 'nope'"),
    ("ego_pose", lambda recs: [r for r in recs if r["token"] != token("ego", "LIDAR_TOP",
                                                                      1532402927647951)],
     r"ego_pose\.json: no record with token"),
    ("sample", lambda recs: [dict(r, next="missing") if r["next"] else r for r in recs],
     r"sample\.json: no record with token 'missing'"),
    ("calibrated_sensor", lambda recs: [dict(r, rotation=[1, 0]) for r in recs],
     r"calibrated_sensor\.json: record .* field 'rotation' must be 4 numbers"),
    ("scene", _drop_field("first_sample_token"), r"scene\.json: .*'first_sample_token' missing"),
    ("sample_data", lambda recs: [r for r in recs if not r["filename"].startswith(
        "samples/LIDAR_TOP")], r"sample_data\.json: scene scene-0061: sample .* no LIDAR_TOP"),
])
def test_malformed_tables(tmp_path, table, edit, match):
    fx = write_nuscenes(tmp_path, images=False)
    if edit is None:
        _table(fx, table).unlink()
    elif edit == "truncate":
        _table(fx, table).write_text(_table(fx, table).read_text()[:50])
    else:
        _edit(fx, table, edit)
    with pytest.raises(DataError, match=match):
        NuScenesLog(tmp_path, "scene-0061").boxes(0)


def test_malformed_annotation_and_scene_name(tmp_path):
    fx = write_nuscenes(tmp_path, images=False)
    _edit(fx, "sample_annotation", _drop_field("size"))
    lg = NuScenesLog(tmp_path, "scene-0061")
    with pytest.raises(DataError, match=r"sample_annotation\.json: record .*'size' missing"):
        lg.boxes(0)
    with pytest.raises(DataError, match=r"scene\.json: no scene named 'scene-9999' \(2 scenes"):
        NuScenesLog(tmp_path, "scene-9999")


def test_bad_lidar_files(tmp_path):
    fx = write_nuscenes(tmp_path, images=False)
    lg = NuScenesLog(tmp_path, "scene-0061")
    path = fx.lidar_files["scene-0061", 1]
    path.write_bytes(path.read_bytes() + b"\0" * 4)
    with pytest.raises(DataError, match=r"\.pcd\.bin: size \d+ bytes is not a multiple of 20"):
        lg.points(1)
    path.unlink()
    with pytest.raises(DataError, match=r"\.pcd\.bin: LiDAR file not found"):
        lg.points(1)
