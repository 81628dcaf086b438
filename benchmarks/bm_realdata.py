"""The real-data benchmark: every real log given, every inference mode, by detections so far.

Extracts the vehicle tracks of each real source (``seqshape tracks``; any reader of
``seqshape.data``), evaluates them with ``seqshape evaluate`` in each mode of the sequential
model (online, ``--smoothing causal``, ``--offline``) beside the per-frame baseline and the
classical box fit, and prints the table real-data changes are judged by (docs/results.md,
"Real sequences"): per source and method, the planar centre error (median, mean and largest),
its signed radial part (positive: too far from the sensor), the yaw error, the share of
180-degree flips (moving and parked vehicles apart: parked = the annotated centre moves less
than ``PARKED_M`` in the fixed frame of the ego poses over the track), the absolute length and
width errors of the estimated extents and the Chamfer distance to each track's accumulated
reference; then the median centre error by detections so far (1, 2-3, 4-8, 9-16, 17+) and the
fusion ratios (the sequential model's median centre error over the baseline's, from the 9th
detection on).

    python benchmarks/bm_realdata.py \\
        --source kitti0000=kitti:../shared/realdata/kitti-tracking/training \\
        --source av2=av2:../shared/realdata/av2/sensor/val
    python benchmarks/bm_realdata.py --dataset av2 --root ROOT     # one source
    python benchmarks/bm_realdata.py --dataset av2 --root ROOT --finetune-steps 300
    python benchmarks/bm_realdata.py --dataset av2 --root ROOT --refiner none --modes online
    python benchmarks/bm_realdata.py ... --size-scale auto    # each log's size calibration
    python benchmarks/bm_realdata.py ... --backend onnx-int8  # the streaming engine's graphs
    python benchmarks/bm_realdata.py ... --track-memory none  # online without the track memory

A log a reader cannot open (e.g. a sequence without sweeps) is reported and skipped. Without
``--source`` or ``--root`` there is nothing to measure: the script says so and exits 0 (real
data is never part of the repository). Timing is not the point here; ``bm_tracks.py`` times
extraction. ``--out`` keeps the work folder: ``--reuse`` then skips what is already there.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from _bench import print_table

from seqshape.cli import main as seqshape_main

METHODS = ("sequential", "baseline", "boxfit")
MODES = ("online", "causal", "offline")
#: Detections-so-far bins of the table (inclusive ranges; None: no upper end).
BINS = ((1, 1), (2, 3), (4, 8), (9, 16), (17, None))
#: Range bins (m, [lo, hi)) of the radial-bias-by-range table.
RANGES = ((0.0, 15.0), (15.0, 30.0), (30.0, None))
#: Annotated centre travel (m, fixed frame) under which a track counts as parked.
PARKED_M = 1.0
#: Rotation error (deg) above which a frame counts as a 180-degree flip (as ``evaluate``).
FLIP_DEG = 150.0


def _f(v, digits: int = 1) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else \
        f"{v:.{digits}f}"


def _quiet(argv: list[str]) -> int:
    """``seqshape ARGV`` with its printed report swallowed (the tables below say it shorter)."""
    with contextlib.redirect_stdout(io.StringIO()):
        return seqshape_main(argv)


def extract(dataset: str, root: Path, out: Path, sequences, split_by: str,
            ego_poses: str = "given") -> None:
    argv = ["tracks", "--dataset", dataset, "--root", str(root), "--out", str(out),
            "--split-by", split_by, "--val-fraction", "0.3" if split_by == "track" else "0",
            "--ego-poses", ego_poses]
    for s in sequences or ():
        argv += ["--sequence", s]
    if split_by == "log":
        argv += ["--split", "val"]
    code = _quiet(argv)
    if not (out / "manifest.json").exists():
        sys.exit(f"seqshape tracks wrote no tracks from {root} (exit {code})")


def evaluate(data: Path, out: Path, checkpoint: str, split: str,
             baseline: str = "pretrained", refiner: str = "pretrained",
             mode: str = "online", reuse: bool = False,
             baseline_refiner: str = "same", size_scale: str = "1",
             backend: str | None = None, track_memory: str = "auto") -> Path:
    """``seqshape evaluate`` of one mode into ``out``; returns its ``per_frame.csv``."""
    if reuse and (out / "per_frame.csv").exists():
        return out / "per_frame.csv"
    argv = ["evaluate", "--data", str(data), "--checkpoint", checkpoint, "--out", str(out),
            "--baseline", baseline, "--refiner", refiner, "--baseline-refiner", baseline_refiner,
            "--split", split, "--workers", "1",
            "--emd-every", "0", "--view", "none"]
    argv += [] if size_scale == "1" else ["--size-scale", size_scale]
    argv += [] if backend is None else ["--backend", backend]
    # the track memory is online (the offline mode's passes do not use it)
    argv += [] if track_memory == "auto" or mode == "offline" else \
        ["--track-memory", track_memory]
    argv += {"online": [], "causal": ["--smoothing", "causal"], "offline": ["--offline"]}[mode]
    if _quiet(argv) != 0:
        sys.exit(f"seqshape evaluate ({mode}) failed on {data}")
    return out / "per_frame.csv"


def read_frames(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """``per_frame.csv`` as per-method columns (centre cm, radial cm, yaw deg, |length| cm,
    |width| cm, CD cm, detections so far, track id)."""
    cols: dict[str, dict[str, list]] = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            c = cols.setdefault(r["method"], {k: [] for k in (
                "centre", "radial", "tangential", "yaw", "length", "width", "cd", "n_det",
                "track", "cls", "distance", "travel")})

            def num(key, scale=1.0, r=r):
                v = r.get(key, "")
                return float(v) * scale if v not in ("", None) else np.nan
            c["centre"].append(num("trans_m", 100))
            c["radial"].append(num("radial_m", 100))
            c["tangential"].append(abs(num("tangential_m", 100)))
            c["yaw"].append(np.degrees(abs(num("rot_rad"))))
            c["length"].append(abs(num("length_err_m", 100)))
            c["width"].append(abs(num("width_err_m", 100)))
            c["cd"].append(num("cd_m", 100))
            c["n_det"].append(int(r["n_det"]))
            c["track"].append(r["track_id"])
            c["cls"].append(r.get("class", ""))
            c["distance"].append(num("distance_m"))
            c["travel"].append(num("world_travel_m"))
    return {m: {k: np.asarray(v) for k, v in c.items()} for m, c in cols.items()}


def _med(x):
    x = x[np.isfinite(x)]
    return float(np.median(x)) if len(x) else None


def _mean(x):
    x = x[np.isfinite(x)]
    return float(np.mean(x)) if len(x) else None


def _in_bin(n_det: np.ndarray, lo: int, hi: int | None) -> np.ndarray:
    return (n_det >= lo) & (n_det <= (hi if hi is not None else np.iinfo(np.int64).max))


def _in_range(d: np.ndarray, lo: float, hi: float | None) -> np.ndarray:
    return (d >= lo) & (d < (hi if hi is not None else np.inf))


def _bias_split(c: dict[str, np.ndarray], use: np.ndarray) -> dict:
    """Where the centre error of the frames ``use`` comes from: each track's mean radial
    error (its bias: the same in every frame, so no fusion over the track removes it; median
    over tracks), the frames' radial error about their track's bias and their tangential
    error (medians, cm)."""
    tracks = c["track"][use]
    radial = c["radial"][use]
    ok = np.isfinite(radial)
    if not ok.any():
        return {"track_bias_med": None, "radial_spread_med": None, "tangential_med": None}
    bias = {t: float(np.mean(radial[ok & (tracks == t)])) for t in set(tracks[ok].tolist())}
    spread = np.abs(radial[ok] - np.array([bias[t] for t in tracks[ok]]))
    return {"track_bias_med": float(np.median(list(bias.values()))),
            "radial_spread_med": float(np.median(spread)),
            "tangential_med": _med(c["tangential"][use])}


def summarise(rows: dict[str, dict[str, np.ndarray]]) -> dict:
    """Per method row of the headline table (numbers, None where there are none)."""
    out = {}
    for name, c in rows.items():
        flips = c["yaw"] > FLIP_DEG
        # parked: the annotated centre travels < PARKED_M in the ego poses' fixed frame
        # (evaluate's world_travel_m; NaN: unknown, neither group)
        with np.errstate(invalid="ignore"):
            mov, par = c["travel"] >= PARKED_M, c["travel"] < PARKED_M
        out[name] = {
            "frames": len(c["centre"]), "centre_med": _med(c["centre"]),
            "centre_mean": _mean(c["centre"]), "centre_max": float(np.nanmax(c["centre"])),
            "radial_med": _med(c["radial"]), "yaw_med": _med(c["yaw"]),
            "flip_pct": 100.0 * float(flips.mean()),
            "flip_moving_pct": 100.0 * float(flips[mov].mean()) if mov.any() else None,
            "flip_parked_pct": 100.0 * float(flips[par].mean()) if par.any() else None,
            "length_med": _med(c["length"]), "width_med": _med(c["width"]),
            "cd_mean": _mean(c["cd"]),
            "bins": [_med(c["centre"][_in_bin(c["n_det"], lo, hi)]) for lo, hi in BINS],
            "range_radial": [_med(c["radial"][_in_range(c["distance"], lo, hi)])
                             for lo, hi in RANGES],
            "range_frames": [int(_in_range(c["distance"], lo, hi).sum()) for lo, hi in RANGES],
            "bin_frames": [int(_in_bin(c["n_det"], lo, hi).sum()) for lo, hi in BINS],
            "from9_med": _med(c["centre"][c["n_det"] >= 9]),
            **_bias_split(c, c["n_det"] >= 9),
            "car_frames": int((c["cls"] == "car").sum()),
            "car_centre_med": _med(c["centre"][c["cls"] == "car"]),
            "larger_centre_med": _med(c["centre"][(c["cls"] != "car") & (c["cls"] != "")]),
        }
    return out


def run_source(name: str, dataset: str, root: Path, work: Path, args) -> dict | None:
    data = work / "tracks"
    if not (args.reuse and (data / "manifest.json").exists()):
        extract(dataset, root, data, args.sequence, "log", args.ego_poses)
    rows: dict[str, dict[str, np.ndarray]] = {}
    for mode in args.modes:
        per_frame = evaluate(data, work / f"eval_{mode}", args.checkpoint, "all",
                             args.baseline, args.refiner, mode, args.reuse,
                             args.baseline_refiner, args.size_scale, args.backend,
                             args.track_memory)
        frames = read_frames(per_frame)
        if mode == args.modes[0]:
            print_size_scale(name, per_frame.parent / "metrics.json")
        rows[f"sequential {mode}"] = frames["sequential"]
        if mode == args.modes[0]:  # the baseline and the box fit do not change with the mode
            for m in ("baseline", "boxfit"):
                if m in frames:
                    rows[m] = frames[m]
    return summarise(rows)


def print_size_scale(name: str, metrics: Path) -> None:
    """The size scales ``seqshape evaluate --size-scale`` used (its settings), if any."""
    try:
        scales = json.loads(metrics.read_text()).get("settings", {}).get("size_scale")
    except (OSError, ValueError):
        return
    for method, cal in (scales or {}).items():
        if isinstance(cal, dict):
            print(f"{name}: {method} size scale {cal['scale']:.3f} (car length seen whole "
                  f"{_f(cal['length'], 3)} m on {cal['tracks']} tracks, {cal['frames']} "
                  f"frames; prior {cal['prior']:.3f} m){' - ' + cal['reason'] if cal['reason'] else ''}")
        else:
            print(f"{name}: {method} size scale {cal}")


def print_source(name: str, s: dict) -> None:
    print(f"\n### {name}\n")
    print_table(["method", "frames", "centre med", "centre mean", "centre max", "radial med",
                 "yaw med", "flips % (moving / parked)", "|length| med", "|width| med",
                 "CD vs ref mean"],
                [[m, v["frames"], _f(v["centre_med"]), _f(v["centre_mean"]),
                  _f(v["centre_max"]), _f(v["radial_med"]), _f(v["yaw_med"]),
                  f'{_f(v["flip_pct"])} ({_f(v["flip_moving_pct"])} / '
                  f'{_f(v["flip_parked_pct"])})', _f(v["length_med"]), _f(v["width_med"]),
                  _f(v["cd_mean"])] for m, v in s.items()])
    print(f"\nmedian centre error (cm), cars / larger vehicles ({name}): " + "; ".join(
        f"{m} {_f(v['car_centre_med'])} / {_f(v['larger_centre_med'])}" for m, v in s.items()))
    labels = [f"{lo}" if lo == hi else (f"{lo}+" if hi is None else f"{lo}-{hi}")
              for lo, hi in BINS]
    print(f"\nmedian centre error (cm) by detections so far ({name}; frames in brackets)\n")
    print_table(["method"] + labels,
                [[m] + [f"{_f(b)} ({n})" for b, n in zip(v["bins"], v["bin_frames"],
                                                        strict=True)]
                 for m, v in s.items()])
    print(f"\nmedian radial error (cm, + = too far from the sensor) by range ({name}; "
          f"frames in brackets)\n")
    print_table(["method"] + [f"{lo:.0f}-{hi:.0f} m" if hi else f"{lo:.0f}+ m"
                              for lo, hi in RANGES],
                [[m] + [f"{_f(b)} ({n})" for b, n in zip(v["range_radial"], v["range_frames"],
                                                        strict=True)]
                 for m, v in s.items()])
    print(f"\nfrom the 9th detection ({name}): each track's radial bias (median over tracks), "
          f"the frames' radial error about it and their |tangential| error (medians, cm); "
          f"fusion can only remove the last two\n")
    print_table(["method", "track radial bias", "radial about the bias", "\\|tangential\\|"],
                [[m, _f(v["track_bias_med"]), _f(v["radial_spread_med"]),
                  _f(v["tangential_med"])] for m, v in s.items()])
    base = s.get("baseline", {}).get("from9_med")
    ratios = [f"{m.split()[1]} {v['from9_med'] / base:.2f}x" for m, v in s.items()
              if m.startswith("sequential") and base and v["from9_med"] is not None]
    if ratios:
        print(f"\nfusion (median centre error from the 9th detection, sequential / baseline): "
              f"{', '.join(ratios)}")


def parse_sources(args) -> list[tuple[str, str, Path]]:
    out = []
    for spec in args.source or ():
        name, sep, rest = spec.partition("=")
        dataset, sep2, root = rest.partition(":")
        if not (sep and sep2 and name and dataset and root):
            sys.exit(f"--source {spec!r}: expected NAME=DATASET:ROOT")
        out.append((name, dataset, Path(root)))
    if args.root is not None:
        out.append((args.dataset, args.dataset, args.root))
    return out


def finetune(dataset: str, root: Path, work: Path, args) -> None:
    """Fine-tune the sequential model on the logs' own references (stage 3), split by track,
    and print the tables before and after, on held-out vehicles and on all."""
    extract(dataset, root, work / "ft_tracks", args.sequence, "track", args.ego_poses)
    train_data = work / "ft_tracks"
    if args.finetune_labels == "pseudo":  # the log's annotations are never read for training
        train_data = work / "ft_pseudo"
        if not (train_data / "manifest.json").exists() and _quiet(
                ["pseudo-label", "--data", str(work / "ft_tracks"), "--out", str(train_data),
                 "--checkpoint", args.checkpoint, "--refiner", args.refiner]) != 0:
            sys.exit("pseudo-labelling failed")
    run = work / f"ft_run_{args.finetune_labels}"
    if _quiet(["train", "--data", str(train_data), "--model", "sequential", "--init",
               args.checkpoint, "--stage-steps", f"0,0,{args.finetune_steps}", "--lr", "2e-4",
               "--no-tensorboard", "--threads", "1", "--out", str(run)]) != 0:
        sys.exit("fine-tuning failed")
    for split in ("val", "all"):
        rows = {}
        for label, ckpt in (("before", args.checkpoint), ("after", str(run / "model.pt"))):
            out = work / (f"ft_eval_{split}_{label}" if label == "before" else
                          f"ft_eval_{split}_{label}_{args.finetune_labels}")
            frames = read_frames(evaluate(work / "ft_tracks", out,
                                          ckpt, split, args.baseline, args.refiner,
                                          baseline_refiner=args.baseline_refiner))
            rows[f"sequential {label}"] = frames["sequential"]
            rows.setdefault("baseline", frames["baseline"])
        print_source(f"fine-tuning, {'held-out vehicles' if split == 'val' else 'all vehicles'}",
                     summarise(rows))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", action="append", default=None, metavar="NAME=DATASET:ROOT",
                    help="a real source (repeatable): a name, a reader (kitti, av2, nuscenes) "
                         "and its dataset folder")
    ap.add_argument("--dataset", default="av2", help="reader of --root: kitti, av2, nuscenes")
    ap.add_argument("--root", type=Path, default=None, help="one dataset folder (real data)")
    ap.add_argument("--sequence", action="append", default=None, help="log(s); default all")
    ap.add_argument("--out", type=Path, default=None, help="work folder (default: temporary)")
    ap.add_argument("--reuse", action="store_true",
                    help="keep what --out already holds (tracks, evaluations)")
    ap.add_argument("--modes", default=",".join(MODES),
                    help=f"sequential modes to evaluate, comma-separated from {MODES}")
    ap.add_argument("--checkpoint", default="pretrained", help="sequential model to evaluate")
    ap.add_argument("--baseline", default="pretrained", help="baseline model to evaluate")
    ap.add_argument("--refiner", default="pretrained",
                    help="placement refiner of both networks: a file, 'pretrained' or 'none'")
    ap.add_argument("--baseline-refiner", default="same",
                    help="the baseline's own refiner when not --refiner's ('same'): a file, "
                         "'pretrained' or 'none'")
    ap.add_argument("--ego-poses", default="given", choices=("given", "lidar"),
                    help="the tracks' ego poses (seqshape tracks --ego-poses): the logs' own "
                         "or LiDAR odometry of their sweeps")
    ap.add_argument("--backend", default=None,
                    help="seqshape evaluate --backend (default: evaluate's own, auto-float); "
                         "e.g. onnx-int8 for the streaming engine's int8 graphs")
    ap.add_argument("--size-scale", default="1",
                    help="seqshape evaluate --size-scale: a number, or 'auto' (each network's "
                         "scale calibrated on the source's own tracks, without labels)")
    ap.add_argument("--track-memory", default="auto", choices=("auto", "none", "parked"),
                    help="seqshape evaluate --track-memory of the online and causal modes "
                         "(auto: the model's default, 'parked')")
    ap.add_argument("--finetune-labels", default="annotations",
                    choices=("annotations", "pseudo"),
                    help="what --finetune-steps tunes on: the log's annotated references, or "
                         "pseudo-labels (`seqshape pseudo-label`: the model's own offline "
                         "estimates and accumulations; self-supervised)")
    ap.add_argument("--finetune-steps", type=int, default=0,
                    help="also fine-tune the sequential model this many stage-3 steps on the "
                         "logs' own references and evaluate again (0: no)")
    args = ap.parse_args()
    args.modes = [m for m in args.modes.split(",") if m]
    if not args.modes or set(args.modes) - set(MODES):
        sys.exit(f"--modes must be a comma-separated list of {MODES}")
    sources = parse_sources(args)
    if not sources:
        print("bm_realdata: no --source or --root given; real data is not part of the "
              "repository, so there is nothing to measure (see the docstring for the command)")
        return 0
    work = args.out or Path(tempfile.mkdtemp(prefix="bm_realdata_"))
    summary = {}
    for name, dataset, root in sources:
        summary[name] = run_source(name, dataset, root, work / name, args)
        print_source(f"{name} ({dataset}: {args.checkpoint} / {args.baseline} weights, "
                     f"refiner {args.refiner}"
                     + (f", baseline's {args.baseline_refiner}"
                        if args.baseline_refiner != "same" else "") + ")", summary[name])
        if args.finetune_steps > 0:
            finetune(dataset, root, work / name, args)
    (work / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"\nwork folder: {work} (summary.json holds the numbers)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
