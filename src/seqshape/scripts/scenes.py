"""``seqshape scenes``: camera + LiDAR scenes in the KITTI tracking layout with exact amodal GT."""

from __future__ import annotations

import time

from seqshape._runner import parse_shard
from seqshape.errors import ConfigError
from seqshape.sim.degrade import NO_DEGRADE, DegradeConfig
from seqshape.sim.scene_writer import generate_scenes, scene_config

HELP = "generate camera+LiDAR scenes in the KITTI tracking layout"


def add_arguments(p) -> None:
    p.add_argument("--preset", default="kitti-tiny", choices=["kitti-tiny", "kitti-like"],
                   help="kitti-tiny: 1 sequence of 20 frames, 5-7 vehicles (seconds); "
                        "kitti-like: 4 sequences of 60-100 frames, 10-20 vehicles")
    p.add_argument("--out", required=True, help="output folder (KITTI tracking layout)")
    p.add_argument("--seed", type=int, default=0, help="master seed")
    p.add_argument("--sensor", default="hdl64", choices=["hdl64", "vlp16"],
                   help="LiDAR preset (hdl64 at 1.73 m as in KITTI)")
    p.add_argument("--sequences", type=int, default=None,
                   help="override the number of sequences (default: the preset's)")
    p.add_argument("--frames", type=int, default=None,
                   help="override the frames per sequence (fixed count; default: the "
                        "preset's range)")
    p.add_argument("--min-visible-area", type=int, default=None,
                   help="smallest visible area (px) of a KINS / 2D instance (default 20)")
    p.add_argument("--workers", type=int, default=1, help="processes (one sequence each)")
    p.add_argument("--shard", default="1/1", metavar="K/N",
                   help="write only part K of N of the sequences (every N-th, from the K-th), "
                        "e.g. on N machines sharing OUT; the files do not depend on the shard")
    g = p.add_argument_group("2D instance degradations (instances_2d/)")
    g.add_argument("--no-degrade", action="store_true", help="write the exact visible masks")
    g.add_argument("--degrade-jitter", type=float, nargs=2, metavar=("MIN", "MAX"),
                   default=(1.0, 3.0), help="boundary noise amplitude range, px")
    g.add_argument("--degrade-dilate", type=int, default=0,
                   help="dilate (>0) or erode (<0) every mask by this many px")
    g.add_argument("--degrade-miss-small", type=float, default=0.05,
                   help="probability of missing an instance smaller than 32x32 px")
    g.add_argument("--degrade-miss", type=float, default=0.0,
                   help="probability of missing a larger instance")
    g.add_argument("--degrade-false", type=float, default=0.02,
                   help="false instances per true instance (Poisson mean)")


def run(args) -> int:
    if args.workers < 1:
        raise ConfigError("--workers must be >= 1")
    shard = parse_shard(args.shard)
    frames = None if args.frames is None else (args.frames, args.frames)
    cfg = scene_config(args.preset, n_sequences=args.sequences, frames=frames,
                       sensor=args.sensor, min_visible_area=args.min_visible_area)
    degrade = NO_DEGRADE if args.no_degrade else DegradeConfig(
        miss_rate_small=args.degrade_miss_small, miss_rate=args.degrade_miss,
        dilate_px=args.degrade_dilate, jitter_px=tuple(args.degrade_jitter),
        false_rate=args.degrade_false)
    start = time.perf_counter()
    results = generate_scenes(args.out, cfg, seed=args.seed, workers=args.workers,
                              degrade=degrade, shard=shard)
    took = time.perf_counter() - start
    n = sum(r.n_frames for r in results)
    for r in results:
        print(f"sequence {r.sequence}: {r.n_frames} frames, {r.n_labels} label rows, "
              f"{r.n_kins} KINS instances")
    if not results:
        part = "" if shard == (1, 1) else f" of shard {shard[0]}/{shard[1]}"
        print(f"{args.out}: every sequence{part} is already complete ({cfg.n_sequences} in all)")
    else:
        print(f"wrote {n} frames to {args.out} in {took:.1f} s ({n / took:.2f} frames/s)")
    return 0
