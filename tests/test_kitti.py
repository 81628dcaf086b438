from pathlib import Path

import cv2
import numpy as np
import pytest

from seqshape.camera import KittiCalib, kitti_default_calib, write_calib
from seqshape.data.crop import CropConfig, crop_box
from seqshape.data.kitti import (
    KittiLabel,
    KittiTrackingSequence,
    extract_tracks,
    format_label,
    image_path,
    label_to_pose,
    oxts_to_poses,
    png_size,
    pose_to_label_fields,
    poses_to_oxts,
    read_labels,
    read_oxts,
    read_velodyne,
    velodyne_path,
    write_labels,
    write_oxts,
    write_velodyne,
)
from seqshape.data.sequence import DrivingLog, open_log
from seqshape.errors import ConfigError, DataError
from seqshape.geometry import (
    canonical_to_sensor,
    points_in_box,
    pose_to_matrix,
    sensor_to_canonical,
)

SAMPLE = Path(__file__).parent / "data" / "kitti_sample"


def _ideal_calib():
    tr = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    p = np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])
    return KittiCalib(P0=p, P1=p, P2=p, P3=p, R_rect=np.eye(3), Tr_velo_cam=tr,
                      Tr_imu_velo=np.eye(4)[:3])


# ----------------------------------------------------------------------------- labels


def test_read_sample_labels():
    labels = read_labels(SAMPLE / "label_02" / "0000.txt")
    assert len(labels) == 6
    dc = labels[0]
    assert dc.is_dontcare and dc.track_id == -1 and dc.frame == 0 and dc.truncated == -1
    van = labels[1]
    assert (van.frame, van.track_id, van.type, van.occluded) == (0, 0, "Van", 0)
    np.testing.assert_array_equal(van.bbox, [296.744956, 161.752147, 455.226042, 292.372804])
    np.testing.assert_array_equal(van.dimensions, [2.0, 1.823255, 4.433886])
    np.testing.assert_array_equal(van.location, [-4.552284, 1.858523, 13.410495])
    assert van.rotation_y == -2.115488 and van.alpha == -1.793451 and van.score is None
    assert labels[-1].frame == 2 and labels[-1].truncated == 1 and labels[-1].occluded == 2
    scored = read_labels(SAMPLE / "label_02" / "0001.txt")
    assert scored[0].score == 0.875 and scored[1].is_dontcare and scored[1].score == -1.0


def test_sample_labels_rewrite_identically(tmp_path):
    src = SAMPLE / "label_02" / "0000.txt"
    write_labels(tmp_path / "l.txt", read_labels(src))
    expected = "".join(line + "\n" for line in src.read_text().splitlines() if line.strip())
    assert (tmp_path / "l.txt").read_text() == expected


def test_label_write_read_exact(tmp_path):
    rng = np.random.default_rng(0)
    labels = [KittiLabel(frame=int(f), track_id=int(t), type=ty, truncated=tr,
                         occluded=int(rng.integers(0, 4)), alpha=rng.uniform(-3, 3),
                         bbox=np.r_[lt := rng.uniform(0, 600, 2), lt + rng.uniform(1, 600, 2)],
                         dimensions=rng.uniform(1, 5, 3),
                         location=rng.normal(0, 20, 3), rotation_y=rng.uniform(-3, 3),
                         score=sc)
              for f, t, ty, tr, sc in [(0, 0, "Car", 0, None), (0, 1, "Van", 0.37, None),
                                       (3, -1, "DontCare", -1, None), (5, 7, "Car", 2, None)]]
    write_labels(tmp_path / "a.txt", labels)
    back = read_labels(tmp_path / "a.txt")
    assert len(back) == len(labels)
    for a, b in zip(labels, back, strict=True):
        assert (a.frame, a.track_id, a.type, a.occluded) == (b.frame, b.track_id, b.type,
                                                            b.occluded)
        for name in ("truncated", "alpha", "bbox", "dimensions", "location", "rotation_y"):
            np.testing.assert_allclose(getattr(b, name), getattr(a, name), atol=5.1e-7)
    write_labels(tmp_path / "b.txt", back)
    assert (tmp_path / "b.txt").read_text() == (tmp_path / "a.txt").read_text()
    # the 18th column survives too
    labels[0].score = 0.123456789
    line = format_label(labels[0])
    assert len(line.split()) == 18 and line.endswith(" 0.123457")


