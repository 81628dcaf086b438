"""Fusion ablations: what the recurrent model takes from a track's past frames (issue 19).

Every row runs the project's own evaluation (:func:`seqshape.evaluation.evaluate_tracks`) on
the val split, the networks fed the points alone (``hints=False``: no heading step, so every
row is the network itself), one method per call:

* ``baseline``: the per-frame model; ``sequential``: the recurrent model as shipped;
* ``seq, heading step``: the sequential model told the (identity) ego poses, so that its
  heading post-processing runs, as ``seqshape evaluate`` does by default (only the yaw moves);
* ``seq, state reset``: the recurrent model with its state dropped before every frame
  (:class:`ResetEachFrame`): the GRU's contribution is what it loses here;
* ``seq, shuffled``: the frames with points permuted within each track (points, poses and
  timestamps together, empty frames left in place), each frame scored against its own truth
  (:class:`ShuffledTracks`): what the order of the frames is worth;
* ``oracle -> baseline`` and ``oracle -> seq, reset``: the input at frame t is every point of
  frames <= t moved into frame t with the TRUE poses (sensor t <- canonical <- sensor s),
  a uniform random subset of the model's ``num_points`` of them, as the model would draw
  (:class:`OracleTracks`): a perfect track memory, the bound on what fusion could give.

Track memory with ESTIMATED alignment (issue 19, item 2; opt-in rows, ``--rows``; the shipped
weights, nothing retrained). Per track a :class:`VoxelMemory` (5 cm cells in the canonical
frame, one centroid and a hit count per cell, at most 20,000 cells) of its frames' points
taken into the canonical frame of each frame's ESTIMATED pose; at frame t the memory is placed
into frame t with frame t's estimate and fed, sampled by hit count, with at least half of the
network's ``num_points`` from frame t itself (:func:`fused_input`):

* ``memory -> baseline``, ``memory -> seq, reset`` (:class:`MemoryTracks`, online: past frames
  only): the pose from the shipped sequential model stepped as usual, then a second pass of
  the baseline, or of the sequential network with its state reset, on frame t + memory;
* ``memory + ICP -> ...``: frame t's pose first refined against the memory by a trimmed planar
  ICP (x, y, yaw: :func:`icp_2d`, :func:`align_to_memory`) before it places the memory and
  before frame t is merged;
* ``memory -> seq``: the second pass is a sequential network with its own state;
* ``memory, true poses -> baseline``: the same machinery with the true poses (the oracle's
  information through the voxel memory and the current-frame share);
* ``seq, offline``: :class:`seqshape.model.offline.OfflineEstimator` with its defaults;
  ``offline memory [+ ICP] -> baseline`` (:class:`OfflineMemory`): every frame of the track
  merged with the offline estimator's smoothed poses, each frame fed with the whole memory.
  The offline rows get the hints (ego poses, class): the smoother works in the fixed frame.

Printed: CD, CD of the shape alone at the true pose, translation, rotation, flips (% of
frames, % of tracks with one), the error at 17+ detections over the first's, and CD and
translation by detections so far (``seqshape.evaluation.report.DETECTION_BINS``) for moving
and parked tracks (``report.motion_groups``). EMD is off unless ``--emd-every K``.

    python benchmarks/bm_fusion.py --data /work/data/paper            # all 165 val tracks
    python benchmarks/bm_fusion.py --data DATA --limit 20             # quick look
    python benchmarks/bm_fusion.py --data DATA --checkpoint RUN/model.pt --baseline B/model.pt
    python benchmarks/bm_fusion.py --data /work/data/traffic_eval --split all \
        --rows baseline,sequential,mem-baseline,mem-icp-baseline,offline,offmem-baseline

With tracks that carry a class (realistic and real sets) the tables are printed again for
cars and for larger vehicles (van, truck, bus, trailer).

No timing: the quantity measured is accuracy. ``--json PATH`` keeps the numbers.
"""

from __future__ import annotations

import argparse
import sys
import time
import zlib
from collections.abc import Sequence
from inspect import signature
from pathlib import Path

