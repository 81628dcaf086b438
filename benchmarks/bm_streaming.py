"""Streaming inference speed of :class:`seqshape.Estimator` (untrained ``small`` model).

* throughput: object-updates per second with 100 live tracks of 100-300 points each, all
  updated in one ``step`` call per frame (target >= 1000 /s on 2 cores);
* latency: one track, one ``step`` per frame, median milliseconds (target <= 2 ms).

Run: ``python benchmarks/bm_streaming.py [--threads 2] [--repeats 5]``
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from seqshape.model import MODEL_PRESETS, Estimator, ShapePoseNet


def make_frames(n_tracks: int, n_frames: int, seed: int = 0) -> list[list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-30, 30, size=(n_tracks, 3))
    sizes = rng.integers(100, 301, size=(n_frames, n_tracks))
    return [[(rng.normal(size=(sizes[t, i], 3)) * [2.0, 0.9, 0.7] + centres[i])
             .astype(np.float32) for i in range(n_tracks)] for t in range(n_frames)]


def throughput(est: Estimator, frames, repeats: int) -> list[float]:
    ids = [f"track{i}" for i in range(len(frames[0]))]
    est.step(ids, frames[0])  # warm-up
    rates = []
    for _ in range(repeats):
        est.reset()
        t0 = time.perf_counter()
        for pts in frames:
            est.step(ids, pts)
        rates.append(len(ids) * len(frames) / (time.perf_counter() - t0))
    return rates


def latency_ms(est: Estimator, frames, repeats: int) -> list[float]:
    single = [f[0] for f in frames]
    for p in single[:5]:
        est.step(["solo"], [p])  # warm-up
    out = []
    for _ in range(repeats):
        est.reset()
        times = []
        for p in single:
            t0 = time.perf_counter()
            est.step(["solo"], [p])
            times.append(time.perf_counter() - t0)
        out.append(1e3 * statistics.median(times))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--tracks", type=int, default=100)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, threads {args.threads}, small preset (untrained)")
    rows = []
    for kind in ("sequential", "baseline"):
        est = Estimator(ShapePoseNet(MODEL_PRESETS["small"], recurrent=kind == "sequential"),
                        threads=args.threads)
        frames = make_frames(args.tracks, args.frames)
        rates = throughput(est, frames, args.repeats)
        lat = latency_ms(est, make_frames(1, 100, seed=1), args.repeats)
        rows.append((kind, statistics.median(rates), min(rates), max(rates),
                     statistics.median(lat)))
    print(f"\n| model | updates/s ({args.tracks} tracks), median | min | max "
          f"| 1-track latency ms, median |")
    print("|---|---|---|---|---|")
    for kind, med, lo, hi, lat in rows:
        print(f"| {kind} | {med:.0f} | {lo:.0f} | {hi:.0f} | {lat:.2f} |")
    print("\ntargets: >= 1000 updates/s, <= 2 ms")


if __name__ == "__main__":
    main()
