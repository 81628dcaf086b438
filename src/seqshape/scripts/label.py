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
``--workers N`` (N > 1) runs N worker processes (:class:`seqshape._runner.WorkerPool`): they
segment (sc-seg) or crop (gt modes) the logs in runs of consecutive frames, a few logs ahead
(joined into tracks here), estimate the tracks (sc-* modes: groups of a log's tracks; each
worker loads the estimator once, in the background from its start) and draw the frames' masks
(runs of consecutive frames of any log); this process hands out the work and writes each
log's file, atomically, once all its frames are drawn. Every file depends only on its log,
so the output does not depend on N (nor on the number of logs; tested).

Every label file records the settings that made it (its ``info`` block,
:func:`seqshape.amodal.labeler.label_settings`). ``--resume`` skips the logs whose files all
exist with this run's settings (a line each, then a count) and labels the others; a file with
other settings is a ConfigError naming it and the settings that differ, before anything is
labelled; a file that is not a complete label file is a DataError naming it. A log's overlays
are written before its label file, so a label file also means that its overlays are complete
(with ``--overlays``, a log whose overlays are missing is labelled again). Without
``--resume`` existing files are overwritten, as before.
"""

from __future__ import annotations

import argparse
import sys
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import seqshape.scripts.export_tracks as export_tracks
from seqshape._io import contained_path, safe_stem
from seqshape._malloc import keep_freed_memory
from seqshape._runner import WorkerPool
from seqshape._threads import limit_openblas
from seqshape.amodal.labeler import (
    MODES,
    EstimatorSpec,
    LabelConfig,
    check_camera,
    label_settings,
    load_estimator,
    preload_estimator,
    preparations,
    read_label_settings,
    set_image_size,
    settings_differences,
    start_labels,
    submit_prepare,
    weights_digest,
    write_labels,
    write_overlays,
)
from seqshape.amodal.masks import ORDERS
from seqshape.amodal.overlay import overlay_path
from seqshape.amodal.refine import REFINE_MODES
from seqshape.data.sequence import log_names
from seqshape.errors import ConfigError, DataError
from seqshape.scripts._config_args import add_config_arguments, config_kwargs
from seqshape.scripts._log_args import add_log_arguments, open_args_log

HELP = "produce amodal mask labels (KINS JSON) for a driving log with cameras"
FIELDS = ["mode", "checkpoint", "backend", "refine", "order", "alpha", "instances", "polygons", "fit_box",
          "fit_box_below", "trim", "observed", "mask_fallback", "align", "online", "placement",
          "max_points"]

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
    parser.add_argument("--image-size", type=int, nargs=2, default=None, metavar=("W", "H"),
                        help="the camera image size in pixels, for a KITTI log without images "
                             "(default: the first image's size, else KITTI's 1242 x 375; "
                             "Argoverse 2 and nuScenes record each camera's size)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads for the estimator (default 1: its per-frame "
                             "batches are small, and more threads only add overhead, a lot of "
                             "it when the cores are busy; docs/amodal.md)")
    parser.add_argument("--overlays", type=Path, default=None,
                        help="write overlay PNGs here (default: none)")
    parser.add_argument("--workers", type=int, default=1,
                        help="worker processes: they segment or crop the logs and draw the "
                             "masks (runs of frames), this one runs the estimator (default: "
                             "1: all in this process); the files do not depend on it")
    parser.add_argument("--resume", action="store_true",
                        help="skip the logs whose label files exist, written with the same "
                             "settings (recorded in each file); a file with other settings is "
                             "an error (default: label every log, overwriting its files)")
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


_ESTIMATOR: dict = {}  # the estimator of this process (sc-* modes), loaded once


def _estimator(mode: str, checkpoint: str | None, backend: str,
               placement: str = "pretrained", max_points: int | None = None):
    """This process's estimator (None for gt-accumulation), loaded at its first use."""
    if mode == "gt-accumulation":
        return None
    if "est" not in _ESTIMATOR:
        import torch  # heavy: only a process that runs the network imports it

        torch.set_num_threads(_THREADS.get("torch", 1))
        _ESTIMATOR["est"] = load_estimator(checkpoint, backend, placement, max_points)
    return _ESTIMATOR["est"]