def test_malformed_label_names_file_and_line(tmp_path):
    with pytest.raises(DataError) as err:
        read_labels(SAMPLE / "label_bad.txt")
    assert err.value.line == 2 and "label_bad.txt:2: expected 17 or 18 columns, got 16" in str(
        err.value)
    lines = (SAMPLE / "label_bad.txt").read_text().splitlines()
    (tmp_path / "x.txt").write_text("\n".join([lines[0], lines[2]]) + "\n")
    with pytest.raises(DataError, match=r"x\.txt:2: bad number"):
        read_labels(tmp_path / "x.txt")
    with pytest.raises(DataError, match="not found"):
        read_labels(tmp_path / "missing.txt")


# ----------------------------------------------------------------------------- velodyne


def test_velodyne_round_trip_and_bad_size(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(1000, 4)).astype(np.float32)
    pts[:, 3] = np.abs(pts[:, 3])  # a reflectance is never negative (seqshape.limits)
    write_velodyne(tmp_path / "a.bin", pts)
    assert (tmp_path / "a.bin").stat().st_size == 16000
    np.testing.assert_array_equal(read_velodyne(tmp_path / "a.bin"), pts)
    write_velodyne(tmp_path / "b.bin", pts[:, :3])
    back = read_velodyne(tmp_path / "b.bin")
    np.testing.assert_array_equal(back[:, :3], pts[:, :3])
    assert np.all(back[:, 3] == 0)
    write_velodyne(tmp_path / "e.bin", np.zeros((0, 3)))
    assert read_velodyne(tmp_path / "e.bin").shape == (0, 4)
    (tmp_path / "bad.bin").write_bytes(b"\0" * 20)
    with pytest.raises(DataError, match=r"bad\.bin: size 20 bytes is not a multiple of 16"):
        read_velodyne(tmp_path / "bad.bin")


# ----------------------------------------------------------------------------- oxts


def _mercator_pose(row, scale):
    """Independent restatement of the KITTI devkit's convertOxtsToPose for one row."""
    lat, lon, alt, roll, pitch, yaw = row[:6]
    t = [scale * lon * np.pi * 6378137.0 / 180,
         scale * 6378137.0 * np.log(np.tan((90 + lat) * np.pi / 360)), alt]
    rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0],
                   [-np.sin(pitch), 0, np.cos(pitch)]])
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rz @ ry @ rx
    m[:3, 3] = t
    return m


def test_oxts_read_write_and_poses(tmp_path):
    rows = read_oxts(SAMPLE / "oxts" / "0000.txt")
    assert rows.shape == (3, 30) and rows[0, 0] == 49.015003823272 and rows[0, 26] == 10
    write_oxts(tmp_path / "o.txt", rows)
    np.testing.assert_array_equal(read_oxts(tmp_path / "o.txt"), rows)
    write_oxts(tmp_path / "p.txt", read_oxts(tmp_path / "o.txt"))
    assert (tmp_path / "p.txt").read_text() == (tmp_path / "o.txt").read_text()
    poses = oxts_to_poses(rows)
    scale = np.cos(rows[0, 0] * np.pi / 180)
    t0 = _mercator_pose(rows[0], scale)
    for i in range(3):
        ref = np.linalg.inv(t0) @ _mercator_pose(rows[i], scale)
        np.testing.assert_allclose(poses[i], ref, atol=1e-9)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    # ~0.7 m of latitude change between rows 0 and 1 (1e-5 deg ~ 1.1 m of northing * scale)
    assert 0.1 < np.linalg.norm(poses[1][:3, 3]) < 20
    with pytest.raises(DataError, match=r"oxts_bad\.txt:1: expected 30 oxts columns, got 29"):
        read_oxts(SAMPLE / "oxts_bad.txt")


def test_poses_to_oxts_round_trip():
    rng = np.random.default_rng(2)
    poses = pose_to_matrix(np.c_[np.cumsum(rng.uniform(0, 2, (20, 2)), 0),
                                 rng.normal(0, 0.1, 20), rng.uniform(-3, 3, 20)])
    poses = np.linalg.inv(poses[0]) @ poses
    rows = poses_to_oxts(poses, heading0=0.7)
    assert rows.shape == (20, 30) and rows[0, 0] == 49.011
    np.testing.assert_allclose(oxts_to_poses(rows), poses, atol=1e-6)


# ----------------------------------------------------------------------------- boxes


