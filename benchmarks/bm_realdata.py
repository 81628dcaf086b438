"""The shipped models on real annotated LiDAR: ``seqshape tracks`` then ``seqshape evaluate``.

Extracts the vehicle tracks of one or more real logs (any reader of ``seqshape.data``), runs the
sequential model, the per-frame baseline and the classical box fit over them, and prints the
tables the real-data issues are judged by: centre error (median and mean, and its signed radial
part: positive = too far from the sensor), yaw error with and without 180-degree flips, the
flip rate, length and width errors of the estimated extents, the CD against the accumulated
reference and its one-way reference->estimate half, and the share of each frame's points left
outside the box on the sensor's side and beyond it, for the estimate and for the annotation
(the annotation's share behind its box tells whether it encloses the cars' own points; the
estimates' shares compare the methods, docs/evaluation.md); cars and larger vehicles separately, and
the centre error by points per frame. The rows "box fits its points" and "box off its points"
split the frames by whether the annotated box's faces seen head-on lie within 0.15 m of the
frame's points (``ref_face_gap_m``, docs/evaluation.md): on the second kind every method is
scored against a box that does not hold its own vehicle. With ``--finetune-steps N`` it also fine-tunes the
sequential model on the logs' own references (``seqshape train --init pretrained``, stage 3
only) and prints the same tables after, on held-out vehicles (``--split-by track``) and on all.

    python benchmarks/bm_realdata.py --dataset av2 --root ../shared/realdata/av2/sensor/val
    python benchmarks/bm_realdata.py --dataset av2 --root ROOT --finetune-steps 300
    python benchmarks/bm_realdata.py --dataset av2 --root ROOT --refiner none  # the networks alone

Without ``--root`` there is nothing to measure: the script says so and exits 0 (real data is
never part of the repository). Timing is not the point here; ``bm_tracks.py`` times extraction.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path

from _bench import print_table

from seqshape.cli import main as seqshape_main

METHODS = ("sequential", "baseline", "boxfit")


def _f(v, digits: int = 1) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def _quiet(argv: list[str]) -> int:
    """``seqshape ARGV`` with its printed report swallowed (the tables below say it shorter)."""
    with contextlib.redirect_stdout(io.StringIO()):
        return seqshape_main(argv)


def extract(dataset: str, root: Path, out: Path, sequences, split_by: str) -> None:
    argv = ["tracks", "--dataset", dataset, "--root", str(root), "--out", str(out),
            "--split-by", split_by, "--val-fraction", "0.3" if split_by == "track" else "0"]
    for s in sequences or ():
        argv += ["--sequence", s]
    if split_by == "log":
        argv += ["--split", "val"]
    if _quiet(argv) != 0:
        sys.exit(f"seqshape tracks failed on {root}")


def evaluate(data: Path, out: Path, checkpoint: str, split: str,
             baseline: str = "pretrained", refiner: str = "pretrained") -> dict:
    if _quiet(["evaluate", "--data", str(data), "--checkpoint", checkpoint, "--out", str(out),
               "--baseline", baseline, "--refiner", refiner,
               "--split", split, "--workers", "1", "--emd-every", "0", "--view", "none"]) != 0:
        sys.exit(f"seqshape evaluate failed on {data}")
    return json.loads((out / "metrics.json").read_text())


def tables(metrics: dict, title: str) -> None:
    print(f"\n### {title}\n")
    b = metrics["breakdown"]
    groups = ([("all", b["all"]["all"])] + sorted(b["class_group"].items())
              + list(b.get("annotation", {}).items()) + list(b.get("face_gap", {}).items()))
    rows = []
    for name, g in groups:
        for m in METHODS:
            s = g.get(m)
            if not s:
                continue
            rows.append([name, m, s["n_frames"], _f(s["centre_cm_median"]),
                         _f(s["centre_cm_mean"]), _f(s["radial_cm_median"]),
                         _f(s["rot_deg_median"]), _f(s["rot_deg_without_flips_median"]),
                         _f(s["flip_pct"]), _f(s["length_abs_cm_median"]),
                         _f(s.get("length_rel_abs_pct_median")),
                         _f(s["width_abs_cm_median"]), _f(s.get("cd_cm_mean")),
                         _f(s.get("ref_to_est_cm_mean")),
                         f'{_f(s.get("est_near_out_pct_mean"))} / {_f(s.get("est_far_out_pct_mean"))}',
                         f'{_f(s.get("ref_near_out_pct_mean"))} / {_f(s.get("ref_far_out_pct_mean"))}'])
    print_table(["group", "method", "frames", "centre med", "centre mean", "radial med",
                 "yaw med", "yaw w/o flips med", "flips %", "|length| med", "|length| % med",
                 "|width| med",
                 "CD vs ref mean", "ref->est mean", "points out near / far % (estimate)",
                 "(annotation)"], rows)
    print("\ncentre error (cm, median) by points per frame\n")
    pts = b["points"]
    keys = [k for k in pts if any(pts[k].get(m) for m in METHODS)]
    rows = [[m] + [f"{_f(pts[k][m]['centre_cm_median'])} ({pts[k][m]['n_frames']})"
                   if pts[k].get(m) else "-" for k in keys] for m in METHODS]
    print_table(["method"] + keys, rows)
    for m in METHODS:  # the share of the classical fit's flips is part of the picture
        d = metrics["details"][m]
        print(f"- {m}: {d['rot_flip_frames']} flipped frames of {d['n_frames']}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="av2", help="reader: kitti, av2, nuscenes")
    ap.add_argument("--root", type=Path, default=None, help="dataset folder (real data)")
    ap.add_argument("--sequence", action="append", default=None, help="log(s); default all")
    ap.add_argument("--out", type=Path, default=None, help="work folder (default: temporary)")
    ap.add_argument("--checkpoint", default="pretrained", help="sequential model to evaluate")
    ap.add_argument("--baseline", default="pretrained", help="baseline model to evaluate")
    ap.add_argument("--refiner", default="pretrained",
                    help="placement refiner of both networks: a file, 'pretrained' or 'none'")
    ap.add_argument("--finetune-steps", type=int, default=0,
                    help="also fine-tune the sequential model this many stage-3 steps on the "
                         "logs' own references and evaluate again (0: no)")
    args = ap.parse_args()
    if args.root is None:
        print("bm_realdata: no --root given; real data is not part of the repository, so there "
              "is nothing to measure (see the docstring for the command)")
        return 0
    work = args.out or Path(tempfile.mkdtemp(prefix="bm_realdata_"))
    extract(args.dataset, args.root, work / "tracks", args.sequence, "log")
    tables(evaluate(work / "tracks", work / "eval", args.checkpoint, "all", args.baseline,
                    args.refiner),
           f"{args.dataset}: {args.checkpoint} / {args.baseline} weights, refiner "
           f"{args.refiner}, all frames")
    if args.finetune_steps > 0:
        extract(args.dataset, args.root, work / "ft_tracks", args.sequence, "track")
        run = work / "ft_run"
        if _quiet(["train", "--data", str(work / "ft_tracks"), "--model", "sequential", "--init",
                args.checkpoint, "--stage-steps", f"0,0,{args.finetune_steps}", "--lr", "2e-4",
                "--no-tensorboard", "--threads", "1", "--out", str(run)]) != 0:
            sys.exit("fine-tuning failed")
        for split in ("val", "all"):
            for name, ckpt in (("before", args.checkpoint), ("after", str(run / "model.pt"))):
                m = evaluate(work / "ft_tracks", work / f"ft_eval_{split}_{name}", ckpt, split,
                             refiner=args.refiner)
                tables(m, f"fine-tuning {name}, {'held-out vehicles' if split == 'val' else 'all vehicles (as the paper: the data to label)'}")
    print(f"\nwork folder: {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
