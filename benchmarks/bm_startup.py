"""Start-up of a fresh process: importing seqshape and loading an estimator, with the disk
cache of exported ONNX graphs (:mod:`seqshape.model.graph_cache`) off, cold and warm.

Each run is a new Python process (what a ``seqshape label`` or ``evaluate`` process, or a
worker of a labelling farm, pays before its first frame) that imports ``torch`` and
``seqshape``, then calls ``Estimator.load(KIND, backend=BACKEND)`` and takes one step. Cases,
interleaved run by run so that the machine's load falls on all alike:

* ``off``: ``SEQSHAPE_CACHE_DIR=none`` (every process exports its graphs: the behaviour
  before the cache);
* ``cold``: an empty cache folder (the first process on a machine: exports and writes);
* ``warm``: the folder the previous ``cold`` run filled (every later process).

The table gives the median and range of each phase (seconds) and whether the ``onnx`` package
was imported. ``--label ROOT --sequence SEQ`` adds the wall time of a whole ``seqshape label``
run on that log (``--max-frames`` frames) per case.

Run: ``python benchmarks/bm_startup.py [--kinds sequential baseline] [--backend auto]
[--repeats 5] [--label SCENES --sequence 0000 --max-frames 10]``
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bench import bench_parser, print_table

CASES = ("off", "cold", "warm")

CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np
import torch
t1 = time.perf_counter()
from seqshape import Estimator
t2 = time.perf_counter()
est = Estimator.load(sys.argv[1], backend=sys.argv[2])
t3 = time.perf_counter()
rng = np.random.default_rng(0)
est.step(["a"], [(rng.normal(size=(200, 3)) * [2, 0.8, 0.5] + [10, 0, -1]).astype(np.float32)])
t4 = time.perf_counter()
print(json.dumps({"torch": t1 - t0, "seqshape": t2 - t1, "load": t3 - t2, "step": t4 - t3,
                  "total": t4 - t0, "onnx": "onnx" in sys.modules,
                  "backend": getattr(est, "backend", "?")}))
"""


def _env(case: str, folder: Path) -> dict:
    env = dict(os.environ)
    env["SEQSHAPE_CACHE_DIR"] = "none" if case == "off" else str(folder)
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("SEQSHAPE_PROGRESS", "0")
    return env


def run_child(kind: str, backend: str, case: str, folder: Path) -> dict:
    """One fresh process's phases (seconds) for ``case``; ``cold`` empties ``folder`` first."""
    if case == "cold":
        shutil.rmtree(folder, ignore_errors=True)
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", CHILD, kind, backend], env=_env(case, folder),
                         capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["wall"] = wall
    return res


def run_label(args, case: str, folder: Path, out: Path) -> float:
    """Wall seconds of one ``seqshape label`` process on ``--label``'s log."""
    if case == "cold":
        shutil.rmtree(folder, ignore_errors=True)
    cmd = [sys.executable, "-m", "seqshape.cli", "label", "--kitti", args.label, "--sequence",
           args.sequence, "--mode", "sc-gt", "--out", str(out), "--workers", "1"]
    if args.max_frames:
        cmd += ["--max-frames", str(args.max_frames)]
    t0 = time.perf_counter()
    subprocess.run(cmd, env=_env(case, folder), capture_output=True, text=True, check=True)
    return time.perf_counter() - t0


def _fmt(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} ({min(values):.2f}-{max(values):.2f})"


def main() -> None:
    ap = bench_parser(__doc__, repeats=5)
    ap.add_argument("--kinds", nargs="+", default=["sequential"],
                    help="shipped weights (sequential, baseline) or weights files")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--label", metavar="ROOT", default=None,
                    help="KITTI-layout scenes to time `seqshape label` on (optional)")
    ap.add_argument("--sequence", default="0000")
    ap.add_argument("--max-frames", type=int, default=10)
    args = ap.parse_args()
    import torch

    from seqshape import __version__

    print(f"seqshape {__version__}, torch {torch.__version__}, backend {args.backend}, "
          f"{args.repeats} runs per case, interleaved, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "cache"
        for kind in args.kinds:
            res = {c: [] for c in CASES}
            for _ in range(args.repeats):
                for case in CASES:
                    res[case].append(run_child(kind, args.backend, case, folder))
            base = statistics.median(r["wall"] for r in res["off"])
            for case in CASES:
                rs = res[case]
                rows.append([kind, case, rs[-1]["backend"],
                             _fmt([r["torch"] + r["seqshape"] for r in rs]),
                             _fmt([r["load"] for r in rs]), _fmt([r["step"] for r in rs]),
                             _fmt([r["wall"] for r in rs]),
                             f"{base / statistics.median(r['wall'] for r in rs):.2f}",
                             "yes" if any(r["onnx"] for r in rs) else "no"])
        print_table(["weights", "cache", "backend", "imports (s)", "load (s)", "first step (s)",
                     "process wall (s)", "x off", "onnx imported"], rows, "lllrrrrrl")
        if args.label:
            walls = {c: [] for c in CASES}
            for _ in range(args.repeats):
                for case in CASES:
                    walls[case].append(run_label(args, case, folder, Path(tmp) / "l.json"))
            base = statistics.median(walls["off"])
            print()
            print_table(["`seqshape label` sc-gt", "cache", "wall (s)", "x off"],
                        [[f"{args.label} {args.sequence}, {args.max_frames} frames", c,
                          _fmt(walls[c]), f"{base / statistics.median(walls[c]):.2f}"]
                         for c in CASES], "llrr")


if __name__ == "__main__":
    main()
