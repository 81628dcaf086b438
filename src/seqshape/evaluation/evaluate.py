"""Evaluate a track dataset and write every output file (``seqshape evaluate``, the demo).

Writes into the output folder: ``metrics.json``, ``metrics.md`` (ours beside the paper's Table
I), ``per_frame.csv``, ``errors_vs_detections.png``, ``errors_vs_distance.png`` and
``track_view.html`` (interactive 3D view of one track). See docs/evaluation.md.

Real Track datasets (``seqshape tracks``; their tracks' meta say ``source: "real"``) are
evaluated the same way, with the classical box fit (:class:`seqshape.model.boxfit
.BoxFitEstimator`) as a third row by default and the breakdowns by class, distance and points
per frame in the reports. ``offline`` runs the sequential model offline
(:mod:`seqshape.model.offline`: every frame's estimate uses the whole track, future frames
too), as the auto-labeller does; the per-frame baseline and the box fit have no state to share
between frames and are unchanged by it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from seqshape._io import atomic_write_text, read_text
from seqshape.data import TrackDataset
from seqshape.errors import ConfigError
from seqshape.evaluation.html import write_track_html
from seqshape.evaluation.plots import write_plots
from seqshape.evaluation.report import write_metrics
from seqshape.evaluation.runner import detection_span, evaluate_tracks, track_kwargs
from seqshape.model.boxfit import BoxFitEstimator
from seqshape.model.calibration import calibrate_size
from seqshape.model.engine import BACKENDS
from seqshape.model.estimator import SMOOTHING, Estimator
from seqshape.model.offline import OfflineEstimator
from seqshape.model.placement import load_refiner
from seqshape.model.size_scale import check_size_scale
from seqshape.model.track_memory import TRACK_MEMORY

log = logging.getLogger(__name__)

#: The values of ``--track-memory``: the model's default, or one of :data:`TRACK_MEMORY`.
TRACK_MEMORY_CHOICES = ("auto", *TRACK_MEMORY)


@dataclass
class EvaluateConfig:
    """Options of :func:`evaluate_dataset` (the flags of ``seqshape evaluate``).

    split: split to evaluate: a split name, 'all', or 'auto' ('val' when the dataset has one,
        else all tracks).
    boxfit: add the classical box fit as a third method (None: on for real datasets, off for
        synthetic ones).
    boxfit_method: box fit: 'lshape' (L-shape fit, Zhang et al. 2017) or 'min_area_rect'
        (cv2 minimum-area rectangle).
    max_tracks: evaluate the first N tracks only (None: all).
    emd_every: EMD on every K-th frame of each track (0: no EMD).
    emd_points: points per cloud for the exact EMD.
    workers: EMD processes.
    batch_tracks: tracks stepped together per forward pass.
    floor: CD floor method: 'auto' (re-sample the mesh if known), 'resample' or 'split'.
    view: track id drawn in track_view.html, 'auto' (the longest track) or 'none'.
    seed: seed of the EMD subsets, the CD floor and the box fit.
    offline: run the sequential model offline: every frame's estimate uses the whole track,
        future frames too (seqshape.model.offline; the per-frame baseline and the box fit are
        unchanged by it).
    hints: feed the networks each track's class and ego poses, as a user's pipeline would
        (off: the points alone, and the heading step then never acts; docs/evaluation.md).
    backend: inference backend of both networks (seqshape.model.engine.BACKENDS; 'auto-float':
        the fastest float32 one that passes its check against PyTorch on this machine, so that
        the metrics are the model's own; 'auto' may take int8, within 0.5 % of them;
        docs/model.md).
    refiner: placement refiner of both networks (seqshape.model.placement): 'pretrained' (the
        shipped one, trained on the shipped networks' estimates), a refiner file, or 'none' (the
        networks' own placement).
    baseline_refiner: the per-frame baseline's refiner when it is not ``refiner``'s ('same',
        the default: the one refiner for both; else as ``refiner``), e.g. a refiner trained on
        the sequential model's estimates alone (``seqshape train-refiner --baseline none``)
        with the shipped one for the baseline.
    max_points: the most points of a frame fed to each network (a seeded subset of a larger
        frame; None: the model's own num_points). Fewer is faster and less accurate
        (docs/model.md, "Fewer points per frame").
    smoothing: the sequential model's online smoothing (Estimator.smoothing): 'none' or
        'causal' (each pose a robust fit over the track's past estimates, each shape the
        average of its past shapes; docs/model.md,
        "Causal pose smoothing (online)"). The per-frame baseline stays per frame, and the
        offline mode has its own whole-track smoothing, so it is refused with --offline.
    size_scale: the world scale both networks see (Estimator.size_scale; seqshape.model
        .calibration): a number (1: off, the default), or 'auto': each network's scale found
        from the evaluated tracks themselves, without their labels (calibrate_size: the median
        length of the car tracks where a frame shows the whole car, against the same figure on
        the network's training data; never below 1). For a log whose cars are shorter than the
        synthetic fleet's; evaluate one region and sensor at a time. The scale found is written
        to metrics.json (settings).
    track_memory: the sequential model's track memory (Estimator.track_memory;
        seqshape.model.track_memory): 'auto' (the model's default: 'parked'), 'parked' (a
        track that looks parked while the ego moves is fed its earlier frames' points with its
        new one, through the ego poses) or 'none'. Online only (the offline mode's batched
        passes do not use it); the per-frame baseline stays per frame.
    """

    split: str = "auto"
    boxfit: bool | None = None
    boxfit_method: str = "lshape"
    max_tracks: int | None = None
    emd_every: int = 1
    emd_points: int = 1024
    workers: int = 2
    batch_tracks: int = 64
    floor: str = "auto"
    view: str = "auto"
    seed: int = 0
    offline: bool = False
    hints: bool = True
    backend: str = "auto-float"
    refiner: str = "pretrained"
    baseline_refiner: str = "same"
    max_points: int | None = None
    smoothing: str = "none"
    size_scale: str = "1"
    track_memory: str = "auto"

    def __post_init__(self):
        if self.track_memory not in TRACK_MEMORY_CHOICES:
            raise ConfigError(f"--track-memory {self.track_memory!r}: choose from "
                              f"{', '.join(TRACK_MEMORY_CHOICES)}")
        if self.size_scale != "auto":
            check_size_scale(self.size_scale, "--size-scale (a number or 'auto')")
        if self.backend not in BACKENDS:
            raise ConfigError(f"--backend {self.backend!r}: choose from {', '.join(BACKENDS)}")
        if self.max_tracks is not None and self.max_tracks < 1:
            raise ConfigError("--max-tracks must be >= 1")
        if self.max_points is not None and self.max_points < 1:
            raise ConfigError("--max-points must be >= 1")
        if self.smoothing not in SMOOTHING:
            raise ConfigError(f"--smoothing {self.smoothing!r}: choose from "
                              f"{', '.join(SMOOTHING)}")
        if self.offline and self.track_memory == "parked":
            raise ConfigError("--track-memory is for the online mode; --offline runs every "
                              "frame of a track in one pass")
        if self.offline and self.smoothing != "none":
            raise ConfigError("--smoothing is for the online mode; --offline smooths the "
                              "whole track already")


def load_estimator(spec: str, kind: str, backend: str = "auto-float",
                   max_points: int | None = None, refiner=None):
    """:meth:`Estimator.load` of ``spec`` ('pretrained': the shipped weights of ``kind``),
    checked to be of ``kind``; the error names the flag that takes the other kind.
    ``refiner``: a loaded placement refiner or None, given at load time so that ``"auto"``'s
    check of the backend runs with it (the refined graphs, issue 47)."""
    est = Estimator.load(kind if spec == "pretrained" else spec, backend=backend,
                         max_points=max_points, refiner=refiner)
    if est.kind != kind:
        other = "baseline" if kind == "sequential" else "sequential"
        flag = "--baseline" if kind == "sequential" else "--checkpoint"
        raise ConfigError(f"{spec} holds a {other} model, not a {kind} one; pass it with {flag}")
    return est


def select_split(dataset, name: str):
    """The tracks to evaluate: split ``name``, ``"all"``, or ``"auto"`` ("val" when any track
    is in it, else every track: real datasets may have one split or none)."""
    if name == "auto":
        if any(e.get("split") == "val" for e in dataset.entries):
            return dataset.split("val")
        log.info("%s has no 'val' split: evaluating all %d tracks", dataset.path, len(dataset))
        name = "all"
    if name == "all":
        if not dataset.entries:
            raise ConfigError(f"{dataset.path}: the dataset has no tracks")
        return TrackDataset(dataset.path, _entries=list(dataset.entries))
    return dataset.split(name)


def dataset_is_real(dataset) -> bool:
    """Whether the dataset's first track comes from a real log (``meta["source"]``)."""
    return len(dataset) > 0 and dataset[0].meta.get("source") == "real"


def choose_view_track(dataset, spec: str, max_tracks: int | None):
    """The track drawn in track_view.html: by id, the longest (``auto``), or None."""
    if spec == "none":
        return None
    n = len(dataset) if max_tracks is None else min(len(dataset), max_tracks)
    if spec != "auto":
        try:
            return dataset.get(spec)
        except KeyError as exc:
            raise ConfigError(str(exc)) from None
    entries = dataset.entries[:n]
    best = max(range(n), key=lambda i: (entries[i].get("n_frames", 0), -i))
    return dataset[best]


def evaluate_to(out: Path, dataset, estimators: dict, max_tracks: int | None = None,
                emd_every: int = 1, emd_points: int = 1024, workers: int = 2,
                batch_tracks: int = 64, floor: str = "auto", view: str = "auto",
                seed: int = 0, hints: bool = True) -> dict:
    """Run the evaluation and write every output file into ``out``; returns the summary."""
    t0 = time.perf_counter()
    result = evaluate_tracks(estimators, dataset, max_tracks=max_tracks, emd_points=emd_points,
                             emd_every=emd_every, batch_tracks=batch_tracks, workers=workers,
                             floor=floor, seed=seed, hints=hints)
    result.settings["seconds"] = round(time.perf_counter() - t0, 1)
    memory = {name: m for name, est in estimators.items()  # online only
              if not getattr(est, "whole_track", False)
              and (m := getattr(est, "track_memory", None))}
    if memory:
        result.settings["track_memory"] = memory
    scales = {name: k for name, est in estimators.items()
              if (k := size_setting(est)) is not None}
    if scales:
        result.settings["size_scale"] = scales
    result.settings["data"] = str(dataset.path)
    summary = write_metrics(out, result)
    mode_note(out / "metrics.md", result.settings.get("modes", {}))
    write_plots(out, result)
    track = choose_view_track(dataset, view, max_tracks)
    if track is not None:
        write_track_html(out / "track_view.html", track, estimators)
    return summary


def size_setting(est) -> dict | float | None:
    """What ``settings["size_scale"]`` records of one method: its calibration
    (:class:`~seqshape.model.calibration.SizeCalibration` as a dict), its fixed scale when not
    1, else None (the box fit and unscaled networks)."""
    inner = getattr(est, "estimator", est)
    cal = getattr(inner, "size_calibration", None)
    if cal is not None:
        return cal.to_dict()
    k = getattr(inner, "size_scale", 1.0)
    return None if k == 1.0 else k


def mode_note(path: Path, modes: dict) -> None:
    """Append the methods' modes (online / offline) to ``metrics.md``."""
    if not modes:
        return
    text = ", ".join(f"{m} {v}" for m, v in modes.items())
    atomic_write_text(path, read_text(path, "metrics") + f"- Mode: {text} (offline: every "
                      f"frame's estimate uses the whole track; docs/model.md).\n")


def build_estimators(checkpoint: str, baseline: str, dataset, cfg: EvaluateConfig) -> dict:
    """The methods to score: the sequential model (offline when asked), the baseline, and the
    box fit when ``cfg.boxfit`` (None: for real datasets)."""
    refiner = load_refiner(cfg.refiner)
    base_refiner = refiner if cfg.baseline_refiner == "same" else \
        load_refiner(cfg.baseline_refiner)
    estimators = {"sequential": load_estimator(checkpoint, "sequential", cfg.backend,
                                               cfg.max_points, refiner),
                  "baseline": load_estimator(baseline, "baseline", cfg.backend, cfg.max_points,
                                             base_refiner)}
    estimators["sequential"].smoothing = cfg.smoothing
    if cfg.track_memory != "auto":  # the per-frame baseline's default is none
        estimators["sequential"].track_memory = cfg.track_memory
    for est in estimators.values():
        set_size_scale(est, cfg.size_scale, dataset, cfg.max_tracks, cfg.hints)
    if cfg.offline:
        estimators["sequential"] = OfflineEstimator(estimators["sequential"])
    use_boxfit = dataset_is_real(dataset) if cfg.boxfit is None else cfg.boxfit
    if use_boxfit:
        k = estimators["sequential"].model.cfg.num_complete
        estimators["boxfit"] = BoxFitEstimator(method=cfg.boxfit_method, num_complete=k,
                                               seed=cfg.seed)
    return estimators


def set_size_scale(est: Estimator, spec: str, dataset, max_tracks: int | None = None,
                   hints: bool = True) -> None:
    """``est.size_scale`` from ``spec``: a number, or ``"auto"``: :func:`~seqshape.model
    .calibration.calibrate_size` over the tracks to evaluate (the first ``max_tracks``; with
    ``hints`` their classes and ego poses, as the evaluation feeds them), recorded as
    ``est.size_calibration`` and logged."""
    if spec != "auto":
        est.size_scale = check_size_scale(spec, "--size-scale")
        return
    n = len(dataset) if max_tracks is None else min(len(dataset), max_tracks)
    tracks = []
    for i in range(n):
        tr = dataset[i]
        span = detection_span(tr)
        if span is not None:
            frames = range(*span)
            tracks.append({"points": [tr.points[t] for t in frames],
                           **track_kwargs(est, tr, frames, hints)})
    cal = calibrate_size(est, tracks)
    est.size_scale, est.size_calibration = cal.scale, cal
    log.info("%s: size scale %.3f (%s)", est.kind, cal.scale,
             cal.reason or f"car length {cal.length:.2f} m seen whole on {cal.tracks} tracks, "
                           f"{cal.prior:.2f} m on the training data")


def evaluate_dataset(data, checkpoint: str, baseline: str, out,
                     cfg: EvaluateConfig | None = None) -> dict:
    """``seqshape evaluate``: score the sequential model beside the baseline (and the box fit)
    on the tracks of the dataset folder ``data`` chosen by ``cfg.split``, writing every output
    file into ``out`` (module doc); returns the summary of :func:`write_metrics`."""
    cfg = EvaluateConfig() if cfg is None else cfg
    dataset = select_split(TrackDataset(data), cfg.split)
    estimators = build_estimators(checkpoint, baseline, dataset, cfg)
    return evaluate_to(Path(out), dataset, estimators, cfg.max_tracks, cfg.emd_every,
                       cfg.emd_points, cfg.workers, cfg.batch_tracks, cfg.floor, cfg.view,
                       cfg.seed, cfg.hints)
