"""Wall time of ``seqshape generate`` for a preset (fresh output folder per run).

    python benchmarks/bm_generate.py [--preset tiny] [--workers 2] [--repeats 3] [--seed 0]

Runs the real command in a subprocess (spawned workers included) into a temporary folder,
after one warm-up run; prints the median wall time and tracks/s. For the paper preset use
``--repeats 1`` (about a minute or two on 2 cores) and ``--out`` to keep the data.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _bench import bench_parser, print_table, time_it


def _run(preset: str, out: Path, workers: int, seed: int) -> None:
    env = {**os.environ, "SEQSHAPE_PROGRESS": "0"}
    subprocess.run([sys.executable, "-m", "seqshape.cli", "generate", "--preset", preset,
                    "--out", str(out), "--workers", str(workers), "--seed", str(seed)],
                   check=True, env=env, capture_output=True)


def main() -> None:
    ap = bench_parser(__doc__, repeats=3)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", help="keep the (last) dataset here instead of a temp folder")
    ap.add_argument("--no-warmup", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        outs = [Path(tmp) / f"run{k}" for k in range(args.repeats)]
        if args.out:
            outs[-1] = Path(args.out)
        warmup = 0 if args.no_warmup else 1
        folders = iter([Path(tmp) / "warmup"] * warmup + outs)  # a fresh folder per run
        timing = time_it(lambda: _run(args.preset, next(folders), args.workers, args.seed),
                         args.repeats, warmup=warmup)
        n = len(json.loads((outs[-1] / "manifest.json").read_text())["tracks"])
    med = timing.median
    print_table(("preset", "workers", "tracks", "runs", "median wall s", "tracks/s"),
                [(args.preset, args.workers, n, len(timing.runs), f"{med:.1f}",
                  f"{n / med:.1f}")], "llrrrr")


if __name__ == "__main__":
    main()