_THREADS: dict = {}  # --threads, set on torch when this process loads the estimator


def _targets(args, name: str | None, cameras: list[str]) -> dict[str, tuple]:
    """``{camera: (label file, overlay folder or None)}`` of one log (``name``; None: the one
    log of ``--sequence``): one camera writes ``--out`` (several logs: ``OUT/<log>.json``),
    several write ``<camera>.json`` into it (several logs: ``OUT/<log>/<camera>.json``)."""
    several = len(cameras) > 1
    out, overlays = args.out, args.overlays
    if name is not None:
        stem = safe_stem(name)  # a log name comes from data (nuScenes: scene.json)
        out = contained_path(out, stem if several else f"{stem}.json")
        overlays = None if overlays is None else contained_path(overlays, stem)
    return {cam: (contained_path(out, f"{safe_stem(cam)}.json") if several else out,
                  None if overlays is None
                  else contained_path(overlays, safe_stem(cam)) if several else overlays)
            for cam in cameras}


def _settings(args, log, cfg: LabelConfig, camera: str, weights: str | None) -> dict:
    if cfg.backend == "auto" and args.mode != "gt-accumulation":  # int8 or float32: ask
        cfg = replace(cfg, backend=_estimator(args.mode, args.checkpoint, args.backend,
                                              args.placement, args.max_points).backend)
    settings = label_settings(cfg, log, camera, max_frames=args.max_frames, weights=weights)
    if getattr(args, "image_size", None) is not None:  # recorded only when given
        settings["image_size"] = list(args.image_size)
    return settings


def _weights(args) -> str | None:
    """The digest of the estimator's weights (None: gt-accumulation runs no network)."""
    return None if args.mode == "gt-accumulation" else weights_digest(args.checkpoint,
                                                                      args.placement)


def _write_results(args, name: str | None, log, cfg: LabelConfig, results: dict,
                   weights: str | None) -> list[str]:
    """Write one log's label files (and overlays, before each label file: a label file
    means that its overlays are complete); returns the lines to print."""
    targets = _targets(args, name, list(results))
    lines = []
    for cam, result in results.items():
        path, folder = targets[cam]
        overlays = None if folder is None else write_overlays(log, result, folder)
        write_labels(path, result, _settings(args, log, cfg, cam, weights))
        t = result.timings
        lines.append(f"{args.mode} {cam}: {len(result.annotations)} instances in "
                     f"{t['frames']} frames, {t['frames'] / max(t['total'], 1e-9):.2f} "
                     f"frames/s -> {path}")
        if overlays is not None:
            lines.append(f"wrote {len(overlays)} overlays to {folder}")
    return lines


def _overlay_files(log, folder: Path) -> list[Path]:
    """The overlay PNGs :func:`seqshape.amodal.overlay.write_overlays` writes for ``log``."""
    return [overlay_path(folder, log.name, f) for f in log.frames]


