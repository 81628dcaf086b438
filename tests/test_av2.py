"""Argoverse 2 reader on logs written in the official schema (tests/_av2_fixture.py)."""

import logging

import _av2_fixture as av2fx
import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest

from seqshape.data.av2 import Av2Log, distort_pixels, quaternion_to_matrix, quaternion_to_yaw
from seqshape.data.sequence import log_names, open_log
from seqshape.errors import ConfigError, DataError
from seqshape.geometry import points_in_box

L = np.array(av2fx.UP_LIDAR["t"])


@pytest.fixture
def fx(tmp_path):
    return av2fx.write_log(tmp_path)


def _log(fx):
    return Av2Log(fx.path.parent, fx.path.name)


def _box(boxes, track):
    return next(b for b in boxes if b.track_id == track)


def _rewrite(path, fn):
    feather.write_feather(fn(feather.read_table(str(path))), str(path))


# conventions

def test_hand_computed_box(fx):
    # yaw 30 deg at (10, 5, 0.75) in the ego frame; up_lidar at (1.375, 0, 1.625)
    b = _box(_log(fx).boxes(0), "car-0")
    np.testing.assert_allclose(b.centre, [8.625, 5.0, -0.875], atol=1e-12)
    assert b.yaw == pytest.approx(np.pi / 6, abs=1e-12)
    np.testing.assert_allclose(b.size, [4.5, 1.875, 1.5])
    np.testing.assert_allclose(b.pose, [8.625, 5.0, -0.875, np.pi / 6], atol=1e-12)
    assert (b.category, b.cls, b.num_points, b.extra["timestamp_ns"]) == (
        "REGULAR_VEHICLE", "car", 40, av2fx.T0)
    b1 = _box(_log(fx).boxes(1), "car-0")  # moved 0.5 m forward one sweep later
    np.testing.assert_allclose(b1.centre, [9.125, 5.0, -0.875], atol=1e-12)


def test_quaternion_conventions():
    c, s = np.cos(np.radians(75)), np.sin(np.radians(75))  # a yaw of 150 deg, scalar first
    for q in ([c, 0, 0, s], [-c, 0, 0, -s], [2 * c, 0, 0, 2 * s]):  # sign and norm do not matter
        assert np.degrees(quaternion_to_yaw(q)) == pytest.approx(150.0)
    r = quaternion_to_matrix(av2fx.yaw_quaternion(np.pi / 6))
    np.testing.assert_allclose(r @ [1, 0, 0], [np.cos(np.pi / 6), 0.5, 0], atol=1e-12)
    rng = np.random.default_rng(1)  # against the fixture's independent matrix -> quaternion
    for _ in range(20):
        m, _r = np.linalg.qr(rng.normal(size=(3, 3)))
        m *= np.sign(np.linalg.det(m))
        q = av2fx.matrix_to_quaternion(m)
        np.testing.assert_allclose(quaternion_to_matrix(q), m, atol=1e-12)


def test_points_in_sensor_frame_not_rotated(fx):
    log = _log(fx)
    raw = feather.read_table(str(fx.path / "sensors" / "lidar" / f"{av2fx.T0}.feather"))
    xyz = np.stack([raw[c].to_numpy().astype(np.float64) for c in "xyz"], -1)
    pts = log.points(0)
    assert pts.dtype == np.float32 and pts.shape == (len(xyz), 4)
    np.testing.assert_array_equal(pts[:, :3], (xyz - L).astype(np.float32))  # up_lidar yaw unused
    np.testing.assert_array_equal(pts[:, 3], raw["intensity"].to_numpy())


def test_num_interior_pts_matches_points_in_box(fx):
    log = _log(fx)
    n_boxes = 0
    for f in log.frames:
        pts = log.points(f)[:, :3]
        for b in log.boxes(f):
            assert int(points_in_box(pts, b.size, b.pose).sum()) == b.num_points
            assert b.num_points == fx.num_interior[(f, b.track_id)]
            n_boxes += 1
    assert n_boxes == 6 * 3
    assert _box(log.boxes(0), "car-5").num_points == 14  # 4 of them exactly on the front face


