"""``seqshape tracks``: vehicle tracks of real driving logs as a track dataset (docs/tracks.md).

The work (layout, resume, sharding, splits) is :func:`seqshape.data.tracks_export
.extract_dataset`; the options are the fields of :class:`~seqshape.data.tracks_export
.TracksConfig`.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import seqshape.data.tracks_export as _tracks
from seqshape._deprecated import forward
from seqshape._runner import parse_shard
from seqshape.data.crop import GROUND_MODES
from seqshape.data.odometry import EGO_POSES
from seqshape.data.sequence import DATASETS, VEHICLE_CLASSES, parse_classes
from seqshape.data.tracks_export import (
    SPLIT_BY,
    SPLITS,
    TracksConfig,
    TracksSummary,
    extract_dataset,
    parse_sequences,
)
from seqshape.scripts._config_args import add_config_arguments, config_kwargs

HELP = ("extract vehicle tracks from real driving logs (KITTI, Argoverse 2, nuScenes) as a "
        "track dataset")
FIELDS = ["min_points", "margin", "ground", "reference", "reference_points", "val_fraction",
          "split_by", "split", "keep_duplicates", "ego_poses"]
_MOVED = ("CONFIG_FILE", "LOGS_DIR", "EXTRACTOR_VERSION", "SPLITS", "SPLIT_BY", "TracksConfig",
          "log_split", "marker_path", "parse_sequences", "select_logs", "read_marker", "LogJob",
          "LogResult", "extract_log", "run_jobs", "TracksSummary", "extract_dataset",
          "write_folder_manifest")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dataset", required=True, choices=sorted(DATASETS),
                        help="the dataset format of --root")
    parser.add_argument("--root", required=True,
                        help="dataset folder (KITTI tracking training/, an Argoverse 2 split "
                             "folder such as sensor/val, a nuScenes root)")
    parser.add_argument("--sequence", action="append", metavar="ID",
                        help="log(s) to extract (repeat, or a comma list; default: every log "
                             "under --root)")
    parser.add_argument("--out", required=True, help="output track dataset folder")
    parser.add_argument("--classes", default=",".join(VEHICLE_CLASSES),
                        help="vehicle classes to keep (default %(default)s)")
    add_config_arguments(parser, TracksConfig, FIELDS, ground={"choices": GROUND_MODES},
                         reference={"action": argparse.BooleanOptionalAction},
                         split_by={"choices": SPLIT_BY}, split={"choices": SPLITS},
                         ego_poses={"choices": EGO_POSES})
    parser.add_argument("--shard", default="1/1", metavar="K/N",
                        help="extract only part K of N (1-based, by log); every run rewrites "
                             "the manifest from all logs done so far (default %(default)s)")
    parser.add_argument("--workers", type=int, default=1,
                        help="worker processes (by log; default %(default)s)")


def run(args: argparse.Namespace) -> int:
    shard = parse_shard(args.shard)
    config = TracksConfig(dataset=args.dataset, root=str(Path(args.root).resolve()),
                          classes=parse_classes(args.classes), **config_kwargs(args, FIELDS))
    s = extract_dataset(config, args.out, parse_sequences(args.sequence), shard, args.workers)
    print_summary(s, args.out)
    return 1 if s.failed else 0


def print_summary(s: TracksSummary, out) -> None:
    done = s.extracted
    frames = sum(m["n_frames"] for m in done)
    points = sum(m["n_points"] for m in done)
    by_class = Counter(e["class"] for m in s.markers for e in m["tracks"])
    classes = ", ".join(f"{c} {v}" for c, v in sorted(by_class.items())) or "none"
    print(f"{out}: {len(done)} logs extracted, {len(s.skipped)} already done, "
          f"{len(s.failed)} failed; {sum(len(m['tracks']) for m in done)} tracks, {frames} "
          f"frames, {points} points in {s.seconds:.1f} s "
          f"({frames / max(s.seconds, 1e-9):.1f} frames/s)")
    print(f"tracks of this shard's logs by class: {classes}")
    no_ref = sum(m.get("n_no_reference", 0) for m in s.markers)
    if no_ref:
        print(f"{no_ref} tracks have no accumulated reference (too few points; their "
              f"meta['reference']['error'] says why)")
    for name, err in s.failed.items():
        print(f"failed: {name}: {err}")
    print(f"manifest written: {Path(out) / 'manifest.json'} ({s.n_manifest_tracks} tracks)")
    if s.missing_logs:
        print(f"{len(s.missing_logs)} logs not done yet (other shards or failures): rerun any "
              f"shard once they are to rewrite the manifest")


__getattr__ = forward(__name__, _tracks, _MOVED)  # moved names, for one release
