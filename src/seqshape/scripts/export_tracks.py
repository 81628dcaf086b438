"""``seqshape export-tracks``: one log's tracks as a track dataset for fine-tuning.

Each track's ``complete`` is its mirrored accumulation
(:func:`seqshape.amodal.accumulate.export_tracks`), the reference the paper's SC-GT
fine-tunes on; ``seqshape tracks`` is the general extraction (many logs, resumable, sharded).
This was ``seqshape label --export-tracks DIR``, which still works.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from seqshape.amodal.accumulate import export_tracks
from seqshape.data.extract import extract_tracks
from seqshape.data.kitti import extract_tracks as kitti_tracks
from seqshape.errors import ConfigError, DataError
from seqshape.scripts._log_args import add_log_arguments, open_args_log

HELP = ("write one log's tracks as a track dataset for `seqshape train` fine-tuning (complete "
        "shapes: mirrored accumulations)")


def add_val_fraction(parser: argparse.ArgumentParser, help_prefix: str = "") -> None:
    parser.add_argument("--val-fraction", type=float, default=0.2,
                        help=f"{help_prefix}share of tracks in the val split (by a hash of the "
                             "track id; at least one train track, and one val track when there "
                             "are two or more; default %(default)s)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_log_arguments(parser)
    parser.add_argument("--out", required=True, type=Path, metavar="DIR",
                        help="output track dataset folder")
    add_val_fraction(parser)


def export_log(log, out: Path, val_fraction: float):
    """The tracks of ``log`` (KITTI's with its own meta keys) written by ``export_tracks``."""
    if not 0 <= val_fraction < 1:
        raise ConfigError(f"--val-fraction must be in [0, 1), got {val_fraction}")
    tracks = kitti_tracks(log) if log.dataset == "kitti" else extract_tracks(log)
    try:
        return export_tracks(tracks, out, val_fraction=val_fraction)
    except ValueError as exc:  # no track with enough points
        raise DataError(log.root, f"{log.dataset} log {log.name}: {exc}") from None


def export(log, out: Path, val_fraction: float) -> int:
    ds = export_log(log, out, val_fraction)
    n_val = sum(e.get("split") == "val" for e in ds.entries)
    print(f"wrote {len(ds)} tracks ({len(ds) - n_val} train, {n_val} val) to "
          f"{out}; fine-tune with `seqshape train --data "
          f"{out} --out RUN --init pretrained --stage-steps 0,0,300 "
          f"--lr 2e-4` (docs/amodal.md)")
    return 0


def run(args: argparse.Namespace) -> int:
    return export(open_args_log(args), args.out, args.val_fraction)
