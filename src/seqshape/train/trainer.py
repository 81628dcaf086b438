"""The three-stage trainer (paper, "Training"), resumable, deterministic, data-parallel.

Outputs in the run folder ``RUN``::

    config.json      resolved configuration (train + model + kind + data path + init source)
    last.pt          latest checkpoint (every ``ckpt_every`` steps and at each stage end)
    stage{1,2,3}.pt  checkpoint at the end of each stage
    model.pt         exported weights (for :class:`seqshape.Estimator`)
    log.csv          training rows (running means) and validation rows
    tb/              TensorBoard events (optional)

Losses are averaged over the window frames that have a known pose and follow the track's
first points (earlier frames have no estimate). The GT complete shape is placed in each
frame with its GT pose; losses are in metres and square metres (with ``scale_norm="length"``
the network rescales its input and output internally; the losses see metres). A
``motion_input`` model gets each window's time steps (from the track's timestamps) and raw
point counts; every window starts as a fresh track (no previous detection).

Data parallelism (``torchrun --nproc_per_node R``, gloo on CPU): every process builds the
same model from the seed, takes its disjoint shard of each global batch
(:func:`seqshape.data.windows.batch_for_step`), and gradients are averaged with one
all-reduce per step before the optimiser step. Only rank 0 writes files.

Throughput (issue 17): the next batch is built in a background thread
(:class:`~seqshape.train.prefetch.BatchPrefetcher`), trailing padding frames are dropped
(:func:`~seqshape.data.windows.trim_padding`), the decoders run on the frames that count only,
Chamfer neighbours come from k-d trees on CPU and Adam is the fused kernel. The losses and
gradients are those of the reference step (:mod:`seqshape.train.reference`) to float rounding;
``benchmarks/bm_train.py`` times the two side by side.

Fine-tuning (``init``): the model starts from the weights of a ``model.pt``, a training
checkpoint or the shipped pretrained file (:func:`seqshape.train.checkpoint.load_init`) instead
of the seeded random initialisation; stages with 0 steps are skipped (no optimiser, no
validation, no ``stage{n}.pt``), so ``stages=(0, 0, N)`` fine-tunes jointly only.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import random
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

import seqshape.train.checkpoint as ckpt
from seqshape._io import atomic_write_json
from seqshape._progress import progress
from seqshape.data.dataset import TrackDataset
from seqshape.data.windows import WindowDataset, collate, trim_padding
from seqshape.errors import ConfigError, DataError
from seqshape.model.estimator import KINDS
from seqshape.model.network import ShapePoseNet
from seqshape.model.transforms import place_points
from seqshape.train.config import STAGE_NAMES, TrainConfig
from seqshape.train.losses import JointLoss, chamfer_distance, pose_loss
from seqshape.train.prefetch import BatchPrefetcher
from seqshape.train.runlog import RunLog

log = logging.getLogger(__name__)


def _trainable(split: TrackDataset, name: str) -> TrackDataset:
    """The tracks of a split that have a complete shape (real tracks without an accumulated
    reference are left out, with a warning); DataError when none is left."""
    keep = split.with_complete()
    if len(keep) < len(split):
        log.warning("%s: %d of %d %s tracks have no complete shape (no accumulated reference) "
                    "and are left out of training", split.path, len(split) - len(keep),
                    len(split), name)
    if not len(keep):
        raise DataError(split.path, f"no {name} track has a complete shape to train against")
    return keep


class Trainer:
    """Train one model (``kind`` "sequential" or "baseline") on ``data`` into ``out``.

    ``init``: weights to start from (a ``model.pt`` / checkpoint path or ``"pretrained"``);
    ignored when resuming an existing run (its checkpoint holds the weights).
    """

    def __init__(self, data: str | Path, out: str | Path, kind: str, cfg: TrainConfig,
                 resume: bool = False, init: str | Path | None = None,
                 data_fractions: list[float] | None = None):
        if kind not in KINDS:
            raise ConfigError(f"unknown model kind {kind!r}; choose from {KINDS}")
        self.out, self.kind = Path(out), kind
        self.data_paths = [Path(d) for d in ([data] if isinstance(data, str | Path) else data)]
        self.data = self.data_paths[0]
        self.data_fractions = data_fractions
        self.rank, self.world = _init_distributed()
        self.is_main = self.rank == 0
        payload = self._resume_payload(resume)
        if payload is not None:
            cfg = self._checked_resume_config(payload, cfg)
        self.cfg = cfg
        torch.set_num_threads(cfg.threads)
        torch.use_deterministic_algorithms(True, warn_only=True)
        try:
            dataset = TrackDataset.union(self.data_paths, self.data_fractions)
        except ValueError as exc:
            raise ConfigError(f"--data-fraction: {exc}") from None
        self.train_tracks = _trainable(dataset.split("train"), "train")
        try:
            self.val_tracks: TrackDataset | None = _trainable(dataset.split("val"), "val")
        except DataError:
            log.warning("%s has no val split (with complete shapes): validation is skipped",
                        self.data)
            self.val_tracks = None
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed % 2**32)  # noqa: NPY002 - seeds code that uses the global RNG
        random.seed(cfg.seed)
        self.model = ShapePoseNet(cfg.model_config(), recurrent=kind == "sequential")
        self.joint = JointLoss()
        self.state: dict[str, Any] = {"stage": 0, "step": 0, "elapsed": 0.0, "global_step": 0,
                                      "sigma_init": False, "optimizer": None}
        self.metrics: dict[str, Any] = {}
        self.init: dict[str, Any] | None = None
        if payload is not None:
            self._load(payload)
            self.init = payload.get("init")
            if init is not None and (self.init or {}).get("source") != str(init):
                log.warning("resuming %s: --init %s is ignored (the checkpoint holds the "
                            "weights; the run started from %s)", self.out, init,
                            (self.init or {}).get("source", "random weights"))
        elif init is not None:
            state_dict, self.init = ckpt.load_init(init, kind, self.model.cfg)
            try:
                self.model.load_state_dict(state_dict)
            except RuntimeError as exc:
                raise DataError(self.init["path"], f"weights do not fit the model they "
                                                   f"describe ({exc})") from None
            log.info("initialised from %s (%s)", self.init["path"], self.init["file"])
        self.runlog = RunLog(self.out, self.state["global_step"], cfg.tensorboard) \
            if self.is_main else None
        self._val_batches = self._make_val_batches()

    # ------------------------------------------------------------------ setup / resume
    def _resume_payload(self, resume: bool) -> dict | None:
        last = self.out / "last.pt"
        if not last.exists():
            if resume:
                log.info("no checkpoint in %s: starting a new run", self.out)
            return None
        if not resume:
            raise ConfigError(f"{self.out} already holds a training run ({last}); pass "
                              f"--resume to continue it or choose another --out")
        return ckpt.load_checkpoint(last)

    def _checked_resume_config(self, payload: dict, cfg: TrainConfig) -> TrainConfig:
        if payload["kind"] != self.kind:
            raise ConfigError(f"{self.out} trains a {payload['kind']} model, not {self.kind}")
        saved = TrainConfig.from_dict(payload["train_config"])
        if saved != cfg:
            log.warning("resuming with the configuration saved in %s/last.pt; the arguments "
                        "given now differ and are ignored", self.out)
        return saved

    def _load(self, payload: dict) -> None:
        self.model.load_state_dict(payload["state_dict"])
        tr = payload["training"]
        self.joint.load_state_dict(tr["joint"])
        self.state.update({k: tr[k] for k in ("stage", "step", "elapsed", "global_step",
                                               "sigma_init", "optimizer")})
        self.metrics = dict(payload.get("metrics", {}))
        ckpt.set_rng_state(tr["rng"])
        log.info("resuming %s at stage %d step %d", self.out, self.state["stage"] + 1,
                 self.state["step"])

    def _make_val_batches(self) -> list[dict[str, torch.Tensor]]:
        if self.val_tracks is None or not self.is_main or self.cfg.val_windows <= 0:
            return []
        c, m = self.cfg, self.model.cfg
        wds = WindowDataset(self.val_tracks, c.window, m.num_points, c.num_complete_gt,
                            windows_per_track=max(1, -(-c.val_windows // len(self.val_tracks))),
                            p_first=0.5, seed=c.seed + 1_000_003, key=0, cache_size=4,
                            **self._length_options())
        idx = np.linspace(0, len(wds) - 1, min(c.val_windows, len(wds))).round().astype(int)
        items = [wds.window_at(int(i), 0) for i in idx]
        return [collate(items[i:i + c.batch_size]) for i in range(0, len(items), c.batch_size)]

    def _length_options(self) -> dict[str, Any]:
        """WindowDataset options: per-frame lengths for the input scale when the model uses
        one (``scale_norm="length"``), the time steps and raw point counts when it reads
        motion inputs (``motion_input``, sequential model); none otherwise (the windows are
        then unchanged)."""
        opts: dict[str, Any] = {}
        if self.model.motion:
            opts["motion"] = True
        if self.model.cfg.scale_norm == "none":
            return opts
        return {**opts, "length_hint_noise": self.cfg.length_hint_noise,
                "length_points_prob": self.cfg.length_points_prob,
                "length_running": self.model.recurrent}

    def _scale(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """The (B, W) input scale of a batch, None without ``scale_norm``."""
        if self.model.cfg.scale_norm == "none":
            return None
        return self.model.cfg.scale_for(batch["length"].float())

    # ------------------------------------------------------------------ losses
    def _losses(self, batch: dict[str, torch.Tensor], stage: int | None,
                weighted: bool = False) -> dict[str, torch.Tensor]:
        """Per-batch mean CD (m) and pose loss (m^2) over the frames that count.

        ``weighted`` (the training objective): with ``TrainConfig.early_weight`` the means are
        weighted, each window's first ``early_frames`` detections by ``1 + early_weight``
        (:func:`early_weights`); validation calls it unweighted.

        ``stage`` 0 / 1 computes only the CD / pose term (stage 1 with the backbone frozen
        and run without gradient); None or 2 computes both. The frames that count are the
        ``valid`` ones after the track's first points; the decoders run on those alone and
        trailing padding frames are dropped first (:func:`trim_padding`): the same losses as
        decoding every frame of the window (:func:`seqshape.train.reference.reference_losses`).
        """
        batch = trim_padding(batch)
        pts, lengths, scale = batch["points"], batch["lengths"], self._scale(batch)
        motion = {"dts": batch.get("dts"), "counts": batch.get("counts")}
        with torch.no_grad() if stage == 1 else contextlib.nullcontext():
            enc = self.model.encode(pts, lengths, scale=scale, **motion)
        sel = batch["valid"] & enc["seen"]  # (B, W)
        h, means = enc["h"][sel], enc["means"][sel]  # (F, H), (F, 3)
        scales = None if enc["scales"] is None else enc["scales"][sel]  # (F,)
        gt_pose = batch["poses"][sel]  # (F, 4)
        gt = place_points(batch["complete"][sel.nonzero()[:, 0]], gt_pose)  # (F, M, 3)
        n = max(1, int(sel.sum()))
        w = None
        if weighted and self.cfg.early_weight > 0:
            w = early_weights(batch["lengths"], self.cfg.early_weight, self.cfg.early_frames)[sel]
            n = w.sum().clamp_min(1.0)
        res = {"frames": torch.tensor(float(sel.sum()))}
        canonical = self.model.cfg.shape_frame == "canonical"
        pose = None
        if stage != 0 or canonical:
            pose = self.model.decode_pose(h, means, scales)  # (F, 4)
        if stage != 1:
            shape = self.model.decode_shape(h, means, pose if canonical else None, scales)
            cd = chamfer_distance(shape, gt)
            res["cd"] = (cd if w is None else cd * w).sum() / n
        if stage != 0:
            pl = pose_loss(pose, gt_pose, gt)
            res["pose"] = (pl if w is None else pl * w).sum() / n
        return res

    def _objective(self, res: dict[str, torch.Tensor], stage: int) -> torch.Tensor:
        if stage == 0:
            return res["cd"]
        if stage == 1:
            return res["pose"]
        return self.joint(res["cd"], res["pose"])

    @torch.inference_mode()
    def validate(self, stage: int) -> dict[str, float]:
        """Frame-weighted CD, pose loss and the stage objective over the fixed val windows."""
        if not self._val_batches:
            return {}
        tot = {"cd": 0.0, "pose": 0.0, "frames": 0.0}
        for batch in self._val_batches:
            res = self._losses(batch, None)
            f = float(res["frames"])
            tot["cd"] += float(res["cd"]) * f
            tot["pose"] += float(res["pose"]) * f
            tot["frames"] += f
        f = max(tot["frames"], 1.0)
        cd, pl = tot["cd"] / f, tot["pose"] / f
        obj = {0: cd, 1: pl}.get(stage)
        if obj is None:
            obj = float(self.joint(torch.tensor(cd), torch.tensor(pl)))
        return {"val_loss": obj, "val_cd_m": cd, "val_pose_m2": pl}

    # ------------------------------------------------------------------ stages
    def _stage_groups(self, stage: int) -> list[dict[str, Any]]:
        m, lr = self.model, self.cfg.stages[stage].lr
        if stage == 0:
            params = m.shape_parameters()
        elif stage == 1:
            params = list(m.pose_decoder.parameters())
        else:
            params = list(m.parameters())
        for p in m.parameters():
            p.requires_grad_(False)
        for p in params:
            p.requires_grad_(True)
        self.joint.log_sigma.requires_grad_(stage == 2)
        groups = [{"params": params, "lr": lr, "base_lr": lr}]
        if stage == 2:
            groups.append({"params": [self.joint.log_sigma], "lr": self.cfg.sigma_lr,
                           "base_lr": self.cfg.sigma_lr})
        return groups

    def _progress_fraction(self, stage: int) -> float:
        sc = self.cfg.stages[stage]
        frac = self.state["step"] / max(1, sc.steps)
        if sc.time_budget_min:
            frac = max(frac, self.state["elapsed"] / (60.0 * sc.time_budget_min))
        return min(1.0, frac)

    def _set_lr(self, opt: torch.optim.Optimizer, stage: int) -> float:
        r = self.cfg.lr_min_ratio
        factor = r + (1 - r) * 0.5 * (1 + math.cos(math.pi * self._progress_fraction(stage)))
        for g in opt.param_groups:
            g["lr"] = g["base_lr"] * factor
        return opt.param_groups[0]["lr"]

    def _stage_done(self, stage: int) -> bool:
        sc = self.cfg.stages[stage]
        if self.state["step"] >= sc.steps:
            return True
        return bool(sc.time_budget_min) and self.state["elapsed"] >= 60.0 * sc.time_budget_min

    def _init_sigmas(self, batch: dict[str, torch.Tensor]) -> None:
        """Start stage 3's sigmas at their optimum ``s^2 = L`` for the current weights.

        The losses are measured on the fixed val windows when there are any (frame-weighted as
        in :meth:`validate`, the main process's figures broadcast to all), else on this step's
        batch (averaged over the processes). One batch can be a poor sample: with one window per step a lucky first
        batch set s_p at a quarter of its typical value and the pose term swamped the rest.
        """
        with torch.no_grad():
            res = self._losses(batch, None)
            vals = _all_reduce_mean(torch.stack([res["cd"], res["pose"]]), self.world)
            v = self.validate(1) if self.is_main else {}
            val = torch.tensor([float(bool(v)), v.get("val_cd_m", 0.0), v.get("val_pose_m2", 0.0)])
            val = _broadcast(val, self.world)
        source = "the first batch"
        if val[0] > 0:
            vals, source = val[1:], "the fixed val windows"
        self.joint.init_from(float(vals[0]), float(vals[1]))
        self.state["sigma_init"] = True
        log.info("stage 3: sigma_cd=%.4g sigma_p=%.4g from %s", *self.joint.sigmas, source)

    def _train_step(self, opt, batches: BatchPrefetcher, stage: int) -> dict[str, float]:
        c = self.cfg
        batch = batches.get(self.state["global_step"])
        if stage == 2 and not self.state["sigma_init"]:
            self._init_sigmas(batch)
        lr = self._set_lr(opt, stage)
        res = self._losses(batch, stage, weighted=True)
        loss = self._objective(res, stage)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        params = [p for g in opt.param_groups for p in g["params"] if p.grad is not None]
        _all_reduce_grads(params, self.world)
        if c.grad_clip:
            torch.nn.utils.clip_grad_norm_(params, c.grad_clip)
        opt.step()
        out = {"loss": float(loss.detach()), "lr": lr, "frames": float(res["frames"])}
        out.update({k: float(res[k].detach()) for k in ("cd", "pose") if k in res})
        return out

    def _optimizer(self, stage: int) -> torch.optim.Optimizer:
        """Adam over the stage's parameters, resumed from the checkpoint's state if any."""
        opt = make_adam(self._stage_groups(stage))
        if self.state["optimizer"] is not None:
            opt.load_state_dict(self.state["optimizer"])
            self.state["optimizer"] = None
        return opt

    def _windows(self, stage: int) -> WindowDataset:
        c = self.cfg
        return WindowDataset(self.train_tracks, c.window, self.model.cfg.num_points,
                             c.num_complete_gt, c.windows_per_track, c.p_first, c.seed,
                             key=stage + 1, cache_size=c.cache_size, **self._length_options())

    def _run_stage(self, stage: int) -> None:
        opt = self._optimizer(stage)
        with BatchPrefetcher(self._windows(stage), self.cfg.batch_size, self.rank,
                             self.world) as batches:
            self._stage_loop(opt, batches, stage)
        if self.is_main:
            self._validate_and_log(stage)
        self.state.update(stage=stage + 1, step=0, elapsed=0.0, optimizer=None)
        if self.is_main:
            self._save(None, stage_end=stage + 1)

    def _stage_loop(self, opt, batches: BatchPrefetcher, stage: int) -> None:
        c = self.cfg
        sc = c.stages[stage]
        # the bar counts the stage's optimiser steps (its rate in steps/s, frames/s beside it);
        # a wall-clock budget may end the stage before its last step (the time left beside it)
        budget = f", budget {sc.time_budget_min:g} min" if sc.time_budget_min else ""
        bar = progress(total=sc.steps, initial=min(self.state["step"], sc.steps), unit="step",
                       desc=f"stage {stage + 1}/3 ({STAGE_NAMES[stage]}, {self.kind}{budget})",
                       disable=None if self.is_main else True)
        frames, t_bar = 0.0, time.monotonic()
        self.model.train()
        t_last = time.monotonic()
        while not self._stage_done(stage):
            row = self._train_step(opt, batches, stage)
            self.state["step"] += 1
            self.state["global_step"] += 1
            now = time.monotonic()
            self.state["elapsed"] = float(_all_reduce_max(
                self.state["elapsed"] + now - t_last, self.world))
            t_last = now
            step = self.state["step"]
            bar.update(1)
            frames += row["frames"] * self.world
            postfix = {"frames/s": f"{frames / max(now - t_bar, 1e-9):.0f}"}
            if sc.time_budget_min:  # the stage ends at its steps or its budget, the first
                left = max(0.0, 60.0 * sc.time_budget_min - self.state["elapsed"])
                postfix["budget left"] = f"{int(left // 60)}:{int(left % 60):02d}"
            bar.set_postfix(postfix, refresh=False)
            if self.is_main:
                row["frames"] *= self.world
                self.runlog.train_row(stage, step, self.state["global_step"], row,
                                      self.joint.sigmas, c.log_every)
                if c.val_every and step % c.val_every == 0 and not self._stage_done(stage):
                    self._validate_and_log(stage)
                if c.ckpt_every and step % c.ckpt_every == 0 and not self._stage_done(stage):
                    self._save(opt)
        bar.close()

    def _validate_and_log(self, stage: int) -> None:
        self.model.eval()
        val = self.validate(stage)
        self.model.train()
        if val:
            self.metrics.update(val, val_stage=stage + 1)
            self.runlog.val_row(stage, self.state["step"], self.state["global_step"], val,
                                self.joint.sigmas)

    # ------------------------------------------------------------------ files
    def _payload(self, opt) -> dict[str, Any]:
        payload = self._model_payload()
        payload["training"] = {
            "stage": self.state["stage"], "step": self.state["step"],
            "elapsed": self.state["elapsed"], "global_step": self.state["global_step"],
            "sigma_init": self.state["sigma_init"],
            "optimizer": None if opt is None else opt.state_dict(),
            "scheduler": {"kind": "cosine-per-stage", "lr_min_ratio": self.cfg.lr_min_ratio},
            "joint": {k: v.clone() for k, v in self.joint.state_dict().items()},
            "rng": ckpt.rng_state(), "world_size": self.world}
        return payload

    def _model_payload(self) -> dict[str, Any]:
        payload = ckpt.model_payload(self.model, self.cfg.to_dict(), self.metrics)
        if self.init is not None:
            payload["init"] = self.init
        return payload

    def _save(self, opt, stage_end: int | None = None) -> None:
        payload = self._payload(opt)
        ckpt.save_payload(self.out / "last.pt", payload)
        if stage_end is not None:
            ckpt.save_payload(self.out / f"stage{stage_end}.pt", payload)
        self.runlog.flush()

    def write_config(self) -> None:
        if self.is_main:
            atomic_write_json(self.out / "config.json", {
                "kind": self.kind, "data": ", ".join(map(str, self.data_paths)),
                "data_fractions": self.data_fractions,
                "world_size": self.world,
                "train_config": self.cfg.to_dict(),
                "model_config": self.model.cfg.to_dict(), "init": self.init})

    def _validate_init(self) -> None:
        """Score the initial weights once (metrics ``init_val_cd_m``, ``init_val_pose_m2``)."""
        if not self.is_main or self.init is None or "init_val_cd_m" in self.metrics:
            return
        self.model.eval()
        val = self.validate(0)
        if val:
            self.metrics.update(init_val_cd_m=val["val_cd_m"],
                                init_val_pose_m2=val["val_pose_m2"])
            log.info("initial weights: val CD %.4f m, pose %.4f m^2", val["val_cd_m"],
                     val["val_pose_m2"])

    def run(self) -> Path:
        """Run the remaining stages, export ``RUN/model.pt`` and return its path."""
        self.write_config()
        self._validate_init()
        for stage in range(self.state["stage"], 3):
            if self.cfg.stages[stage].steps == 0:
                log.info("stage %d/3 (%s): 0 steps, skipped", stage + 1, STAGE_NAMES[stage])
                self.state.update(stage=stage + 1, step=0, elapsed=0.0, optimizer=None)
                continue
            self._run_stage(stage)
        path = self.out / "model.pt"
        if self.is_main:
            sig = self.joint.sigmas
            self.metrics.update(global_steps=self.state["global_step"], sigma_cd=sig[0],
                                sigma_p=sig[1])
            ckpt.save_payload(path, self._model_payload())
            self.runlog.close()
            log.info("wrote %s (%s)", path, {k: round(v, 5) for k, v in self.metrics.items()
                                             if isinstance(v, float)})
        _barrier(self.world)
        return path


def train(data: str | Path, out: str | Path, kind: str = "sequential",
          cfg: TrainConfig | None = None, resume: bool = False,
          init: str | Path | None = None) -> Path:
    """Train (or resume) a run, optionally from ``init`` weights; returns ``RUN/model.pt``."""
    return Trainer(data, out, kind, cfg or TrainConfig(), resume, init).run()


def early_weights(lengths: torch.Tensor, extra: float, frames: int) -> torch.Tensor:
    """``(B, W)`` float32 loss weights of a batch of windows with ``lengths (B, W)`` points per
    frame: ``1 + extra`` on each window's first ``frames`` detections (frames with points; an
    empty frame between them counts with the detections before it), 1 elsewhere."""
    seen = torch.cumsum((lengths > 0).long(), dim=1)  # detections up to and including a frame
    early = (seen >= 1) & (seen <= frames)
    return 1.0 + float(extra) * early.float()


def make_adam(groups: list[dict[str, Any]]) -> torch.optim.Optimizer:
    """Adam with PyTorch's fused kernel where it runs (CPU since torch 2.4; one kernel over
    all parameters, 3 ms instead of 14 ms per step for the ``small`` network), else the plain
    one. The two agree to float32 rounding (weights at most 1.5e-8 apart after 23 steps of the
    ``small`` network; tests/test_train_fast.py). A checkpoint's optimizer state keeps the
    kind it was saved with: runs resumed from older checkpoints continue with plain Adam."""
    try:
        return torch.optim.Adam(groups, fused=True)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(groups)


# ---------------------------------------------------------------------- distributed helpers
def _init_distributed() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("gloo")
    return dist.get_rank(), dist.get_world_size()


def _all_reduce_grads(params: list[torch.Tensor], world: int) -> None:
    if world <= 1 or not params:
        return
    import torch.distributed as dist

    flat = torch.cat([p.grad.reshape(-1) for p in params])
    dist.all_reduce(flat)
    flat /= world
    offset = 0
    for p in params:
        n = p.grad.numel()
        p.grad.copy_(flat[offset:offset + n].view_as(p.grad))
        offset += n


def _all_reduce_mean(t: torch.Tensor, world: int) -> torch.Tensor:
    if world <= 1:
        return t
    import torch.distributed as dist

    t = t.clone()
    dist.all_reduce(t)
    return t / world


def _broadcast(t: torch.Tensor, world: int) -> torch.Tensor:
    """Rank 0's ``t`` on every process."""
    if world <= 1:
        return t
    import torch.distributed as dist

    t = t.clone()
    dist.broadcast(t, 0)
    return t


def _all_reduce_max(x: float, world: int) -> float:
    if world <= 1:
        return x
    import torch.distributed as dist

    t = torch.tensor([x], dtype=torch.float64)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return float(t)


def _barrier(world: int) -> None:
    if world > 1:
        import torch.distributed as dist

        dist.barrier()
