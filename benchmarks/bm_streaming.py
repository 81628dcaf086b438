"""Streaming inference speed of :class:`seqshape.Estimator`: configurations (or backends) side
by side.

* throughput: object-updates per second with ``--tracks`` (100) live tracks of 100-300 points
  each (the near half of a car-sized box surface), all updated in one ``step`` call per frame
  (issue 17 target >= 3000 /s on 2 cores);
* latency: one track, one ``step`` per frame, median milliseconds (target <= 1 ms).

Rows (``--configs``, the default): the configurations a user gets, each on backend ``auto``:
``default`` first (``Estimator.from_pretrained("sequential")``: the shipped placement refiner
on, no smoothing), then ``no-refiner`` (``refiner="none"``) and ``causal``
(``smoothing="causal"``, the refiner on); targets of issue 47: the default at least 3,000
updates/s with 100 live tracks and at most 1 ms a single-track step, ``causal`` at least
2,000 updates/s. ``--backends B ...`` instead: one row per backend, all with ``--refiner``
and ``--smoothing`` (the tables of issue 17).

The weights are the shipped ``sequential`` one by default (``--weights``
also takes weights files, ``untrained`` for a random ``small`` model, and ``NAME@N`` for
weights fed at most N points a frame, ``Estimator(max_points=N)``). Every backend of
``--backends`` runs on the same frames, and the repeats go round the backends in turn, so the
ratios to the PyTorch reference are measured side by side even on a busy machine. ``--busy
K`` starts K busy-looping processes for the duration (CPU contention, as on a labelling farm
running many processes per machine); they are stopped at the end.

Warm-up (one step per track and five single-track steps per backend, plus the backend's own
set-up), then the median and spread (min-max) of ``--repeats`` passes; fixed seeds
(``--seed``: the clouds and an untrained network's weights).

``--compare-with OLD_SRC`` (the ``src`` folder of a frozen copy of the tree, e.g. ``git archive
HEAD | tar -x -C /tmp/old``, then ``/tmp/old/src``) measures that copy's seqshape against this
tree's side by side: two worker processes (this script with ``--worker``, one importing each
tree), the repeats alternating between them, one process timing at a time; the table gains a
``tree`` column (``old`` / ``new``) and the ratios are to the old copy's first backend.

``--drive-by`` adds the default estimator given ego poses, the cars parked and the ego
driving past them at 7 m/s, with its track memory of parked vehicles (the default) and without
(``track_memory="none"``): what the memory costs a step.

``--agreement`` adds a table of each backend's agreement with the reference on partial car
views (``engine.car_stream``; medians and 90th percentiles of the worst shape point, the centre
and the yaw), beside the reference's own deviation under 1 cm of noise on the points, the
bound ``"onnx-int8"`` is held to (``engine.INT8_NOISE``).

Run: ``python benchmarks/bm_streaming.py [--configs default no-refiner causal | --backends torch
onnx onnx-int8] [--threads 1] [--busy 0] [--weights sequential baseline] [--repeats 5] [--seed 0]
[--compare-with OLD_SRC] [--agreement] [--drive-by]``; issue 47's table: ``python benchmarks/bm_streaming.py
--repeats 3 --compare-with OLD/src``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import time

import numpy as np
import torch
from _bench import bench_parser, machine_line, print_table, time_it

from seqshape.model import MODEL_PRESETS, Estimator, ShapePoseNet
from seqshape.model.engine import BACKENDS, INT8_NOISE, car_stream
from seqshape.model.estimator import noise_quantiles
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


def load(spec: str, backend: str, threads: int | None, seed: int,
         refiner: str = "none", smoothing: str = "none") -> Estimator:
    """The estimator of ``spec``; ``NAME@N`` feeds at most N points a frame
    (``Estimator(max_points=N)``)."""
    name, _, cut = spec.rpartition("@")
    extra = {"max_points": int(cut)} if name and cut.isdigit() else {}
    spec = name if extra else spec
    if spec == "untrained":
        torch.manual_seed(seed)
        return Estimator(ShapePoseNet(MODEL_PRESETS["small"]), threads=threads, backend=backend,
                         smoothing=smoothing, **extra)
    extra["refiner"] = refiner  # explicit: the loaders' default is the shipped refiner
    return Estimator.load(spec, threads=threads, backend=backend, smoothing=smoothing, **extra)


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


#: The configurations of ``--configs``: (backend, refiner, smoothing).
CONFIGS = {"default": ("auto", "pretrained", "none"), "no-refiner": ("auto", "none", "none"),
           "causal": ("auto", "pretrained", "causal")}


def row_settings(args) -> dict[str, tuple[str, str, str]]:
    """The rows of this run: label -> (backend, refiner, smoothing)."""
    if args.backends:
        return {b: (b, args.refiner, args.smoothing) for b in args.backends}
    return {c: CONFIGS[c] for c in args.configs}


class Runner:
    """The estimators of one set of weights, one per row (:func:`row_settings`), warmed up on
    the inputs."""

    def __init__(self, spec: str, rows: dict[str, tuple[str, str, str]], args):
        self.ests = {label: load(spec, b, args.threads, args.seed, r, sm)
                     for label, (b, r, sm) in rows.items()}
        self.frames = make_frames(args.tracks, args.frames, seed=args.seed)
        self.single = [f[0] for f in make_frames(1, 100, seed=args.seed + 1)]
        ids = [f"track{i}" for i in range(args.tracks)]
        for est in self.ests.values():  # warm-up
            est.step(ids, self.frames[0])
            for p in self.single[:5]:
                est.step(["solo"], [p])

    def repeat(self) -> dict[str, tuple[float, float]]:
        """One timed pass of every backend in turn: (updates/s, single-track median ms)."""
        work = len(self.frames[0]) * len(self.frames)
        return {b: (work / throughput_run(est, self.frames), latency_run(est, self.single))
                for b, est in self.ests.items()}

    def names(self) -> dict[str, str]:
        return {b: est.backend for b, est in self.ests.items()}


def table_rows(spec: str, results: dict[str, list[tuple[float, float]]], ref: str,
               names: dict[str, str], tree: dict[str, str] | None = None) -> list[tuple]:
    """Rows of the table for one set of weights; ``results[key]`` the repeats of one row,
    ``ref`` the key of the ratio columns' reference."""
    ref_rate = statistics.median(r for r, _ in results[ref])
    ref_lat = statistics.median(m for _, m in results[ref])
    rows = []
    for key, runs in results.items():
        rates, lat = [r for r, _ in runs], [m for _, m in runs]
        r, m = statistics.median(rates), statistics.median(lat)
        rows.append((spec, *([] if tree is None else [tree[key]]), names[key],
                     f"{r:.0f}", f"{min(rates):.0f}", f"{max(rates):.0f}", f"{r / ref_rate:.2f}",
                     f"{m:.2f}", f"{min(lat):.2f}", f"{max(lat):.2f}", f"{ref_lat / m:.2f}"))
    return rows


