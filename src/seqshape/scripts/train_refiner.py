"""``seqshape train-refiner``: train the placement refiner on the networks' own estimates.

The work is :mod:`seqshape.train.refiner` (what is collected, the augmentation, the loss,
checkpoints); docs/model.md, "Placement refinement", has the recipe of the shipped refiner and
its figures. The frames each network's estimates give are cached in ``OUT/frames/`` (a rerun
or ``--resume`` reads them instead of estimating again).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from seqshape.data import TrackDataset
from seqshape.errors import ConfigError
from seqshape.model.estimator import Estimator
from seqshape.model.placement import load_refiner
from seqshape.scripts._config_args import add_config_arguments, config_kwargs
from seqshape.train.refiner import (
    RefinerTrainConfig,
    collect_frames,
    concat_frames,
    describe,
    load_frames,
    save_frames,
    train_refiner,
)

HELP = "train the placement refiner on the networks' own estimates"
FIELDS = ["steps", "batch", "lr", "jitter", "max_error", "minutes", "checkpoint_every", "seed",
          "threads", "size"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, nargs="+", type=Path,
                        help="track dataset folders (their train split trains, their val split "
                             "checks)")
    parser.add_argument("--every", nargs="+", type=int, default=[1],
                        help="use every K-th track of each --data folder (one K for all, or "
                             "one per folder)")
    parser.add_argument("--checkpoint", default="pretrained",
                        help="sequential model whose estimates are refined: a path or "
                             "'pretrained'")
    parser.add_argument("--baseline", default="pretrained",
                        help="per-frame baseline whose estimates are refined too: a path, "
                             "'pretrained' or 'none'")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--resume", action="store_true",
                        help="continue from OUT/refiner.ckpt (the same options)")
    parser.add_argument("--init", default="none",
                        help="start from this refiner's weights: 'pretrained', a refiner file "
                             "or 'none' (a size head added by --size starts at 0)")
    add_config_arguments(parser, RefinerTrainConfig, FIELDS)


def run(args: argparse.Namespace) -> int:
    cfg = RefinerTrainConfig(**config_kwargs(args, FIELDS))
    every = args.every if len(args.every) == len(args.data) else args.every[:1] * len(args.data)
    if len(args.every) not in (1, len(args.data)):
        raise ConfigError(f"--every: give one value or one per --data folder ({len(args.data)})")
    models = {"sequential": args.checkpoint}
    if args.baseline != "none":
        models["baseline"] = args.baseline
    cache = args.out / "frames"
    cache.mkdir(parents=True, exist_ok=True)
    train, val = [], {}
    for i, (data, k) in enumerate(zip(args.data, every, strict=True)):
        ds = TrackDataset(data)
        for kind, spec in models.items():
            est = None
            for split in ("train", "val"):
                tag = f"_every{k}" if split == "train" else ""
                path = cache / f"{i}_{data.name}_{kind}_{split}{tag}.npz"
                if path.exists():
                    frames = load_frames(path)
                else:
                    if est is None:
                        est = Estimator.load(kind if spec == "pretrained" else spec, kind=kind,
                                             threads=cfg.threads, backend="torch",
                                             refiner="none")  # the networks' own estimates
                    frames = collect_frames(est, ds.split(split), k if split == "train" else 1,
                                            seed=cfg.seed, desc=f"{data.name} {split} {kind}")
                    save_frames(path, frames)
                if split == "train":
                    train.append(frames)
                elif len(frames["n"]):
                    val[f"{data.name} val, {kind}"] = frames
    meta = {"data": [str(d) for d in args.data], "every": every, "models": models}
    init = load_refiner(args.init)
    if init is not None:
        meta["init"] = args.init
    refiner = train_refiner(concat_frames(train), val, args.out, cfg, args.resume, meta, init)
    print(describe(refiner.meta["val"]))
    print(f"wrote {args.out / 'refiner.pt'} (use it with --refiner {args.out / 'refiner.pt'})")
    return 0
