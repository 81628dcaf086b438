"""Time the evaluation metrics: Chamfer (cKDTree) and exact EMD (linear_sum_assignment).

Run: ``python benchmarks/bm_metrics.py [--repeats 5]``. Clouds are a vehicle-sized box surface
(4.5 x 1.8 x 1.5 m) sampled twice with fixed seeds, as an estimate against ground truth would be.
Prints the median and spread (min-max) over the repeats after one warm-up call.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from seqshape.evaluation.metrics import chamfer_distance, earth_movers_distance


def box_surface(n: int, seed: int, size=(4.5, 1.8, 1.5)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    size = np.asarray(size, dtype=np.float64)
    ln, w, h = size
    areas = np.array([w * h, w * h, ln * h, ln * h, ln * w, ln * w])
    face = rng.choice(6, n, p=areas / areas.sum())
    u = rng.uniform(-0.5, 0.5, (n, 3)) * size
    for i, (axis, sign) in enumerate(zip([0, 0, 1, 1, 2, 2], [1, -1] * 3, strict=True)):
        u[face == i, axis] = sign * size[axis] / 2
    return u.astype(np.float32)


def timeit(fn, repeats: int) -> tuple[float, float, float]:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times), max(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    rows = []
    for n in (1024, 2048):
        a = box_surface(n, 1)
        b = box_surface(n, 2) + np.float32(0.05)  # a slightly offset second sampling
        for name, fn in (("chamfer", lambda a=a, b=b: chamfer_distance(a, b)),
                         ("emd", lambda a=a, b=b: earth_movers_distance(a, b))):
            med, lo, hi = timeit(fn, args.repeats)
            rows.append((name, n, med, lo, hi, fn()))
    print(f"{'metric':<8} {'points':>6} {'median ms':>10} {'min ms':>8} {'max ms':>8} "
          f"{'value m':>8}")
    for name, n, med, lo, hi, value in rows:
        print(f"{name:<8} {n:>6} {med * 1e3:>10.2f} {lo * 1e3:>8.2f} {hi * 1e3:>8.2f} "
              f"{value:>8.4f}")


if __name__ == "__main__":
    main()
