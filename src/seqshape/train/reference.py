"""The training step as it was before the fast path (issue 17): the reference it is checked
against (tests/test_train_fast.py) and timed against (benchmarks/bm_train.py).

The reference decodes every frame of the full window (padding included) and selects the
frames that count afterwards, finds Chamfer neighbours with the dense search, builds each batch
in the calling thread and steps a plain (unfused) Adam. The fast path
(:meth:`seqshape.train.trainer.Trainer._losses`) computes the same losses and gradients.
"""

from __future__ import annotations

from typing import Any

import torch

from seqshape.data.windows import WindowDataset, batch_for_step
from seqshape.model.network import ShapePoseNet
from seqshape.model.transforms import place_points
from seqshape.train.losses import chamfer_distance, pose_loss


def reference_losses(model: ShapePoseNet, batch: dict[str, torch.Tensor], stage: int | None,
                     scale: torch.Tensor | None) -> dict[str, torch.Tensor]:
    """Per-batch mean CD (m) and pose loss (m^2) over the frames that count, the slow way.

    ``stage`` as in :meth:`~seqshape.train.trainer.Trainer._losses`; ``scale`` the batch's
    (B, W) input scale (None without ``scale_norm``).
    """
    pts, lengths = batch["points"], batch["lengths"]
    motion = {"dts": batch.get("dts"), "counts": batch.get("counts")}
    if stage == 1:
        with torch.no_grad():
            enc = model.encode(pts, lengths, scale=scale, **motion)
        out = {"pose": model.decode_pose(enc["h"], enc["means"], enc["scales"]),
               "seen": enc["seen"]}
    else:
        out = model(pts, lengths, shape=True, pose=stage != 0, scale=scale, **motion)
    sel = batch["valid"] & out["seen"]  # (B, W)
    gt_pose = batch["poses"][sel]
    gt = place_points(batch["complete"][sel.nonzero()[:, 0]], gt_pose)
    n = max(1, int(sel.sum()))
    res = {"frames": torch.tensor(float(sel.sum()))}
    if "complete" in out:
        res["cd"] = chamfer_distance(out["complete"][sel], gt, method="dense").sum() / n
    if "pose" in out:
        res["pose"] = pose_loss(out["pose"][sel], gt_pose, gt).sum() / n
    return res


def reference_step(trainer: Any, opt: torch.optim.Optimizer, windows: WindowDataset,
                   stage: int) -> dict[str, float]:
    """One optimiser step of ``trainer`` (a :class:`~seqshape.train.trainer.Trainer`, one
    process) the reference way: the batch built here, :func:`reference_losses`, backward,
    gradient clipping and ``opt`` (pass a plain ``torch.optim.Adam`` for the old step)."""
    c = trainer.cfg
    batch = batch_for_step(windows, trainer.state["global_step"], c.batch_size)
    lr = trainer._set_lr(opt, stage)
    res = reference_losses(trainer.model, batch, stage, trainer._scale(batch))
    loss = trainer._objective(res, stage)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if c.grad_clip:
        params = [p for g in opt.param_groups for p in g["params"] if p.grad is not None]
        torch.nn.utils.clip_grad_norm_(params, c.grad_clip)
    opt.step()
    return {"loss": float(loss.detach()), "lr": lr, "frames": float(res["frames"])}