import numpy as np
from _bench import print_table
from scipy.spatial import cKDTree

from seqshape._io import atomic_write_json
from seqshape.data import Track, TrackDataset
from seqshape.errors import ConfigError
from seqshape.evaluation import detection_span, evaluate_tracks
from seqshape.evaluation.evaluate import select_split
from seqshape.evaluation.metrics import flip_stats
from seqshape.evaluation.report import (
    DETECTION_LABELS,
    FLIP_DEG,
    detection_summary,
    floor_summary,
    method_summary,
)
from seqshape.geometry import canonical_to_sensor, sensor_to_canonical
from seqshape.model.estimator import Estimate, Estimator
from seqshape.model.heading import wrap_angle
from seqshape.model.offline import OfflineEstimator, estimate_track

#: Row keys (``--rows``) and their names in the tables.
ROWS = {"baseline": "baseline", "sequential": "sequential", "heading": "seq, heading step",
        "reset": "seq, state reset", "shuffled": "seq, shuffled",
        "oracle-baseline": "oracle -> baseline", "oracle-reset": "oracle -> seq, reset",
        "mem-baseline": "memory -> baseline", "mem-icp-baseline": "memory + ICP -> baseline",
        "mem-reset": "memory -> seq, reset", "mem-icp-reset": "memory + ICP -> seq, reset",
        "mem-seq": "memory -> seq", "offline": "seq, offline",
        "offmem-baseline": "offline memory -> baseline",
        "offmem-icp-baseline": "offline memory + ICP -> baseline",
        "offmem-icp-reset": "offline memory + ICP -> seq, reset",
        "mem-true-baseline": "memory, true poses -> baseline",
        "mem-icp-shape": "memory + ICP -> baseline, shape at seq pose",
        "offmem-icp-shape": "offline memory + ICP -> baseline, shape at offline pose"}
#: The rows run by default (the memory rows are opt-in: ``--rows``).
DEFAULT_ROWS = ("baseline", "sequential", "heading", "reset", "shuffled", "oracle-baseline",
                "oracle-reset")


class ResetEachFrame:
    """An estimator whose inner estimator's state is dropped before every step: a recurrent
    model run as a per-frame one."""

    recurrent = False

    def __init__(self, inner):
        self.inner = inner

    def step(self, track_ids: Sequence[str], point_lists: Sequence[np.ndarray],
             timestamps: Sequence[float] | None = None, **hints):
        for t in track_ids:
            self.inner.reset(t)
        # the runner passes timestamps to a ``step`` that names them; forward them if the
        # inner estimator takes them too (a model with motion inputs)
        if timestamps is not None and "timestamps" in signature(self.inner.step).parameters:
            hints["timestamps"] = timestamps
        return self.inner.step(track_ids, point_lists, **hints)

    def reset(self, track_id: str | None = None) -> None:
        self.inner.reset(track_id)


def shuffle_track(track: Track, rng: np.random.Generator) -> tuple[Track, np.ndarray]:
    """``track`` with its frames that hold points permuted among themselves (points, poses,
    timestamps together; empty frames keep their place, so the scored span is unchanged).
    Returns the track and ``order`` (T,): new frame i holds old frame ``order[i]``."""
    order = np.arange(len(track))
    det = np.flatnonzero(track.num_points > 0)
    order[det] = rng.permutation(det)
    return Track(track.track_id, [track.points[i] for i in order], track.poses[order],
                 track.complete, track.size, track.timestamps[order], dict(track.meta)), order