def test_frames_timestamps_and_classes(fx):
    log = _log(fx)
    assert log.frames == [0, 1, 2] and len(log) == 3
    assert log.timestamp(2) == pytest.approx((av2fx.T0 + 2 * av2fx.DT) * 1e-9, abs=1e-9)
    assert all("orphan" not in [b.track_id for b in log.boxes(f)] for f in log.frames)
    classes = {b.track_id: b.cls for b in log.boxes(0)}
    assert classes == {"car-0": "car", "truck-1": "truck", "bus-2": "bus", "ped-3": None,
                       "van-4": "van", "car-5": "car"}
    assert [b.track_id for b in log.vehicle_boxes(0, ["truck", "bus"])] == ["truck-1", "bus-2"]
    assert log.dataset == "av2" and log.sensor == "vlp32c-x2"
    with pytest.raises(ConfigError, match="frames 0..2"):
        log.points(3)


def test_unknown_category_counted_once(tmp_path, caplog):
    def boxes(i):
        return av2fx.default_boxes(i) + [av2fx.FixtureBox("hc", "HOVERCRAFT", (0.0, 25.0, 1.0),
                                              (3.0, 2.0, 1.5), 0.0, n_inside=3)]
    fx = av2fx.write_log(tmp_path, boxes_fn=boxes)
    log = _log(fx)
    with caplog.at_level(logging.WARNING, logger="seqshape.data.av2"):
        got = [log.boxes(f) for f in log.frames] + [log.boxes(0)]
    warnings = [r for r in caplog.records if "outside the AV2 taxonomy" in r.getMessage()]
    assert len(warnings) == 1 and "3 box(es)" in warnings[0].getMessage()
    assert log.unknown_categories == {"HOVERCRAFT": 3}
    assert _box(got[0], "hc").cls is None and _box(got[0], "hc").category == "HOVERCRAFT"


# ego motion

def _static_point_in_sensor(fx, frame, p_city):
    c = av2fx.city_matrix(0.4 + 0.05 * frame, (100.0 + 2.0 * frame, -50.0 + 0.5 * frame, 20.0),
                    roll=0.01 * frame)  # what av2fx.write_log wrote at the sweep times
    return np.linalg.solve(c, np.r_[p_city, 1.0])[:3] - L


def test_ego_pose_round_trip(fx):
    log = _log(fx)
    np.testing.assert_allclose(log.ego_pose(0), np.eye(4), atol=1e-12)
    for p_city in ([110.0, -40.0, 21.0], [95.0, -60.0, 18.5]):
        p0 = _static_point_in_sensor(fx, 0, p_city)
        for f in (1, 2):
            pf = _static_point_in_sensor(fx, f, p_city)
            np.testing.assert_allclose((log.ego_pose(f) @ np.r_[pf, 1])[:3], p0, atol=1e-9)
        rel = np.linalg.inv(log.ego_pose(1)) @ log.ego_pose(2)  # sensor 2 -> sensor 1
        np.testing.assert_allclose((rel @ np.r_[_static_point_in_sensor(fx, 2, p_city), 1])[:3],
                                   _static_point_in_sensor(fx, 1, p_city), atol=1e-9)


def test_ego_pose_nearest_within_50ms(fx):
    stamps = [av2fx.T0, av2fx.T0 + av2fx.DT + 30_000_000, av2fx.T0 + 2 * av2fx.DT + 80_000_000]
    av2fx.write_city_poses(fx.path, stamps, [av2fx.city_matrix(0.0, (0.0, 0.0, 0.0)),
                                       av2fx.city_matrix(0.0, (2.0, 0.0, 0.0)),
                                       av2fx.city_matrix(0.0, (4.0, 0.0, 0.0))])
    log = _log(fx)
    np.testing.assert_allclose(log.ego_pose(1)[:3, 3], [2.0, 0.0, 0.0], atol=1e-12)
    assert log.ego_pose(2) is None


# cameras

def _expected_uv(rel):
    """Camera looking forward (optical axes), fx = fy = 1000, cx = 775, cy = 1024; ``rel`` is
    the point minus the camera position in ego axes."""
    x, y, z = rel
    return [775 + 1000 * -y / x, 1024 + 1000 * -z / x], x


