"""Causal (online) smoothing: the shipped setting beside its variants and the baseline.

``Estimator(smoothing="causal")`` runs a :class:`seqshape.model.smooth.CausalSmoother` after
the refiner and the heading step (docs/model.md, "Causal pose smoothing (online)"): the
poses fitted over the track's past, the shapes averaged over it. This benchmark scores, on
one dataset and with the shipped networks and refiner, the online estimates without
smoothing, with the shipped smoother, with each of its settings changed (``--windows``, the
frame weights by points and by detections, each alone and neither, the shape average's decay
and none, the first frames smoothed too, the smoother's own front), and the per-frame
baseline without and with the same smoother (a reference only: the baseline stays per frame
in ``seqshape evaluate``). The smoother is applied to each track's online estimates frame by
frame, as ``Estimator.step`` applies it. ``--offline`` adds the offline mode with its
variants.

    python benchmarks/bm_causal_smoothing.py --data TRAFFIC --split all
    python benchmarks/bm_causal_smoothing.py --data PAPER --split val --windows 5
    python benchmarks/bm_causal_smoothing.py --data PAPER --split val --windows --offline

No timing (``bm_streaming.py --smoothing`` measures the cost): frame-pooled means, CD and
translation in cm (shape CD: the estimated shape at the true pose), rotation in degrees;
rotation at 2-4 detections shows what smoothing from the first frames costs; translation 17+
/ 1st: the mean over frames at 17 or more detections over the mean at the first (pooled
over tracks).
"""

from __future__ import annotations

import argparse

import numpy as np
from _bench import print_table

from seqshape.data import TrackDataset
from seqshape.evaluation import evaluate_tracks
from seqshape.evaluation.evaluate import load_estimator, select_split
from seqshape.evaluation.report import FLIP_DEG
from seqshape.model.offline import OfflineConfig, OfflineEstimator, estimate_track
from seqshape.model.placement import load_refiner
from seqshape.model.smooth import (
    CAUSAL_MIN_FRAMES,
    CAUSAL_WINDOW,
    FULL_POINTS,
    RAMP,
    SHAPE_DECAY,
    CausalSmoother,
)


class Smoothed:
    """A whole-track estimator: ``estimator``'s online estimates through a
    :class:`CausalSmoother` built with ``options``."""

    whole_track = True

    def __init__(self, estimator, **options):
        self.estimator, self.options = estimator, options

    recurrent = property(lambda self: self.estimator.recurrent)
    kind = property(lambda self: self.estimator.kind)
    model = property(lambda self: self.estimator.model)

    def reset(self, track_id=None) -> None:
        """No state between tracks."""

    def estimate_track(self, points, **kwargs):
        out = estimate_track(self.estimator, points, mode="online", **kwargs)
        smoother = CausalSmoother(**self.options)
        egos, times = kwargs.get("ego_poses"), kwargs.get("timestamps")
        for t, est in enumerate(out):
            smoother.update_estimate(est, None if egos is None else egos[t],
                                     None if times is None else float(times[t]),
                                     1.0 / self.estimator.frame_period)
        return out


def methods(seq, base, windows: list[int], offline: bool = False) -> dict:
    """The rows: name -> estimator."""
    rows = {"sequential": seq,
            f"sequential + smoother (shipped: window {CAUSAL_WINDOW}, from detection "
            f"{CAUSAL_MIN_FRAMES}, estimate's front, weights: {FULL_POINTS} points, ramp "
            f"{RAMP}, shape decay {SHAPE_DECAY})": Smoothed(seq)}
    for w in windows:
        if w != CAUSAL_WINDOW:
            rows[f"sequential + smoother, window {w}"] = Smoothed(seq, window=w)
    rows["sequential + smoother, weights by points only"] = Smoothed(seq, ramp=None)
    rows["sequential + smoother, detection ramp only"] = Smoothed(seq, full_points=None)
    rows["sequential + smoother, equal weights (session 28's pose fit)"] = Smoothed(
        seq, full_points=None, ramp=None)
    rows["sequential + smoother, no shape average (poses only)"] = Smoothed(seq,
                                                                          shape_decay=None)
    for decay in (0.8, 0.9, 0.95, 1.0):
        if decay != SHAPE_DECAY:
            rows[f"sequential + smoother, shape decay {decay}"] = Smoothed(seq,
                                                                       shape_decay=decay)
    rows["sequential + smoother, from the first detection"] = Smoothed(seq, min_frames=1)
    rows["sequential + smoother, the smoother's own front"] = Smoothed(seq, keep_front=False)
    rows["sequential + smoother, from the first detection, its own front"] = Smoothed(
        seq, min_frames=1, keep_front=False)
    rows["baseline"] = base
    rows["baseline + smoother (reference only)"] = Smoothed(base)
    if offline:
        rows["sequential, offline (shipped OfflineConfig: shape average, equal weights)"] = \
            OfflineEstimator(seq)
        rows["sequential, offline, each frame's own shape (before session 30)"] = \
            OfflineEstimator(seq, OfflineConfig(shape="online"))
        rows["sequential, offline, the causal smoother's frame weights"] = OfflineEstimator(
            seq, OfflineConfig(full_points=FULL_POINTS, ramp=RAMP))
    return rows


def late_over_first(err: np.ndarray, n_det: np.ndarray) -> float:
    """Mean error at 17 or more detections over the mean at the first (nan if either is
    missing)."""
    late, first = err[n_det >= 17], err[n_det == 1]
    if not len(late) or not len(first):
        return float("nan")
    return float(np.nanmean(late) / np.nanmean(first))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="track dataset folder")
    ap.add_argument("--split", default="val", help="split name or 'all'")
    ap.add_argument("--windows", type=int, nargs="*", default=[3, 8, 12],
                    help="other local windows (frames) to measure beside the shipped one")
    ap.add_argument("--offline", action="store_true",
                    help="add the offline estimates without (shipped) and with the frame "
                         "weights")
    ap.add_argument("--max-tracks", type=int, default=None)
    args = ap.parse_args()
    refiner = load_refiner("pretrained")
    seq, base = load_estimator("pretrained", "sequential"), load_estimator("pretrained",
                                                                           "baseline")
    seq.refiner = base.refiner = refiner
    rows = methods(seq, base, args.windows, args.offline)
    dataset = select_split(TrackDataset(args.data), args.split)
    result = evaluate_tracks(rows, dataset, emd_every=0, workers=0, max_tracks=args.max_tracks)
    table = []
    for name in rows:
        r = result.of(name)
        rot = np.degrees(r["rot_rad"])
        early = (r["n_det"] >= 2) & (r["n_det"] <= 4)
        table.append([name, len(rot), f"{100 * np.nanmean(r['cd_m']):.2f}",
                      f"{100 * np.nanmean(r['cd_true_pose_m']):.2f}",
                      f"{100 * np.nanmean(r['trans_m']):.2f}", f"{np.nanmean(rot):.2f}",
                      f"{100 * np.mean(rot > FLIP_DEG):.1f}", f"{np.nanmean(rot[early]):.2f}",
                      f"{late_over_first(r['trans_m'], r['n_det']):.2f}"])
    print(f"\n### causal pose smoothing on {args.data} ({args.split}), shipped networks and "
          "refiner, online\n")
    print_table(["method", "frames", "CD", "shape CD", "translation", "rotation", "flips %",
                 "rotation, detections 2-4", "translation 17+ / 1st"], table)


if __name__ == "__main__":
    main()