def accumulate_track(track: Track, num_points: int, rng: np.random.Generator) -> Track:
    """The oracle input (module doc): frame t holds a uniform random subset of at most
    ``num_points`` of the points of frames <= t, moved into frame t with the true poses.

    Frames after the last detection stay empty (the scored span is the original one), frames
    with an unknown pose neither give nor receive points (they keep their own points).
    """
    span = detection_span(track)
    known = np.all(np.isfinite(track.poses), axis=1)
    canon = [sensor_to_canonical(p, track.poses[t]) if known[t] else np.zeros((0, 3))
             for t, p in enumerate(track.points)]
    pool = np.concatenate(canon).astype(np.float64)  # (sum N_t, 3), in frame order
    ends = np.cumsum([len(c) for c in canon])  # (T,) points of frames <= t
    points = []
    for t in range(len(track)):
        if span is None or t >= span[1] or not known[t] or ends[t] == 0:
            points.append(track.points[t] if span is None or t < span[1] else np.zeros((0, 3)))
            continue
        idx = rng.choice(ends[t], size=min(num_points, ends[t]), replace=False)
        points.append(canonical_to_sensor(pool[np.sort(idx)], track.poses[t]).astype(np.float32))
    return Track(track.track_id, points, track.poses, track.complete, track.size,
                 track.timestamps, dict(track.meta))


def restore_counts(rec: dict[str, np.ndarray], tracks: list[Track]) -> None:
    """Set ``n_det`` and ``n_points`` of oracle records to the original tracks' (the oracle
    frames all hold points, so the runner counts every frame as a detection)."""
    by_id = {tr.track_id: tr for tr in tracks}
    n_det = {tid: np.cumsum(tr.num_points > 0) for tid, tr in by_id.items()}
    for i, (tid, f) in enumerate(zip(rec["track_id"], rec["frame"], strict=True)):
        rec["n_det"][i] = n_det[tid][f]
        rec["n_points"][i] = by_id[tid].num_points[f]


# ---------------------------------------------------------------------------------------------
# Track memory with ESTIMATED alignment (issue 19 item 2): rows "memory -> ..."


class VoxelMemory:
    """A track's past points in its canonical frame, one centroid per ``voxel`` cell (bounded:
    at most ``max_voxels`` cells, the least recently hit dropped first)."""

    def __init__(self, voxel: float = 0.05, max_voxels: int = 20000):
        self.voxel, self.max_voxels = float(voxel), int(max_voxels)
        self.index: dict[tuple, int] = {}
        self.sums = np.zeros((0, 3))
        self.counts = np.zeros(0)
        self.stamp = np.zeros(0)
        self.frames = 0

    def __len__(self) -> int:
        return len(self.counts)

    def points(self) -> np.ndarray:
        """(M, 3) voxel centroids."""
        return self.sums / self.counts[:, None]

    def add(self, canon: np.ndarray) -> None:
        """Merge (N, 3) canonical points."""
        self.frames += 1
        if not len(canon):
            return
        keys = np.floor(canon / self.voxel).astype(np.int64)
        uniq, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        sums = np.zeros((len(uniq), 3))
        np.add.at(sums, inv, canon)
        counts = np.bincount(inv, minlength=len(uniq)).astype(float)
        rows, new = [], []
        for u, k in enumerate(map(tuple, uniq.tolist())):
            i = self.index.get(k)
            if i is None:
                new.append(u)
            else:
                rows.append((i, u))
        if rows:
            i, u = np.array(rows).T
            self.sums[i] += sums[u]
            self.counts[i] += counts[u]
            self.stamp[i] = self.frames
        if new:
            start = len(self.counts)
            for j, u in enumerate(new):
                self.index[tuple(uniq[u].tolist())] = start + j
            self.sums = np.concatenate([self.sums, sums[new]])
            self.counts = np.concatenate([self.counts, counts[new]])
            self.stamp = np.concatenate([self.stamp, np.full(len(new), float(self.frames))])
        if len(self.counts) > self.max_voxels:
            keep = np.sort(np.argsort(-self.stamp, kind="stable")[:self.max_voxels])
            key_of = {v: k for k, v in self.index.items()}
            self.index = {key_of[int(i)]: j for j, i in enumerate(keep)}
            self.sums, self.counts = self.sums[keep], self.counts[keep]
            self.stamp = self.stamp[keep]


