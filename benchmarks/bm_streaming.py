"""Streaming inference speed of :class:`seqshape.Estimator`, inference backends side by side.

* throughput: object-updates per second with ``--tracks`` (100) live tracks of 100-300 points
  each (the near half of a car-sized box surface), all updated in one ``step`` call per frame
  (issue 17 target >= 3000 /s on 2 cores);
* latency: one track, one ``step`` per frame, median milliseconds (target <= 1 ms).

The weights are the shipped ``sequential`` and ``baseline`` ones by default (``--weights``
also takes weights files, and ``untrained`` for a random ``small`` model). Every backend of
``--backends`` runs on the same frames, and the repeats go round the backends in turn, so the
ratios to the PyTorch reference are measured side by side even on a busy machine. ``--busy
K`` starts K busy-looping processes for the duration (CPU contention, as on a labelling farm
running many processes per machine); they are stopped at the end.

Warm-up (one step per track and five single-track steps per backend, plus the backend's own
set-up), then the median and spread (min-max) of ``--repeats`` passes; fixed seeds
(``--seed``: the clouds and an untrained network's weights).

Run: ``python benchmarks/bm_streaming.py [--backends torch onnx onnx-int8] [--threads 1] [--busy 0]
[--weights sequential baseline] [--repeats 5] [--seed 0]``
"""

from __future__ import annotations

import multiprocessing
import statistics
import time

import numpy as np
import torch
from _bench import bench_parser, print_table, time_it

from seqshape.model import MODEL_PRESETS, Estimator, ShapePoseNet
from seqshape.model.engine import BACKENDS
from seqshape.testing import box_surface


def make_frames(n_tracks: int, n_frames: int, seed: int = 0) -> list[list[np.ndarray]]:
    """``n_frames`` frames of ``n_tracks`` partial car views (100-300 points: the half of a
    box surface nearer the sensor), each track at its own fixed pose."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(5, 40, size=(n_tracks, 2)) * rng.choice([-1, 1], size=(n_tracks, 2))
    yaws = rng.uniform(-np.pi, np.pi, size=n_tracks)
    counts = rng.integers(100, 301, size=(n_frames, n_tracks))
    frames = []
    for t in range(n_frames):
        row = []
        for i in range(n_tracks):
            pose = (xy[i, 0], xy[i, 1], -0.9, yaws[i])
            pts = box_surface(2 * counts[t, i], rng, pose=pose, dtype=np.float32)
            near = np.linalg.norm(pts[:, :2], axis=1) <= np.linalg.norm(xy[i])
            row.append(pts[near][:counts[t, i]])
        frames.append(row)
    return frames


def _busy() -> None:
    while True:
        pass


def start_busy(k: int) -> list[multiprocessing.Process]:
    """K busy-looping processes (stopped by :func:`stop_busy`)."""
    procs = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(k)]
    for p in procs:
        p.start()
    return procs


def stop_busy(procs: list[multiprocessing.Process]) -> None:
    for p in procs:
        p.terminate()
        p.join()


def load(spec: str, backend: str, threads: int | None, seed: int) -> Estimator:
    if spec == "untrained":
        torch.manual_seed(seed)
        return Estimator(ShapePoseNet(MODEL_PRESETS["small"]), threads=threads, backend=backend)
    return Estimator.load(spec, threads=threads, backend=backend)


def throughput_run(est: Estimator, frames) -> float:
    """Seconds of one pass over ``frames`` from a reset estimator (all tracks per step)."""
    ids = [f"track{i}" for i in range(len(frames[0]))]
    est.reset()
    return time_it(lambda: [est.step(ids, pts) for pts in frames], 1, warmup=0).runs[0]


def latency_run(est: Estimator, single: list[np.ndarray]) -> float:
    """Median ms of one single-track ``step`` per cloud of ``single``, from a reset state."""
    est.reset()
    clouds = iter(single)
    return 1e3 * time_it(lambda: est.step(["solo"], [next(clouds)]), len(single),
                         warmup=0).median


def bench_weights(spec: str, backends: list[str], args) -> list[tuple]:
    """Rows of the table for one set of weights: every backend, repeats interleaved."""
    ests = {b: load(spec, b, args.threads, args.seed) for b in backends}
    frames = make_frames(args.tracks, args.frames, seed=args.seed)
    single = [f[0] for f in make_frames(1, 100, seed=args.seed + 1)]
    ids = [f"track{i}" for i in range(args.tracks)]
    for est in ests.values():  # warm-up
        est.step(ids, frames[0])
        for p in single[:5]:
            est.step(["solo"], [p])
    rates = {b: [] for b in backends}
    lat = {b: [] for b in backends}
    for _ in range(args.repeats):
        for b, est in ests.items():
            rates[b].append(args.tracks * args.frames / throughput_run(est, frames))
            lat[b].append(latency_run(est, single))
    ref_rate = statistics.median(rates[backends[0]])
    ref_lat = statistics.median(lat[backends[0]])
    rows = []
    for b, est in ests.items():
        r, m = statistics.median(rates[b]), statistics.median(lat[b])
        rows.append((spec, f"{b} ({est.backend})", f"{r:.0f}", f"{min(rates[b]):.0f}",
                     f"{max(rates[b]):.0f}", f"{r / ref_rate:.2f}", f"{m:.2f}",
                     f"{min(lat[b]):.2f}", f"{max(lat[b]):.2f}", f"{ref_lat / m:.2f}"))
    return rows


def main() -> None:
    ap = bench_parser(__doc__, repeats=5)
    ap.add_argument("--threads", type=int, default=None,
                    help="intra-op threads per estimator (default: each backend's default)")
    ap.add_argument("--tracks", type=int, default=100)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--busy", type=int, default=0, help="busy-looping processes to run beside")
    ap.add_argument("--weights", nargs="+", default=["sequential", "baseline"],
                    help="shipped names, weights files, or 'untrained' (random small model)")
    ap.add_argument("--backends", nargs="+", default=["torch", "onnx", "torch-lean", "onnx-int8"],
                    choices=BACKENDS, help="the first is the reference of the ratio columns")
    args = ap.parse_args()
    print(f"torch {torch.__version__}, threads {args.threads}, busy processes {args.busy}, "
          f"{time.strftime('%Y-%m-%d %H:%M %Z')}")
    busy = start_busy(args.busy)
    try:
        rows = [row for spec in args.weights for row in bench_weights(spec, args.backends, args)]
    finally:
        stop_busy(busy)
    print()
    print_table(("weights", "backend", f"updates/s ({args.tracks} tracks), median", "min",
                 "max", "x ref", "1-track ms, median", "min", "max", "x ref"), rows,
                align="llrrrrrrrr")
    print("\ntargets (issue 17): >= 3000 updates/s, <= 1 ms; 'x ref': speed-up over the first "
          "backend")


if __name__ == "__main__":
    main()
