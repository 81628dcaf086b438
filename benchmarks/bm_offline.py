"""Offline (whole-track) estimation of many tracks: one pass per track against batched passes.

:func:`seqshape.model.offline.estimate_track` called track by track (what the labeller does
today, one network pass per track and pass) against
:func:`seqshape.model.offline.estimate_tracks` (the tracks in chunks of at most
``--chunk-frames`` padded frames, one batched pass per chunk), on the first ``--tracks``
tracks of a dataset's split, with the shipped (or ``--weights``) sequential model on the
PyTorch reference path, for each ``--configs`` offline configuration (``default`` = the
shipped :class:`~seqshape.model.offline.OfflineConfig`; ``two-pass``, ``bidirectional``).
Both run on the same tracks in turn, ``--repeats`` times (median, min-max), after one
untimed warm-up of each; the last columns are the largest difference between the two
(shape points, pose centres, yaw), which must be float rounding.

Run: ``python benchmarks/bm_offline.py --data DATA [--split val] [--tracks 50]
[--configs default two-pass bidirectional] [--chunk-frames 512] [--threads 1]
[--repeats 3]``
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch
from _bench import bench_parser, print_table, time_it

from seqshape.data.dataset import TrackDataset
from seqshape.model import Estimator
from seqshape.model.heading import wrap_angle
from seqshape.model.offline import CHUNK_FRAMES, OfflineConfig, estimate_track, estimate_tracks

CONFIGS = {"default": OfflineConfig(),
           "two-pass": OfflineConfig(shape="two-pass", pose="two-pass"),
           "bidirectional": OfflineConfig(shape="bidirectional", pose="bidirectional")}


def load_tracks(data: str, split: str, n: int) -> list[dict]:
    """The first ``n`` tracks of ``split`` as :func:`estimate_tracks` arguments (points,
    timestamps, track id)."""
    ds = TrackDataset(data)
    ds = ds if split == "all" else ds.split(split)
    return [{"points": tr.points, "timestamps": tr.timestamps, "track_id": tr.track_id}
            for tr in (ds[i] for i in range(min(n, len(ds))))]


def max_difference(a: list[list], b: list[list]) -> tuple[float, float, float]:
    """Largest shape-point, centre (m) and yaw (rad) difference between two runs."""
    shape = centre = yaw = 0.0
    for ta, tb in zip(a, b, strict=True):
        for x, y in zip(ta, tb, strict=True):
            shape = max(shape, float(np.abs(x.complete - y.complete).max()))
            centre = max(centre, float(np.abs(x.pose[:3] - y.pose[:3]).max()))
            yaw = max(yaw, abs(float(wrap_angle(x.pose[3] - y.pose[3]))))
    return shape, centre, yaw


def bench_config(est: Estimator, tracks: list[dict], name: str, args) -> tuple:
    cfg = CONFIGS[name]

    def one_by_one():
        return [estimate_track(est, config=cfg, **tr) for tr in tracks]

    def batched():
        return estimate_tracks(est, tracks, config=cfg, chunk_frames=args.chunk_frames)

    ref, fast = one_by_one(), batched()  # warm-up
    times = {"per track": [], "batched": []}
    for _ in range(args.repeats):
        times["per track"].append(time_it(one_by_one, 1, warmup=0).runs[0])
        times["batched"].append(time_it(batched, 1, warmup=0).runs[0])
    frames = sum(len(tr["points"]) for tr in tracks)
    a, b = statistics.median(times["per track"]), statistics.median(times["batched"])
    shape, centre, yaw = max_difference(ref, fast)
    return (name, f"{len(tracks)}", f"{frames}", f"{frames / a:.0f}",
            f"{frames / max(times['per track']):.0f}-{frames / min(times['per track']):.0f}",
            f"{frames / b:.0f}",
            f"{frames / max(times['batched']):.0f}-{frames / min(times['batched']):.0f}",
            f"{a / b:.2f}", f"{shape * 1e3:.3f}", f"{centre * 1e3:.4f}", f"{yaw:.1e}")


def main() -> None:
    ap = bench_parser(__doc__, repeats=3)
    ap.add_argument("--data", help="a track dataset folder (e.g. one of `seqshape generate "
                                   "--preset paper`); without it, says so and exits")
    ap.add_argument("--split", default="val", help="split to take tracks from ('all': any)")
    ap.add_argument("--tracks", type=int, default=50)
    ap.add_argument("--weights", default="sequential", help="shipped name or weights file")
    ap.add_argument("--configs", nargs="+", default=["default"], choices=list(CONFIGS))
    ap.add_argument("--chunk-frames", type=int, default=CHUNK_FRAMES)
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    args = ap.parse_args()
    if args.data is None:
        print("bm_offline: no --data given (a track dataset folder); nothing measured")
        return
    est = Estimator.load(args.weights, threads=args.threads, backend="torch", refiner="none")
    tracks = load_tracks(args.data, args.split, args.tracks)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, chunk frames "
          f"{args.chunk_frames}, {time.strftime('%Y-%m-%d %H:%M %Z')}")
    rows = [bench_config(est, tracks, name, args) for name in args.configs]
    print()
    print_table(("config", "tracks", "frames", "per track frames/s, median", "min-max",
                 "batched frames/s, median", "min-max", "x", "max shape diff mm",
                 "centre mm", "yaw rad"), rows, align="lrrrrrrrrrr")


if __name__ == "__main__":
    main()
