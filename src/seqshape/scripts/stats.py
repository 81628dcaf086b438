"""``seqshape stats``: tracks, frames, empty frames and points per frame by distance band.

The tables are :mod:`seqshape.data.stats`.
"""

from __future__ import annotations

import argparse

from seqshape.data import TrackDataset
from seqshape.data.stats import BANDS, collect, format_table

HELP = "print statistics of a track dataset"
__all__ = ["BANDS", "HELP", "add_arguments", "collect", "format_table", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DIR", help="track dataset folder (with manifest.json)")


def run(args: argparse.Namespace) -> int:
    ds = TrackDataset(args.dataset)
    if len(ds) == 0:
        print(f"{args.dataset}: no tracks")
        return 0
    print(f"{args.dataset}: {len(ds)} tracks (distance: planar, sensor to box centre)\n")
    print(format_table(collect(ds)))
    return 0
