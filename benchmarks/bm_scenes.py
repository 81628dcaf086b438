"""Frames per second of camera + LiDAR scene generation at kitti-like size.

Stages timed per frame on the frames of one kitti-like sequence (10-20 vehicles, HDL-64E
sweep of 64 x 4500 rays, 1242 x 375 camera = 466k pixel rays plus the amodal rays):

* lidar   : ``render_lidar`` (all returns, noise, reflectance)
* camera  : ``render_camera`` (image, amodal + visible masks, truncation rays)
* truth   : ``frame_truth`` (label rows, KINS RLEs, occlusion order)
* frame   : the whole frame as ``seqshape scenes`` does it, files written (PNG, .bin)

Warm-up of one frame (Embree BVHs, pixel rays), then ``--repeats`` passes over ``--frames``
frames; the table shows the median per-frame time over passes. Single process.

    python benchmarks/bm_scenes.py [--frames 8] [--repeats 3] [--sensor hdl64] [--seed 0]
"""

from __future__ import annotations

import tempfile

import numpy as np
from _bench import bench_parser, print_table, time_it

from seqshape._io import atomic_write_bytes
from seqshape.camera import kitti_default_calib
from seqshape.data.kitti import image_path, velodyne_path, write_velodyne
from seqshape.sim.render import camera_rays, render_camera, render_lidar
from seqshape.sim.scene_writer import _png, _rng, frame_truth, make_scene, scene_config
from seqshape.sim.scenes import ground_material
from seqshape.sim.sensors import get_sensor


def main() -> None:
    ap = bench_parser(__doc__, repeats=3)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--sensor", default="hdl64")
    args = ap.parse_args()

    cfg = scene_config("kitti-like", sensor=args.sensor)
    scene = make_scene(cfg, args.seed, 0)
    calib, lidar = kitti_default_calib(), get_sensor(args.sensor)
    rays = camera_rays(calib)
    meshes = [scene.mesh(k) for k in range(len(scene.agents))]
    frames = np.linspace(0, scene.n_frames - 1, args.frames).astype(int)
    out = tempfile.mkdtemp(prefix="bm_scenes_")

    def lidar_stage(t):
        return render_lidar(meshes, scene.sensor_poses(t), scene.colours, lidar,
                            _rng(0, 0, 1, t), ground_material=ground_material(scene, t))

    def camera_stage(t):
        return render_camera(meshes, scene.sensor_poses(t), scene.colours, rays,
                             -scene.sensor_height, ground_material(scene, t))

    def frame_stage(t):
        pts, _ = lidar_stage(t)
        cam = camera_stage(t)
        write_velodyne(velodyne_path(out, "0000", t), pts)
        atomic_write_bytes(image_path(out, "0000", t), _png(cam.image))
        frame_truth(scene, t, cam, calib, cfg.min_visible_area)

    cams = {t: camera_stage(t) for t in frames[:1]}  # warm-up
    lidar_stage(frames[0])
    stages = {"lidar": lidar_stage, "camera": camera_stage,
              "truth": lambda t: frame_truth(scene, t, cams.setdefault(t, camera_stage(t)),
                                             calib, cfg.min_visible_area),
              "frame": frame_stage}
    for t in frames:  # cache camera frames so that "truth" times only the labelling
        cams.setdefault(t, camera_stage(t))
    rows = []
    for name, fn in stages.items():  # warmed up above: no warm-up pass here
        passes = time_it(lambda fn=fn: [fn(t) for t in frames], args.repeats, warmup=0)
        med = passes.median / len(frames)
        rows.append((name, f"{med * 1e3:.1f}", f"{1.0 / med:.2f}"))
    pts, _ = lidar_stage(frames[0])
    print(f"kitti-like sequence 0 (seed {args.seed}): {len(scene.agents)} vehicles, "
          f"{scene.n_frames} frames; {args.sensor} {lidar.rays_per_sweep} rays/sweep "
          f"({len(pts)} returns); camera {calib.width}x{calib.height}; "
          f"{args.frames} frames x {args.repeats} passes, median")
    print_table(("stage", "ms/frame", "frames/s"), rows)


if __name__ == "__main__":
    main()
