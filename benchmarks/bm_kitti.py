"""Throughput of the KITTI I/O and camera hot paths on an HDL-64E-sized scan (~120k points).

Run: python benchmarks/bm_kitti.py
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from seqshape.amodal.kins import mask_to_rle, rle_to_mask
from seqshape.camera import kitti_default_calib, project_points
from seqshape.data.kitti import crop_box, read_velodyne, write_velodyne


def bench(fn, repeats=7, warmup=2):
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times), max(times)


def main():
    rng = np.random.default_rng(0)
    n = 120_000
    scan = np.c_[rng.uniform(-80, 80, (n, 2)), rng.uniform(-2, 2, n),
                 rng.uniform(0, 1, n)].astype(np.float32)
    calib = kitti_default_calib()
    mask = np.zeros((375, 1242), bool)
    mask[150:260, 300:520] = True
    mask[200:230, 400:430] = False
    pose, size = np.array([12.0, 3.0, -0.98, 0.3]), np.array([4.2, 1.8, 1.5])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "000000.bin"
        write_velodyne(path, scan)
        rows = [
            ("read_velodyne (120k pts)", lambda: read_velodyne(path)),
            ("write_velodyne (120k pts)", lambda: write_velodyne(path, scan)),
            ("project_points (120k pts)", lambda: project_points(scan[:, :3], calib)),
            ("crop_box (120k pts, 1 box)", lambda: crop_box(scan, pose, size)),
            ("mask_to_rle (1242x375)", lambda: mask_to_rle(mask)),
            ("rle_to_mask (1242x375)", lambda: rle_to_mask(mask_to_rle(mask))),
        ]
        print(f"{'operation':30s} {'median ms':>10s} {'min ms':>8s} {'max ms':>8s}")
        for name, fn in rows:
            med, lo, hi = bench(fn)
            print(f"{name:30s} {med * 1e3:10.2f} {lo * 1e3:8.2f} {hi * 1e3:8.2f}")


if __name__ == "__main__":
    main()