def _rot2(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def icp_2d(src: np.ndarray, tree, dst: np.ndarray, iters: int = 30, trim: float = 0.95,
           max_dist: float = 1.0) -> tuple[float, np.ndarray, float]:
    """Trimmed point-to-point ICP in the plane: ``(theta, d, residual)`` with
    ``R(theta) src_xy + d`` aligned to ``dst`` (nearest neighbours in 3D, z untouched);
    residual = mean distance of the kept pairs at the last step."""
    theta, d = 0.0, np.zeros(2)
    resid = np.inf
    for _ in range(iters):
        cur = src.copy()
        cur[:, :2] = src[:, :2] @ _rot2(theta).T + d
        dist, idx = tree.query(cur)
        keep = dist <= min(max_dist, float(np.quantile(dist, trim)))
        resid = float(dist[keep].mean()) if keep.any() else np.inf
        if keep.sum() < 10:
            break
        a, b = cur[keep, :2], dst[idx[keep], :2]
        ma, mb = a.mean(0), b.mean(0)
        h = (a - ma).T @ (b - mb)
        dth = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
        r = _rot2(dth)
        step = mb - r @ ma
        theta += dth
        d = r @ d + step
        if abs(dth) < 1e-4 and np.hypot(*step) < 1e-4:
            break
    return theta, d, resid


def corrected_pose(pose: np.ndarray, theta: float, d: np.ndarray) -> np.ndarray:
    """The pose whose canonical frame is ``R(theta) c + d`` of ``pose``'s canonical ``c``."""
    out = np.array(pose, dtype=np.float64)
    out[3] = pose[3] - theta
    out[:2] = pose[:2] - _rot2(out[3]) @ d
    return out


def _trimmed_residual(src: np.ndarray, tree, trim: float = 0.7) -> float:
    dist, _ = tree.query(src)
    return float(np.sort(dist)[:max(1, int(trim * len(dist)))].mean())


def align_to_memory(points: np.ndarray, pose: np.ndarray, mem: VoxelMemory, icp: bool,
                    max_shift: float = 1.0, max_turn: float = np.radians(30),
                    flip_test: bool = False) -> np.ndarray:
    """The pose of frame t that puts its points onto the memory: ``pose`` refined by
    :func:`icp_2d` when ``icp`` (a correction beyond ``max_shift`` / ``max_turn`` is dropped).
    ``flip_test``: also try ``pose`` turned by pi and keep whichever fits the memory better
    (off: measured worse, the chain flips on near-symmetric views; docs/model.md)."""
    pose = np.asarray(pose, dtype=np.float64)
    if len(mem) < 10 or len(points) < 10 or not np.all(np.isfinite(pose)):
        return pose
    dst = mem.points()
    tree = cKDTree(dst)
    best, best_r = pose, np.inf
    for turn in (0.0, np.pi) if flip_test else (0.0,):
        cand = pose.copy()
        cand[3] = cand[3] + turn
        src = sensor_to_canonical(points, cand)
        r = np.inf
        if icp:
            theta, d, r = icp_2d(src, tree, dst)
            if abs(theta) <= max_turn and np.hypot(*d) <= max_shift:
                cand = corrected_pose(cand, theta, d)
            else:
                r = np.inf
        if not np.isfinite(r):
            r = _trimmed_residual(src, tree)
        if r < best_r:
            best, best_r = cand, r
    return best


def fused_input(points: np.ndarray, pose: np.ndarray, mem: VoxelMemory, num_points: int,
                current_share: float, rng: np.random.Generator, weighted: bool = True
                ) -> np.ndarray:
    """Frame t's input: at least ``current_share`` of ``num_points`` from its own points
    (all of them when fewer), the rest a uniform sample of the memory placed with ``pose``."""
    n_cur = min(len(points), num_points)
    if len(mem) and np.all(np.isfinite(pose)):
        n_cur = min(len(points), max(int(np.ceil(current_share * num_points)),
                                     num_points - len(mem)))
    else:
        return np.asarray(points, dtype=np.float32)
    cur = points if n_cur == len(points) else points[np.sort(
        rng.choice(len(points), n_cur, replace=False))]
    n_mem = min(len(mem), num_points - n_cur)
    prob = mem.counts / mem.counts.sum() if weighted else None
    mem_pts = mem.points()[np.sort(rng.choice(len(mem), n_mem, replace=False, p=prob))]
    return np.concatenate([cur, canonical_to_sensor(mem_pts, pose)]).astype(np.float32)


def place_at(est, pose: np.ndarray):
    """``est`` with its complete shape moved to ``pose`` (taken into its canonical frame with
    its own pose, turned by pi when that is nearer the new yaw, placed with ``pose``), and
    ``pose`` as its pose: the memory's shape at another estimator's placement."""
    pose = np.asarray(pose, dtype=np.float64)
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(est.pose))):
        return est
    own = np.array(est.pose, dtype=np.float64)
    if abs(wrap_angle(own[3] - pose[3])) > np.pi / 2:
        own[3] = wrap_angle(own[3] + np.pi)
    est.complete = canonical_to_sensor(sensor_to_canonical(est.complete, own), pose)
    est.pose = pose.copy()
    return est