def test_label_to_pose_ideal_calibration_by_hand():
    calib = _ideal_calib()
    lab = KittiLabel(0, 1, "Car", 0, 0, 0.0, [0, 0, 1, 1], dimensions=[1.5, 1.8, 4.0],
                     location=[2.0, 1.7, 15.0], rotation_y=0.3)
    pose, size = label_to_pose(lab, calib)
    # velodyne x = cam z, y = -cam x, z = -cam y; centre is h/2 above the bottom
    np.testing.assert_allclose(pose[:3], [15.0, -2.0, -(1.7 - 0.75)], atol=1e-12)
    assert pose[3] == pytest.approx(-0.3 - np.pi / 2)
    np.testing.assert_allclose(size, [4.0, 1.8, 1.5])
    fields = pose_to_label_fields(pose, size, calib)
    np.testing.assert_allclose(fields["location"], lab.location, atol=1e-12)
    np.testing.assert_allclose(fields["dimensions"], lab.dimensions)
    assert fields["rotation_y"] == pytest.approx(0.3, abs=1e-12)
    assert fields["alpha"] == pytest.approx(0.3 - np.arctan2(2.0, 15.0))


def test_label_pose_round_trip_default_calibration():
    calib = kitti_default_calib()
    rng = np.random.default_rng(3)
    for _ in range(50):
        pose = np.r_[rng.uniform(3, 60), rng.uniform(-20, 20), rng.uniform(-1.5, 0),
                     rng.uniform(-np.pi, np.pi)]
        size = rng.uniform([3, 1.5, 1.3], [6, 2.2, 2.5])
        fields = pose_to_label_fields(pose, size, calib)
        lab = KittiLabel(0, 0, "Car", 0, 0, bbox=np.zeros(4), **fields)
        back, bsize = label_to_pose(lab, calib)
        np.testing.assert_allclose(back[:3], pose[:3], atol=1e-9)
        np.testing.assert_allclose(bsize, size, atol=1e-12)
        assert abs(np.angle(np.exp(1j * (back[3] - pose[3])))) < 1e-12
        # the textbook shortcut holds to within the calibration's small rotation
        assert abs(np.angle(np.exp(1j * (pose[3] + fields["rotation_y"] + np.pi / 2)))) < 5e-4


def test_sample_van_alpha_consistent():
    calib = kitti_default_calib()
    van = read_labels(SAMPLE / "label_02" / "0000.txt")[1]
    fields = pose_to_label_fields(*label_to_pose(van, calib), calib)
    assert fields["alpha"] == pytest.approx(van.alpha, abs=0.01)
    np.testing.assert_allclose(fields["location"], van.location, atol=1e-9)


# ----------------------------------------------------------------------------- sequences


def test_sample_sequence():
    seq = KittiTrackingSequence(SAMPLE, 0)
    assert seq.sequence == "0000" and seq.frames == [0, 1, 2] and len(seq.labels) == 6
    assert [lab.track_id for lab in seq.frame_labels(0)] == [-1, 0, 1]
    assert seq.calib.P2[0, 0] == 721.5377 and seq.oxts.shape == (3, 30)
    assert seq.ego_poses.shape == (3, 4, 4)
    np.testing.assert_allclose(seq.ego_poses[0], np.eye(4), atol=1e-12)
    assert KittiTrackingSequence.sequences(SAMPLE) == ["0000", "0001"]
    assert seq.image_path(7) == SAMPLE / "image_02" / "0000" / "000007.png"
    with pytest.raises(DataError, match="velodyne file not found"):
        seq.velodyne(0)


def _box_points(rng, pose, size, n):
    """n points strictly inside the box, above the ground band, in the sensor frame."""
    l, w, h = size  # noqa: E741
    local = np.c_[rng.uniform(-0.45 * l, 0.45 * l, n), rng.uniform(-0.45 * w, 0.45 * w, n),
                  rng.uniform(-h / 2 + 0.25, h / 2 - 0.05, n)]
    margin = np.array([[l / 2 + 0.1, 0.0, 0.0], [0.0, -w / 2 - 0.15, 0.2]])  # within margin
    return canonical_to_sensor(np.r_[local, margin], pose)


