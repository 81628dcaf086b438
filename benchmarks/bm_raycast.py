"""Raycasting throughput: seqshape.sim.raycast vs a bare trimesh+embreex full-sweep call.

For each shipped procedural vehicle kind and several distances, in the same run:

* bare:  ``RayMeshIntersector(posed_mesh).intersects_first`` with every ray of a VLP-16 sweep
         (28,800 rays; the mesh moved to the pose beforehand, intersector built and warm);
* frame: ``scan_vehicle`` (window culling, rays mapped to the canonical frame, exact ranges);
* track: ``scan_track`` on a 70-frame track through the same distance (one Embree call);
* same:  the bare ``intersects_first`` on exactly the rays ``scan_track`` casts (canonical
         frame): Embree's own cost for these rays, which mostly hit and cost more than the
         mostly-missing rays of a full sweep.

"rays/s" counts the rays actually cast (ours cast only the culled window; the bare call casts
the whole sweep); "sweeps/s" is the number of vehicle frames per second. Medians of --repeats
runs after a warm-up, fixed seeds.

    python benchmarks/bm_raycast.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main() -> None:
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    from seqshape.geometry import pose_to_matrix
    from seqshape.sim.raycast import (
        full_sweep,
        mesh_raycaster,
        scan_track,
        scan_vehicle,
        track_rays,
    )
    from seqshape.sim.sensors import get_sensor
    from seqshape.vehicles import vehicle_library

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--sensor", default="vlp16")
    args = ap.parse_args()
    cfg = get_sensor(args.sensor).without_noise()
    vehicles = vehicle_library(5, seed=0)  # one of each kind
    rows = []
    for v in vehicles:
        mesh = v.mesh
        z = -cfg.height - mesh.bounds[0, 2]
        for dist in (5.0, 10.0, 20.0, 40.0):
            pose = np.array([dist * np.cos(0.6), dist * np.sin(0.6), z, 1.1])
            posed = mesh.copy()
            posed.apply_transform(pose_to_matrix(pose))
            bare_isect = RayMeshIntersector(posed)
            t_bare = _median_time(lambda: full_sweep(bare_isect, cfg), args.repeats)  # noqa: B023
            mesh_raycaster(mesh)
            rng = np.random.default_rng(0)
            n_frame = len(track_rays(mesh_raycaster(mesh).bounds, pose[None], cfg)[0])
            t_frame = _median_time(lambda: scan_vehicle(mesh, pose, cfg, rng), args.repeats)  # noqa: B023
            # a 70-frame track passing at this distance (1 m per frame, heading along the path)
            s = np.linspace(-35, 35, 70)
            track = np.stack([dist * np.cos(0.6) - s * np.sin(0.6),
                              dist * np.sin(0.6) + s * np.cos(0.6), np.full(70, z),
                              np.full(70, 0.6 + np.pi / 2)], 1)
            n_track = len(track_rays(mesh_raycaster(mesh).bounds, track, cfg)[0])
            t_track = _median_time(lambda: scan_track(mesh, track, cfg, rng), args.repeats)  # noqa: B023
            # the bare call on exactly the rays ours casts (nearly all aimed at the car)
            same = _same_rays(mesh, track, cfg)
            t_same = _median_time(lambda: same[0].intersects_first(same[1], same[2]),  # noqa: B023
                                  args.repeats)
            rows.append((v.kind, len(mesh.faces), dist, cfg.rays_per_sweep / t_bare,
                         cfg.rays_per_sweep / t_bare / cfg.rays_per_sweep, n_frame,
                         n_frame / t_frame, 1 / t_frame, n_track / t_track, 70 / t_track,
                         n_track / t_same))
    _print(rows)


def _same_rays(mesh, track, cfg):
    """A fresh bare intersector of the mesh and exactly the rays ours casts for the track
    (already in the canonical frame): the Embree work inside ours, without our preparation."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    from seqshape.sim.raycast import _to_canonical, mesh_raycaster, track_rays

    dirs, frame = track_rays(mesh_raycaster(mesh).bounds, track, cfg)
    origins, d = _to_canonical(dirs, frame, track)
    return RayMeshIntersector(mesh), origins, d


def _print(rows) -> None:
    head = ("kind", "faces", "dist m", "bare full-sweep Mrays/s", "bare sweeps/s",
            "frame rays", "ours frame Mrays/s", "ours frame sweeps/s", "ours track Mrays/s",
            "ours track sweeps/s", "bare same-rays Mrays/s", "track/bare rays/s")
    print("| " + " | ".join(head) + " |")
    print("|" + "|".join("---" for _ in head) + "|")
    for kind, faces, dist, bare, bs, nf, fr, fs, tr, ts, same in rows:
        print(f"| {kind} | {faces} | {dist:.0f} | {bare / 1e6:.1f} | {bs:.0f} | {nf} | "
              f"{fr / 1e6:.2f} | {fs:.0f} | {tr / 1e6:.2f} | {ts:.0f} | {same / 1e6:.2f} | "
              f"{tr / bare:.2f} |")
    a = np.array([r[3:] for r in rows], dtype=float)
    med = np.median(a, axis=0)
    print(f"\nmedians over {len(rows)} cases: bare full sweep {med[0] / 1e6:.1f} Mrays/s "
          f"({med[1]:.0f} sweeps/s); ours per frame {med[3] / 1e6:.2f} Mrays/s "
          f"({med[4]:.0f} sweeps/s); ours per track {med[5] / 1e6:.2f} Mrays/s "
          f"({med[6]:.0f} sweeps/s); bare call on our rays {med[7] / 1e6:.2f} Mrays/s; "
          f"ours/bare rays/s {np.median(a[:, 5] / a[:, 0]):.2f} (full sweep), "
          f"{np.median(a[:, 5] / a[:, 7]):.2f} (same rays); ours/bare sweeps/s "
          f"{np.median(a[:, 6] / a[:, 1]):.0f}x")


if __name__ == "__main__":
    main()