def _step_kw(est, timestamps) -> dict:
    if timestamps is not None and "timestamps" in signature(est.step).parameters:
        return {"timestamps": timestamps}
    return {}


class MemoryTracks:
    """Online track memory (rows ``memory -> ...``): per track a :class:`VoxelMemory` of its
    past frames' points in the canonical frames of the ESTIMATED poses (the sequential
    model's, stepped as shipped), placed into frame t with frame t's estimate (refined against
    the memory by :func:`icp_2d` when ``icp``) and fed with frame t's points to
    ``fuse`` (the baseline, the sequential model reset every frame, or a second sequential
    model with its own state)."""

    recurrent = True

    def __init__(self, pose_est, fuse, icp: bool = False, current_share: float = 0.5,
                 voxel: float = 0.05, seed: int = 0, shape_only: bool = False):
        self.pose_est, self.fuse, self.icp = pose_est, fuse, icp
        self.shape_only = shape_only
        self.current_share, self.voxel, self.seed = current_share, voxel, seed
        self.num_points = pose_est.config.num_points
        self.mem: dict[str, VoxelMemory] = {}
        self.rng: dict[str, np.random.Generator] = {}

    def reset(self, track_id: str | None = None) -> None:
        self.pose_est.reset(track_id)
        self.fuse.reset(track_id)
        if track_id is None:
            self.mem.clear()
            self.rng.clear()
        else:
            self.mem.pop(track_id, None)
            self.rng.pop(track_id, None)

    def step(self, track_ids: Sequence[str], point_lists: Sequence[np.ndarray],
             timestamps: Sequence[float] | None = None, **hints):
        poses = self.pose_est.step(track_ids, point_lists,
                                   **_step_kw(self.pose_est, timestamps), **hints)
        inputs = []
        for tid, pts, est in zip(track_ids, point_lists, poses, strict=True):
            mem = self.mem.setdefault(tid, VoxelMemory(self.voxel))
            rng = self.rng.setdefault(tid, np.random.default_rng(
                [self.seed, zlib.crc32(tid.encode())]))
            pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
            pose = align_to_memory(pts, est.pose, mem, self.icp)
            inputs.append(fused_input(pts, pose, mem, self.num_points, self.current_share, rng))
            if np.all(np.isfinite(pose)):
                mem.add(sensor_to_canonical(pts, pose))
        out = self.fuse.step(track_ids, inputs, **_step_kw(self.fuse, timestamps), **hints)
        if self.shape_only:  # the memory's shape at the sequential model's own pose
            out = [place_at(e, p.pose) for e, p in zip(out, poses, strict=True)]
        return out


