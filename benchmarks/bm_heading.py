"""Heading post-processing variants: 180-degree flips of both networks per HeadingConfig.

Scores the sequential model and the baseline (shipped weights or ``--checkpoint`` /
``--baseline``, with the shipped refiner and the hints as ``seqshape evaluate`` gives them)
on one split of a dataset under each heading configuration: motion only (the default before
2026-12-05), and the track vote at decays 0.8, 0.95 (the default since) and 0.99. A flip is
a rotation error above 150 degrees (``report.FLIP_DEG``); CD and translation do not depend
on the heading step (a flip keeps the placed shape), so only flips and rotation are printed.
The table of docs/model.md ("The vote, long memory, by default") came from this script.

Run: ``python benchmarks/bm_heading.py --data DATA [--split val|train|all]
[--checkpoint pretrained] [--baseline pretrained]``
"""

from __future__ import annotations

import argparse

import numpy as np
from _bench import print_table

from seqshape.data.dataset import TrackDataset
from seqshape.evaluation.evaluate import EvaluateConfig, build_estimators, select_split
from seqshape.evaluation.report import FLIP_DEG
from seqshape.evaluation.runner import evaluate_tracks
from seqshape.model.heading import HeadingConfig

VARIANTS = {"motion only": HeadingConfig(vote=False),
            "vote, decay 0.8": HeadingConfig(vote_decay=0.8),
            "vote, decay 0.95 (default)": HeadingConfig(),
            "vote, decay 0.99": HeadingConfig(vote_decay=0.99)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="track dataset folder")
    ap.add_argument("--split", default="val", help="split to score: val, train or all")
    ap.add_argument("--checkpoint", default="pretrained", help="sequential model")
    ap.add_argument("--baseline", default="pretrained", help="baseline model")
    args = ap.parse_args()
    ds = select_split(TrackDataset(args.data), args.split)
    cfg = EvaluateConfig(split=args.split, emd_every=0, view="none", workers=0)
    rows = []
    for name, heading in VARIANTS.items():
        estimators = build_estimators(args.checkpoint, args.baseline, ds, cfg)
        for est in estimators.values():
            est.heading = heading
        rec = evaluate_tracks(estimators, ds, emd_every=0, workers=0).records
        row = [name]
        for method in ("sequential", "baseline"):
            sel = rec["method"] == method
            rot = np.degrees(np.abs(rec["rot_rad"][sel]))
            flipped = rot > FLIP_DEG
            row += [f"{100 * flipped.mean():.2f} % ({len(set(rec['track_id'][sel][flipped]))})",
                    f"{rot.mean():.2f}"]
        rows.append(row)
    print_table(["heading", "sequential flips (tracks)", "seq. rotation (deg)",
                 "baseline flips (tracks)", "base. rotation (deg)"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