def bench_weights(spec: str, rows: dict, args) -> list[tuple]:
    """Rows of the table for one set of weights: every row, repeats interleaved."""
    runner = Runner(spec, rows, args)
    backends = list(rows)
    results = {b: [] for b in backends}
    for _ in range(args.repeats):
        for b, value in runner.repeat().items():
            results[b].append(value)
    names = {b: f"{b} ({n})" for b, n in runner.names().items()}
    return table_rows(spec, results, backends[0], names)


def worker_args(args, spec: str) -> list[str]:
    """The command line of a ``--worker`` process for ``spec`` (this run's settings)."""
    rows = ["--backends", *args.backends] if args.backends else ["--configs", *args.configs]
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", "--weights", spec,
           *rows, "--tracks", str(args.tracks), "--frames",
           str(args.frames), "--seed", str(args.seed), "--refiner", args.refiner,
           "--smoothing", args.smoothing]
    return cmd + ([] if args.threads is None else ["--threads", str(args.threads)])


class Worker:
    """A ``--worker`` process importing seqshape from ``src`` (None: this tree's)."""

    def __init__(self, args, spec: str, src: str | None):
        env = dict(os.environ)
        if src is not None:
            env["PYTHONPATH"] = os.pathsep.join([src, *filter(None, [env.get("PYTHONPATH")])])
        self.proc = subprocess.Popen(worker_args(args, spec), env=env, text=True,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self.names = self._reply()  # after the warm-up

    def _reply(self):
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"benchmark worker {self.proc.args} stopped (see its stderr)")
        return json.loads(line)

    def repeat(self) -> dict[str, tuple[float, float]]:
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()
        return {b: tuple(v) for b, v in self._reply().items()}

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def compare_weights(spec: str, rows: dict, args) -> list[tuple]:
    """Rows for one set of weights, the old copy's rows and this tree's, the repeats
    alternating between the two worker processes (one timing at a time); each tree's row
    beside the other's."""
    backends = list(rows)
    workers = {"old": Worker(args, spec, args.compare_with), "new": Worker(args, spec, None)}
    try:
        results = {(t, b): [] for b in backends for t in workers}
        for _ in range(args.repeats):
            for t, w in workers.items():
                for b, value in w.repeat().items():
                    results[t, b].append(value)
    finally:
        for w in workers.values():
            w.close()
    names = {(t, b): f"{b} ({workers[t].names[b]})" for t, b in results}
    return table_rows(spec, results, ("old", backends[0]), names, {k: k[0] for k in results})