class OfflineMemory:
    """Offline track memory (rows ``offline memory -> ...``): the poses of the offline
    estimator (:func:`seqshape.model.offline.estimate_track`, its default: online shape,
    smoothed pose, whole-track heading), every frame merged into one memory in their
    canonical frames (in frame order, each aligned to the memory so far as online), then
    each frame fed with the whole memory placed with its own pose to ``fuse``."""

    whole_track = True
    recurrent = True

    def __init__(self, seq, fuse, icp: bool = False, current_share: float = 0.5,
                 voxel: float = 0.05, seed: int = 0, shape_only: bool = False):
        self.seq, self.fuse, self.icp = seq, fuse, icp
        self.estimator = seq  # the runner reads the hints (ego poses, class) for this one
        self.shape_only = shape_only
        self.current_share, self.voxel, self.seed = current_share, voxel, seed
        self.num_points = seq.config.num_points

    def reset(self, track_id: str | None = None) -> None:
        self.fuse.reset(track_id)

    def estimate_track(self, points: Sequence[np.ndarray], timestamps=None,
                       track_id: str = "track", **hints) -> list:
        off = estimate_track(self.seq, points, timestamps=timestamps, track_id=track_id,
                             **hints)
        mem = VoxelMemory(self.voxel)
        rng = np.random.default_rng([self.seed, zlib.crc32(track_id.encode())])
        pts = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in points]
        poses = []
        for p, e in zip(pts, off, strict=True):
            pose = align_to_memory(p, e.pose, mem, self.icp)
            if np.all(np.isfinite(pose)):
                mem.add(sensor_to_canonical(p, pose))
            poses.append(pose)
        self.fuse.reset(track_id)
        out = []
        for t, (p, pose) in enumerate(zip(pts, poses, strict=True)):
            x = fused_input(p, pose, mem, self.num_points, self.current_share, rng)
            ts = None if timestamps is None else [float(timestamps[t])]
            out.append(self.fuse.step([track_id], [x], **_step_kw(self.fuse, ts))[0])
            if self.shape_only:  # the memory's shape at the offline estimator's pose
                out[-1] = place_at(out[-1], off[t].pose)
        self.fuse.reset(track_id)
        return out


class TruePoses:
    """A stand-in pose estimator for :class:`MemoryTracks` that returns each track's TRUE pose
    of the frame stepped (row ``memory, true poses -> baseline``: the memory machinery itself,
    voxels and the current frame's share, measured against the oracle)."""

    def __init__(self, tracks: Sequence[Track], config):
        self.tracks = {tr.track_id: tr for tr in tracks}
        self.config = config
        self.next: dict[str, int] = {}

    def reset(self, track_id: str | None = None) -> None:
        if track_id is None:
            self.next.clear()
        else:
            self.next.pop(track_id, None)

    def step(self, track_ids: Sequence[str], point_lists: Sequence[np.ndarray], **_):
        out = []
        for tid, pts in zip(track_ids, point_lists, strict=True):
            tr = self.tracks[tid]
            t = self.next.get(tid, detection_span(tr)[0])
            self.next[tid] = t + 1
            out.append(Estimate(tid, np.zeros((0, 3), np.float32), tr.poses[t].copy(), len(pts)))
        return out


def twin(est: Estimator) -> Estimator:
    """Another estimator over the same network (its own track states)."""
    return Estimator(est.model, est.threads, seed=est.seed, heading=est.heading,
                     frame_period=est.frame_period, backend=est.backend)


def row_estimator(key: str, seq: Estimator, base: Estimator, seed: int,
                  tracks: Sequence[Track] = ()):
    """``(estimator, hints)`` of row ``key``. The offline rows get the hints (ego poses and
    class): the offline smoother works in the fixed frame of the ego poses."""
    if key in ("baseline", "oracle-baseline"):
        return base, False
    if key in ("sequential", "shuffled"):
        return seq, False
    if key == "heading":
        return seq, True
    if key in ("reset", "oracle-reset"):
        return ResetEachFrame(seq), False
    if key == "offline":
        return OfflineEstimator(seq), True
    if key == "mem-true-baseline":
        return MemoryTracks(TruePoses(tracks, seq.config), base, seed=seed), False
    if key == "mem-icp-shape":
        return MemoryTracks(twin(seq), base, icp=True, seed=seed, shape_only=True), False
    if key == "offmem-icp-shape":
        return OfflineMemory(seq, base, icp=True, seed=seed, shape_only=True), True
    icp = "icp" in key
    fuse = base if key.endswith("baseline") else ResetEachFrame(twin(seq)) \
        if key.endswith("reset") else twin(seq)
    if key.startswith("offmem"):
        return OfflineMemory(seq, fuse, icp=icp, seed=seed), True
    return MemoryTracks(twin(seq), fuse, icp=icp, seed=seed), False


