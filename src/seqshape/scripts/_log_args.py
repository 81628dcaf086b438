"""The options that name one driving log, shared by ``seqshape label`` and ``export-tracks``.

``--dataset {kitti,av2,nuscenes} --root DIR --sequence ID`` opens the log
(:func:`seqshape.data.sequence.open_log`); ``--kitti DIR`` is short for ``--dataset kitti
--root DIR``; ``--max-frames F`` keeps its first F frames; ``--ego-poses lidar`` replaces its
ego poses by LiDAR odometry (:mod:`seqshape.data.odometry`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from seqshape.data.odometry import EGO_POSES, with_lidar_odometry
from seqshape.data.sequence import DATASETS, open_log
from seqshape.errors import ConfigError


def add_log_arguments(parser: argparse.ArgumentParser) -> None:
    """``--dataset``, ``--root``, ``--kitti``, ``--sequence``, ``--max-frames`` and
    ``--ego-poses``."""
    parser.add_argument("--dataset", choices=list(DATASETS), default=None,
                        help="dataset format of --root (default kitti)")
    parser.add_argument("--root", type=Path, default=None,
                        help="dataset root folder (or --kitti; no default)")
    parser.add_argument("--kitti", type=Path, default=None, metavar="DIR",
                        help="KITTI tracking root folder (= --dataset kitti --root DIR; no "
                             "default)")
    parser.add_argument("--sequence", required=True,
                        help="log id: KITTI sequence (0003), Argoverse 2 log id, nuScenes scene")
    parser.add_argument("--max-frames", type=int, default=None, metavar="F",
                        help="use only the first F frames (the sequence as if it ended there; "
                             "default: all)")
    parser.add_argument("--ego-poses", choices=EGO_POSES, default="given",
                        help="the ego poses the smoothers and the heading vote work in: the "
                             "log's own (given) or LiDAR odometry of its sweeps (lidar, about "
                             "0.25 s a sweep; for poses that stretch or jitter, or none; "
                             "default %(default)s)")


def open_args_log(args: argparse.Namespace):
    """The log of ``--dataset/--root`` or ``--kitti``, restricted to ``--max-frames``."""
    if args.kitti is not None:
        if args.root is not None or args.dataset not in (None, "kitti"):
            raise ConfigError("--kitti DIR is short for --dataset kitti --root DIR: give one "
                              "or the other")
        dataset, root = "kitti", args.kitti
    elif args.root is not None:
        dataset, root = args.dataset or "kitti", args.root
    else:
        raise ConfigError("give the data: --dataset NAME --root DIR (or --kitti DIR)")
    log = open_log(dataset, root, args.sequence).restrict(args.max_frames)
    if getattr(args, "ego_poses", "given") == "lidar":
        with_lidar_odometry(log)
    return log
