"""``seqshape label``: automatic amodal mask labels (KINS JSON) for one driving log.

``--dataset {kitti,av2,nuscenes} --root DIR --sequence ID`` opens the log
(:func:`seqshape.data.sequence.open_log`; ``--kitti DIR`` is short for ``--dataset kitti --root
DIR``). ``--camera`` picks the camera(s) (default: the log's default camera; ``all``: every
camera); one camera writes the KINS file ``--out``, several write ``OUT/<camera>.json`` (and
overlays under ``OVERLAYS/<camera>/``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "produce amodal mask labels (KINS JSON) for a driving log with cameras"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from seqshape.amodal.labeler import DEFAULT_REFINE, MODES, LabelConfig
    from seqshape.amodal.masks import ORDERS
    from seqshape.amodal.refine import REFINE_MODES
    from seqshape.data.sequence import DATASETS

    parser.add_argument("--dataset", choices=list(DATASETS), default=None,
                        help="dataset format of --root (default kitti)")
    parser.add_argument("--root", type=Path, default=None, help="dataset root folder")
    parser.add_argument("--kitti", type=Path, default=None, metavar="DIR",
                        help="KITTI tracking root folder (= --dataset kitti --root DIR)")
    parser.add_argument("--sequence", required=True,
                        help="log id: KITTI sequence (0003), Argoverse 2 log id, nuScenes scene")
    parser.add_argument("--camera", nargs="+", default=None, metavar="NAME",
                        help="camera(s) to label (KITTI image_02 image_03; nuScenes CAM_FRONT "
                             "...; Argoverse 2 ring_front_center ...), or 'all' (default: the "
                             "log's default camera). Several cameras: --out is a folder of "
                             "<camera>.json")
    parser.add_argument("--polygons", action="store_true",
                        help="write segmentations as polygons (outer contours) instead of RLE")
    parser.add_argument("--mode", choices=MODES, default="sc-gt",
                        help="gt-accumulation | sc-gt (3D boxes) | sc-seg (2D masks only)")
    parser.add_argument("--out", type=Path,
                        help="output KINS JSON (one camera) or folder (several cameras)")
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
    parser.add_argument("--online", action="store_true",
                        help="sc-*: run the estimator online, frame t seeing frames 0..t only "
                             "(default: offline, every estimate uses the whole track; "
                             "docs/model.md, 'Offline mode')")
    parser.add_argument("--order", choices=ORDERS, default="pixel",
                        help="occlusion rule: per-pixel depth or median depth")
    parser.add_argument("--alpha", type=float, default=None,
                        help="alpha-shape alpha (1/pixels); default from the point spacing")
    parser.add_argument("--instances", type=Path, default=None,
                        help="sc-seg: COCO instance masks, images matched by file name "
                             "(default ROOT/instances_2d/<sequence>.json)")
    parser.add_argument("--max-frames", type=int, default=None, metavar="F",
                        help="label only the first F frames (the sequence as if it ended there)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads for the estimator (default 1: its per-frame "
                             "batches are small, and more threads only add overhead, a lot of "
                             "it when the cores are busy; docs/amodal.md)")
    parser.add_argument("--overlays", type=Path, default=None, help="write overlay PNGs here")
    parser.add_argument("--export-tracks", type=Path, default=None, metavar="DIR",
                        help="write the log's GT-cropped tracks as a track dataset "
                             "(complete = mirrored accumulation) for `seqshape train` "
                             "fine-tuning, and stop (`seqshape tracks` is the general way)")
    parser.add_argument("--val-fraction", type=float, default=0.2,
                        help="--export-tracks: share of tracks in the val split (by a hash of "
                             "the track id; at least one train track, and one val track when "
                             "there are two or more)")


def open_args_log(args):
    """The log of ``--dataset/--root`` or ``--kitti``, restricted to ``--max-frames``."""
    from seqshape.data.sequence import open_log
    from seqshape.errors import ConfigError

    if args.kitti is not None:
        if args.root is not None or args.dataset not in (None, "kitti"):
            raise ConfigError("--kitti DIR is short for --dataset kitti --root DIR: give one "
                              "or the other")
        dataset, root = "kitti", args.kitti
    elif args.root is not None:
        dataset, root = args.dataset or "kitti", args.root
    else:
        raise ConfigError("give the data: --dataset NAME --root DIR (or --kitti DIR)")
    return open_log(dataset, root, args.sequence).restrict(args.max_frames)


def cameras_of(args, log) -> list[str]:
    """The cameras ``--camera`` asks for (``all``: every camera of the log)."""
    from seqshape.amodal.labeler import check_camera

    if not args.camera:
        return [check_camera(log, None)]
    if args.camera == ["all"]:
        check_camera(log, None)
        return list(log.camera_names)
    return list(dict.fromkeys(check_camera(log, c) for c in args.camera))


def export(args, log) -> int:
    """``--export-tracks``: the log's tracks with accumulated references, for fine-tuning."""
    from seqshape.amodal.accumulate import export_tracks
    from seqshape.data.extract import extract_tracks
    from seqshape.errors import ConfigError, DataError

    if not 0 <= args.val_fraction < 1:
        raise ConfigError(f"--val-fraction must be in [0, 1), got {args.val_fraction}")
    if log.dataset == "kitti":
        from seqshape.data.kitti import extract_tracks as kitti_tracks

        tracks = kitti_tracks(log)
    else:
        tracks = extract_tracks(log)
    try:
        ds = export_tracks(tracks, args.export_tracks, val_fraction=args.val_fraction)
    except ValueError as exc:  # no track with enough points
        raise DataError(log.root, f"{log.dataset} log {log.name}: {exc}") from None
    n_val = sum(e.get("split") == "val" for e in ds.entries)
    print(f"wrote {len(ds)} tracks ({len(ds) - n_val} train, {n_val} val) to "
          f"{args.export_tracks}; fine-tune with `seqshape train --data "
          f"{args.export_tracks} --out RUN --init pretrained --stage-steps 0,0,300 "
          f"--lr 2e-4` (docs/amodal.md)")
    return 0