def run_rows(tracks: list[Track], seq, base, rows: Sequence[str], emd_every: int,
             workers: int, seed: int) -> dict[str, dict]:
    """Evaluate each row of :data:`ROWS` whose key is in ``rows``; ``{row name: {"rec",
    "floor_cm", "seconds"}}``."""
    out = {}
    for key in rows:
        name = ROWS[key]
        est, hints = row_estimator(key, seq, base, seed, tracks)
        data = tracks
        if key == "shuffled":
            data = [shuffle_track(tr, np.random.default_rng([seed, i]))[0]
                    for i, tr in enumerate(tracks)]
        elif key.startswith("oracle"):
            k = (base if key == "oracle-baseline" else seq).config.num_points
            data = [accumulate_track(tr, k, np.random.default_rng([seed, i]))
                    for i, tr in enumerate(tracks)]
        t0 = time.perf_counter()
        res = evaluate_tracks({name: est}, data, emd_every=emd_every, workers=workers,
                              hints=hints, seed=seed)
        rec = res.of(name)
        if key.startswith("oracle"):
            restore_counts(rec, tracks)
        out[name] = {"rec": rec, "floor_cm": floor_summary(res, name)["cd_floor_cm"],
                     "seconds": time.perf_counter() - t0}
        print(f"{name}: {len(rec['frame'])} frames in {out[name]['seconds']:.0f} s",
              file=sys.stderr, flush=True)
    return out


#: Class groups reported separately when the tracks carry a class (realistic and real sets).
CLASS_GROUPS = {"cars": {"car"}, "larger vehicles": {"van", "truck", "bus", "trailer"}}


def class_subset(results: dict[str, dict], members: set[str]) -> dict[str, dict]:
    """``results`` restricted to the frames of tracks whose class is in ``members`` (empty
    when no frame is)."""
    out = {}
    for name, r in results.items():
        keep = np.isin(r["rec"]["class"], sorted(members))
        if not keep.any():
            return {}
        out[name] = {**r, "rec": {k: v[keep] for k, v in r["rec"].items()}}
    return out


