"""The int8 engine's layer choices: agreement with the reference and the time of a step's passes.

For each shipped network, the ``"onnx-int8"`` estimator's deviations from the float32
reference as ratios of :data:`~seqshape.model.engine.INT8_NOISE`'s bound (the reference's own
deviations under 1 cm of point noise; the check ``"auto"`` runs, and every ratio must stay at
most 1): the worst over the median and 90th percentile of the worst shape point, the centre
and the yaw, on :func:`~seqshape.model.engine.car_stream` seeds 0, 1, 2 and 5 with and
without the shipped refiner, and on the 24-track seed-5 stream with the refiner. Then the
refined batch graph's passes over a 100-track step (``bm_streaming.make_frames``) side by side
in one process, with the per-track row layers of ``quantize_onnx(rows=...)`` off, as shipped
(:data:`~seqshape.model.engine.INT8_ROW_LAYERS`), and with the first MLP's last layer instead.

    python benchmarks/bm_int8.py                  # both networks, 30 timed rounds
    python benchmarks/bm_int8.py --kinds sequential --rounds 10
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _bench import print_table
from bm_streaming import make_frames

from seqshape.model import Estimator
from seqshape.model import engine as E
from seqshape.model.estimator import noise_quantiles
from seqshape.model.int8 import quantize_onnx
from seqshape.model.placement import load_refiner

SEEDS = (0, 1, 2, 5)


def agreement(kind: str) -> list:
    """One table row: the worst ratio to the bound per stream."""
    net = Estimator.load(kind, backend="torch").model
    refiner = load_refiner("pretrained")
    cars = 0.0
    for ref in (refiner, None):
        fast = Estimator(net, backend="onnx-int8", refiner=ref)
        for seed in SEEDS:
            mine, allowed = noise_quantiles(fast, E.car_stream(net.cfg.num_points, seed=seed),
                                            E.INT8_NOISE)
            cars = max(cars, float((mine / allowed).max()))
    fast = Estimator(net, backend="onnx-int8", refiner=refiner)
    small = E.car_stream(net.cfg.num_points, seed=5, n_tracks=24, n_steps=3)
    mine, allowed = noise_quantiles(fast, small, E.INT8_NOISE)
    return [kind, f"{cars:.2f}", f"{float((mine / allowed).max()):.2f}"]


def pass_times(rounds: int) -> list:
    """Rows: threads, then the median ms of a step's refined passes per row-layer choice."""
    est = Estimator.from_pretrained("sequential")
    feeds, real_run = [], E._Session.run

    def record(session, inputs):
        feeds.append({k: getattr(inputs, k).copy() for k in session.inputs})
        return real_run(session, inputs)

    E._Session.run = record
    try:
        for row in make_frames(100, 2, seed=0):
            est.step([f"t{i}" for i in range(100)], row)
    finally:
        E._Session.run = real_run
    feeds = [f for f in feeds[-2:] if f["points"].shape[0] > 1]
    graph = E.export_onnx(est.model, refiner=est.refiner.net)
    layers = E.INT8_STEP_LAYERS + E.INT8_REFINER_LAYERS
    sample = E.equalisation_sample(est.model)
    first = f"mlp1.{len(est.model.encoder.mlp1) - 1}"
    variants = {"none": (), "shipped": E.INT8_ROW_LAYERS, "first MLP's last": (first,)}
    graphs = {k: quantize_onnx(graph, layers, rows, sample) for k, rows in variants.items()}
    import onnxruntime as ort

    out = []
    for threads in (1, 2):
        sessions = {k: ort.InferenceSession(g, E._session_options(ort, threads),
                                            providers=["CPUExecutionProvider"])
                    for k, g in graphs.items()}
        times = {k: [] for k in sessions}
        for r in range(rounds + 3):
            for k, s in sessions.items():
                t = time.perf_counter()
                for f in feeds:
                    s.run(None, f)
                if r >= 3:  # warm-up
                    times[k].append(time.perf_counter() - t)
        ref = np.median(times["none"])
        out.append([threads] + [f"{1e3 * np.median(v):.1f} ({np.median(v) / ref:.2f}x)"
                                for v in times.values()])
    return out, list(variants)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kinds", nargs="+", default=["sequential", "baseline"])
    ap.add_argument("--rounds", type=int, default=30, help="timed rounds per variant")
    args = ap.parse_args()
    print("int8 deviations as ratios of the noise bound (at most 1 passes)\n")
    print_table(["weights", "car streams 0, 1, 2, 5 (+/- refiner)", "24-track stream, refiner"],
                [agreement(k) for k in args.kinds])
    rows, names = pass_times(args.rounds)
    print(f"\nrefined passes of one 100-track step, ms (median of {args.rounds}), by int8 row "
          f"layers\n")
    print_table(["threads"] + names, rows)


if __name__ == "__main__":
    main()
