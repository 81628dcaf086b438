"""``seqshape evaluate``: score the sequential model beside the per-frame baseline.

Writes into ``--out``: ``metrics.json``, ``metrics.md`` (ours beside the paper's Table I),
``per_frame.csv``, ``errors_vs_detections.png``, ``errors_vs_distance.png`` and
``track_view.html`` (interactive 3D view of one track). See docs/evaluation.md.

Real Track datasets (``seqshape tracks``; their tracks' meta say ``source: "real"``) are
evaluated the same way, with the classical box fit (:class:`seqshape.model.boxfit
.BoxFitEstimator`) as a third row by default and the breakdowns by class, distance and points
per frame in the reports.

``--offline`` runs the sequential model offline (:mod:`seqshape.model.offline`: every frame's
estimate uses the whole track, future frames too), as the auto-labeller does; the per-frame
baseline and the box fit have no state to share between frames and are unchanged by it.
``metrics.json`` (``settings.modes``) and ``metrics.md`` say which mode each method ran in.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from seqshape.errors import ConfigError

HELP = "evaluate shape and pose estimates on a dataset's val split (or a real dataset)"
log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, type=Path, help="track dataset folder")
    parser.add_argument("--checkpoint", required=True,
                        help="sequential model: a checkpoint / model.pt path, or 'pretrained' "
                             "for the shipped weights")
    parser.add_argument("--baseline", default="pretrained",
                        help="per-frame baseline: a path or 'pretrained' (default)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--split", default="auto",
                        help="split to evaluate: a split name, 'all', or 'auto' (default: 'val' "
                             "when the dataset has one, else all tracks)")
    parser.add_argument("--boxfit", action=argparse.BooleanOptionalAction, default=None,
                        help="add the classical box fit as a third method (default: on for "
                             "real datasets, off for synthetic ones)")
    parser.add_argument("--boxfit-method", choices=("lshape", "min_area_rect"),
                        default="lshape",
                        help="box fit: L-shape fit (Zhang et al. 2017, default) or cv2 "
                             "minimum-area rectangle")
    parser.add_argument("--max-tracks", type=int, default=None, help="first N tracks only")
    parser.add_argument("--emd-every", type=int, default=1,
                        help="EMD on every K-th frame of each track (0: no EMD; default 1)")
    parser.add_argument("--emd-points", type=int, default=1024,
                        help="points per cloud for the exact EMD (default 1024)")
    parser.add_argument("--workers", type=int, default=2, help="EMD processes (default 2)")
    parser.add_argument("--batch-tracks", type=int, default=64,
                        help="tracks stepped together per forward pass (default 64)")
    parser.add_argument("--floor", choices=("auto", "resample", "split"), default="auto",
                        help="CD floor method (default auto: re-sample the mesh if known)")
    parser.add_argument("--view", default="auto",
                        help="track id for track_view.html, 'auto' (longest track) or 'none'")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--offline", action="store_true",
                        help="run the sequential model offline: every frame's estimate uses the "
                             "whole track, future frames too (seqshape.model.offline; the "
                             "per-frame baseline and the box fit are unchanged by it)")
    parser.add_argument("--no-hints", dest="hints", action="store_false",
                        help="feed the networks the points alone: no class and no ego poses "
                             "(the heading step then never acts; docs/evaluation.md)")


def load_estimator(spec: str, kind: str):
    """An Estimator from 'pretrained' or a weights path, checked to be of ``kind``."""
    from seqshape.model.estimator import Estimator

    est = (Estimator.from_pretrained(kind) if spec == "pretrained"
           else Estimator.from_checkpoint(spec))
    if est.recurrent != (kind == "sequential"):
        other = "baseline" if kind == "sequential" else "sequential"
        flag = "--baseline" if kind == "sequential" else "--checkpoint"
        raise ConfigError(f"{spec} holds a {other} model, not a {kind} one; pass it with {flag}")
    return est


def select_split(dataset, name: str):
    """The tracks to evaluate: split ``name``, ``"all"``, or ``"auto"`` ("val" when any track
    is in it, else every track: real datasets may have one split or none)."""
    from seqshape.data import TrackDataset

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
    from seqshape.evaluation.html import write_track_html
    from seqshape.evaluation.plots import write_plots
    from seqshape.evaluation.report import write_metrics
    from seqshape.evaluation.runner import evaluate_tracks

    t0 = time.perf_counter()
    result = evaluate_tracks(estimators, dataset, max_tracks=max_tracks, emd_points=emd_points,
                             emd_every=emd_every, batch_tracks=batch_tracks, workers=workers,
                             floor=floor, seed=seed, hints=hints)
    result.settings["seconds"] = round(time.perf_counter() - t0, 1)
    result.settings["data"] = str(dataset.path)
    summary = write_metrics(out, result)
    mode_note(out / "metrics.md", result.settings.get("modes", {}))
    write_plots(out, result)
    track = choose_view_track(dataset, view, max_tracks)
    if track is not None:
        write_track_html(out / "track_view.html", track, estimators)
    return summary


def mode_note(path: Path, modes: dict) -> None:
    """Append the methods' modes (online / offline) to ``metrics.md``."""
    from seqshape._io import atomic_write_text, read_text

    if not modes:
        return
    text = ", ".join(f"{m} {v}" for m, v in modes.items())
    atomic_write_text(path, read_text(path, "metrics") + f"- Mode: {text} (offline: every "
                      f"frame's estimate uses the whole track; docs/model.md).\n")


def run(args: argparse.Namespace) -> int:
    from seqshape.data import TrackDataset
    from seqshape.evaluation.report import metrics_markdown

    if args.max_tracks is not None and args.max_tracks < 1:
        raise ConfigError("--max-tracks must be >= 1")
    dataset = select_split(TrackDataset(args.data), args.split)
    estimators = {"sequential": load_estimator(args.checkpoint, "sequential"),
                  "baseline": load_estimator(args.baseline, "baseline")}
    if args.offline:
        from seqshape.model.offline import OfflineEstimator

        estimators["sequential"] = OfflineEstimator(estimators["sequential"])
    use_boxfit = dataset_is_real(dataset) if args.boxfit is None else args.boxfit
    if use_boxfit:
        from seqshape.model.boxfit import BoxFitEstimator

        k = estimators["sequential"].model.cfg.num_complete
        estimators["boxfit"] = BoxFitEstimator(method=args.boxfit_method, num_complete=k,
                                               seed=args.seed)
    summary = evaluate_to(args.out, dataset, estimators, args.max_tracks, args.emd_every,
                          args.emd_points, args.workers, args.batch_tracks, args.floor,
                          args.view, args.seed, args.hints)
    print(metrics_markdown(summary)
          + f"- Mode: sequential {'offline' if args.offline else 'online'}.")
    print(f"wrote {args.out}/metrics.json, metrics.md, per_frame.csv, plots"
          f"{', track_view.html' if args.view != 'none' else ''}")
    return 0
