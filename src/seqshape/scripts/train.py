"""``seqshape train``: the three-stage training of the sequential model or the baseline.

Examples::

    seqshape train --data data/paper --model sequential --preset small --out runs/seq
    seqshape train --data data/paper --model baseline --out runs/base --time-budget-min 35
    seqshape train --data data/paper --out runs/seq --resume          # after a kill
    seqshape train --data TRACKS --out runs/ft --init pretrained --stage-steps 0,0,300 \
        --lr 2e-4                                                    # joint-only fine-tune
    torchrun --nproc_per_node 2 -m seqshape.cli train --data ... --out ...   # data-parallel
"""

from __future__ import annotations

import argparse
import dataclasses
import json

from seqshape.errors import ConfigError
from seqshape.train.config import get_train_config
from seqshape.train.trainer import Trainer

HELP = "train the sequential model or the per-frame baseline (3 stages, resumable)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, nargs="+",
                        help="track dataset folder(s) (train/val splits); several folders are "
                             "trained on as one dataset (e.g. the paper preset and a real one)")
    parser.add_argument("--data-fraction", type=float, nargs="+", default=None, metavar="F",
                        help="with several --data folders: the share of each folder's tracks "
                             "to use, one value per folder in (0, 1] (chosen by a stable hash "
                             "of the track id), to balance a large dataset against a small one "
                             "(default: all tracks of every folder)")
    parser.add_argument("--out", required=True, help="run folder (checkpoints, logs, model.pt)")
    parser.add_argument("--model", choices=("sequential", "baseline"), default="sequential",
                        help="the recurrent model or the per-frame baseline")
    parser.add_argument("--preset", default="small",
                        help="training preset: small (2 CPU cores), paper (GPU), smoke (tests)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last checkpoint")
    parser.add_argument("--init", default=None, metavar="CHECKPOINT|pretrained",
                        help="start from these weights (a model.pt, a training checkpoint, or "
                             "'pretrained' = the shipped weights of --model) instead of random "
                             "ones; kind and model config must match; stages with 0 steps "
                             "(--stage-steps 0,0,N) are skipped (default: random weights)")
    parser.add_argument("--seed", type=int, default=None, help="seed (default: the preset's)")
    parser.add_argument("--stage-steps", default=None, metavar="A,B,C",
                        help="optimiser steps of stages 1,2,3 (upper bounds with a time budget; "
                             "default: the preset's)")
    parser.add_argument("--time-budget-min", type=float, default=None,
                        help="total wall-clock minutes, split 45/15/40%% over the stages "
                             "(a budget-limited run is not bit-reproducible; default: no budget)")
    parser.add_argument("--stage-budget-min", default=None, metavar="A,B,C",
                        help="wall-clock minutes per stage (overrides --time-budget-min; "
                             "default: no budget)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="windows per step (default: the preset's)")
    parser.add_argument("--window", type=int, default=None,
                        help="frames per window (default: the preset's)")
    parser.add_argument("--lr", type=float, default=None,
                        help="learning rate of stages 1 and 2 (stage 3 uses half; default: the "
                             "preset's)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads per process (default: the preset's)")
    parser.add_argument("--val-every", type=int, default=None,
                        help="validate every N steps (default: the preset's)")
    parser.add_argument("--ckpt-every", type=int, default=None,
                        help="write a checkpoint every N steps (default: the preset's)")
    parser.add_argument("--model-set", action="append", default=[], metavar="FIELD=VALUE",
                        help="override a ModelConfig field of the preset, VALUE in JSON "
                             "(repeatable), e.g. --model-set view_input=true "
                             "--model-set num_complete=2048")
    parser.add_argument("--early-weight", type=float, default=None, metavar="X",
                        help="extra loss weight of each training window's first detections, "
                             "where the GRU starts cold (default: the preset's, 0)")
    parser.add_argument("--early-frames", type=int, default=None, metavar="K",
                        help="how many of a window's first detections --early-weight weighs "
                             "(default 4)")
    parser.add_argument("--no-tensorboard", action="store_true",
                        help="write no TensorBoard logs")


def _triple(text: str, name: str, cast):
    parts = text.split(",")
    try:
        values = tuple(cast(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3:
        raise ConfigError(f"{name} needs three comma-separated numbers, got {text!r}")
    return values


def build_config(args: argparse.Namespace):
    """The :class:`TrainConfig` from a preset and the command-line overrides."""
    cfg = get_train_config(args.preset)
    if args.stage_steps:
        cfg = cfg.with_stage_steps(_triple(args.stage_steps, "--stage-steps", int))
    if args.time_budget_min is not None:
        cfg = cfg.with_time_budget(args.time_budget_min)
    if args.stage_budget_min:
        budgets = _triple(args.stage_budget_min, "--stage-budget-min", float)
        cfg = dataclasses.replace(cfg, stages=tuple(
            dataclasses.replace(s, time_budget_min=b) for s, b in zip(cfg.stages, budgets,
                                                                      strict=True)))
    if args.lr is not None:
        lrs = (args.lr, args.lr, args.lr / 2)
        cfg = dataclasses.replace(cfg, stages=tuple(
            dataclasses.replace(s, lr=lr) for s, lr in zip(cfg.stages, lrs, strict=True)))
    overrides = {"seed": args.seed, "batch_size": args.batch_size, "window": args.window,
                 "threads": args.threads, "val_every": args.val_every,
                 "ckpt_every": args.ckpt_every, "early_weight": args.early_weight,
                 "early_frames": args.early_frames}
    cfg = dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
    if args.no_tensorboard:
        cfg = dataclasses.replace(cfg, tensorboard=False)
    init = _init_model_config(args)
    if args.model_set or init:
        # a fine-tune takes the architecture of the weights it starts from; --model-set wins
        cfg = dataclasses.replace(cfg, model_overrides={**cfg.model_overrides, **init,
                                                        **_model_sets(args.model_set)})
        cfg.model_config()  # validate now
    return cfg


def _init_model_config(args: argparse.Namespace) -> dict:
    """The model configuration of the ``--init`` weights (empty without ``--init``), so that
    ``--init pretrained`` fine-tunes the shipped architecture whatever the preset's is."""
    if not getattr(args, "init", None) or getattr(args, "resume", False):
        return {}
    from seqshape.model.estimator import read_model_file
    from seqshape.train.checkpoint import resolve_init

    payload = read_model_file(resolve_init(args.init, args.model))
    return dict(payload.get("model_config") or {})


def _model_sets(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--model-set needs FIELD=VALUE, got {item!r}")
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            raise ConfigError(f"--model-set {key}: {value!r} is not a JSON value") from None
    return out


def run(args: argparse.Namespace) -> int:
    trainer = Trainer(args.data, args.out, args.model, build_config(args), resume=args.resume,
                      data_fractions=args.data_fraction,
                      init=args.init)
    path = trainer.run()
    if trainer.is_main:
        m = trainer.metrics
        if trainer.init is not None:
            print(f"initialised from {trainer.init['path']}")
            if "init_val_cd_m" in m:
                print(f"initial weights: val CD {100 * m['init_val_cd_m']:.2f} cm, pose loss "
                      f"{m['init_val_pose_m2']:.4f} m^2")
        if "val_cd_m" in m:
            print(f"val CD {100 * m['val_cd_m']:.2f} cm, pose loss {m['val_pose_m2']:.4f} m^2")
        print(f"wrote {path}")
    return 0
