"""Training windows: W consecutive frames of one track, padded to fixed-size tensors.

A window is a pure function of ``(seed, key, epoch, index)`` (``key`` separates streams, e.g.
the training stage), so a resumed run sees exactly the windows an uninterrupted run would and
data-parallel processes can each take their share of the same global order.

Item ``i`` of :class:`WindowDataset` is a window of track ``i // windows_per_track``::

    points    float32 (W, N, 3)   sensor-frame points per frame, resampled/padded to N
    lengths   int64   (W,)        real points per frame (0 = empty frame)
    poses     float32 (W, 4)      ground-truth (x, y, z, yaw) per frame (0 where unknown)
    valid     bool    (W,)        frame exists (short tracks are padded) and its pose is known
    complete  float32 (M, 3)      ground-truth complete shape, canonical frame, M points
    start     int64   ()          first frame index of the window in its track
    length    float32 (W,)        vehicle length L per frame for the input scale (only when
                                  ``length_hint_noise`` is set; see below)
    dts       float32 (W,)        time (s) from the track's previous frame to this one (only
                                  with ``motion``; 0 at the window's first frame, NaN where a
                                  timestamp is unknown: the network then assumes its frame
                                  period)
    counts    int64   (W,)        points per frame before resampling to N (only with ``motion``)

The motion inputs (``ModelConfig.motion_input``) treat a window like a fresh track: its first
frame with points has no "previous" detection (zero displacement and time), exactly as the
``Estimator`` does at a track's first step, wherever the window starts.

Input-scale lengths (``ModelConfig.scale_norm="length"``): per window, with probability
``length_points_prob`` the points' own estimate (:func:`points_length`, the running maximum
over the window's frames for the sequential model, as the ``Estimator`` does without hints),
otherwise a tracker's box length: the true length times ``exp(b + e_t)``, b ~ N(0,
noise) per window (a box's size bias) and e_t ~ N(0, noise / 3) per frame (its jitter).
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np
import torch

from seqshape.data.dataset import TrackDataset
from seqshape.data.track import Track
from seqshape.errors import DataError

log = logging.getLogger(__name__)


def resample_frame(points: np.ndarray, num_points: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Fit one frame (n, 3) into exactly ``num_points`` rows.

    More than ``num_points``: a random subset without replacement. Fewer: the points repeated
    cyclically to fill the rows (the returned length n tells the network which rows are real,
    so the mean and the max-pool see each point once). Returns (points (N, 3) float32, length).
    """
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = len(points)
    if n > num_points:
        idx = np.sort(rng.choice(n, num_points, replace=False))
        return points[idx], num_points
    if n == 0:
        return np.zeros((num_points, 3), np.float32), 0
    return np.resize(points, (num_points, 3)), n


#: Bird's-eye directions (0, 22.5, ..., 157.5 deg) over which :func:`points_length` takes the
#: percentile extent; the largest is within cos(11.25 deg) = 2 % of the true diameter.
_DIRECTIONS = np.stack([np.cos(np.arange(8) * np.pi / 8), np.sin(np.arange(8) * np.pi / 8)])
LENGTH_PERCENTILES = (1.0, 99.0)
_COS32, _SIN32 = (_DIRECTIONS[k].astype(np.float32) for k in range(2))


def points_length(points: np.ndarray) -> float:
    """A vehicle length estimate from its points alone: the largest bird's-eye extent (1st
    to 99th percentile, linear interpolation, so a stray return does not count) over 8
    directions; 0 for fewer than two points. A partial view gives a lower bound: take the
    running maximum over a track. Many frames at once: :func:`points_lengths`."""
    return float(points_lengths([points])[0])


def points_lengths(frames: Sequence[np.ndarray]) -> np.ndarray:
    """``(F,)`` float64 :func:`points_length` of each frame of finite points, with a few array
    operations for all frames (a streaming step of many tracks); a frame's length does not
    depend on the others in the batch (tested)."""
    frames = [np.asarray(f, dtype=np.float32).reshape(-1, 3) for f in frames]
    counts = np.array([len(f) for f in frames], dtype=np.int64)
    out = np.zeros(len(frames))
    ok = np.flatnonzero(counts >= 2)
    if not len(ok):
        return out
    n = counts[ok]
    pts = frames[ok[0]] if len(ok) == 1 else np.concatenate([frames[i] for i in ok])
    # (8, P) projections as two products and a sum per entry: no fused multiply-add whose use
    # would depend on the shape of a matrix product; laid out for per-frame sorts
    proj = np.multiply.outer(_COS32, pts[:, 0])
    proj += np.multiply.outer(_SIN32, pts[:, 1])
    if len(ok) == 1:  # one frame (a single-track step): no padding
        batch = proj[None]
    else:
        batch = np.full((len(ok), 8, int(n.max())), np.inf, dtype=np.float32)
        ends = np.cumsum(n)
        for k, (e, m) in enumerate(zip(ends.tolist(), n.tolist(), strict=True)):
            batch[k, :, :m] = proj[:, e - m:e]
    batch.sort(axis=2)  # the padding (inf) after each frame's own values
    ext = []
    rows = np.arange(len(ok))
    for q in LENGTH_PERCENTILES:  # linear interpolation between the two nearest ranks
        pos = q / 100.0 * (n - 1)
        i = pos.astype(np.int64)
        j = np.minimum(i + 1, n - 1)
        frac = (pos - i).astype(np.float32)[:, None]
        a, b = batch[rows, :, i], batch[rows, :, j]  # (F', 8)
        ext.append(a + frac * (b - a))
    out[ok] = (ext[1] - ext[0]).max(axis=1)
    return out


