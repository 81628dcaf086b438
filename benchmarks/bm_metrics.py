"""Time the evaluation metrics: Chamfer (cKDTree) and exact EMD (linear_sum_assignment).

Run: ``python benchmarks/bm_metrics.py [--repeats 5] [--seed 0]``. Clouds are a vehicle-sized
box surface (4.5 x 1.8 x 1.5 m) sampled twice with fixed seeds (``seed + 1``, ``seed + 2``), as an
estimate against ground truth would be. Prints the median and spread (min-max) over the repeats
after one warm-up call.
"""

from __future__ import annotations

import numpy as np
from _bench import bench_parser, print_table, time_it

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


def main() -> None:
    args = bench_parser(__doc__, repeats=5).parse_args()
    rows = []
    for n in (1024, 2048):
        a = box_surface(n, args.seed + 1)
        b = box_surface(n, args.seed + 2) + np.float32(0.05)  # a slightly offset second sampling
        for name, fn in (("chamfer", lambda a=a, b=b: chamfer_distance(a, b)),
                         ("emd", lambda a=a, b=b: earth_movers_distance(a, b))):
            t = time_it(fn, args.repeats)
            rows.append((name, n, f"{t.median * 1e3:.2f}", f"{t.min * 1e3:.2f}",
                         f"{t.max * 1e3:.2f}", f"{t.result:.4f}"))
    print_table(("metric", "points", "median ms", "min ms", "max ms", "value m"), rows)


if __name__ == "__main__":
    main()