def _build_sequence(root: Path, calib):
    rng = np.random.default_rng(4)
    write_calib(root / "calib" / "0005.txt", calib)
    tracks = {  # track id -> (type, size, pose per frame or None)
        2: ("Car", np.array([4.2, 1.8, 1.5]), [[12.0, 3.0, -0.98, 0.2], [12.8, 3.1, -0.98, 0.22],
                                               [13.6, 3.2, -0.98, 0.24]]),
        5: ("Van", np.array([5.0, 2.0, 2.1]), [[20.0, -4.0, -0.68, -1.0], None,
                                               [19.0, -4.5, -0.68, -1.1]]),
        9: ("Pedestrian", np.array([0.8, 0.6, 1.7]), [[8.0, -2.0, -0.88, 0.0]] * 3),
    }
    labels, expected = [], {}
    for frame in range(3):
        scan = [np.c_[rng.uniform(30, 50, 50), rng.uniform(-30, 30, 50), rng.uniform(-2, 2, 50)],
                np.c_[rng.uniform(-40, 40, 300), rng.uniform(-40, 40, 300),
                      np.full(300, -1.73)]]  # clutter far away and the road
        for tid, (ty, size, poses) in tracks.items():
            if poses[frame] is None:
                continue
            pose = np.array(poses[frame])
            inside = _box_points(rng, pose, size, (40 if tid == 2 else 20) + 10 * frame)
            ground = canonical_to_sensor(np.c_[rng.uniform(-2, 2, 20), rng.uniform(-0.8, 0.8, 20),
                                               np.full(20, -size[2] / 2 + 0.05)], pose)
            scan += [inside, ground]
            expected[(tid, frame)] = inside.astype(np.float32)
            fields = pose_to_label_fields(pose, size, calib)
            labels.append(KittiLabel(frame, tid, ty, 0, 0, bbox=[1, 2, 3, 4], **fields))
        labels.append(KittiLabel(frame, -1, "DontCare", -1, -1, -10, [5, 5, 9, 9],
                                 [-1000] * 3, [-1000] * 3, -10))
        pts = np.concatenate(scan)
        write_velodyne(velodyne_path(root, 5, frame), pts[rng.permutation(len(pts))])
    write_labels(root / "label_02" / "0005.txt", labels)
    ego = pose_to_matrix(np.array([[0, 0, 0, 0], [1.0, 0, 0, 0.01], [2.0, 0.05, 0, 0.02]]))
    write_oxts(root / "oxts" / "0005.txt", poses_to_oxts(ego))
    return tracks, expected, ego


def _sorted_rows(a):
    a = np.asarray(a)
    return a[np.lexsort(a.T[::-1])]


@pytest.mark.parametrize("calib", [kitti_default_calib(), _ideal_calib()])
def test_extract_tracks_returns_exactly_the_box_points(tmp_path, calib):
    tracks, expected, ego = _build_sequence(tmp_path, calib)
    seq = KittiTrackingSequence(tmp_path, "5")
    assert seq.frames == [0, 1, 2]
    out = extract_tracks(seq)
    assert [t.track_id for t in out] == ["0005_0002", "0005_0005"]
    for tr in out:
        tid = tr.meta["kitti_track_id"]
        ty, size, poses = tracks[tid]
        frames = [f for f in range(3) if poses[f] is not None]
        assert tr.meta["frames"] == frames and tr.meta["type"] == ty
        assert tr.meta["sequence"] == "0005" and tr.complete is None
        np.testing.assert_allclose(tr.timestamps, np.array(frames) / 10.0)
        np.testing.assert_allclose(tr.size, size, atol=2e-6)
        for k, f in enumerate(frames):
            np.testing.assert_array_equal(_sorted_rows(tr.points[k]),
                                          _sorted_rows(expected[(tid, f)]))
            np.testing.assert_allclose(tr.poses[k][:3], poses[f][:3], atol=2e-5)
            assert abs(np.angle(np.exp(1j * (tr.poses[k][3] - poses[f][3])))) < 2e-6
        # ego poses: oxts -> IMU poses -> velodyne poses (identity Tr_imu_velo for _ideal_calib)
        got_ego = np.array(tr.meta["ego_poses"])
        assert got_ego.shape == (len(frames), 4, 4)
        if np.allclose(calib.Tr_imu_velo, np.eye(4)[:3]):
            np.testing.assert_allclose(got_ego, ego[frames], atol=1e-6)
    # generic meta schema beside the KITTI keys
    assert out[1].meta["dataset"] == "kitti" and out[1].meta["class"] == "van"
    assert out[1].meta["object_id"] == "0005" and out[1].meta["category"] == "Van"
    # ground kept when asked; only vehicles (a pedestrian is no vehicle class any more); and
    # the min_points filter
    with_ground = extract_tracks(seq, crop=CropConfig(ground="none"))
    assert all(len(a) >= len(b) + 20 for t0, t1 in zip(out, with_ground, strict=True)
               for a, b in zip(t1.points, t0.points, strict=True))
    assert [t.meta["type"] for t in extract_tracks(seq, types=("Van",))] == ["Van"]
    with pytest.raises(ConfigError, match="Pedestrian"):
        extract_tracks(seq, types=("Pedestrian",))
    # car: 42, 52, 62 points per frame; van: 22, 42
    assert extract_tracks(seq, min_points=63) == []
    assert [t.track_id for t in extract_tracks(seq, min_points=43)] == ["0005_0002"]