def _to_label(args, opened: tuple, weights: Callable[[], str | None]
              ) -> tuple[list[str], bool]:
    """Why the log of ``opened`` (:func:`_open_one`) is to be labelled by a ``--resume`` run
    (its files missing; empty: every file of it exists with this run's settings), and
    whether some label file of it exists. ``weights()`` gives the weights' digest.

    Raises:
        ConfigError: a label file of it holds other settings, or none (every existing file
            is checked, so the run stops before labelling anything).
        DataError: a label file of it is not a complete label file.
    """
    args, name, log, cameras, cfg, _ = opened
    missing, started = [], False
    for cam, (path, folder) in _targets(args, name, cameras).items():
        if not path.exists():
            missing.append(f"{path} missing")
            continue
        started = True
        if not path.is_file():
            raise DataError(path, "not a file, where the label file of this log goes")
        recorded = read_label_settings(path)
        if recorded is None:
            raise ConfigError(f"{path} records no settings (written by an older seqshape or "
                              f"another tool): --resume cannot tell whether it matches; use "
                              f"another --out folder, or run without --resume to label "
                              f"again (overwriting it)")
        diff = settings_differences(recorded, _settings(args, log, cfg, cam, weights()))
        if diff:
            raise ConfigError(f"{path} holds labels made with other settings "
                              f"({'; '.join(diff)}); use another --out folder, or run "
                              f"without --resume to label again (overwriting it)")
        if folder is not None:
            absent = [p for p in _overlay_files(log, folder) if not p.is_file()]
            if absent:
                missing.append(f"{len(absent)} of its overlays missing in {folder}")
    return missing, started


def _resume(args, jobs: list) -> tuple[list, str | None]:
    """The jobs of a ``--resume`` run still to label, and the weights' digest if it was
    needed (a file to check: the digest imports PyTorch); prints a line for each log
    skipped (and for each labelled again: some of its files are missing), then a count.
    Every log's files are checked before anything is labelled."""
    known: dict = {}

    def weights() -> str | None:
        if "digest" not in known:
            known["digest"] = _weights(args)
        return known["digest"]

    todo, skipped = [], 0
    for name in jobs:
        opened = _open_one(args, name)
        missing, started = _to_label(args, opened, weights)
        label = opened[2].name if name is None else name
        if not missing:
            skipped += 1
            files = [str(p) for p, _ in _targets(args, name, opened[3]).values()]
            print(f"resume: {label} skipped, labelled before with the same settings "
                  f"({', '.join(files)})")
            continue
        todo.append(name)
        if started:
            print(f"resume: {label} labelled again ({'; '.join(missing)})")
    print(f"resume: {skipped} of {len(jobs)} logs skipped, {len(todo)} to label", flush=True)
    return todo, known.get("digest")


def _set_threads(mode: str, threads: int) -> None:
    if threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {threads}")
    _THREADS["torch"] = threads
    if mode != "gt-accumulation" and "est" in _ESTIMATOR:
        import torch  # heavy: only a process that runs the network imports it

        torch.set_num_threads(threads)


def _open_one(args: argparse.Namespace, name: str | None, pool=None) -> tuple:
    """Open one log (``name``; None: ``--sequence`` itself) and check its cameras and options;
    with ``pool``, its tracks are prepared (segmented or cropped) by a worker meanwhile."""
    if name is not None:
        args = argparse.Namespace(**{**vars(args), "sequence": name})
    log = open_args_log(args)
    cameras = cameras_of(args, log)
    if args.image_size is not None:
        set_image_size(log, args.image_size)
    values = config_kwargs(args, FIELDS)
    cfg = LabelConfig(**{**values, "instances": values["instances"] or None})
    tasks = {} if pool is None else {cam: submit_prepare(pool, log, cfg, cam)
                                     for cam in preparations(log, cfg, cameras)}
    return args, name, log, cameras, cfg, tasks


def _start_one(opened: tuple, pool=None) -> tuple:
    """Label one log (:func:`_open_one`): its tracks are completed here, its frames drawn
    here (``pool`` None) or by ``pool``'s workers. Returns what :func:`_finish_one` needs."""
    args, name, log, cameras, cfg, tasks = opened
    prepared = {cam: task.get() for cam, task in tasks.items()}
    estimator = _estimator(args.mode, args.checkpoint, args.backend, args.placement,
                           args.max_points) if pool is None or args.online else _spec(args)
    pending = start_labels(log, cfg, cameras, estimator, pool=pool,
                           keep_masks=args.overlays is not None, prepared=prepared)
    return args, name, log, cfg, pending


