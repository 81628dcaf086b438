"""Benchmark seqshape.vehicles: library build time, outer-surface sampling, mesh loading.

Run: python benchmarks/bm_vehicles.py [--repeats 5]
Fixed seeds; one warm-up run, then the median of the repeats.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from seqshape.vehicles import load_vehicle_folder, sample_outer_surface, vehicle_library


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    cars = vehicle_library(20, seed=0)
    faces = np.mean([len(v.mesh.faces) for v in cars])
    rows = [("vehicle_library(183, seed=0)", _median_time(lambda: vehicle_library(183), 3), "s")]
    t = _median_time(lambda: [sample_outer_surface(v.mesh, 2048, seed=0) for v in cars],
                     args.repeats)
    rows.append(("sample_outer_surface(n=2048), per car", t / len(cars), "s"))
    with tempfile.TemporaryDirectory() as tmp:
        for v in cars:
            v.mesh.export(Path(tmp) / f"{v.vehicle_id}.obj")
        t = _median_time(lambda: load_vehicle_folder(tmp), args.repeats)
    rows.append(("load_vehicle (OBJ), per file", t / len(cars), "s"))
    print(f"procedural meshes: {faces:.0f} faces on average (20 cars)")
    print(f"| {'operation':<40} | {'median':>10} |")
    print(f"| {'-' * 40} | {'-' * 10} |")
    for name, value, unit in rows:
        print(f"| {name:<40} | {value * 1e3:>7.1f} ms |" if value < 1 else
              f"| {name:<40} | {value:>8.2f} {unit} |")


if __name__ == "__main__":
    main()
