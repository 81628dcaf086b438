"""Training throughput (frames per second) of the ``small`` preset, both models, per stage.

Frames = window frames pushed through the network per optimiser step (batch_size * window).
Uses ``--data`` if given (e.g. the paper preset dataset), else a generated dataset of box
tracks (``--seed``). Runs the real trainer step (data windows, forward, losses, backward, Adam):
two warm-up steps, then ``--repeats`` timed runs of ``--steps`` steps; median and min-max.

Run: ``python benchmarks/bm_train.py [--data DIR] [--threads 1] [--steps 8] [--repeats 3]``
"""

from __future__ import annotations

import dataclasses
import statistics
import tempfile
from pathlib import Path

import numpy as np
import torch
from _bench import bench_parser, print_table, time_it

from seqshape.data import Track, write_dataset
from seqshape.data.windows import WindowDataset
from seqshape.geometry import canonical_to_sensor
from seqshape.testing import box_shell
from seqshape.train import Trainer, get_train_config


def box_dataset(path: Path, n: int = 24, frames: int = 40, seed: int = 0):
    """Box-shaped vehicles on straight lines; partial frames = the sensor-facing side."""
    rng = np.random.default_rng(seed)
    tracks = []
    for i in range(n):
        size = np.array([rng.uniform(3.5, 5), rng.uniform(1.6, 2), rng.uniform(1.3, 1.8)])
        c = box_shell(2048, rng, size)
        yaw, x0, y0 = rng.uniform(-np.pi, np.pi), rng.uniform(5, 25), rng.uniform(-8, 8)
        t = np.arange(frames)
        poses = np.stack([x0 + 0.5 * t * np.cos(yaw), y0 + 0.5 * t * np.sin(yaw),
                          np.full(frames, -1.0), np.full(frames, yaw)], 1)
        pts = []
        for k in range(frames):
            s = canonical_to_sensor(c, poses[k])
            s = s[np.linalg.norm(s[:, :2], axis=1) < np.linalg.norm(poses[k, :2])]
            pts.append(s[rng.random(len(s)) < 0.2])
        tracks.append(Track(f"box{i:03d}", pts, poses, c.astype(np.float32), size, t * 0.1,
                            {"split": "train" if i % 6 else "val"}))
    return write_dataset(path, tracks)


def measure(data: Path, kind: str, stage: int, threads: int, steps: int, repeats: int):
    cfg = dataclasses.replace(get_train_config("small"), threads=threads, tensorboard=False,
                              val_windows=0)
    with tempfile.TemporaryDirectory() as out:
        tr = Trainer(data, out, kind, cfg)
        opt = torch.optim.Adam(tr._stage_groups(stage))
        wds = WindowDataset(tr.train_tracks, cfg.window, tr.model.cfg.num_points,
                            cfg.num_complete_gt, cfg.windows_per_track, cfg.p_first,
                            cfg.seed, key=stage + 1, cache_size=4096)
        tr.state["sigma_init"] = True
        tr.model.train()
        for _ in range(2):  # warm-up (and fill the track cache)
            tr._train_step(opt, wds, stage)

        def run() -> None:
            for _ in range(steps):
                tr._train_step(opt, wds, stage)
                tr.state["global_step"] += 1  # next batch, as the trainer does

        return time_it(run, repeats, warmup=0).rates(steps * cfg.batch_size * cfg.window)


def main() -> None:
    ap = bench_parser(__doc__, repeats=3)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--steps", type=int, default=8)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or box_dataset(Path(tmp) / "boxes", seed=args.seed).path
        cfg = get_train_config("small")
        print(f"torch {torch.__version__}, threads {args.threads}, data {data}, "
              f"{cfg.batch_size} windows x {cfg.window} frames per step")
        rows = []
        for kind in ("sequential", "baseline"):
            for stage, name in ((0, "1 shape"), (1, "2 pose"), (2, "3 joint")):
                r = measure(data, kind, stage, args.threads, args.steps, args.repeats)
                med = statistics.median(r)
                print(f"  {kind} stage {name}: {med:.0f} frames/s", flush=True)
                rows.append((kind, name, f"{med:.0f}", f"{min(r):.0f}", f"{max(r):.0f}",
                             f"{cfg.batch_size * cfg.window / med:.2f}"))
    print()
    print_table(("model", "stage", "frames/s median", "min", "max", "s/step"), rows, "llrrrr")


if __name__ == "__main__":
    main()
