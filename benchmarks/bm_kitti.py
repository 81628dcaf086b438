"""Throughput of the KITTI I/O and camera hot paths on an HDL-64E-sized scan (~120k points).

Run: python benchmarks/bm_kitti.py [--repeats 7] [--seed 0]
Two warm-up calls, then the median and spread (min-max) of the timed calls; fixed seed.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from _bench import bench_parser, print_table, time_it

from seqshape.camera import kitti_default_calib, project_points
from seqshape.data.crop import crop_box, crop_vehicle
from seqshape.data.kins import mask_to_polygons, mask_to_rle, rle_to_mask, segm_to_mask
from seqshape.data.kitti import read_velodyne, write_velodyne


def main():
    args = bench_parser(__doc__, repeats=7).parse_args()
    rng = np.random.default_rng(args.seed)
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
            ("crop_vehicle (120k pts, 1 box, ground plane)",
             lambda: crop_vehicle(scan, pose, size)),
            ("mask_to_rle (1242x375)", lambda: mask_to_rle(mask)),
            ("rle_to_mask (1242x375)", lambda: rle_to_mask(mask_to_rle(mask))),
            ("mask_to_polygons (1242x375)", lambda: mask_to_polygons(mask)),
            ("polygons -> mask (1242x375)",
             lambda: segm_to_mask(mask_to_polygons(mask), 375, 1242)),
        ]
        table = []
        for name, fn in rows:
            t = time_it(fn, args.repeats, warmup=2)
            table.append((name, *(f"{v * 1e3:.2f}" for v in (t.median, t.min, t.max))))
    print_table(("operation", "median ms", "min ms", "max ms"), table)


if __name__ == "__main__":
    main()