def test_camera_projection_of_a_hand_made_point(fx):
    log = _log(fx)
    assert log.camera_names == av2fx.RING and log.default_camera == "ring_front_center"
    cam = log.camera()
    assert cam.image_size == (1550, 2048) and cam.name == "ring_front_center"
    # sensor frame; ego (21.375, 2, 2.125); the camera sits at (1.625, 0, 1.375) in the ego frame
    p = np.array([[20.0, 2.0, 0.5]])
    uv, depth = cam.project(p)
    want, d = _expected_uv([19.75, 2.0, 0.75])
    np.testing.assert_allclose(uv[0], want, atol=1e-9)
    assert depth[0] == pytest.approx(d)
    np.testing.assert_allclose(cam.unproject(uv, depth), p, atol=1e-9)
    np.testing.assert_allclose(cam.position, [1.625 - 1.375, 0.0, 1.375 - 1.625], atol=1e-12)
    assert log.camera(av2fx.STEREO[0]).name == av2fx.STEREO[0]  # asked for by name, not listed
    with pytest.raises(ConfigError, match="no camera"):
        log.camera("ring_top")


def test_radial_distortion_is_offered_not_applied(fx):
    log = _log(fx)
    k = log.distortion()
    np.testing.assert_allclose(k, [-0.25, -0.2, 0.3])
    cam = log.camera()
    # x = 0.5 in normalised coordinates: r^2 = 0.25, scale = 1 - 0.0625 - 0.0125 + 0.0046875
    uv = distort_pixels([[775.0, 1024.0], [1275.0, 1024.0], [775.0, 524.0]], cam.K, k)
    np.testing.assert_allclose(uv, [[775.0, 1024.0], [775.0 + 464.84375, 1024.0],
                                    [775.0, 1024.0 - 464.84375]], atol=1e-9)


def test_camera_follows_ego_motion_to_the_image(fx):
    cam_dir = fx.path / "sensors" / "cameras" / "ring_front_center"
    cam_dir.mkdir(parents=True)
    image_ns = av2fx.T0 + 25_000_000
    (cam_dir / f"{image_ns}.jpg").write_bytes(b"")
    (cam_dir / f"{av2fx.T0 + av2fx.DT}.jpg").write_bytes(b"")  # same time as sweep 1
    # ego drives 0.5 m forward between sweep 0 and its image
    ahead = (100.0 + 0.5 * np.cos(0.3), 50.0 + 0.5 * np.sin(0.3), 0.0)
    av2fx.write_city_poses(fx.path, [av2fx.T0, image_ns, av2fx.T0 + av2fx.DT],
                           [av2fx.city_matrix(0.3, (100.0, 50.0, 0.0)),
                            av2fx.city_matrix(0.3, ahead),
                            av2fx.city_matrix(0.3, (101.0, 50.0, 0.0))])
    log = _log(fx)
    assert log.image_path(0) == cam_dir / f"{image_ns}.jpg"
    rel = f"{fx.path.name}/sensors/cameras/ring_front_center/{image_ns}.jpg"
    assert log.image_file_name(0) == rel
    assert log.image_path(2) is None  # next image 100 ms away
    assert log.image_path(0, "ring_rear_left") is None  # no images at all
    uv, depth = log.camera(frame=0).project(np.array([[20.0, 2.0, 0.5]]))
    want, d = _expected_uv([19.25, 2.0, 0.75])
    np.testing.assert_allclose(uv[0], want, atol=1e-6)
    assert depth[0] == pytest.approx(d, abs=1e-9)
    np.testing.assert_allclose(log.camera(frame=1).matrix, log.camera().matrix, atol=1e-12)


# listing and opening

def test_log_names_and_open_log(fx, tmp_path):
    (tmp_path / "not-a-log").mkdir()
    av2fx.write_log(tmp_path, name="second-log", n_sweeps=1)
    assert log_names("av2", tmp_path) == sorted([fx.path.name, "second-log"])
    log = open_log("av2", tmp_path, "second-log")
    assert isinstance(log, Av2Log) and log.frames == [0] and log.name == "second-log"
    with pytest.raises(DataError, match="no such Argoverse 2 folder"):
        Av2Log.log_names(tmp_path / "nowhere")


# errors and laziness

def test_missing_folders_and_files(fx, tmp_path):
    with pytest.raises(DataError, match="no such Argoverse 2 log folder"):
        Av2Log(tmp_path, "nope")
    lidar = fx.path / "sensors" / "lidar"
    for p in lidar.iterdir():
        p.unlink()
    with pytest.raises(DataError, match="no LiDAR sweeps"):
        _log(fx)
    lidar.rmdir()
    with pytest.raises(DataError, match="missing LiDAR folder"):
        _log(fx)


