"""Training throughput (frames/s) per stage and model, the reference step against the fast one.

The shipped recipe by default (src/seqshape/pretrained/*_config.json and docs/results.md,
round 8): ``small`` preset, windows of 64 frames, 2 windows per step, ``scale_norm="length"``,
and for the sequential model ``motion_input`` and ``frame_skip``; weights from the shipped
models (``--init pretrained``, as the recipe fine-tunes) unless ``--init none``.

Two steps, side by side in one process, interleaved (before, after, after, before, ...) so that
the load of a shared machine falls on both alike, each run of both on the same batches:

* **before**: :func:`seqshape.train.reference.reference_step`: the step as it was (batch built
  in the step, every window frame decoded, dense Chamfer search, plain Adam);
* **after**: ``Trainer._train_step``: batches prefetched in a thread, trailing padding trimmed,
  only the frames that count decoded, k-d-tree Chamfer search, fused Adam.

Frames = window frames per optimiser step (batch_size * window, padding included, as before).
``frames/CPU-s`` divides by the process CPU time (all its threads, the prefetch thread too):
the throughput per busy core. Uses ``--data`` if given, else a generated dataset of box tracks
(``--seed``). One warm-up step per variant, then ``--repeats`` timed runs of ``--steps`` steps
each; medians, and the ratio after / before of the medians.

Run: ``python benchmarks/bm_train.py [--data DIR [DIR ...]] [--threads 1] [--steps 4]
[--repeats 3] [--stages 1,2,3] [--models sequential,baseline]``
"""

from __future__ import annotations

import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _bench import bench_parser, print_table

from seqshape.data import Track, write_dataset
from seqshape.geometry import canonical_to_sensor
from seqshape.testing import box_shell
from seqshape.train import TrainConfig, Trainer, get_train_config
from seqshape.train.prefetch import BatchPrefetcher
from seqshape.train.reference import reference_step
from seqshape.train.trainer import make_adam

STAGES = {1: "1 shape", 2: "2 pose", 3: "3 joint"}


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


def recipe_config(kind: str, threads: int, window: int, batch_size: int) -> TrainConfig:
    """The shipped recipe's training configuration for ``kind``."""
    overrides = {"scale_norm": "length"}
    if kind == "sequential":
        overrides.update(motion_input=True, frame_skip=True)
    return dataclasses.replace(get_train_config("small"), threads=threads, tensorboard=False,
                               val_windows=0, window=window, batch_size=batch_size,
                               model_overrides=overrides)


def _timed_steps(step, steps: int) -> tuple[float, float]:
    """Wall and process-CPU seconds of ``steps`` calls of ``step()``."""
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        step()
    return time.perf_counter() - w0, time.process_time() - c0


def measure(data: list[Path], kind: str, stage: int, args) -> dict[str, list[tuple[float, float]]]:
    """Interleaved timings (wall s, CPU s) per variant of ``args.steps`` steps of ``stage``."""
    cfg = recipe_config(kind, args.threads, args.window, args.batch_size)
    init = None if args.init == "none" else args.init
    with tempfile.TemporaryDirectory() as out:
        tr = Trainer(data, out, kind, cfg, init=init)
        tr.state["sigma_init"] = True
        tr.model.train()
        plain = torch.optim.Adam(tr._stage_groups(stage))
        fused = make_adam(tr._stage_groups(stage))
        ref_windows, windows = tr._windows(stage), tr._windows(stage)

        def before() -> None:
            reference_step(tr, plain, ref_windows, stage)
            tr.state["global_step"] += 1

        with BatchPrefetcher(windows, cfg.batch_size) as batches:
            def after() -> None:
                tr._train_step(fused, batches, stage)
                tr.state["global_step"] += 1

            variants = {"before": before, "after": after}
            for fn in variants.values():  # warm-up (kernels, the track cache)
                tr.state["global_step"] = 0
                fn()
            runs: dict[str, list[tuple[float, float]]] = {k: [] for k in variants}
            for r in range(args.repeats):
                order = list(variants) if r % 2 == 0 else list(variants)[::-1]
                for name in order:  # both variants train on the same batches
                    tr.state["global_step"] = 1 + r * args.steps
                    runs[name].append(_timed_steps(variants[name], args.steps))
    return runs


def _row(kind: str, stage: int, runs, frames_per_step: int, steps: int) -> list[str]:
    frames = frames_per_step * steps
    wall = {k: statistics.median(frames / w for w, _ in v) for k, v in runs.items()}
    cpu = {k: statistics.median(frames / c for _, c in v) for k, v in runs.items()}
    lo = min(frames / w for w, _ in runs["after"])
    hi = max(frames / w for w, _ in runs["after"])
    return [kind, STAGES[stage], f"{wall['before']:.0f}", f"{wall['after']:.0f}",
            f"{lo:.0f}-{hi:.0f}", f"{wall['after'] / wall['before']:.2f}",
            f"{cpu['before']:.0f}", f"{cpu['after']:.0f}",
            f"{cpu['after'] / cpu['before']:.2f}"]


def main() -> None:
    ap = bench_parser(__doc__, repeats=3)
    ap.add_argument("--data", type=Path, nargs="+", default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--window", type=int, default=64)
    ap.add_argument("--batch-size", type=int, default=2)
    ap.add_argument("--init", default="pretrained",
                    help="weights to start from: 'pretrained' (default), a model.pt, or 'none'")
    ap.add_argument("--stages", default="1,2,3", help="comma-separated stages (1, 2, 3)")
    ap.add_argument("--models", default="sequential,baseline")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    stages = [int(s) for s in args.stages.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or [box_dataset(Path(tmp) / "boxes", seed=args.seed).path]
        per_step = args.batch_size * args.window
        print(f"torch {torch.__version__}, threads {args.threads}, data "
              f"{' '.join(map(str, data))}, {args.batch_size} windows x {args.window} frames "
              f"per step, init {args.init}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
        rows = []
        for kind in args.models.split(","):
            for stage in stages:
                runs = measure(data, kind, stage - 1, args)
                rows.append(_row(kind, stage, runs, per_step, args.steps))
                print("  " + " | ".join(rows[-1]), flush=True)
    print()
    print_table(("model", "stage", "frames/s before", "after", "after min-max", "ratio",
                 "frames/CPU-s before", "after", "ratio"), rows, "llrrrrrrr")


if __name__ == "__main__":
    main()