def run_worker(args) -> None:
    """``--worker``: warm up, print the backends' names, then one repeat per line "go"."""
    runner = Runner(args.weights[0], row_settings(args), args)
    print(json.dumps(runner.names()), flush=True)
    for line in sys.stdin:
        if line.strip() == "go":
            print(json.dumps(runner.repeat()), flush=True)


def main() -> None:
    ap = bench_parser(__doc__, repeats=5)
    ap.add_argument("--threads", type=int, default=None,
                    help="intra-op threads per estimator (default: each backend's default)")
    ap.add_argument("--tracks", type=int, default=100)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--busy", type=int, default=0, help="busy-looping processes to run beside")
    ap.add_argument("--weights", nargs="+", default=["sequential"],
                    help="shipped names, weights files, or 'untrained' (random small model); "
                         "NAME@N: at most N points a frame fed (Estimator max_points)")
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS),
                    help="rows: configurations on backend auto (default first); the first is "
                         "the reference of the ratio columns")
    ap.add_argument("--backends", nargs="+", default=None, choices=BACKENDS,
                    help="rows: these backends instead of --configs, each with --refiner and "
                         "--smoothing (e.g. torch onnx torch-lean onnx-int8; the first is the "
                         "reference of the ratio columns)")
    ap.add_argument("--compare-with", metavar="OLD_SRC", default=None,
                    help="the src folder of a frozen copy of the tree to measure side by side")
    ap.add_argument("--refiner", default="none",
                    help="placement refiner of the estimators: 'pretrained', a file or 'none'")
    ap.add_argument("--smoothing", default="none", choices=("none", "causal"),
                    help="the estimators' online pose smoothing (Estimator.smoothing)")
    ap.add_argument("--agreement", action="store_true",
                    help="also print each backend's agreement with the reference on partial car "
                         "views, beside the reference's own under 1 cm of noise on the points")
    ap.add_argument("--drive-by", action="store_true",
                    help="also time the default estimator given ego poses, parked cars passed "
                         "by the ego, with and without its track memory")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        run_worker(args)
        return
    settings = row_settings(args)
    print(f"torch {torch.__version__}, threads {args.threads}, busy processes {args.busy}, "
          + ("rows: " + "; ".join(f"{k} = backend {b}, refiner {r}, smoothing {sm}"
                                  for k, (b, r, sm) in settings.items()) + ", ")
          + f"load {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}, "
          f"{time.strftime('%Y-%m-%d %H:%M %Z')}"
          + ("" if args.compare_with is None else f", old tree {args.compare_with}"))
    print(machine_line(), flush=True)
    bench = bench_weights if args.compare_with is None else compare_weights
    busy = start_busy(args.busy)
    try:
        rows = [row for spec in args.weights for row in bench(spec, settings, args)]
    finally:
        stop_busy(busy)
    print()
    tree = [] if args.compare_with is None else ["tree"]
    print(f"load after: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}")
    print_table(("weights", *tree, "row (backend)", f"updates/s ({args.tracks} tracks), median", "min",
                 "max", "x ref", "1-track ms, median", "min", "max", "x ref"), rows,
                align="l" * (2 + len(tree)) + "rrrrrrrr")
    print("\ntargets (issues 17 and 47): the default >= 3000 updates/s, <= 1 ms; causal >= "
          "2000 updates/s; 'x ref': speed-up over the first row"
          + ("" if args.compare_with is None else " of the old tree"))
    if args.agreement:
        print_agreement(args)
    if args.drive_by:
        print_drive_by(args)


