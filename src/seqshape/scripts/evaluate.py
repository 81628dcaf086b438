"""``seqshape evaluate``: score the sequential model beside the per-frame baseline.

The work is :func:`seqshape.evaluation.evaluate.evaluate_dataset` (outputs, real datasets and
the offline mode are described there and in docs/evaluation.md); the options are the fields of
:class:`~seqshape.evaluation.evaluate.EvaluateConfig`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import seqshape.evaluation.evaluate as _evaluate
from seqshape._deprecated import forward
from seqshape.evaluation.evaluate import TRACK_MEMORY_CHOICES, EvaluateConfig, evaluate_dataset
from seqshape.evaluation.report import metrics_markdown
from seqshape.model.engine import BACKENDS
from seqshape.model.estimator import SMOOTHING
from seqshape.scripts._config_args import add_config_arguments, config_kwargs

HELP = "evaluate shape and pose estimates on a dataset's val split (or a real dataset)"
FIELDS = ["split", "boxfit", "boxfit_method", "max_tracks", "emd_every", "emd_points", "workers",
          "batch_tracks", "floor", "view", "seed", "offline", "hints", "backend",
          "refiner", "baseline_refiner", "max_points", "smoothing", "size_scale", "track_memory"]
_MOVED = ("load_estimator", "select_split", "dataset_is_real", "choose_view_track",
          "evaluate_to", "mode_note")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, type=Path, help="track dataset folder")
    parser.add_argument("--checkpoint", required=True,
                        help="sequential model: a checkpoint / model.pt path, or 'pretrained' "
                             "for the shipped weights")
    parser.add_argument("--baseline", default="pretrained",
                        help="per-frame baseline: a path or 'pretrained' (default)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    add_config_arguments(parser, EvaluateConfig, FIELDS,
                         boxfit_method={"choices": ("lshape", "min_area_rect")},
                         floor={"choices": ("auto", "resample", "split")},
                         backend={"choices": BACKENDS},
                         smoothing={"choices": SMOOTHING},
                         track_memory={"choices": TRACK_MEMORY_CHOICES})


def run(args: argparse.Namespace) -> int:
    cfg = EvaluateConfig(**config_kwargs(args, FIELDS))
    summary = evaluate_dataset(args.data, args.checkpoint, args.baseline, args.out, cfg)
    print(metrics_markdown(summary)
          + f"- Mode: sequential {'offline' if args.offline else 'online'}.")
    print(f"wrote {args.out}/metrics.json, metrics.md, per_frame.csv, plots"
          f"{', track_view.html' if args.view != 'none' else ''}")
    return 0


__getattr__ = forward(__name__, _evaluate, _MOVED)  # moved names, for one release