def test_kitti_sequence_is_a_driving_log(tmp_path):
    calib = kitti_default_calib()
    tracks, expected, ego = _build_sequence(tmp_path, calib)
    log = open_log("kitti", tmp_path, "0005")
    assert isinstance(log, DrivingLog) and isinstance(log, KittiTrackingSequence)
    assert (log.dataset, log.name, log.sensor, log.frames) == ("kitti", "0005", "hdl64", [0, 1, 2])
    assert KittiTrackingSequence.log_names(tmp_path) == ["0005"]
    assert log.timestamp(2) == pytest.approx(0.2)
    assert log.points(1).shape[1] == 4
    boxes = log.boxes(1)  # DontCare left out; the van has no box in frame 1
    assert [(b.track_id, b.category, b.cls) for b in boxes] == [
        ("0002", "Car", "car"), ("0009", "Pedestrian", None)]
    car = boxes[0]
    np.testing.assert_allclose(car.pose[:3], tracks[2][2][1][:3], atol=2e-5)
    np.testing.assert_allclose(car.size, tracks[2][1], atol=2e-6)
    assert car.visibility == 0.0 and car.extra["truncated"] == 0
    assert [b.track_id for b in log.vehicle_boxes(1)] == ["0002"]
    np.testing.assert_allclose(log.ego_pose(0), np.eye(4), atol=1e-9)
    assert log.ego_pose(3) is None
    assert log.camera_names == ("image_02", "image_03") and log.default_camera == "image_02"
    cam2, cam3 = log.camera(), log.camera("image_03")
    np.testing.assert_array_equal(cam2.P, calib.P2)
    np.testing.assert_array_equal(cam3.P, calib.P3)
    assert log.image_path(4, "image_03") == tmp_path / "image_03" / "0005" / "000004.png"
    assert log.image_path(4, 3) == log.image_path(4, "image_03")  # former int form
    assert log.image_file_name(4, "image_02") == "0005/000004.png"
    with pytest.raises(ConfigError, match="image_01"):
        log.camera("image_01")
    # restrict drops the later frames' labels too
    log.restrict(1)
    assert log.frames == [0] and set(log.labels_by_frame) == {0}


def test_kitti_sequence_without_calib_has_no_cameras(tmp_path):
    write_velodyne(velodyne_path(tmp_path, 2, 0), np.zeros((3, 4), np.float32))
    log = KittiTrackingSequence(tmp_path, 2)
    assert log.camera_names == () and log.default_camera is None
    with pytest.raises(ConfigError, match="no calibration"):
        log.camera()


def test_image_size_from_png(tmp_path):
    write_calib(tmp_path / "calib" / "0001.txt", kitti_default_calib())
    p = image_path(tmp_path, 1, 0)
    p.parent.mkdir(parents=True)
    cv2.imwrite(str(p), np.zeros((37, 124, 3), np.uint8))
    assert png_size(p) == (124, 37)
    seq = KittiTrackingSequence(tmp_path, 1)
    assert seq.frames == [0] and seq.calib.image_size == (124, 37)
    (tmp_path / "x.png").write_bytes(b"GIF89a" + b"\0" * 30)
    with pytest.raises(DataError, match="not a PNG"):
        png_size(tmp_path / "x.png")
    head = bytearray(p.read_bytes())
    head[16:20] = b"\0\0\0\0"  # width 0
    (tmp_path / "z.png").write_bytes(bytes(head))
    with pytest.raises(DataError, match=r"z\.png: PNG header gives an image size of 0 x 37"):
        png_size(tmp_path / "z.png")


def test_crop_box_matches_slow_reference():
    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(-6, 6, (20000, 2)), rng.uniform(-2, 2, 20000)].astype(np.float32)
    for margin in (0.0, 0.2, 1.5):
        pose = np.r_[rng.uniform(-1, 1, 2), -0.5, rng.uniform(-np.pi, np.pi)]
        size = np.array([4.0, 1.8, 1.6])
        inside = points_in_box(pts, size, pose, margin)
        local_z = sensor_to_canonical(pts.astype(np.float64), pose)[:, 2]
        ref = pts[inside & (local_z >= -0.8 + 0.15)]
        got = crop_box(pts, pose, size, margin, ground=0.15)
        assert len(ref) > 100
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(crop_box(pts, pose, size, margin, ground=None), pts[inside])
