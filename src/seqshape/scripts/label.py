"""``seqshape label``: automatic amodal mask labels (KINS JSON) for a KITTI tracking sequence."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "produce amodal mask labels for a KITTI tracking sequence"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from seqshape.amodal.labeler import DEFAULT_REFINE, MODES, LabelConfig
    from seqshape.amodal.masks import ORDERS
    from seqshape.amodal.refine import REFINE_MODES

    parser.add_argument("--kitti", required=True, type=Path, help="KITTI tracking root folder")
    parser.add_argument("--sequence", required=True, help="sequence, e.g. 0003")
    parser.add_argument("--mode", choices=MODES, default="sc-gt",
                        help="gt-accumulation | sc-gt (3D boxes) | sc-seg (2D masks only)")
    parser.add_argument("--out", type=Path, help="output KINS JSON (labels.json)")
    parser.add_argument("--checkpoint", default="pretrained",
                        help="estimator weights (model.pt / checkpoint) or 'pretrained'")
    parser.add_argument("--refine", choices=REFINE_MODES, default=DEFAULT_REFINE,
                        help=f"offline refinement (default {DEFAULT_REFINE}; docs/amodal.md)")
    parser.add_argument("--no-refine", dest="refine", action="store_const", const="none",
                        help="the paper's forward-only completion")
    parser.add_argument("--fit-box", action="store_true",
                        help="sc-gt: stretch each completed shape to its ground-truth box and "
                             "place it at the box pose")
    parser.add_argument("--fit-box-below", type=int, default=LabelConfig.fit_box_below,
                        metavar="N",
                        help="sc-gt: fit only the tracks whose best estimate fused fewer than N "
                             "LiDAR points to their box (default %(default)s; 0: never)")
    parser.add_argument("--no-mask-fallback", dest="mask_fallback", action="store_false",
                        help="sc-seg: do not label 2D instances without LiDAR points from "
                             "their own masks")
    parser.add_argument("--trim", type=float, default=LabelConfig.trim, metavar="P",
                        help="sc-*: drop the points of each completed shape outside its "
                             "P..100-P percentile box (default %(default)s; 0: keep all)")
    parser.add_argument("--no-align", dest="align", action="store_false",
                        help="sc-seg: do not move the completed vehicles in the image to match "
                             "their 2D instance masks")
    parser.add_argument("--no-observed", dest="observed", action="store_false",
                        help="sc-*: do not add each frame's own segmented points to its "
                             "completed cloud before the alpha shape")
    parser.add_argument("--order", choices=ORDERS, default="pixel",
                        help="occlusion rule: per-pixel depth or median depth")
    parser.add_argument("--alpha", type=float, default=None,
                        help="alpha-shape alpha (1/pixels); default from the point spacing")
    parser.add_argument("--instances", type=Path, default=None,
                        help="sc-seg: COCO instance masks (default KITTI/instances_2d/SSSS.json)")
    parser.add_argument("--max-frames", type=int, default=None, metavar="F",
                        help="label only the first F frames (the sequence as if it ended there)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads for the estimator (default 1: its per-frame "
                             "batches are small, and more threads only add overhead, a lot of "
                             "it when the cores are busy; docs/amodal.md)")
    parser.add_argument("--overlays", type=Path, default=None, help="write overlay PNGs here")
    parser.add_argument("--export-tracks", type=Path, default=None, metavar="DIR",
                        help="write the sequence's GT-cropped tracks as a track dataset "
                             "(complete = mirrored accumulation) for `seqshape train` "
                             "fine-tuning, and stop")
    parser.add_argument("--val-fraction", type=float, default=0.2,
                        help="--export-tracks: share of tracks in the val split (by a hash of "
                             "the track id; at least one train track, and one val track when "
                             "there are two or more)")


def run(args: argparse.Namespace) -> int:
    from seqshape.amodal.labeler import (
        LabelConfig,
        label_sequence,
        open_sequence,
        write_labels,
        write_overlays,
    )
    from seqshape.data.kitti import KittiTrackingSequence, extract_tracks
    from seqshape.errors import ConfigError, DataError

    if args.export_tracks is not None:
        from seqshape.amodal.accumulate import export_tracks

        seq = KittiTrackingSequence(args.kitti, args.sequence)
        if not 0 <= args.val_fraction < 1:
            raise ConfigError(f"--val-fraction must be in [0, 1), got {args.val_fraction}")
        try:
            ds = export_tracks(extract_tracks(seq), args.export_tracks,
                               val_fraction=args.val_fraction)
        except ValueError as exc:  # no track with enough points
            raise DataError(args.kitti, f"sequence {args.sequence}: {exc}") from None
        n_val = sum(e.get("split") == "val" for e in ds.entries)
        print(f"wrote {len(ds)} tracks ({len(ds) - n_val} train, {n_val} val) to "
              f"{args.export_tracks}; fine-tune with `seqshape train --data "
              f"{args.export_tracks} --out RUN --init pretrained --stage-steps 0,0,300 "
              f"--lr 2e-4` (docs/amodal.md)")
        return 0
    if args.out is None:
        raise ConfigError("--out is required (unless --export-tracks)")
    cfg = LabelConfig(mode=args.mode, checkpoint=args.checkpoint, refine=args.refine,
                      order=args.order, alpha=args.alpha, fit_box=args.fit_box,
                      fit_box_below=args.fit_box_below, observed=args.observed,
                      mask_fallback=args.mask_fallback, align=args.align, trim=args.trim,
                      instances=str(args.instances) if args.instances else None)
    if args.threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {args.threads}")
    if args.mode != "gt-accumulation":
        import torch

        torch.set_num_threads(args.threads)
    result = label_sequence(args.kitti, args.sequence, cfg, max_frames=args.max_frames)
    write_labels(args.out, result)
    t = result.timings
    print(f"{args.mode}: {len(result.annotations)} instances in {t['frames']} frames, "
          f"{t['frames'] / max(t['total'], 1e-9):.2f} frames/s -> {args.out}")
    if args.overlays is not None:
        seq = open_sequence(args.kitti, args.sequence, args.max_frames)
        paths = write_overlays(seq, result, args.overlays)
        print(f"wrote {len(paths)} overlays to {args.overlays}")
    return 0
