"""``seqshape evaluate-masks``: score amodal mask labels against a reference (Table II).

The work is :func:`seqshape.amodal.evaluate.write_mask_report` (files paired by
:func:`~seqshape.amodal.evaluate.resolve_pairs`); the table's title says whether the reference
is the exact ground truth of a ``seqshape scenes`` folder, its row names the predictions.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from seqshape.amodal.evaluate import default_row_name, resolve_pairs, write_mask_report

HELP = "score amodal mask labels against a reference (per-image Hungarian matching on IoU)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pred", action="append", required=True, type=Path,
                        help="predicted KINS JSON, or a directory of SSSS.json files (repeatable)")
    parser.add_argument("--gt", action="append", required=True, type=Path,
                        help="reference KINS JSON (e.g. amodal/SSSS.json), or a directory; "
                             "paired with --pred in order")
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument("--name", default=None,
                        help="row name in the markdown table (default: the prediction file's "
                             "name, or its folder's for a folder)")
    parser.add_argument("--categories", type=int, nargs="*", default=None,
                        help="category ids to score (default: all)")
    parser.add_argument("--max-distance", type=float, default=None, metavar="M",
                        help="also report the metrics over reference instances at most M "
                             "metres away (matching still uses every instance; default: no "
                             "distance limit)")


def run(args: argparse.Namespace) -> int:
    pairs = resolve_pairs(args.pred, args.gt)
    name = args.name or default_row_name(args.pred)  # a folder given: its name
    print(write_mask_report(pairs, args.out, name, args.categories, args.max_distance))
    print(f"wrote {args.out / 'metrics.json'}")
    return 0