def _f(v, digits: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def summarise(results: dict[str, dict]) -> dict[str, dict]:
    """Per row: the report's method summary, flips, detection groups and the share of frames
    whose rotation error lies between 90 degrees and the flip threshold."""
    out = {}
    for name, r in results.items():
        rec = r["rec"]
        table, details = method_summary(rec)
        by_det, ratios = detection_summary(rec)
        rot = np.degrees(rec["rot_rad"][np.isfinite(rec["rot_rad"])])
        out[name] = {**table, "shape_cd_cm": details.get("shape_cd_cm"),
                     "flips": flip_stats(rec["rot_rad"], rec["track_id"], FLIP_DEG),
                     "wrong_way_pct": float(100 * (rot > 90.0).mean()) if len(rot) else None,
                     "by_detections": by_det, "late_over_first": ratios,
                     "floor_cm": r["floor_cm"], "n_frames": int(len(rec["frame"])),
                     "n_tracks": int(len(np.unique(rec["track_id"]))),
                     "seconds": r["seconds"]}
    return out


def print_tables(summary: dict[str, dict]) -> None:
    head = ["row", "CD (cm)", "shape CD (cm)", "transl. (cm)", "rot. (deg)",
            f"flips > {FLIP_DEG:.0f} deg (%)", "> 90 deg (%)", "tracks with a flip (%)",
            "CD 17+/1", "transl. 17+/1"]
    rows = []
    for name, s in summary.items():
        f, r = s["flips"], s["late_over_first"].get("all", {})
        rows.append([name, _f(s["cd_cm"]), _f(s["shape_cd_cm"]), _f(s["trans_cm"]),
                     _f(s["rot_deg"]), _f(f["flip_pct"], 1), _f(s["wrong_way_pct"], 1),
                     _f(f["tracks_with_flip_pct"], 1), _f(r.get("cd")), _f(r.get("trans"))])
    print_table(head, rows)
    first = next(iter(summary.values()))
    print(f"\nAll frames, {first['n_tracks']} tracks, {first['n_frames']} frames per row; "
          f"CD floor {_f(first['floor_cm'])} cm.\n")
    labels = DETECTION_LABELS
    groups = [g for g in ("moving", "parked") if g in first["by_detections"]] or ["all"]
    for g in groups:
        per = first["by_detections"][g]
        rows = [["frames", *[str(per.get(lab, {}).get("n_frames", 0)) for lab in labels],
                 "", ""]]
        for name, s in summary.items():
            per = s["by_detections"].get(g, {})
            r = s["late_over_first"].get(g, {})
            rows.append([name, *[_f(per.get(lab, {}).get("cd_cm")) for lab in labels],
                         _f(r.get("cd")), ""])
            rows.append(["", *[_f(per.get(lab, {}).get("trans_cm")) for lab in labels],
                         "", _f(r.get("trans"))])
        print(f"{g} tracks: CD (first line) and translation (second line, cm) by detections "
              f"so far")
        print_table([f"{g}", *labels, "CD 17+/1", "transl. 17+/1"], rows)
        print()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True,
                    help="track dataset folder (e.g. one made by seqshape generate --preset paper)")
    ap.add_argument("--split", default="val",
                    help="split to evaluate (default val; \"all\": every track)")
    ap.add_argument("--checkpoint", default="pretrained", help="sequential model")
    ap.add_argument("--baseline", default="pretrained", help="per-frame baseline model")
    ap.add_argument("--limit", type=int, default=None, help="first N tracks of the split")
    ap.add_argument("--rows", default=",".join(DEFAULT_ROWS),
                    help="comma-separated row keys, of: " + ", ".join(ROWS))
    ap.add_argument("--emd-every", type=int, default=0, help="EMD every K frames (0: off)")
    ap.add_argument("--workers", type=int, default=1, help="EMD processes")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--seed", type=int, default=0, help="shuffle and oracle subsets")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = ap.parse_args()
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = [r for r in rows if r not in ROWS]
    if unknown:
        sys.exit(f"unknown rows {unknown}; choose from {', '.join(ROWS)}")
    split = select_split(TrackDataset(args.data), args.split)
    n = len(split) if args.limit is None else min(args.limit, len(split))
    tracks = [split[i] for i in range(n)]
    tracks = [tr for tr in tracks if detection_span(tr) is not None]
    try:
        seq = Estimator.load(args.checkpoint, kind="sequential", threads=args.threads,
                             refiner="none")  # the ablations: the networks alone
        base = Estimator.load(args.baseline, kind="baseline", threads=args.threads,
                              refiner="none")
    except ConfigError as exc:  # a wrong or missing model: say so without a traceback
        sys.exit(str(exc))
    results = run_rows(tracks, seq, base, rows, args.emd_every, args.workers, args.seed)
    summary = summarise(results)
    print_tables(summary)
    by_class = {}
    for group, members in CLASS_GROUPS.items():
        sub = class_subset(results, members)
        if sub:
            print(f"\n=== {group} ({', '.join(sorted(members))}) ===\n")
            by_class[group] = summarise(sub)
            print_tables(by_class[group])
    if args.json:
        atomic_write_json(args.json, {"settings": {k: str(v) for k, v in vars(args).items()},
                                      "rows": summary, "by_class": by_class})
    return 0


if __name__ == "__main__":
    sys.exit(main())
