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
from seqshape.testing import box_surface


def main() -> None:
    args = bench_parser(__doc__, repeats=5).parse_args()
    rows = []
    for n in (1024, 2048):
        a = box_surface(n, args.seed + 1, dtype=np.float32)
        b = box_surface(n, args.seed + 2, dtype=np.float32) + np.float32(0.05)  # a slightly offset second sampling
        for name, fn in (("chamfer", lambda a=a, b=b: chamfer_distance(a, b)),
                         ("emd", lambda a=a, b=b: earth_movers_distance(a, b))):
            t = time_it(fn, args.repeats)
            rows.append((name, n, f"{t.median * 1e3:.2f}", f"{t.min * 1e3:.2f}",
                         f"{t.max * 1e3:.2f}", f"{t.result:.4f}"))
    print_table(("metric", "points", "median ms", "min ms", "max ms", "value m"), rows)


if __name__ == "__main__":
    main()
