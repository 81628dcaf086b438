"""``seqshape generate``: write a synthetic LiDAR track dataset (see docs/generation.md).

The config is :func:`seqshape.sim.generate.scaled_preset_config` (``--vehicles`` scales the
val share, ``--mean-frames`` the length range); the work is
:func:`~seqshape.sim.generate.generate_dataset`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from seqshape._runner import parse_shard
from seqshape.sim.generate import PRESETS, generate_dataset, scaled_preset_config
from seqshape.sim.sensors import SENSORS

HELP = "generate a synthetic LiDAR track dataset"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", choices=sorted(PRESETS), default="tiny",
                        help="tiny: a few short tracks in seconds; paper: 183 vehicles x 11 "
                             "tracks, VLP-16; realistic: paper + ground, occluders, noise; "
                             "real: fleet vehicles, sensor mix, glass, dark surfaces, edge "
                             "mixing, ground and clutter, tracker-box crop (docs/generation.md)")
    parser.add_argument("--out", required=True, help="output dataset folder")
    parser.add_argument("--meshes", help="folder of vehicle meshes (OBJ/PLY/STL/OFF/GLB/GLTF) "
                                         "to use instead of procedural vehicles (default: none)")
    parser.add_argument("--mesh-up", default=None, help="up axis of --meshes (default z)")
    parser.add_argument("--mesh-forward", default=None,
                        help="forward axis of --meshes (default x)")
    parser.add_argument("--mesh-scale", type=float, default=None,
                        help="scale of --meshes to metres (default 1)")
    parser.add_argument("--trajectories", metavar="CSV_OR_DIR",
                        help="drive the vehicles along CSV logs (t,x,y,yaw in the sensor frame) "
                             "instead of sampled trajectories (default: none)")
    parser.add_argument("--sensor", choices=sorted(SENSORS), default=None,
                        help="LiDAR preset (default vlp16; with --preset real: one sensor "
                             "instead of the preset's mix)")
    parser.add_argument("--library", choices=("procedural", "fleet"), default=None,
                        help="vehicle library (default: procedural; fleet for --preset real)")
    parser.add_argument("--placement", choices=("crossing", "traffic"), default=None,
                        help="where sampled tracks are placed: crossing the line of sight "
                             "(default; the paper) or in road traffic around a moving ego (the "
                             "default of --preset real; docs/generation.md)")
    parser.add_argument("--vehicles", type=int, default=None, dest="n_vehicles",
                        help="number of vehicles (default: the preset's; the val share "
                             "scales with it)")
    parser.add_argument("--tracks-per-vehicle", type=int, default=None,
                        help="trajectories per vehicle (default: the preset's)")
    parser.add_argument("--mean-frames", type=float, default=None,
                        help="mean track length in frames (default: the preset's; the longest "
                             "track is capped at 3x this mean, or the preset's cap if smaller)")
    parser.add_argument("--seed", type=int, default=None, help="master seed (default 0)")
    parser.add_argument("--num-points", type=int, default=None,
                        help="points of the complete shape per vehicle (default 2048)")
    parser.add_argument("--workers", type=int, default=1, help="worker processes")
    parser.add_argument("--shard", default="1/1", metavar="K/N",
                        help="generate only part K of N (1-based, by vehicle); rerun without "
                             "--shard (or any shard) once all parts exist to write the manifest")


def run(args: argparse.Namespace) -> int:
    shard = parse_shard(args.shard)
    meshes = str(Path(args.meshes).resolve()) if args.meshes else None
    trajs = str(Path(args.trajectories).resolve()) if args.trajectories else None
    config = scaled_preset_config(args.preset, n_vehicles=args.n_vehicles,
                                  mean_frames=args.mean_frames, sensor=args.sensor,
                                  seed=args.seed, num_points=args.num_points, meshes=meshes,
                                  trajectories=trajs, mesh_up=args.mesh_up,
                                  mesh_forward=args.mesh_forward, mesh_scale=args.mesh_scale,
                                  library=args.library, placement=args.placement,
                                  tracks_per_vehicle=args.tracks_per_vehicle)
    s = generate_dataset(config, args.out, workers=args.workers, shard=shard)
    print(f"{args.out}: {s.n_generated} tracks generated, {s.n_skipped} already there, "
          f"{s.n_tracks} in the preset ({s.seconds:.1f} s)")
    if s.manifest_written:
        print(f"manifest written: {Path(args.out) / 'manifest.json'}")
    else:
        print(f"{len(s.missing)} tracks of other shards are still missing; the manifest is "
              f"written by the run that completes the set")
    return 0