def running_lengths(frame_lengths: np.ndarray, running: bool) -> np.ndarray:
    """Per-frame lengths with empty frames (0) carrying the last known one, and with
    ``running`` the running maximum (frames before the first points stay 0 = unknown)."""
    out = np.asarray(frame_lengths, dtype=np.float64).copy()
    for k in range(1, len(out)):
        if out[k] <= 0 or (running and out[k] < out[k - 1]):
            out[k] = out[k - 1]
    return out


class TrackCache:
    """Tracks of a dataset loaded lazily, the ``size`` most recently used kept in memory."""

    def __init__(self, tracks: TrackDataset, size: int = 128):
        self.tracks = tracks
        self.size = max(1, int(size))
        self._cache: OrderedDict[int, Track] = OrderedDict()

    def __len__(self) -> int:
        return len(self.tracks)

    def get(self, i: int) -> Track:
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        track = self.tracks[i]
        if track.complete is None or len(track.complete) == 0:
            raise DataError(self.tracks.path / self.tracks.entries[i]["file"],
                            "track has no ground-truth complete shape; cannot train on it")
        self._cache[i] = track
        if len(self._cache) > self.size:
            self._cache.popitem(last=False)
        return track


class WindowDataset(torch.utils.data.Dataset):
    """Windows of ``window`` consecutive frames over the tracks of one split.

    Args:
        tracks: a :class:`TrackDataset` (typically ``ds.split("train")``).
        window: W, frames per window (tracks shorter than W are padded with invalid frames).
        num_points: N, points per frame (random subset without replacement if more; padded
            with a lengths mask if fewer).
        num_complete: M, ground-truth complete points per window (subset without replacement,
            or with replacement when the track holds fewer).
        windows_per_track: windows drawn per track and epoch.
        p_first: probability that a window starts at frame 0 (the paper's recursion from the
            first detection); otherwise the start is uniform over the track.
        seed, key: select the random stream; ``set_epoch`` selects the epoch.
        cache_size: tracks kept in memory (a track file holds all its frames).
        length_hint_noise: None (no ``length`` entry; the windows are then exactly those of
            a dataset without the option) or the log-normal sigma of a tracker's box length.
        length_points_prob: probability that a window's lengths come from its points.
        length_running: points lengths are running maxima (sequential) or per frame.
        motion: add ``dts`` and ``counts`` (the motion inputs' time steps and raw point
            counts; no random draws, so the other entries are unchanged).
    """

    def __init__(self, tracks: TrackDataset, window: int = 8, num_points: int = 256,
                 num_complete: int = 1024, windows_per_track: int = 1, p_first: float = 0.25,
                 seed: int = 0, key: int = 0, cache_size: int = 128,
                 length_hint_noise: float | None = None, length_points_prob: float = 0.0,
                 length_running: bool = True, motion: bool = False):
        if len(tracks) == 0:
            raise DataError(tracks.path, "no tracks to draw training windows from")
        self.cache = TrackCache(tracks, cache_size)
        self.window = int(window)
        self.num_points = int(num_points)
        self.num_complete = int(num_complete)
        self.windows_per_track = max(1, int(windows_per_track))
        self.p_first = float(p_first)
        self.seed = int(seed)
        self.key = int(key)
        self.epoch = 0
        self.length_hint_noise = None if length_hint_noise is None else float(length_hint_noise)
        self.length_points_prob = float(length_points_prob)
        self.length_running = bool(length_running)
        self.motion = bool(motion)

    def __len__(self) -> int:
        return len(self.cache) * self.windows_per_track

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        return self.window_at(i, self.epoch)

    def window_at(self, i: int, epoch: int) -> dict[str, np.ndarray]:
        """Window ``i`` of ``epoch`` (deterministic)."""
        if not 0 <= i < len(self):
            raise IndexError(f"window {i} out of range for {len(self)} windows")
        rng = np.random.default_rng([self.seed, self.key, int(epoch), int(i)])
        track = self.cache.get(i // self.windows_per_track)
        t, w = len(track), self.window
        start = 0
        if t > w and rng.random() >= self.p_first:
            start = int(rng.integers(0, t - w + 1))
        n = min(w, t - start)
        points = np.zeros((w, self.num_points, 3), np.float32)
        lengths = np.zeros(w, np.int64)
        for k in range(n):
            points[k], lengths[k] = resample_frame(track.points[start + k], self.num_points, rng)
        poses = np.zeros((w, 4), np.float32)
        valid = np.zeros(w, bool)
        gt = track.poses[start:start + n]
        known = np.all(np.isfinite(gt), axis=1)
        poses[:n][known] = gt[known]
        valid[:n] = known
        m = len(track.complete)
        idx = rng.choice(m, self.num_complete, replace=m < self.num_complete)
        out = {"points": points, "lengths": lengths, "poses": poses, "valid": valid,
               "complete": track.complete[idx].astype(np.float32), "start": np.int64(start)}
        if self.length_hint_noise is not None:  # drawn last: the rest stays as without it
            out["length"] = self._lengths(track, points, lengths, rng)
        if self.motion:
            out["dts"], out["counts"] = window_motion(track, start, n, w)
        return out

    def _lengths(self, track: Track, points: np.ndarray, lengths: np.ndarray,
                 rng: np.random.Generator) -> np.ndarray:
        w, sigma = self.window, self.length_hint_noise
        if rng.random() < self.length_points_prob:
            per_frame = points_lengths([points[k, :lengths[k]] for k in range(w)])
            return running_lengths(per_frame, self.length_running).astype(np.float32)
        log_noise = rng.normal(0.0, sigma) + rng.normal(0.0, sigma / 3.0, size=w)
        return (float(track.size[0]) * np.exp(log_noise)).astype(np.float32)


def window_motion(track: Track, start: int, n: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """``dts`` (W,) float32 and ``counts`` (W,) int64 of the window of ``n`` real frames of
    ``track`` from ``start`` (padded to ``w``): time steps from the previous frame (0 at the
    window's first frame and on padding, NaN where a timestamp is not finite) and raw point
    counts. Differences are taken in float64 before the cast (timestamps can be ~1e9 s)."""
    dts = np.zeros(w, np.float32)
    ts = np.asarray(track.timestamps[start:start + n], dtype=np.float64)
    if n > 1:
        dts[1:n] = np.diff(ts)  # NaN stays NaN
    counts = np.zeros(w, np.int64)
    counts[:n] = [len(track.points[start + k]) for k in range(n)]
    return dts, counts


def collate(items: Sequence[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
    """Stack windows into a batch: every array gains a leading batch axis B."""
    return {k: torch.from_numpy(np.stack([it[k] for it in items])) for k in items[0]}


#: Batch entries with a frame axis (B, W, ...); the others (``complete``, ``start``) have none.
FRAME_KEYS = ("points", "lengths", "poses", "valid", "length", "dts", "counts")


def trim_padding(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The batch without its trailing frames in which no window has points or a known pose.

    Windows of tracks shorter than W end in padding (no points, ``valid`` False). The network
    is causal (frame t's estimate depends on frames <= t only) and the losses skip frames that
    are not ``valid``, so dropping the frames after the last one that has points or a pose in
    some window changes no loss and no gradient; it only saves the encoder's work on them.
    At least one frame is kept. The batch is returned unchanged when there is nothing to trim.
    """
    live = ((batch["lengths"] > 0) | batch["valid"]).any(0)  # (W,)
    last = live.nonzero()
    w = max(1, int(last[-1]) + 1) if len(last) else 1
    if w == live.shape[0]:
        return batch
    return {k: v[:, :w] if k in FRAME_KEYS else v for k, v in batch.items()}


def stream_indices(n: int, seed: int, key: int, start: int, count: int) -> list[tuple[int, int]]:
    """Positions ``start .. start+count-1`` of an endless shuffled stream over ``n`` items.

    Each epoch is a fresh permutation (from ``seed``, ``key``, epoch). Returns
    ``(epoch, index)`` pairs. Data-parallel rank r of R with per-rank batch B takes, at global
    step s, positions ``s*B*R + r*B .. + B``: disjoint shards of one global order.
    """
    out = []
    perms: dict[int, np.ndarray] = {}
    for pos in range(start, start + count):
        epoch, j = divmod(pos, n)
        if epoch not in perms:
            perms[epoch] = np.random.default_rng([seed, key, epoch, 7919]).permutation(n)
        out.append((epoch, int(perms[epoch][j])))
    return out


def batch_for_step(ds: WindowDataset, step: int, batch_size: int, rank: int = 0,
                   world: int = 1) -> dict[str, torch.Tensor]:
    """The batch of data-parallel ``rank`` (of ``world``) at global training ``step``."""
    first = step * batch_size * world + rank * batch_size
    pairs = stream_indices(len(ds), ds.seed, ds.key, first, batch_size)
    return collate([ds.window_at(i, e) for e, i in pairs])
