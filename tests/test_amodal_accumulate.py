"""GT-Accumulation: mirrored accumulation of a symmetric box, placement, export."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from seqshape.amodal.accumulate import (
    accumulate_canonical,
    export_tracks,
    mirror_y,
    place_in_frames,
    voxel_downsample,
)
from seqshape.data.track import Track
from seqshape.geometry import canonical_to_sensor
from seqshape.testing import box_shell

SIZE = np.array([4.0, 1.8, 1.5])


def box_surface(n, seed):
    return box_shell(n, seed, SIZE)


def chamfer(a, b):
    return cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean()


def left_side_track():
    """A box seen only from its left (y > 0) side and its rear, over 5 frames and poses."""
    poses = np.array([[10, 5, -0.9, 0.1], [12, 5, -0.9, 0.2], [14, 5.5, -0.9, 0.0],
                      [16, 6, -0.9, -0.1], [18, 6, -0.9, 0.05]])
    frames = []
    for t, pose in enumerate(poses):
        p = box_surface(3000, t)
        p = p[(p[:, 1] > 0.05) | (p[:, 0] < -SIZE[0] / 2 + 1e-6)]  # left side and rear only
        frames.append(canonical_to_sensor(p.astype(np.float32), pose))
    return Track("t0", frames, poses, None, SIZE, np.arange(5) / 10.0)


def test_core_lives_in_the_data_layer():
    from seqshape.amodal import accumulate
    from seqshape.data import reference

    for name in ("accumulate_canonical", "mirror_y", "voxel_downsample", "VOXEL", "BOX_MARGIN"):
        assert getattr(accumulate, name) is getattr(reference, name)


def test_mirror_y():
    p = np.array([[1.0, 2.0, 3.0]])
    assert mirror_y(p).tolist() == [[1.0, -2.0, 3.0]]
    assert p[0, 1] == 2.0  # input untouched


def test_mirrored_accumulation_recovers_symmetric_box():
    tr = left_side_track()
    full = box_surface(20000, 99)
    no_mirror = accumulate_canonical(tr, mirror=False, voxel=0.05)
    mirrored = accumulate_canonical(tr, mirror=True, voxel=0.05)
    sides = no_mirror[no_mirror[:, 0] > -SIZE[0] / 2 + 0.1]
    assert sides[:, 1].min() > -0.1  # only the left half (and the rear) was seen
    assert mirrored[:, 1].min() < -SIZE[1] / 2 + 0.05  # the right side is there now
    # the right side's points are all on the true box surface
    d = cKDTree(full).query(mirrored)[0]
    assert np.quantile(d, 0.99) < 0.06
    # and the mirrored cloud covers the whole box except the unseen front face
    no_front = full[full[:, 0] < SIZE[0] / 2 - 1e-6]
    cover = cKDTree(mirrored).query(no_front)[0]
    assert np.quantile(cover, 0.99) < 0.08
    # symmetric: the cloud is its own mirror image
    assert chamfer(mirrored, mirror_y(mirrored)) < 0.05


def test_place_in_frames_round_trip():
    tr = left_side_track()
    canon = accumulate_canonical(tr)
    placed = place_in_frames(canon, tr.poses)
    for cloud, pts in zip(placed, tr.points, strict=True):
        assert cloud.shape == canon.shape and cloud.dtype == np.float32
        assert cKDTree(cloud).query(pts)[0].max() < 0.06  # observed points lie on it
    nan = place_in_frames(canon, np.full((1, 4), np.nan))
    assert nan[0].shape == (0, 3)


def test_outliers_outside_box_dropped_and_voxel():
    tr = left_side_track()
    tr.points[0] = np.vstack([tr.points[0], [[30.0, 30.0, 0.0]]]).astype(np.float32)
    canon = accumulate_canonical(tr, mirror=False)
    assert np.abs(canon).max() < 2.2
    v = voxel_downsample(np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [1, 1, 1]]), 0.1)
    assert len(v) == 2 and np.allclose(sorted(v[:, 0]), [0.015, 1.0])


def test_export_tracks(tmp_path):
    tracks = [left_side_track()]
    tracks.append(Track("t1", tracks[0].points, tracks[0].poses, None, SIZE,
                        np.arange(5) / 10.0))
    ds = export_tracks(tracks, tmp_path / "ds", val_fraction=0.5)
    assert len(ds) == 2
    assert {ds[i].split for i in range(2)} == {"train", "val"}
    assert ds[0].complete is not None and len(ds[0].complete) > 100
    with pytest.raises(ValueError):
        export_tracks([Track("e", [np.zeros((0, 3))], np.zeros((1, 4)), None, SIZE, [0.0])],
                      tmp_path / "empty")
