"""``seqshape label``: automatic amodal mask labels (KINS JSON) for driving logs.

``--dataset {kitti,av2,nuscenes} --root DIR --sequence ID`` opens the log
(:func:`seqshape.data.sequence.open_log`; ``--kitti DIR`` is short for ``--dataset kitti --root
DIR``). ``--camera`` picks the camera(s) (default: the log's default camera; ``all``: every
camera); one camera writes the KINS file ``--out``, several write ``OUT/<camera>.json`` (and
overlays under ``OVERLAYS/<camera>/``). The labelling options are the fields of
:class:`seqshape.amodal.labeler.LabelConfig`. ``--export-tracks DIR`` is deprecated: it runs
``seqshape export-tracks``.

Several logs: ``--sequence A,B,...`` or ``--sequence all`` (every log under the root); ``--out``
is then a folder of ``<log>.json`` (several cameras: ``<log>/<camera>.json``), and
``--workers N`` labels the logs in N processes (:func:`seqshape._runner.run_pool`, one log
each; every file depends only on its log, so the output does not depend on N).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import seqshape.scripts.export_tracks as export_tracks
from seqshape._io import contained_path, safe_stem
from seqshape._runner import run_pool
from seqshape.amodal.labeler import (
    MODES,
    LabelConfig,
    check_camera,
    label_log_cameras,
    load_estimator,
    write_labels,
    write_overlays,
)
from seqshape.amodal.masks import ORDERS
from seqshape.amodal.refine import REFINE_MODES
from seqshape.data.sequence import log_names
from seqshape.errors import ConfigError
from seqshape.scripts._config_args import add_config_arguments, config_kwargs
from seqshape.scripts._log_args import add_log_arguments, open_args_log

HELP = "produce amodal mask labels (KINS JSON) for a driving log with cameras"
FIELDS = ["mode", "checkpoint", "backend", "refine", "order", "alpha", "instances", "polygons", "fit_box",
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
    parser.add_argument("--workers", type=int, default=1,
                        help="processes for several logs (--sequence A,B or all), one log "
                             "each (default: 1)")
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


def sequences_of(args) -> list[str] | None:
    """The logs ``--sequence`` names when it names several (``A,B,...`` or ``all``: every log
    of the dataset under the root), else None (one log)."""
    if args.sequence != "all" and "," not in args.sequence:
        return None
    if args.sequence == "all":
        dataset, root = ("kitti", args.kitti) if args.kitti is not None else (
            args.dataset or "kitti", args.root)
        if root is None:
            raise ConfigError("give the data: --dataset NAME --root DIR (or --kitti DIR)")
        names = log_names(dataset, root)
    else:
        names = [n.strip() for n in args.sequence.split(",") if n.strip()]
    if not names:
        raise ConfigError(f"--sequence {args.sequence}: no logs found")
    return list(dict.fromkeys(names))


_ESTIMATOR: dict = {}  # the estimator of this process (sc-* modes), loaded once per worker


def _init_worker(mode: str, threads: int, checkpoint: str | None, backend: str) -> None:
    """Worker start: torch threads and the estimator, once per process."""
    _set_threads(mode, threads)
    if mode != "gt-accumulation":
        _ESTIMATOR["est"] = load_estimator(checkpoint, backend)


def _write_results(args, log, results: dict, out: Path, overlays: Path | None) -> list[str]:
    """Write one log's label files (and overlays); returns the lines to print."""
    several = len(results) > 1
    lines = []
    for cam, result in results.items():
        path = contained_path(out, f"{safe_stem(cam)}.json") if several else out
        write_labels(path, result)
        t = result.timings
        lines.append(f"{args.mode} {cam}: {len(result.annotations)} instances in "
                     f"{t['frames']} frames, {t['frames'] / max(t['total'], 1e-9):.2f} "
                     f"frames/s -> {path}")
        if overlays is not None:
            folder = contained_path(overlays, safe_stem(cam)) if several else overlays
            paths = write_overlays(log, result, folder)
            lines.append(f"wrote {len(paths)} overlays to {folder}")
    return lines


def _set_threads(mode: str, threads: int) -> None:
    if threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {threads}")
    if mode != "gt-accumulation":
        import torch  # heavy: only the sc-* modes run the network

        torch.set_num_threads(threads)


def _label_one(job: tuple[argparse.Namespace, str | None]) -> list[str]:
    """Label one log (``job``: the arguments and the log name, None: ``--sequence`` itself);
    the lines to print. Runs in a worker process of :func:`run_pool`."""
    args, name = job
    if name is not None:
        args = argparse.Namespace(**{**vars(args), "sequence": name})
    log = open_args_log(args)
    cameras = cameras_of(args, log)
    values = config_kwargs(args, FIELDS)
    cfg = LabelConfig(**{**values, "instances": values["instances"] or None})
    results = label_log_cameras(log, cfg, cameras, estimator=_ESTIMATOR.get("est"))
    if name is None:
        return _write_results(args, log, results, args.out, args.overlays)
    stem = safe_stem(name)  # a log name comes from data (nuScenes: scene.json)
    out = contained_path(args.out, stem if len(results) > 1 else f"{stem}.json")
    overlays = None if args.overlays is None else contained_path(args.overlays, stem)
    return _write_results(args, log, results, out, overlays)


def run(args: argparse.Namespace) -> int:
    if args.export_tracks is not None:
        log = open_args_log(args)
        print("seqshape label --export-tracks is deprecated and goes in the next release: use "
              "`seqshape export-tracks` (same options)", file=sys.stderr)
        return export_tracks.export(log, args.export_tracks, args.val_fraction)
    if args.out is None:
        raise ConfigError("--out is required (unless --export-tracks)")
    if args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    names = sequences_of(args)
    LabelConfig(**{**config_kwargs(args, FIELDS), "instances": None})  # options checked first
    _set_threads(args.mode, args.threads)
    jobs = [(args, None)] if names is None else [(args, n) for n in names]
    init = (args.mode, args.threads, args.checkpoint, args.backend)
    for lines in run_pool(_label_one, jobs, args.workers, initializer=_init_worker,
                          initargs=init, desc="label", unit="log", progress_bar=False):
        for line in lines:
            print(line)
    return 0