def drive_by(n_tracks: int, n_frames: int, seed: int = 0, step: float = 0.7
             ) -> tuple[list[list[np.ndarray]], list[np.ndarray]]:
    """:func:`make_frames`' parked cars seen from an ego driving along x by ``step`` m a frame
    (7 m/s at 10 Hz): each frame's points in that frame's sensor frame, and its ego pose."""
    frames, egos = [], []
    for t, row in enumerate(make_frames(n_tracks, n_frames, seed=seed)):
        ego = np.eye(4)
        ego[0, 3] = step * t
        frames.append([p - np.float32([step * t, 0.0, 0.0]) for p in row])
        egos.append(ego)
    return frames, egos


def print_drive_by(args) -> None:
    """``--drive-by``: the default estimator given ego poses, with and without the track memory
    of parked vehicles (``Estimator(track_memory=...)``, docs/model.md "Track memory"), on
    ``--tracks`` parked cars passed by the ego; repeats interleaved; updates/s."""
    frames, egos = drive_by(args.tracks, max(args.frames, 10), seed=args.seed)
    ids = [f"track{i}" for i in range(args.tracks)]
    ests = {m: Estimator.load(args.weights[0], threads=args.threads, track_memory=m)
            for m in ("parked", "none")}
    work = args.tracks * len(frames)
    rates: dict[str, list[float]] = {m: [] for m in ests}
    for _ in range(args.repeats):
        for m, est in ests.items():
            est.reset()
            rates[m].append(work / time_it(lambda est=est: [
                est.step(ids, f, ego_poses=[e] * len(ids)) for f, e in zip(frames, egos,
                                                                           strict=True)],
                1, warmup=0).runs[0])
    fed = sum(st.memory is not None and st.memory.parked(egos[-1][:3, 3])
              for st in ests["parked"]._states.values())
    ref = statistics.median(rates["none"])
    print(f"\ndrive-by: {args.tracks} parked cars passed at 7 m/s, ego poses given, "
          f"{len(frames)} steps; {fed} tracks fed by the memory at the end")
    print_table(("track_memory", "updates/s, median", "min", "max", "x none"),
                [(m, f"{statistics.median(r):.0f}", f"{min(r):.0f}", f"{max(r):.0f}",
                  f"{statistics.median(r) / ref:.2f}") for m, r in rates.items()],
                align="lrrrr")


def agreement_rows(spec: str, backends: list[str] | None, args) -> list[tuple]:
    """Rows of the agreement table for one set of weights: per backend other than the
    reference, the median and 90th percentile of its estimates' deviations from the
    reference's over ``engine.car_stream`` (worst shape point and centre, cm; yaw, degrees),
    then the reference's own under ``engine.INT8_NOISE`` of Gaussian noise on the points."""
    rows, noise = [], None
    for b in backends or ["torch", "onnx", "onnx-int8"]:
        if b == "torch":
            continue
        est = load(spec, b, args.threads, args.seed)
        mine, noise = noise_quantiles(est, car_stream(est.model.cfg.num_points, args.seed),
                                      INT8_NOISE)
        rows.append((spec, f"{b} ({est.backend})", *_agreement_cells(mine)))
    if noise is not None:
        rows.append((spec, f"torch, {100 * INT8_NOISE:g} cm noise on the points",
                     *_agreement_cells(noise)))
    return rows


def _agreement_cells(q: np.ndarray) -> list[str]:
    """``q`` (2, 3): p50 / p90 of shape (m), centre (m), yaw (rad) -> cells (cm, cm, deg)."""
    scale = np.array([100.0, 100.0, 180.0 / np.pi])
    return [f"{v:.2f}" for v in (q * scale).T.ravel()]


def print_agreement(args) -> None:
    rows = [row for spec in args.weights for row in agreement_rows(spec, args.backends, args)]
    print()
    print_table(("weights", "backend", "shape p50 (cm)", "shape p90", "centre p50 (cm)",
                 "centre p90", "yaw p50 (deg)", "yaw p90"), rows, align="llrrrrrr")
    print("\nagreement with the reference over partial car views (seqshape.model.engine."
          "car_stream): per estimate the worst shape point, the centre and the yaw; the last "
          "row per weights is the reference's own deviation under noise, onnx-int8's bound")


if __name__ == "__main__":
    main()
