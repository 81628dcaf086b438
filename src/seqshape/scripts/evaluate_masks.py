"""``seqshape evaluate-masks``: score amodal mask labels against a reference (Table II)."""

from __future__ import annotations

import argparse
from pathlib import Path

from seqshape._io import atomic_write_json, atomic_write_text
from seqshape.amodal.evaluate import (
    breakdown,
    breakdown_table,
    evaluate_files,
    markdown_table,
    results_to_records,
    summarise,
    within_distance,
)
from seqshape.errors import ConfigError

HELP = "score amodal mask labels against a reference (per-image Hungarian matching on IoU)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pred", action="append", required=True, type=Path,
                        help="predicted KINS JSON, or a directory of SSSS.json files (repeatable)")
    parser.add_argument("--gt", action="append", required=True, type=Path,
                        help="reference KINS JSON (e.g. amodal/SSSS.json), or a directory; "
                             "paired with --pred in order")
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument("--name", default="labels", help="row name in the markdown table")
    parser.add_argument("--categories", type=int, nargs="*", default=None,
                        help="category ids to score (default: all)")
    parser.add_argument("--max-distance", type=float, default=None, metavar="M",
                        help="also report the metrics over reference instances at most M "
                             "metres away (matching still uses every instance; default: no "
                             "distance limit)")


def resolve_pairs(preds: list[Path], gts: list[Path]) -> list[tuple[Path, Path]]:
    """Pair prediction and reference files; directories pair their ``*.json`` by file name."""
    if len(preds) != len(gts):
        raise ConfigError(f"{len(preds)} --pred but {len(gts)} --gt: give them in pairs")
    pairs = []
    for p, g in zip(preds, gts, strict=True):
        if p.is_dir() != g.is_dir():
            raise ConfigError(f"--pred {p} and --gt {g}: pair a file with a file, or a "
                              "directory with a directory")
        if not p.is_dir():
            for f in (p, g):
                if not f.is_file():
                    raise ConfigError(f"{f}: no such file")
            pairs.append((p, g))
            continue
        gt_files = sorted(g.glob("*.json"))
        if not gt_files:
            raise ConfigError(f"{g}: no *.json reference files")
        for gf in gt_files:
            pf = p / gf.name
            if not pf.is_file():
                raise ConfigError(f"{pf}: missing prediction for reference {gf}")
            pairs.append((pf, gf))
    return pairs


def run(args: argparse.Namespace) -> int:
    pairs = resolve_pairs(args.pred, args.gt)
    results, unmatched = evaluate_files(pairs, args.categories)
    metrics = summarise(results, unmatched)
    bd = breakdown(results)
    rows = {args.name: metrics}
    extra = {}
    if args.max_distance is not None:
        if not args.max_distance > 0:
            raise ConfigError(f"--max-distance must be > 0, got {args.max_distance}")
        near = within_distance(results, args.max_distance)
        extra["within_max_distance"] = {**summarise(near), "max_distance_m": args.max_distance}
        rows[f"{args.name} (<= {args.max_distance:g} m)"] = extra["within_max_distance"]
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out / "metrics.json",
                      {**metrics, **extra, "breakdown": bd, "iou_threshold": 0.5,
                       "pairs": [[str(p), str(g)] for p, g in pairs]})
    atomic_write_json(args.out / "instances.json", results_to_records(results), indent=None)
    table = markdown_table(rows) + "\n" + breakdown_table(bd)
    atomic_write_text(args.out / "metrics.md", table)
    print(table)
    print(f"wrote {args.out / 'metrics.json'}")
    return 0
