"""Benchmark seqshape.vehicles: library build time, outer-surface sampling, mesh loading,
and the fleet generator per kind (build time, triangles).

Run: python benchmarks/bm_vehicles.py [--repeats 5] [--seed 0]
Fixed seeds; one warm-up run, then the median of the repeats (the 183-vehicle library build:
always 3 repeats). Fleet kinds: 10 vehicles per kind (seeds seed..seed+9) per timed run; the
table gives the median build time per vehicle and the triangle counts (min / median / max).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from _bench import bench_parser, print_table, time_it

from seqshape.vehicles import (
    FLEET_KINDS,
    fleet_library,
    fleet_vehicle,
    load_vehicle_folder,
    sample_outer_surface,
    vehicle_library,
)


def fleet_table(seed: int, repeats: int) -> None:
    """Per fleet kind: median build time per vehicle and triangle counts over 10 seeds."""
    rows = []
    for kind, cls in FLEET_KINDS.items():
        seeds = range(seed, seed + 10)
        t = time_it(lambda kind=kind, seeds=seeds: [fleet_vehicle(kind, s) for s in seeds],
                    repeats)
        faces = np.array([len(v.mesh.faces) for v in t.result])
        rows.append((kind, cls, f"{t.median / len(seeds) * 1e3:.1f} ms",
                     f"{faces.min()} / {int(np.median(faces))} / {faces.max()}"))
    print_table(("fleet kind", "class", "build / vehicle", "triangles min / median / max"),
                rows, align="llrr")
    t = time_it(lambda: fleet_library(183, seed=seed), 1)
    faces = np.mean([len(v.mesh.faces) for v in t.result])
    print(f"\nfleet_library(183, seed={seed}): {t.median:.2f} s, {faces:.0f} triangles on "
          "average")
    lib = t.result[:20]
    t = time_it(lambda: [sample_outer_surface(v.mesh, 2048, seed=seed) for v in lib], repeats)
    print(f"sample_outer_surface(n=2048) on the first 20 fleet vehicles: "
          f"{t.median / len(lib) * 1e3:.1f} ms per vehicle")


def main() -> None:
    args = bench_parser(__doc__, repeats=5).parse_args()
    seed = args.seed
    cars = vehicle_library(20, seed=seed)
    faces = np.mean([len(v.mesh.faces) for v in cars])
    rows = [(f"vehicle_library(183, seed={seed})",
             time_it(lambda: vehicle_library(183, seed=seed), 3).median)]
    t = time_it(lambda: [sample_outer_surface(v.mesh, 2048, seed=seed) for v in cars],
                args.repeats).median
    rows.append(("sample_outer_surface(n=2048), per car", t / len(cars)))
    with tempfile.TemporaryDirectory() as tmp:
        for v in cars:
            v.mesh.export(Path(tmp) / f"{v.vehicle_id}.obj")
        t = time_it(lambda: load_vehicle_folder(tmp), args.repeats).median
    rows.append(("load_vehicle (OBJ), per file", t / len(cars)))
    print(f"procedural meshes: {faces:.0f} faces on average (20 cars)")
    print_table(("operation", "median"),
                [(name, f"{value * 1e3:.1f} ms" if value < 1 else f"{value:.2f} s")
                 for name, value in rows])
    print()
    fleet_table(seed, args.repeats)


if __name__ == "__main__":
    main()
