"""The placement refiner frame by frame: each network's own online estimates before and after it.

For every track of a dataset folder (a split of a synthetic set, or the tracks ``seqshape
tracks`` / ``bm_realdata.py`` extracted from a real log), both shipped networks (or
``--checkpoint`` / ``--baseline``) estimate the track online as ``Estimator`` does, with the
class and ego-pose hints (:func:`seqshape.train.refiner.collect_frames`); each refiner of
``--refiners`` then corrects those same estimates. Printed per network, class group (cars,
larger vehicles) and refiner: frames, median and mean bird's-eye centre error, median signed
radial error (positive: too far from the sensor), median error of the heading axis (modulo
180 degrees). ``seqshape evaluate --refiner`` gives the full metrics; this isolates the
refiner's own effect on identical estimates, and compares refiner files (e.g. checkpoints of
one training) cheaply: the estimates are computed once.

    python benchmarks/bm_refiner.py --data TRAFFIC --split all --refiners pretrained
    python benchmarks/bm_refiner.py --data AV2_TRACKS --split all --refiners pretrained OUT/refiner.pt
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools

import numpy as np
from _bench import print_table

from seqshape.data.dataset import TrackDataset
from seqshape.model.estimator import Estimator
from seqshape.model.placement import RefinerConfig, load_refiner, targets
from seqshape.scripts._config_args import add_config_arguments, config_kwargs
from seqshape.train.refiner import collect_frames, frame_points

#: The RefinerConfig fields of further passes that the options set (default: the shipped ones).
PASS_FIELDS = ("iterations", "repeat_shift", "repeat_min_points", "repeat_min_length", "points")


def _row(frames: dict, poses: np.ndarray, mask: np.ndarray) -> list[str]:
    err = poses[mask, :2] - frames["true"][mask, :2]
    truth = frames["true"][mask, :2]
    radial = np.sum(err * truth / np.linalg.norm(truth, axis=1, keepdims=True), axis=1)
    axis = np.degrees(np.abs(targets(poses[mask], frames["true"][mask])[:, 3]))
    dist = np.hypot(err[:, 0], err[:, 1])
    return [f"{100 * np.median(dist):.1f}", f"{100 * np.mean(dist):.1f}",
            f"{100 * np.median(radial):+.1f}", f"{np.median(axis):.2f}"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="track dataset folder")
    ap.add_argument("--split", default="val", help="split ('all': every track)")
    ap.add_argument("--every", type=int, default=1, help="every K-th track")
    ap.add_argument("--checkpoint", default="sequential")
    ap.add_argument("--baseline", default="baseline")
    ap.add_argument("--refiners", nargs="+", default=["pretrained"],
                    help="'pretrained' and/or refiner files")
    add_config_arguments(ap, RefinerConfig, list(PASS_FIELDS), iterations={"nargs": "+"},
                         points={"nargs": "+"})
    args = ap.parse_args()
    ds = TrackDataset(args.data)
    ds = ds if args.split == "all" else ds.split(args.split)
    shipped = RefinerConfig()
    iterations = args.iterations if isinstance(args.iterations, list) else [args.iterations]
    counts = args.points if isinstance(args.points, list) else [args.points]
    refiners = {}
    for spec in args.refiners:
        for it, n in itertools.product(iterations, counts):
            cfg = dataclasses.replace(shipped, **{**config_kwargs(args, PASS_FIELDS),
                                                  "iterations": it, "points": n})
            name = spec if cfg == shipped else f"{spec} " + " ".join(
                f"{k}={getattr(cfg, k)}" for k in PASS_FIELDS if getattr(cfg, k) != getattr(
                    shipped, k))
            refiners[name] = load_refiner(spec, cfg)
    rows = []
    for kind, spec in (("sequential", args.checkpoint), ("baseline", args.baseline)):
        est = Estimator.load(spec, kind=kind, threads=1, backend="torch", refiner="none")
        frames = collect_frames(est, ds, args.every, desc=kind)
        n = len(frames["n"])
        if not n:
            continue
        pts = [frame_points(frames, i) for i in range(n)]
        refined = {spec: r.refine_poses(pts, frames["est"], frames["ext"], seeds=list(range(n)))
                   for spec, r in refiners.items()}
        groups = (("cars", frames["cls"] == "car"), ("larger", frames["cls"] != "car"))
        for group, mask in groups:
            if not mask.any():
                continue
            rows.append([kind, group, int(mask.sum()), "none", *_row(frames, frames["est"],
                                                                    mask)])
            for spec, poses in refined.items():
                rows.append([kind, group, int(mask.sum()), spec, *_row(frames, poses, mask)])
    print_table(["network", "vehicles", "frames", "refiner", "centre med (cm)",
                 "centre mean (cm)", "radial med (cm)", "axis med (deg)"], rows)


if __name__ == "__main__":
    main()
