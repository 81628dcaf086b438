"""Training the placement refiner (:mod:`seqshape.model.placement`): ``seqshape train-refiner``.

1. **Frames.** Each network (the sequential model and the baseline) estimates every track of
   the training datasets online, frame by frame as :class:`~seqshape.model.Estimator` would
   (:func:`collect_frames`, with the class and ego-pose hints a user's pipeline has); a frame
   with points keeps up to :data:`STORED_POINTS` of them, its estimate, the estimate's
   extents (:func:`~seqshape.model.placement.extents_of`) and the truth. The refiner thus
   learns the errors the networks make, both of them, on the data it will correct.
2. **Training** (:func:`train_refiner`): batches of frames drawn at random; with probability
   ``jitter`` an estimate is disturbed further (centre N(0, 12 cm) in the plane, 3.6 cm in
   height, yaw N(0, 3 degrees), extents x exp(N(0, 5 %))), so that the refiner also sees the
   errors a network makes on data unlike its training split; with probability 1/2 the frame is
   mirrored across the estimate's long axis (vehicles are left-right symmetric). The inputs
   are :func:`~seqshape.model.placement.refine_inputs` (the inference path calls its batched
   form, :func:`~seqshape.model.placement.refine_inputs_batch`, tested equal), the targets :func:`~seqshape.model.placement.targets`; loss: smooth L1 of the
   centre correction (in units of the input scale, beta 5 cm) plus half the smooth L1 of the
   axis correction (rad, beta 0.02). Adam with a one-cycle schedule.
3. **Checkpoints**: ``OUT/refiner.ckpt`` (weights, optimiser, schedule, random states) every
   ``checkpoint_every`` steps, atomically; ``--resume`` continues from it bit for bit. The
   final weights go to ``OUT/refiner.pt`` (the file :meth:`PlacementRefiner.load` reads),
   with the validation figures in its ``meta``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from seqshape._io import atomic_save_npz, atomic_write_bytes, atomic_write_json
from seqshape._progress import progress
from seqshape.errors import ConfigError, DataError
from seqshape.model import placement as P
from seqshape.model.offline import estimate_tracks

log = logging.getLogger(__name__)

STORED_POINTS = 512  # points kept per frame (a random subset of a larger frame)
FRAME_KEYS = ("est", "ext", "true", "n", "pts", "cls", "size")


@dataclass(frozen=True)
class RefinerTrainConfig:
    """Options of :func:`train_refiner` (the flags of ``seqshape train-refiner``).

    steps: optimiser steps.
    batch: frames per step.
    lr: peak learning rate (one-cycle schedule).
    jitter: probability of disturbing an estimate further (module doc).
    max_error: frames whose estimate is farther than this (m) from the truth are left out of
        training (lost tracks).
    minutes: stop after this much wall-clock time (0: no limit), saving as at the end.
    checkpoint_every: steps between checkpoints.
    seed: the batches, the jitter, the subsets and the weights' initialisation.
    threads: intra-op threads (and the estimators' while collecting).
    size: train the size head too (:data:`~seqshape.model.placement.SIZE_OUTPUTS`): the log
        ratios of the true shape's length and width (1st-99th percentiles) to the estimate's,
        half the smooth L1 (beta 0.02) in the loss; frames without a true shape do not count.
    """

    steps: int = 10000
    batch: int = 128
    lr: float = 1e-3
    jitter: float = 0.5
    max_error: float = 3.0
    minutes: float = 0.0
    checkpoint_every: int = 500
    seed: int = 0
    threads: int = 1
    size: bool = False

    def __post_init__(self):
        if self.steps < 1 or self.batch < 1:
            raise ConfigError("--steps and --batch must be >= 1")
        if not 0.0 <= self.jitter <= 1.0:
            raise ConfigError(f"--jitter must be in [0, 1], got {self.jitter}")


def collect_frames(estimator, dataset, every: int = 1, seed: int = 0,
                   desc: str = "frames") -> dict[str, np.ndarray]:
    """Online estimates of ``estimator`` on every ``every``-th track of ``dataset`` (a
    :class:`~seqshape.data.dataset.TrackDataset` or a list of tracks), one row per frame with
    points (module doc, 1): ``est`` (F, 4), ``ext`` (F, 3), ``true`` (F, 4), ``n`` (F,)
    points, ``pts`` (F, STORED_POINTS, 3) float32 (NaN rows past ``n``), ``cls`` (F,),
    ``size`` (F, 3) the true shape's extents (NaN without one)."""
    rng = np.random.default_rng(seed)
    rows: dict[str, list] = {k: [] for k in FRAME_KEYS}
    tracks = [dataset[i] for i in range(0, len(dataset), max(int(every), 1))]
    for tr in progress(tracks, desc=desc, unit="track"):
        det = np.flatnonzero(tr.num_points > 0)
        if not len(det):
            continue
        size = np.full(3, np.nan) if tr.complete is None or not len(tr.complete) \
            else P.extents_of(tr.complete, np.zeros(4))
        frames = range(int(det[0]), int(det[-1]) + 1)
        egos = [tr.ego_pose(t) for t in frames]
        res = estimate_tracks(estimator, [{
            "points": [tr.points[t] for t in frames],
            "timestamps": tr.timestamps[frames.start:frames.stop],
            "cls": tr.meta.get("class") or None,
            "ego_poses": egos if any(e is not None for e in egos) else None,
            "track_id": tr.track_id}], "online")[0]
        for t, e in zip(frames, res, strict=True):
            p = tr.points[t]
            if not len(p) or not e.valid:
                continue
            sel = p if len(p) <= STORED_POINTS else p[rng.choice(len(p), STORED_POINTS,
                                                                  replace=False)]
            buf = np.full((STORED_POINTS, 3), np.nan, np.float32)
            buf[:len(sel)] = sel
            rows["est"].append(np.asarray(e.pose, np.float64))
            rows["ext"].append(P.extents_of(e.complete, e.pose))
            rows["true"].append(tr.poses[t])
            rows["n"].append(len(p))
            rows["pts"].append(buf)
            rows["cls"].append(str(tr.meta.get("class") or "car"))
            rows["size"].append(size)
    if not rows["n"]:
        return _empty_frames()
    return {k: np.asarray(v) for k, v in rows.items()}


def _empty_frames() -> dict[str, np.ndarray]:
    return {"est": np.zeros((0, 4)), "ext": np.zeros((0, 3)), "true": np.zeros((0, 4)),
            "n": np.zeros(0, np.int64), "pts": np.zeros((0, STORED_POINTS, 3), np.float32),
            "cls": np.zeros(0, "<U8"), "size": np.zeros((0, 3))}


def save_frames(path: Path, frames: Mapping[str, np.ndarray]) -> None:
    atomic_save_npz(path, compressed=False, **frames)


def load_frames(path: Path) -> dict[str, np.ndarray]:
    """Frames of :func:`collect_frames` saved with :func:`save_frames`."""
    try:
        with np.load(path) as z:
            out = {k: z[k] for k in FRAME_KEYS if k != "size" or k in z.files}
            if "size" not in out:  # a file from before the size head: sizes unknown
                out["size"] = np.full((len(out["n"]), 3), np.nan)
    except (OSError, ValueError, KeyError) as exc:
        raise DataError(path, f"not a frames file of train-refiner ({exc})") from None
    n = len(out["n"])
    if any(len(v) != n for v in out.values()):
        raise DataError(path, "arrays of different lengths")
    return out


def concat_frames(parts: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    parts = [p for p in parts if len(p["n"])]
    if not parts:
        return _empty_frames()
    return {k: np.concatenate([p[k] for p in parts]) for k in FRAME_KEYS}


def frame_points(frames: Mapping[str, np.ndarray], i: int) -> np.ndarray:
    p = frames["pts"][i]
    return p[np.isfinite(p[:, 0])]


def _mirror(pts: np.ndarray, est: np.ndarray, true: np.ndarray) -> None:
    """Mirror a frame (in place) across the vertical plane through the estimate's long axis,
    then move it so that the sensor is back at the origin."""
    c, s = math.cos(est[3]), math.sin(est[3])
    rot = np.array([[c, -s], [s, c]])
    m = rot @ np.diag([1.0, -1.0]) @ rot.T
    o = est[:2].copy()
    sensor = m @ -o + o  # where the reflection puts the sensor
    pts[:, :2] = (pts[:, :2] - o) @ m.T + o - sensor
    true[:2] = m @ (true[:2] - o) + o - sensor
    true[3] = 2 * est[3] - true[3]
    est[:2] -= sensor


def make_batch(frames: Mapping[str, np.ndarray], idx: np.ndarray, rng: np.random.Generator,
               jitter: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inputs ``(xyz (B, n, 3), cond (B, C))`` and targets ``(B, 6)`` (the centre in units of
    the input scale, the axis, the log ratios of the true length and width to the estimate's
    extents: NaN where unknown) of frames ``idx``, augmented with ``rng`` (module doc, 2)."""
    xyz, cond, tgt = [], [], []
    for i in idx:
        pts = frame_points(frames, i).astype(np.float64)
        est = frames["est"][i].astype(np.float64).copy()
        ext = frames["ext"][i].astype(np.float64).copy()
        true = frames["true"][i].astype(np.float64).copy()
        if rng.random() < jitter:
            est[:3] += rng.normal(0.0, 0.12, 3) * np.array([1.0, 1.0, 0.3])
            est[3] += rng.normal(0.0, 0.05)
            ext = ext * np.exp(rng.normal(0.0, 0.05, 3))
        if rng.random() < 0.5:
            _mirror(pts, est, true)
        x, _, c, s = P.refine_inputs(pts, est, ext, rng)
        t = np.r_[P.targets(est, true)[0], np.log(frames["size"][i, :2] / ext[:2])]
        t[:3] /= s
        xyz.append(x)
        cond.append(c)
        tgt.append(t)
    return (torch.from_numpy(np.stack(xyz)), torch.from_numpy(np.stack(cond)),
            torch.from_numpy(np.stack(tgt)).float())


def loss_terms(out: torch.Tensor, tgt: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``(total, centre, axis, size)`` losses (module doc, 2; ``size`` 0 for a network
    without the size head or a batch without known sizes)."""
    centre = F.smooth_l1_loss(out[:, :3], tgt[:, :3], beta=0.05)
    axis = F.smooth_l1_loss(out[:, 3], tgt[:, 3], beta=0.02)
    size = out.new_zeros(())
    if out.shape[1] > 4:
        known = torch.isfinite(tgt[:, 4:6])
        if bool(known.any()):
            size = F.smooth_l1_loss(out[:, 4:6][known], tgt[:, 4:6][known], beta=0.02)
    return centre + 0.5 * axis + 0.5 * size, centre, axis, size


def placement_errors(refiner: P.PlacementRefiner | None, frames: Mapping[str, np.ndarray],
                     limit: int | None = None, seed: int = 1) -> dict[str, float]:
    """Median and mean bird's-eye centre error (m), median axis error (deg) and median
    length and width errors (m, where the true shape is known) of the estimates in
    ``frames`` (None: as estimated) or refined (``limit``: a seeded random subset of that
    many frames)."""
    idx = np.arange(len(frames["n"]))
    if limit is not None and len(idx) > limit:
        idx = np.sort(np.random.default_rng(seed).choice(idx, limit, replace=False))
    poses, ext = frames["est"][idx], frames["ext"][idx, :2]
    if refiner is not None:
        poses, sizes = refiner.refine([frame_points(frames, i) for i in idx], poses,
                                      frames["ext"][idx], seeds=list(idx))
        ext = ext * np.exp(sizes)
    err = np.hypot(*(poses[:, :2] - frames["true"][idx, :2]).T)
    axis = np.degrees(np.abs(P.targets(poses, frames["true"][idx])[:, 3]))
    size_err = np.abs(ext - frames["size"][idx, :2])
    known = np.isfinite(size_err[:, 0])
    med = (lambda a: float(np.median(a))) if known.any() else (lambda a: float("nan"))
    return {"frames": int(len(idx)), "centre_median": float(np.median(err)),
            "centre_mean": float(np.mean(err)), "axis_median_deg": float(np.median(axis)),
            "length_median": med(size_err[known, 0]), "width_median": med(size_err[known, 1])}


def _warm_start(net, init) -> None:
    """Copy ``init``'s weights into ``net`` (same width); the rows of ``net``'s last layer
    beyond ``init``'s (the size head) stay 0, so ``net`` starts as ``init`` with no size
    correction."""
    src = init.state_dict()
    with torch.no_grad():
        for name, t in net.state_dict().items():
            if name not in src:
                continue
            a = src[name]
            if a.shape == t.shape:
                t.copy_(a)
            elif a.shape[1:] == t.shape[1:] and a.shape[0] < t.shape[0]:
                t[:a.shape[0]].copy_(a)
            else:
                raise ConfigError(f"--init refiner's {name} {tuple(a.shape)} does not fit "
                                  f"{tuple(t.shape)} (another --width?)")


def train_refiner(train: Mapping[str, np.ndarray], val: Mapping[str, Mapping[str, np.ndarray]],
                  out: Path, cfg: RefinerTrainConfig, resume: bool = False,
                  meta: dict | None = None, init: P.PlacementRefiner | None = None
                  ) -> P.PlacementRefiner:
    """Train a refiner on ``train`` frames (module doc), checking it on each of ``val``; writes
    ``out/refiner.ckpt`` as it goes and ``out/refiner.pt`` at the end; returns the refiner.
    ``init``: start from this refiner's weights (a size head added to one without starts at
    0)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(cfg.threads)
    keep = np.hypot(*(train["est"][:, :2] - train["true"][:, :2]).T) < cfg.max_error
    train = {k: v[keep] for k, v in train.items()}
    if not len(train["n"]):
        raise ConfigError("no training frames (every estimate beyond --max-error, or no data)")
    if cfg.size and not np.isfinite(train["size"][:, 0]).any():
        raise ConfigError("--size: no training frame has a true shape (tracks without "
                          "'complete', or frames cached before the size head: remove "
                          "OUT/frames)")
    log.info("refiner: %d training frames (%d left out beyond %.1f m)", len(train["n"]),
             int((~keep).sum()), cfg.max_error)
    torch.manual_seed(cfg.seed)
    net = P.build_net(outputs=P.SIZE_OUTPUTS if cfg.size else 4)
    if init is not None:  # warm start: every weight of ``init`` that fits (a new head row: 0)
        _warm_start(net, init.net)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=cfg.steps,
                                                pct_start=0.05)
    rng = np.random.default_rng(cfg.seed)
    step = 0
    ckpt = out / "refiner.ckpt"
    if resume and ckpt.exists():
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        if state.get("config") != asdict(cfg):
            raise ConfigError(f"{ckpt}: made with other settings ({state.get('config')}); "
                              "resume with the same options or start a new --out")
        net.load_state_dict(state["net"])
        opt.load_state_dict(state["opt"])
        sched.load_state_dict(state["sched"])
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        step = int(state["step"])
        log.info("refiner: resumed at step %d", step)
    t0 = time.monotonic()
    bar = progress(total=cfg.steps, initial=step, desc="refiner", unit="step")
    running = None
    try:
        while step < cfg.steps:
            idx = rng.integers(0, len(train["n"]), cfg.batch)
            xyz, cond, tgt = make_batch(train, idx, rng, cfg.jitter)
            loss = loss_terms(net(xyz, cond), tgt)[0]
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            value = float(loss.detach())
            running = value if running is None else 0.98 * running + 0.02 * value
            bar.update(1)
            bar.set_postfix(loss=f"{running:.4f}", refresh=False)
            over = cfg.minutes > 0 and (time.monotonic() - t0) / 60 >= cfg.minutes
            if step % cfg.checkpoint_every == 0 or step == cfg.steps or over:
                _checkpoint(ckpt, net, opt, sched, rng, step, cfg)
            if over:
                log.info("refiner: --minutes %.1f reached at step %d", cfg.minutes, step)
                break
    finally:
        bar.close()
    refiner = P.PlacementRefiner(net)
    scores = {name: {"estimated": placement_errors(None, v, 5000),
                     "refined": placement_errors(refiner, v, 5000)} for name, v in val.items()}
    refiner.meta = {**(meta or {}), "steps": step, "config": asdict(cfg), "val": scores,
                    "train_frames": int(len(train["n"]))}
    refiner.save(out / "refiner.pt")
    atomic_write_json(out / "refiner_val.json", scores)
    return refiner


def _checkpoint(path: Path, net, opt, sched, rng, step: int, cfg: RefinerTrainConfig) -> None:
    import io

    buf = io.BytesIO()
    torch.save({"net": net.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
                "step": step, "config": asdict(cfg)}, buf)
    atomic_write_bytes(path, buf.getvalue())


def describe(scores: Mapping[str, Mapping[str, Mapping[str, float]]]) -> str:
    """A markdown table of :func:`train_refiner`'s validation figures."""
    lines = ["| set | frames | centre median (cm), estimated -> refined | centre mean (cm) "
             "| axis median (deg) | \\|length\\| median (cm) | \\|width\\| median (cm) |",
             "|---|---:|---|---|---|---|---|"]
    for name, s in scores.items():
        a, b = s["estimated"], s["refined"]
        lines.append(f"| {name} | {a['frames']} | {100 * a['centre_median']:.1f} -> "
                     f"{100 * b['centre_median']:.1f} | {100 * a['centre_mean']:.1f} -> "
                     f"{100 * b['centre_mean']:.1f} | {a['axis_median_deg']:.2f} -> "
                     f"{b['axis_median_deg']:.2f} | {100 * a.get('length_median', np.nan):.1f} "
                     f"-> {100 * b.get('length_median', np.nan):.1f} | "
                     f"{100 * a.get('width_median', np.nan):.1f} -> "
                     f"{100 * b.get('width_median', np.nan):.1f} |")
    return "\n".join(lines)


__all__ = ["RefinerTrainConfig", "collect_frames", "concat_frames", "describe",
           "load_frames", "make_batch", "placement_errors", "save_frames", "train_refiner"]