def run(args: argparse.Namespace) -> int:
    from seqshape.amodal.labeler import (
        LabelConfig,
        label_log_cameras,
        write_labels,
        write_overlays,
    )
    from seqshape.errors import ConfigError

    log = open_args_log(args)
    if args.export_tracks is not None:
        return export(args, log)
    if args.out is None:
        raise ConfigError("--out is required (unless --export-tracks)")
    cameras = cameras_of(args, log)
    cfg = LabelConfig(mode=args.mode, checkpoint=args.checkpoint, refine=args.refine,
                      order=args.order, alpha=args.alpha, fit_box=args.fit_box,
                      fit_box_below=args.fit_box_below, observed=args.observed,
                      mask_fallback=args.mask_fallback, align=args.align, trim=args.trim,
                      instances=str(args.instances) if args.instances else None,
                      polygons=args.polygons, online=args.online)
    if args.threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {args.threads}")
    if args.mode != "gt-accumulation":
        import torch

        torch.set_num_threads(args.threads)
    results = label_log_cameras(log, cfg, cameras)
    several = len(cameras) > 1
    for cam, result in results.items():
        out = args.out / f"{cam}.json" if several else args.out
        write_labels(out, result)
        t = result.timings
        print(f"{args.mode} {cam}: {len(result.annotations)} instances in {t['frames']} "
              f"frames, {t['frames'] / max(t['total'], 1e-9):.2f} frames/s -> {out}")
        if args.overlays is not None:
            folder = args.overlays / cam if several else args.overlays
            paths = write_overlays(log, result, folder)
            print(f"wrote {len(paths)} overlays to {folder}")
    return 0
