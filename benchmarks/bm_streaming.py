"""Streaming inference speed of :class:`seqshape.Estimator` (untrained ``small`` model).

* throughput: object-updates per second with 100 live tracks of 100-300 points each, all
  updated in one ``step`` call per frame (target >= 1000 /s on 2 cores);
* latency: one track, one ``step`` per frame, median milliseconds (target <= 2 ms).

Warm-up, then the median and spread (min-max) of ``--repeats`` passes; fixed seeds (``--seed``:
the network's initial weights and the point clouds).

Run: ``python benchmarks/bm_streaming.py [--threads 2] [--repeats 5] [--seed 0]``
"""

from __future__ import annotations

import dataclasses
import statistics

import numpy as np
import torch
from _bench import bench_parser, print_table, time_it

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

    def one_pass() -> None:
        for pts in frames:
            est.step(ids, pts)

    return time_it(one_pass, repeats, warmup=0, setup=est.reset).rates(len(ids) * len(frames))


def latency_ms(est: Estimator, frames, repeats: int) -> list[float]:
    single = [f[0] for f in frames]
    for p in single[:5]:
        est.step(["solo"], [p])  # warm-up
    return [_latency_pass_ms(est, single) for _ in range(repeats)]


def _latency_pass_ms(est: Estimator, single: list[np.ndarray]) -> float:
    """Median ms of one ``step`` per cloud of ``single``, from a reset estimator."""
    est.reset()
    clouds = iter(single)
    return 1e3 * time_it(lambda: est.step(["solo"], [next(clouds)]), len(single),
                         warmup=0).median


def main() -> None:
    ap = bench_parser(__doc__, repeats=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--tracks", type=int, default=100)
    ap.add_argument("--frames", type=int, default=20)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    print(f"torch {torch.__version__}, threads {args.threads}, small preset (untrained)")
    rows = []
    small = MODEL_PRESETS["small"]
    models = {"sequential": (small, True),
              "sequential, frame_skip": (dataclasses.replace(small, frame_skip=True), True),
              "baseline": (small, False)}
    for kind, (cfg, recurrent) in models.items():
        est = Estimator(ShapePoseNet(cfg, recurrent=recurrent), threads=args.threads)
        frames = make_frames(args.tracks, args.frames, seed=args.seed)
        rates = throughput(est, frames, args.repeats)
        lat = latency_ms(est, make_frames(1, 100, seed=args.seed + 1), args.repeats)
        rows.append((kind, f"{statistics.median(rates):.0f}", f"{min(rates):.0f}",
                     f"{max(rates):.0f}", f"{statistics.median(lat):.2f}"))
    print()
    print_table(("model", f"updates/s ({args.tracks} tracks), median", "min", "max",
                 "1-track latency ms, median"), rows)
    print("\ntargets: >= 1000 updates/s, <= 2 ms")


if __name__ == "__main__":
    main()
