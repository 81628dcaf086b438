"""A hand-built KITTI tracking sequence 0000 in the official layout: box cars driving along x
over a flat ground, the sensor-facing surface of each car in the velodyne scans, their boxes in
label_02, the default calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seqshape.camera import kitti_default_calib, write_calib
from seqshape.data.kitti import KittiLabel, pose_to_label_fields, write_velodyne
from seqshape.data.kitti import write_labels as write_kitti
from seqshape.geometry import canonical_to_sensor
from seqshape.testing import box_shell

GROUND_Z = -1.73  # the ground under KITTI's Velodyne
TWO_CARS = ((8, 2.5, 0.5, 0.2), (14, -3.0, 0.7, -0.1))  # (x, y, speed m/frame, yaw)


def write_box_kitti(root: Path, frames: int = 4, cars=TWO_CARS, size=(4.0, 1.8, 1.5),
                    ground_points: int = 1000) -> Path:
    """Write ``root`` (calib, velodyne, label_02 of sequence 0000) and return it; frame t draws
    from ``np.random.default_rng(t)``."""
    calib = kitti_default_calib()
    write_calib(root / "calib" / "0000.txt", calib)
    z = GROUND_Z + size[2] / 2
    labels = []
    for t in range(frames):
        rng = np.random.default_rng(t)
        scan = [np.c_[rng.uniform([3, -10], [40, 10], (ground_points, 2)),
                      np.full(ground_points, GROUND_Z)]]
        for k, (x, y, v, yaw) in enumerate(cars):
            pose = np.array([x + v * t, y, z, yaw])
            s = canonical_to_sensor(box_shell(3000, rng, size, dtype=np.float32), pose)
            scan.append(s[np.linalg.norm(s[:, :2], axis=1) < np.linalg.norm(pose[:2])])
            labels.append(KittiLabel(frame=t, track_id=k, type="Car", truncated=0, occluded=0,
                                     bbox=[0, 0, 1, 1], **pose_to_label_fields(pose, size, calib)))
        scan = np.vstack(scan).astype(np.float32)
        write_velodyne(root / "velodyne" / "0000" / f"{t:06d}.bin",
                       np.c_[scan, np.zeros(len(scan))])
    write_kitti(root / "label_02" / "0000.txt", labels)
    return root
