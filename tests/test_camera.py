from pathlib import Path

import numpy as np
import pytest

from seqshape.camera import (
    KittiCalib,
    cam_to_velo,
    in_image,
    kitti_default_calib,
    project_points,
    read_calib,
    unproject_points,
    velo_to_cam,
    write_calib,
)
from seqshape.errors import DataError

SAMPLE = Path(__file__).parent / "data" / "kitti_sample"


def _ideal_calib(f=700.0, cx=600.0, cy=180.0):
    """Camera at the LiDAR origin, no rectification, no baseline: hand-checkable."""
    velo_to_cam = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    p = np.array([[f, 0.0, cx, 0.0], [0.0, f, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
    return KittiCalib(P0=p, P1=p, P2=p, P3=p, R_rect=np.eye(3), Tr_velo_cam=velo_to_cam,
                      Tr_imu_velo=np.eye(4)[:3])


def test_read_tracking_calib_colonless_keys():
    calib = read_calib(SAMPLE / "calib" / "0000.txt")
    assert calib.P2[0, 0] == 721.5377 and calib.P2[0, 3] == 44.85728
    assert calib.P1[0, 3] == -387.5744
    assert calib.R_rect[0, 1] == 9.837760e-03
    assert calib.Tr_velo_cam[2, 3] == -2.717806e-01
    assert calib.Tr_imu_velo[0, 3] == -8.086759e-01
    ref = kitti_default_calib()
    for name in ("P0", "P1", "P2", "P3", "R_rect", "Tr_velo_cam", "Tr_imu_velo"):
        np.testing.assert_array_equal(getattr(calib, name), getattr(ref, name))
    assert calib.image_size == (1242, 375)


def test_read_object_calib():
    calib = read_calib(SAMPLE / "calib_object_000000.txt")
    assert calib.P2[0, 2] == 604.0814 and calib.P2[1, 3] == -0.3454157
    assert calib.R_rect[2, 2] == 0.9999556
    assert calib.Tr_velo_cam[0, 3] == -0.02457729
    assert calib.Tr_imu_velo[1, 3] == 0.3195559


def test_malformed_calib_names_file_and_line():
    with pytest.raises(DataError) as err:
        read_calib(SAMPLE / "calib_bad.txt")
    assert err.value.line == 2 and "calib_bad.txt:2" in str(err.value)
    assert "expected 12 numbers, got 6" in str(err.value)


def test_missing_calib_key(tmp_path):
    p = tmp_path / "c.txt"
    p.write_text("P2: 1 0 0 0 0 1 0 0 0 0 1 0\nR_rect 1 0 0 0 1 0 0 0 1\n")
    with pytest.raises(DataError, match="Tr_velo_cam"):
        read_calib(p)
    with pytest.raises(DataError, match="not found"):
        read_calib(tmp_path / "nope.txt")


def test_write_read_calib_exact(tmp_path):
    rng = np.random.default_rng(0)
    c = kitti_default_calib()
    c.P2 = c.P2 + rng.normal(size=(3, 4)) * 1e-7  # full float64 precision
    write_calib(tmp_path / "c.txt", c)
    text = (tmp_path / "c.txt").read_text()
    assert text.startswith("P0: ") and "\nR_rect " in text and "\nTr_velo_cam " in text
    back = read_calib(tmp_path / "c.txt")
    for name in ("P0", "P1", "P2", "P3", "R_rect", "Tr_velo_cam", "Tr_imu_velo"):
        np.testing.assert_array_equal(getattr(back, name), getattr(c, name))
    write_calib(tmp_path / "d.txt", back)
    assert (tmp_path / "d.txt").read_text() == text


def test_box_projects_to_hand_computed_box():
    # 2 m cube centred 10 m ahead: X = -y, Y = -z in [-1, 1], Z = x in [9, 11].
    f, cx, cy = 700.0, 600.0, 180.0
    calib = _ideal_calib(f, cx, cy)
    s = np.array([-1.0, 1.0])
    corners = np.array([[10 + a, b, c] for a in s for b in s for c in s])
    uv, depth = project_points(corners, calib)
    assert uv[:, 0].min() == pytest.approx(cx - f / 9) and uv[:, 0].max() == pytest.approx(cx + f / 9)
    assert uv[:, 1].min() == pytest.approx(cy - f / 9) and uv[:, 1].max() == pytest.approx(cy + f / 9)
    np.testing.assert_allclose(np.sort(np.unique(depth)), [9.0, 11.0])


def test_box_projection_matches_plain_matrix_chain():
    calib = kitti_default_calib()
    # corners of a 4.2 x 1.8 x 1.5 box, yaw 0.4, centre (15, -3, -0.9), built explicitly
    length, w, h, yaw = 4.2, 1.8, 1.5, 0.4
    c, s = np.cos(yaw), np.sin(yaw)
    corners = []
    for dx in (-length / 2, length / 2):
        for dy in (-w / 2, w / 2):
            for dz in (-h / 2, h / 2):
                corners.append([15 + c * dx - s * dy, -3 + s * dx + c * dy, -0.9 + dz])
    corners = np.array(corners)
    r4 = np.eye(4)
    r4[:3, :3] = calib.R_rect
    t4 = np.eye(4)
    t4[:3] = calib.Tr_velo_cam
    hom = (calib.P2 @ r4 @ t4 @ np.c_[corners, np.ones(8)].T).T
    ref_uv = hom[:, :2] / hom[:, 2:]
    ref_box = [ref_uv[:, 0].min(), ref_uv[:, 1].min(), ref_uv[:, 0].max(), ref_uv[:, 1].max()]
    uv, depth = project_points(corners, calib)
    box = [uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()]
    np.testing.assert_allclose(box, ref_box, atol=1e-9)
    np.testing.assert_allclose(depth, hom[:, 2], atol=1e-12)
    # sanity: a car 15 m ahead, 3 m right, lands right of centre and fully in the image
    assert 609.6 < box[0] < box[2] < 1242 and 0 < box[1] < box[3] < 375


def test_project_unproject_round_trip():
    calib = kitti_default_calib()
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(3, 60, 200), rng.uniform(-15, 15, 200), rng.uniform(-2, 2, 200)]
    uv, depth = project_points(pts, calib)
    np.testing.assert_allclose(unproject_points(uv, depth, calib), pts, atol=1e-9)
    np.testing.assert_allclose(cam_to_velo(velo_to_cam(pts, calib), calib), pts, atol=1e-12)
    # depth is metres along the optical axis: ~ x_velo for the standard calibration
    np.testing.assert_allclose(depth, pts[:, 0], atol=0.35)


def test_standard_axes_and_in_image():
    calib = kitti_default_calib()
    cam = velo_to_cam(np.array([[10.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]), calib)
    origin = velo_to_cam(np.zeros((1, 3)), calib)[0]
    d = cam - origin
    np.testing.assert_allclose(d[0], [0, 0, 10], atol=0.2)   # forward -> +z
    np.testing.assert_allclose(d[1], [-1, 0, 0], atol=0.02)  # left -> -x
    np.testing.assert_allclose(d[2], [0, -1, 0], atol=0.02)  # up -> -y
    uv, depth = project_points(np.array([[10.0, 0, 0], [-10.0, 0, 0], [10, 40, 0]]), calib)
    assert in_image(uv, depth, calib).tolist() == [True, False, False]


def test_radial_distortion_round_trip_and_no_fold_back():
    from seqshape.camera import PinholeCamera

    K = np.array([[1000.0, 0, 800], [0, 1000.0, 600], [0, 0, 1]])
    t = np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]])  # x fwd -> z
    cam = PinholeCamera.from_intrinsics(K, t, (1600, 1200), radial=(-0.27, 0.08, -0.01))
    plain = PinholeCamera.from_intrinsics(K, t, (1600, 1200))
    pts = np.array([[10.0, 0.0, 0.0], [10.0, -4.0, -3.0], [10.0, 5.0, 2.0]])
    uv, depth = cam.project(pts)
    uv0, _ = plain.project(pts)
    np.testing.assert_allclose(uv[0], [800, 600])  # nothing moves at the principal point
    # by hand: point 2 has normalised (0.4, 0.3), r^2 = 0.25, scale 1 - 0.0675 + 0.005 - 0.00015625
    s = 1 - 0.27 * 0.25 + 0.08 * 0.0625 - 0.01 * 0.015625
    np.testing.assert_allclose(uv[1], [800 + 400 * s, 600 + 300 * s])
    np.testing.assert_allclose(cam.unproject(uv, depth), pts, atol=1e-6)
    assert np.linalg.norm(uv[2] - [800, 600]) < np.linalg.norm(uv0[2] - [800, 600])  # barrel
    # far off-axis (past the radius where the polynomial turns) never folds into the image
    far = np.array([[1.0, -40.0, 0.0]])
    assert not cam.in_image(*cam.project(far)).any()