def test_missing_calibration_and_poses(tmp_path):
    fx = av2fx.write_log(tmp_path, n_sweeps=1)
    (fx.path / "city_SE3_egovehicle.feather").unlink()
    (fx.path / "calibration" / "intrinsics.feather").unlink()
    log = _log(fx)
    assert log.camera_names == () and log.default_camera is None and log.image_path(0) is None
    with pytest.raises(DataError, match="city_SE3_egovehicle.feather: missing ego poses"):
        log.ego_pose(0)
    with pytest.raises(DataError, match="intrinsics.feather: missing camera intrinsics"):
        log.camera("ring_front_center")
    ext = fx.path / "calibration" / "egovehicle_SE3_sensor.feather"
    _rewrite(ext, lambda t: t.filter(pa.array([n != "up_lidar"
                                                for n in t["sensor_name"].to_pylist()])))
    with pytest.raises(DataError, match="no up_lidar row"):
        _log(fx)
    ext.unlink()
    with pytest.raises(DataError, match="egovehicle_SE3_sensor.feather: missing sensor extrinsics"):
        _log(fx)


def test_malformed_annotations(tmp_path):
    fx = av2fx.write_log(tmp_path, n_sweeps=1)
    ann = fx.path / "annotations.feather"
    good = feather.read_table(str(ann))
    cases = [
        (lambda t: t.drop_columns(["qz", "num_interior_pts"]),
         r"missing column\(s\) \['qz', 'num_interior_pts'\]"),
        (lambda t: t.set_column(0, "timestamp_ns",
                                t["timestamp_ns"].cast(pa.float64(), safe=False)),
         "timestamp_ns: expected integers, got double"),
        (lambda t: t.set_column(10, "tx_m", pa.array([np.nan] + t["tx_m"].to_pylist()[1:])),
         "tx_m: 1 non-finite"),
        (lambda t: t.set_column(2, "category", pa.array([None] + t["category"].to_pylist()[1:],
                                                        pa.string())),
         "category: 1 null"),
        (lambda t: t.set_column(2, "category", pa.array(np.arange(t.num_rows))),
         "category: expected strings"),
        (lambda t: t.set_column(6, "qw", pa.array([0.0] * t.num_rows)).set_column(
            9, "qz", pa.array([0.0] * t.num_rows)),
         r"quaternion \(qw qx qy qz\) \(0, 0, 0, 0\) has norm 0"),
    ]
    for fn, msg in cases:
        feather.write_feather(fn(good), str(ann))
        with pytest.raises(DataError, match=msg) as err:
            _log(fx).boxes(0)
        assert str(ann) in str(err.value)
    ann.write_bytes(b"not a feather file")
    with pytest.raises(DataError, match="cannot read annotations"):
        _log(fx).boxes(0)
    ann.unlink()
    with pytest.raises(DataError, match="annotations.feather: missing annotations"):
        _log(fx).boxes(0)
    # pandas categoricals are written as dictionary columns: read them like strings
    feather.write_feather(good.set_column(2, "category", good["category"].dictionary_encode()),
                          str(ann))
    assert _box(_log(fx).boxes(0), "car-0").cls == "car"


def test_malformed_sweeps_and_lazy_loading(fx):
    lidar = fx.path / "sensors" / "lidar"
    (lidar / f"{fx.timestamps[2]}.feather").write_bytes(b"garbage")
    _rewrite(lidar / f"{fx.timestamps[1]}.feather", lambda t: t.drop_columns(["intensity"]))
    log = _log(fx)  # sweeps are read on demand only
    assert len(log.points(0)) > 0
    with pytest.raises(DataError, match=r"missing column\(s\) \['intensity'\]"):
        log.points(1)
    with pytest.raises(DataError, match=f"{fx.timestamps[2]}.feather: cannot read LiDAR sweep"):
        log.points(2)
    assert len(log.boxes(0)) == 6
    (fx.path / "annotations.feather").unlink()  # read once, kept
    assert len(log.boxes(1)) == 6
    (lidar / "latest.feather").write_bytes(b"")
    with pytest.raises(DataError, match="latest.feather: file name is not a timestamp"):
        _log(fx)
