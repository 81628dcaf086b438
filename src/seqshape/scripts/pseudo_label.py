"""``seqshape pseudo-label``: label a track dataset with the models' own offline estimates.

For self-supervised fine-tuning on a user's own log (no annotations needed): every track of
``--data`` (a ``seqshape tracks`` output, or any track dataset) gets its poses from the
sequential model offline, its size from the estimated extents and its complete shape from its
own points accumulated in those boxes (:mod:`seqshape.train.pseudo`). Then
``seqshape train --data OUT --out RUN --init pretrained --stage-steps 0,0,300 --lr 2e-4``
fine-tunes on them (docs/how-to/fine-tune.md).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from seqshape.data import TrackDataset
from seqshape.data.dataset import write_dataset
from seqshape.data.reference import MIN_POINTS
from seqshape.errors import ConfigError, DataError
from seqshape.model.estimator import Estimator
from seqshape.train.pseudo import pseudo_label

HELP = ("label a track dataset with the sequential model's offline estimates and its own "
        "accumulated points, for self-supervised fine-tuning")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, type=Path,
                        help="track dataset folder to label (its own labels are not used)")
    parser.add_argument("--out", required=True, type=Path,
                        help="new track dataset folder for the pseudo-labelled tracks")
    parser.add_argument("--checkpoint", default="pretrained",
                        help="sequential model that estimates: a path or 'pretrained'")
    parser.add_argument("--refiner", default="pretrained",
                        help="its placement refiner: a file, 'pretrained' or 'none'")
    parser.add_argument("--split", default="all", choices=("all", "train", "val"),
                        help="label only this split of --data (default: %(default)s, "
                             "every track)")
    parser.add_argument("--threads", type=int, default=None,
                        help="intra-op threads (default: %(default)s, the estimator's choice)")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out} exists and is not empty; give a new folder for the "
                          f"pseudo-labelled tracks")
    ds = TrackDataset(args.data)
    if args.split != "all":
        ds = ds.split(args.split)
    est = Estimator.load(args.checkpoint, kind="sequential", threads=args.threads,
                         refiner=args.refiner)
    tracks = pseudo_label((ds[i] for i in range(len(ds))), est,
                          source=f"{args.checkpoint} + refiner {args.refiner}")
    shaped = [tr for tr in tracks if tr.complete is not None]
    if not shaped:
        raise DataError(args.data, f"none of its {len(tracks)} tracks has {MIN_POINTS} points "
                                   f"inside its estimated boxes: nothing to fine-tune on")
    # written next to OUT and renamed when complete: an interrupted run leaves no half dataset
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    write_dataset(partial, shaped, {"pseudo_label": {
        "data": str(args.data), "split": args.split, "checkpoint": str(args.checkpoint),
        "refiner": str(args.refiner), "left_out": [tr.track_id for tr in tracks
                                                   if tr.complete is None]}})
    if out.exists():
        out.rmdir()  # empty (checked above)
    partial.rename(out)
    left = len(tracks) - len(shaped)
    print(f"wrote {len(shaped)} pseudo-labelled tracks to {out}"
          + (f" ({left} left out: too few points inside their estimated boxes for a shape)"
             if left else "")
          + f"; fine-tune with `seqshape train --data {out} --out RUN --init "
            f"{args.checkpoint} --stage-steps 0,0,300 --lr 2e-4`")
    return 0