def _spec(args) -> EstimatorSpec | None:
    """What the workers load to estimate the tracks (None: gt-accumulation). ``--backend
    auto`` is resolved here first (int8 or float32: the label files record which; every
    worker then runs the same), the other backends in the workers."""
    if args.mode == "gt-accumulation":
        return None
    backend = args.backend
    if backend == "auto":
        backend = _estimator(args.mode, args.checkpoint, args.backend, args.placement,
                             args.max_points).backend
    return EstimatorSpec(args.checkpoint, backend, args.placement, args.max_points)


def _finish_one(started, weights: str | None) -> list[str]:
    """Wait for one log's labels (:func:`_start_one`) and write them (atomically, one file
    per log and camera, with the run's settings: ``weights`` is :func:`_weights`); the
    lines to print."""
    args, name, log, cfg, pending = started
    results = {cam: p.result() for cam, p in pending.items()}
    return _write_results(args, name, log, cfg, results, weights)


def _ready(started) -> bool:
    return all(p.ready() for p in started[4].values())


def _worker_start(preload: EstimatorSpec | None = None) -> None:
    """Start of a worker (unpickling this function has imported the labeller, OpenCV and
    SciPy): OpenBLAS held to one thread (:mod:`seqshape._threads`), freed memory kept for reuse
    (:mod:`seqshape._malloc`); in the sc-* modes the estimator starts loading in the
    background (:func:`~seqshape.amodal.labeler.preload_estimator`: the workers estimate the
    tracks, and their first tasks, crops or segments, overlap with the load)."""
    limit_openblas(1)
    keep_freed_memory()
    if preload is not None:
        preload_estimator(preload)


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
    keep_freed_memory()  # frames reuse their arrays' pages (seqshape._malloc)
    jobs = [None] if names is None else names
    weights = None
    if args.resume:
        jobs, weights = _resume(args, jobs)
        if not jobs:
            return 0
    try:
        return _label(args, jobs, weights)
    except KeyboardInterrupt:
        if names is not None:
            print("seqshape label: the logs written so far are complete; rerun with --resume "
                  "to label only the others", file=sys.stderr)
        raise


def _label(args: argparse.Namespace, jobs: list, weights: str | None) -> int:
    """Label ``jobs`` (:func:`run`), in this process or with ``args.workers`` workers;
    ``weights``: the weights' digest when known already."""
    if args.workers == 1:
        _set_threads(args.mode, args.threads)
        weights = weights or _weights(args)
        for name in jobs:
            for line in _finish_one(_start_one(_open_one(args, name)), weights):
                print(line)
        return 0
    # The workers segment or crop the logs (a few logs ahead), estimate their tracks and draw
    # the frames (any log's, in runs of frames); this process hands out the work and writes
    # each log's files once all its frames are drawn, in the order of the logs.
    # At most `workers` logs wait for their frames (their clouds are held here until then).
    # With workers every core is busy: OpenBLAS's spinning threads would only take cores from
    # the other processes (one worker alone gains from them: sc-seg 0.85x without; docs/amodal.md)
    limit_openblas(1)
    preload = None if args.mode == "gt-accumulation" else EstimatorSpec(
        args.checkpoint, args.backend, args.placement, args.max_points)
    with WorkerPool(args.workers, initializer=_worker_start, initargs=(preload,)) as pool:
        todo = deque(jobs)
        opened: deque = deque(_open_one(args, todo.popleft(), pool)
                              for _ in range(min(args.workers, len(todo))))
        _set_threads(args.mode, args.threads)
        weights = weights or _weights(args)  # after the workers have started
        started: deque = deque()
        while opened:
            current = opened.popleft()
            if todo:
                opened.append(_open_one(args, todo.popleft(), pool))
            started.append(_start_one(current, pool))
            while started and (_ready(started[0]) or len(started) > args.workers):
                for line in _finish_one(started.popleft(), weights):
                    print(line, flush=True)
        while started:
            for line in _finish_one(started.popleft(), weights):
                print(line, flush=True)
    return 0
