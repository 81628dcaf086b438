"""What the readers' input checks cost on real files (issue 45), against an older seqshape.

Times each reader over every real file of its kind under the given roots (KITTI tracking:
every velodyne sweep, calibration, label_02 and oxts file; Argoverse 2: every sweep's points
and the annotations of each log; a track dataset: every track), in this tree and, with
``--old SRC`` (the ``src`` folder of another checkout, e.g. ``git worktree add /tmp/old HEAD~3``),
in that one, in the same run: each side runs in its own worker process (``PYTHONPATH``), the
two alternating ``--rounds`` times so that a busy machine slows both alike. Per reader: files,
median time of one pass over them (ms) with min-max over every timed pass, the overhead of
this tree over the old one, and whether both give the same output (a SHA-256 over every array
they return, in order).

Rules (benchmarks/README.md): one untimed warm-up pass per worker, ``--repeats`` timed passes
per round, median and spread. Real data is never copied into the repository: give the
folders as arguments::

    python benchmarks/bm_readers.py --kitti ../shared/realdata/kitti-tracking/training \\
        --av2 ../shared/realdata/av2/sensor/val --tracks TRACKS --old /tmp/old/src
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from _bench import bench_parser, print_table


def _digest(h, value) -> None:
    """Feed every array / number of ``value`` (arrays, lists, dataclass-like objects) to ``h``."""
    if isinstance(value, np.ndarray):
        h.update(str(value.dtype).encode() + str(value.shape).encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, (list, tuple)):
        for v in value:
            _digest(h, v)
    elif isinstance(value, dict):
        for k in sorted(value, key=str):
            h.update(str(k).encode())
            _digest(h, value[k])
    elif hasattr(value, "__dict__"):
        _digest(h, {k: v for k, v in vars(value).items() if not k.startswith("_")})
    else:
        h.update(repr(value).encode())


def _readers(args) -> dict[str, tuple[int, object]]:
    """Reader name -> (number of files, a function reading all of them once)."""
    out = {}
    if args.kitti:
        from seqshape.camera import read_calib
        from seqshape.data.kitti import read_labels, read_oxts, read_velodyne

        root = Path(args.kitti)
        for name, pattern, fn in (("KITTI velodyne", "velodyne/*/*.bin", read_velodyne),
                                  ("KITTI calibration", "calib/*.txt", read_calib),
                                  ("KITTI label_02", "label_02/*.txt", read_labels),
                                  ("KITTI oxts", "oxts/*.txt", read_oxts)):
            files = sorted(root.glob(pattern))
            if files:
                out[name] = (len(files), lambda files=files, fn=fn: [fn(f) for f in files])
    if args.av2:
        from seqshape.data.av2 import Av2Log

        root = Path(args.av2)
        logs = Av2Log.log_names(root)
        n_sweeps = sum(len(Av2Log(root, name).frames) for name in logs)

        def av2_points():
            res = []
            for name in logs:
                log = Av2Log(root, name)
                res += [log.points(f) for f in log.frames]
            return res

        def av2_boxes():
            res = []
            for name in logs:
                log = Av2Log(root, name)
                res += [[(b.track_id, b.centre, b.size, b.yaw) for b in log.boxes(f)]
                        for f in log.frames]
            return res
        out["Argoverse 2 sweeps"] = (n_sweeps, av2_points)
        out["Argoverse 2 annotations"] = (len(logs), av2_boxes)
    if args.tracks:
        from seqshape.data import TrackDataset

        def tracks():
            ds = TrackDataset(args.tracks)
            return [(t.track_id, t.points, t.poses, t.size) for t in ds]
        out["track dataset"] = (len(TrackDataset(args.tracks)), tracks)
    return out


def worker(args) -> None:
    """Time every reader in this process; print one JSON line."""
    result = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, (n, fn) in _readers(args).items():
            value = fn()  # warm-up (page cache, imports)
            h = hashlib.sha256()
            _digest(h, value)
            runs = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                fn()
                runs.append(time.perf_counter() - t0)
            result[name] = {"files": n, "runs": runs, "digest": h.hexdigest()}
    print(json.dumps(result))


def _run_side(src: str, argv: list[str]) -> dict:
    env = {**os.environ, "PYTHONPATH": src}
    out = subprocess.run([sys.executable, __file__, "--worker", *argv], env=env, check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = bench_parser(__doc__, repeats=7)
    parser.add_argument("--kitti", type=Path, help="a KITTI tracking training/ folder")
    parser.add_argument("--av2", type=Path, help="an Argoverse 2 sensor split folder (LOG/...)")
    parser.add_argument("--tracks", type=Path, help="a seqshape track dataset folder")
    parser.add_argument("--old", type=Path, help="the src/ folder of the seqshape to compare")
    parser.add_argument("--rounds", type=int, default=3,
                        help="alternations of the two trees (each runs --repeats passes)")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return
    if not (args.kitti or args.av2 or args.tracks):
        print("bm_readers: no --kitti, --av2 or --tracks given; real data is not part of the "
              "repository, so there is nothing to measure (see the docstring for the command)")
        return
    argv = ["--repeats", str(args.repeats)]
    for key in ("kitti", "av2", "tracks"):
        if getattr(args, key):
            argv += [f"--{key}", str(getattr(args, key))]
    new_src = str(Path(__file__).resolve().parents[1] / "src")
    sides = {"new": new_src, **({"old": str(args.old)} if args.old else {})}
    runs: dict[str, dict[str, list[float]]] = {s: {} for s in sides}
    digests: dict[str, dict[str, str]] = {s: {} for s in sides}
    files: dict[str, int] = {}
    for _ in range(args.rounds):
        for side, src in sides.items():
            for name, r in _run_side(src, argv).items():
                runs[side].setdefault(name, []).extend(r["runs"])
                digests[side][name] = r["digest"]
                files[name] = r["files"]
    rows = []
    for name in files:
        new = runs["new"][name]
        row = [name, files[name], f"{statistics.median(new) * 1e3:.2f} "
                                  f"({min(new) * 1e3:.2f}-{max(new) * 1e3:.2f})"]
        if "old" in sides and name in runs["old"]:
            old = runs["old"][name]
            over = statistics.median(new) / statistics.median(old) - 1
            row[2:2] = [f"{statistics.median(old) * 1e3:.2f} "
                        f"({min(old) * 1e3:.2f}-{max(old) * 1e3:.2f})"]
            row += [f"{over * 100:+.1f} %",
                    "yes" if digests["old"][name] == digests["new"][name] else "NO"]
        rows.append(row)
    headers = ["reader", "files", "this tree ms (min-max)"]
    if "old" in sides:
        headers[2:2] = ["old tree ms (min-max)"]
        headers += ["overhead", "same output"]
    print(f"{args.rounds} rounds x {args.repeats} passes per tree, alternating; "
          f"this tree {new_src}" + (f", old tree {args.old}" if args.old else ""))
    print_table(headers, rows)


if __name__ == "__main__":
    main()
