"""Wall time of ``seqshape generate`` for a preset (fresh output folder per run).

    python benchmarks/bm_generate.py [--preset tiny] [--workers 2] [--repeats 3]

Runs the real command in a subprocess (spawned workers included) into a temporary folder,
after one warm-up run; prints the median wall time and tracks/s. For the paper preset use
``--repeats 1`` (about a minute or two on 2 cores) and ``--out`` to keep the data.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _run(preset: str, out: Path, workers: int) -> float:
    env = {**os.environ, "SEQSHAPE_PROGRESS": "0"}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "seqshape.cli", "generate", "--preset", preset,
                    "--out", str(out), "--workers", str(workers), "--seed", "0"],
                   check=True, env=env, capture_output=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", help="keep the (last) dataset here instead of a temp folder")
    ap.add_argument("--no-warmup", action="store_true")
    args = ap.parse_args()
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        if not args.no_warmup:
            _run(args.preset, Path(tmp) / "warmup", args.workers)
        for k in range(args.repeats):
            last = k == args.repeats - 1
            out = Path(args.out) if (args.out and last) else Path(tmp) / f"run{k}"
            times.append(_run(args.preset, out, args.workers))
        n = len(json.loads((out / "manifest.json").read_text())["tracks"])
    med = float(np.median(times))
    print("| preset | workers | tracks | runs | median wall s | tracks/s |")
    print("|---|---|---|---|---|---|")
    print(f"| {args.preset} | {args.workers} | {n} | {len(times)} | {med:.1f} | {n / med:.1f} |")


if __name__ == "__main__":
    main()
