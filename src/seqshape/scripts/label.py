"""``seqshape label``: automatic amodal mask labels (KINS JSON) for one driving log.

``--dataset {kitti,av2,nuscenes} --root DIR --sequence ID`` opens the log
(:func:`seqshape.data.sequence.open_log`; ``--kitti DIR`` is short for ``--dataset kitti --root
DIR``). ``--camera`` picks the camera(s) (default: the log's default camera; ``all``: every
camera); one camera writes the KINS file ``--out``, several write ``OUT/<camera>.json`` (and
overlays under ``OVERLAYS/<camera>/``). The labelling options are the fields of
:class:`seqshape.amodal.labeler.LabelConfig`. ``--export-tracks DIR`` is deprecated: it runs
``seqshape export-tracks``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import seqshape.scripts.export_tracks as export_tracks
from seqshape.amodal.labeler import (
    MODES,
    LabelConfig,
    check_camera,
    label_log_cameras,
    write_labels,
    write_overlays,
)
from seqshape.amodal.masks import ORDERS
from seqshape.amodal.refine import REFINE_MODES
from seqshape.errors import ConfigError
from seqshape.scripts._config_args import add_config_arguments, config_kwargs
from seqshape.scripts._log_args import add_log_arguments, open_args_log

HELP = "produce amodal mask labels (KINS JSON) for a driving log with cameras"
FIELDS = ["mode", "checkpoint", "refine", "order", "alpha", "instances", "polygons", "fit_box",
          "fit_box_below", "trim", "observed", "mask_fallback", "align", "online"]

__all__ = ["HELP", "add_arguments", "cameras_of", "open_args_log", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_log_arguments(parser)
    parser.add_argument("--camera", nargs="+", default=None, metavar="NAME",
                        help="camera(s) to label (KITTI image_02 image_03; nuScenes CAM_FRONT "
                             "...; Argoverse 2 ring_front_center ...), or 'all' (default: the "
                             "log's default camera). Several cameras: --out is a folder of "
                             "<camera>.json")
    parser.add_argument("--out", type=Path,
                        help="output KINS JSON (one camera) or folder (several cameras); "
                             "required (no default)")
    add_config_arguments(parser, LabelConfig, FIELDS, mode={"choices": MODES},
                         refine={"choices": REFINE_MODES}, order={"choices": ORDERS},
                         fit_box_below={"metavar": "N"}, trim={"metavar": "P"})
    parser.add_argument("--no-refine", dest="refine", action="store_const", const="none",
                        help="the paper's forward-only completion (= --refine none)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads for the estimator (default 1: its per-frame "
                             "batches are small, and more threads only add overhead, a lot of "
                             "it when the cores are busy; docs/amodal.md)")
    parser.add_argument("--overlays", type=Path, default=None,
                        help="write overlay PNGs here (default: none)")
    parser.add_argument("--export-tracks", type=Path, default=None, metavar="DIR",
                        help="deprecated, use `seqshape export-tracks`: write the log's tracks "
                             "as a track dataset for fine-tuning, and stop (default: label)")
    export_tracks.add_val_fraction(parser, help_prefix="--export-tracks: ")


def cameras_of(args, log) -> list[str]:
    """The cameras ``--camera`` asks for (``all``: every camera of the log)."""
    if not args.camera:
        return [check_camera(log, None)]
    if args.camera == ["all"]:
        check_camera(log, None)
        return list(log.camera_names)
    return list(dict.fromkeys(check_camera(log, c) for c in args.camera))


def _set_threads(mode: str, threads: int) -> None:
    if threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {threads}")
    if mode != "gt-accumulation":
        import torch  # heavy: only the sc-* modes run the network

        torch.set_num_threads(threads)


def run(args: argparse.Namespace) -> int:
    log = open_args_log(args)
    if args.export_tracks is not None:
        print("seqshape label --export-tracks is deprecated and goes in the next release: use "
              "`seqshape export-tracks` (same options)", file=sys.stderr)
        return export_tracks.export(log, args.export_tracks, args.val_fraction)
    if args.out is None:
        raise ConfigError("--out is required (unless --export-tracks)")
    cameras = cameras_of(args, log)
    values = config_kwargs(args, FIELDS)
    cfg = LabelConfig(**{**values, "instances": values["instances"] or None})
    _set_threads(args.mode, args.threads)
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
