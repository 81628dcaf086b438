"""``seqshape scenes``: camera + LiDAR scenes in the KITTI tracking layout with exact amodal GT.

The work is :func:`seqshape.sim.scene_writer.generate_scenes`; the ``--degrade-*`` options are
the fields of :class:`seqshape.sim.degrade.DegradeConfig` (help and defaults from the class).
"""

from __future__ import annotations

import time

from seqshape._runner import parse_shard
from seqshape.errors import ConfigError
from seqshape.scripts._config_args import add_config_arguments, config_kwargs, field_help
from seqshape.sim.degrade import NO_DEGRADE, DegradeConfig
from seqshape.sim.scene_writer import generate_scenes, scene_config
from seqshape.sim.scenes import check_vehicle_range

HELP = "generate camera+LiDAR scenes in the KITTI tracking layout"
#: DegradeConfig fields and their option names (``--degrade-*``, as released)
DEGRADE_FLAGS = {"dilate_px": "--degrade-dilate", "miss_rate_small": "--degrade-miss-small",
                 "miss_rate": "--degrade-miss", "false_rate": "--degrade-false"}


def _add_degrade_arguments(group) -> None:
    """``--degrade-jitter MIN MAX`` and the :data:`DEGRADE_FLAGS` from ``DegradeConfig``."""
    # a (min, max) pair: by hand, as the config options take one value each
    group.add_argument("--degrade-jitter", dest="jitter_px", type=float, nargs=2,
                       metavar=("MIN", "MAX"), default=DegradeConfig().jitter_px,
                       help=field_help(DegradeConfig)["jitter_px"].removesuffix("."))
    add_config_arguments(group, DegradeConfig, list(DEGRADE_FLAGS), **{
        name: {"flag": flag, "metavar": flag[2:].upper().replace("-", "_")}
        for name, flag in DEGRADE_FLAGS.items()})


def degrade_config(args) -> DegradeConfig:
    """The :class:`DegradeConfig` of the parsed ``--no-degrade`` / ``--degrade-*`` options."""
    if args.no_degrade:
        return NO_DEGRADE
    return DegradeConfig(**config_kwargs(args, list(DEGRADE_FLAGS)),
                         jitter_px=tuple(args.jitter_px))


def add_arguments(p) -> None:
    p.add_argument("--preset", default="kitti-tiny", choices=["kitti-tiny", "kitti-like"],
                   help="kitti-tiny: 1 sequence of 20 frames, 5-7 vehicles (seconds); "
                        "kitti-like: 4 sequences of 60-100 frames, 10-20 vehicles (vehicles "
                        "per sequence, not all in view)")
    p.add_argument("--out", required=True, help="output folder (KITTI tracking layout)")
    p.add_argument("--seed", type=int, default=0, help="master seed")
    p.add_argument("--sensor", default="hdl64", choices=["hdl64", "vlp16"],
                   help="LiDAR preset (hdl64 at 1.73 m as in KITTI)")
    p.add_argument("--sequences", type=int, default=None,
                   help="override the number of sequences (default: the preset's)")
    p.add_argument("--frames", type=int, default=None,
                   help="override the frames per sequence (fixed count; default: the "
                        "preset's range)")
    p.add_argument("--vehicles", nargs=2, metavar=("MIN", "MAX"), default=None,
                   help="non-ego vehicles per sequence, an inclusive range (0 <= MIN <= "
                        "MAX; as many as fit on the road are placed: section Denser scenes "
                        "of docs/scenes.md; default: the preset's range)")
    p.add_argument("--min-visible-area", type=int, default=None,
                   help="smallest visible area (px) of a KINS / 2D instance (default 20)")
    p.add_argument("--workers", type=int, default=1, help="processes (one sequence each)")
    p.add_argument("--shard", default="1/1", metavar="K/N",
                   help="write only part K of N of the sequences (every N-th, from the K-th), "
                        "e.g. on N machines sharing OUT; the files do not depend on the shard")
    g = p.add_argument_group("2D instance degradations (instances_2d/)")
    g.add_argument("--no-degrade", action="store_true", help="write the exact visible masks")
    _add_degrade_arguments(g)


def run(args) -> int:
    if args.workers < 1:
        raise ConfigError("--workers must be >= 1")
    shard = parse_shard(args.shard)
    frames = None if args.frames is None else (args.frames, args.frames)
    vehicles = None if args.vehicles is None else check_vehicle_range(args.vehicles,
                                                                      "--vehicles")
    cfg = scene_config(args.preset, n_sequences=args.sequences, frames=frames,
                       n_vehicles=vehicles, sensor=args.sensor,
                       min_visible_area=args.min_visible_area)
    degrade = degrade_config(args)
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
