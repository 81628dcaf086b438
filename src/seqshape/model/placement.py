"""Placement refinement: a second look at a frame's points in the estimate's own box frame.

The network regresses a vehicle's centre from one max-pooled feature of the demeaned points;
where the points sit on the vehicle (which faces are seen, how far the near face lies from the
centre) reaches the centre only through that global feature. A box fit anchors the visible
faces and out-places it on dense frames (docs/history/results.md, "Why real cars are placed too far
from the sensor"). The refiner is the two-stage detectors' answer (a proposal's points in its
canonical frame, PointRCNN / PV-RCNN style): the frame's points are moved into the estimated
box frame (centre at the origin, heading along +x), a small PointNet reads them with the
estimate's extents and the direction of the sensor in that frame, and regresses a correction
``(dx, dy, dz)`` of the centre in the box frame and ``dyaw`` of the heading axis (modulo pi:
which end is the front stays the estimator's and the heading step's business). The placed
complete shape moves rigidly with the pose.

Inputs (:func:`refine_inputs`, one function for training and inference): up to ``n`` points
(a seeded random subset) in the box frame divided by the scale ``s = clip(L / SCALE_REF, 1,
SCALE_MAX)`` of the estimated length L, so a bus reaches the network at a car's scale, and
the conditioning vector :data:`COND_FIELDS`. Output corrections are multiplied back by s.
A refiner with the size head (``outputs=6``, :data:`CORRECTION_FIELDS`) also regresses the log
ratios of the true length and width to the placed shape's, which stretch the shape about its
centre (:class:`RefinerConfig` ``size``, ``size_width``; docs/history/model.md, "Size head").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seqshape.errors import ConfigError, DataError

SCALE_REF = 4.5  # m: an estimate up to this long is not rescaled
SCALE_MAX = 4.0
NUM_POINTS = 256
WIDTH = 128  # the second PointNet's width
#: The conditioning vector's entries, in order.
COND_FIELDS = ("length/s", "width/s", "height/s", "sensor_dir_x", "sensor_dir_y",
               "log_range/4", "log_points/7", "s/4")
FORMAT = "seqshape-placement-refiner"
#: Columns of a correction (:meth:`PlacementRefiner.corrections_of`): the pose's (dx, dy, dz,
#: dyaw) in the box frame, then the log ratios of the placed shape's length and width (0 for
#: a refiner without the size head).
CORRECTION_FIELDS = ("dx", "dy", "dz", "dyaw", "log_length", "log_width")
SIZE_OUTPUTS = 6
#: The refiner network's forward pass, ``(xyz (B, n, 3), cond (B, C)) -> (B, 4)`` (``(B, 6)``
#: with the size head), float32.
Forward = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _torch():
    import torch  # lazy: the module is importable without torch for its numpy helpers

    return torch


def scale_of(length: float) -> float:
    """The input scale for an estimated vehicle length (m)."""
    if not np.isfinite(length):
        return 1.0
    return float(np.clip(length / SCALE_REF, 1.0, SCALE_MAX))


def box_frame(points: np.ndarray, pose) -> np.ndarray:
    """``points (N, 3)`` (sensor frame) in the box frame of ``pose`` (x, y, z, yaw)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c, s = math.cos(float(pose[3])), math.sin(float(pose[3]))
    d = pts - np.asarray(pose[:3], dtype=np.float64)
    return np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]]


def refine_inputs(points: np.ndarray, pose, extents, rng: np.random.Generator,
                  n: int = NUM_POINTS) -> tuple[np.ndarray, int, np.ndarray, float]:
    """The refiner's input for one frame.

    Args:
        points: (N, 3) the frame's points, sensor frame (N >= 1).
        pose: the estimate (x, y, z, yaw).
        extents: the estimate's (length, width, height), m.
        rng: draws the subset when N > n.
        n: points fed.

    Returns ``(xyz (n, 3) float32, count, cond (len(COND_FIELDS),) float32, s)``: rows past
    ``count`` repeat the real ones cyclically (the max-pool then sees each real point, exactly
    as without padding).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise ValueError("refine_inputs needs at least one point")
    if len(pts) > n:
        pts = pts[rng.choice(len(pts), n, replace=False)]
    s = scale_of(float(extents[0]))
    q = box_frame(pts, pose) / s
    count = len(q)
    xyz = q[np.arange(n) % count].astype(np.float32)
    sensor = box_frame(np.zeros((1, 3)), pose)[0, :2]
    rng_m = float(np.hypot(*sensor))
    direction = sensor / max(rng_m, 1e-6)
    ext = np.nan_to_num(np.asarray(extents, dtype=np.float64)[:3], nan=0.0) / s
    cond = np.array([ext[0], ext[1], ext[2], direction[0], direction[1],
                     math.log1p(rng_m) / 4.0, math.log1p(len(points)) / 7.0, s / 4.0],
                    dtype=np.float32)
    return xyz, count, cond, s


def refine_inputs_batch(points: Sequence[np.ndarray], poses: np.ndarray, extents: np.ndarray,
                        seeds: Sequence[int], n: int = NUM_POINTS
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`refine_inputs` of many frames at once (frame i's subset drawn with
    ``np.random.default_rng(seeds[i])``): ``(xyz (B, n, 3) float32, cond (B, C) float32,
    scales (B,))``, equal to stacking the single-frame inputs (tested)."""
    b = len(points)
    gathered = np.empty((b, n, 3), dtype=np.float64)
    counts = np.empty(b, dtype=np.int64)
    cycle = np.arange(n)
    for i, p in enumerate(points):
        pts = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        m = len(pts)
        if m == 0:
            raise ValueError("refine_inputs needs at least one point")
        counts[i] = m
        if m > n:
            gathered[i] = pts[np.random.default_rng(seeds[i]).choice(m, n, replace=False)]
        else:
            gathered[i] = pts if m == n else pts[cycle % m]
    poses = np.asarray(poses, dtype=np.float64).reshape(b, 4)
    ext = np.asarray(extents, dtype=np.float64).reshape(b, -1)[:, :3]
    length = ext[:, 0]
    scales = np.where(np.isfinite(length), np.clip(length / SCALE_REF, 1.0, SCALE_MAX), 1.0)
    c, s = np.cos(poses[:, 3])[:, None], np.sin(poses[:, 3])[:, None]
    q = _to_box(gathered, poses, c, s)
    q /= scales[:, None, None]
    xyz = q.astype(np.float32)
    o = -poses[:, :3]
    cond = np.empty((b, len(COND_FIELDS)))
    sensor = cond[:, 3:5]  # the sensor's direction, once divided by the range
    sensor[:, 0] = c[:, 0] * o[:, 0] + s[:, 0] * o[:, 1]
    sensor[:, 1] = -s[:, 0] * o[:, 0] + c[:, 0] * o[:, 1]
    rng_m = np.hypot(sensor[:, 0], sensor[:, 1])
    sensor /= np.maximum(rng_m, 1e-6)[:, None]
    cond[:, :3] = np.nan_to_num(ext, nan=0.0) / scales[:, None]
    cond[:, 5] = np.log1p(rng_m) / 4.0
    cond[:, 6] = np.log1p(counts) / 7.0
    cond[:, 7] = scales / 4.0
    return xyz, cond.astype(np.float32), scales


def _net_class():
    torch = _torch()
    from torch import nn

    from seqshape.model.network import mlp

    class RefinerNet(nn.Module):
        """PointNet (3-64-64 / 128-W-W, max-pools) + conditioning -> (dx, dy, dz, dyaw) and,
        with ``outputs`` 6, (log length ratio, log width ratio) of the placed shape.

        The last layer starts at zero: an untrained refiner leaves the estimate as it is."""

        def __init__(self, width: int = WIDTH, outputs: int = 4):
            super().__init__()
            if outputs not in (4, 6):
                raise ConfigError(f"a refiner has 4 or 6 outputs, got {outputs}")
            self.width, self.outputs = int(width), int(outputs)
            self.mlp1 = mlp([3, 64, 64], point_wise=True)
            self.mlp2 = mlp([128, width, width], point_wise=True)
            self.head = mlp([width + len(COND_FIELDS), 256, 128, outputs])
            nn.init.zeros_(self.head[-1].weight)
            nn.init.zeros_(self.head[-1].bias)

        def forward(self, xyz: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
            x = self.mlp1(xyz)  # (B, n, 128)
            g = x.max(dim=1, keepdim=True).values.expand_as(x)
            y = self.mlp2(torch.cat([x, g], dim=-1)).max(dim=1).values
            return self.head(torch.cat([y, cond], dim=-1))

    return RefinerNet


def build_net(width: int = WIDTH, outputs: int = 4):
    """A fresh :class:`RefinerNet` (the identity refinement); ``outputs`` 6: with the size
    head (:data:`SIZE_OUTPUTS`)."""
    return _net_class()(width, outputs)


@dataclass(frozen=True)
class RefinerConfig:
    """How the refiner is applied. The default: up to three passes for estimates of 6 m and
    more (trucks, buses, trailers: their errors are large against the per-pass clip and the
    training disturbances), one for cars, on which further passes helped nothing on synthetic
    data and compounded a wrong first correction on a real car (docs/history/model.md,
    "Further passes for long vehicles").

    iterations: most passes; each re-reads the points in the box frame the last one corrected.
    min_points: a frame with fewer points is left alone.
    max_shift: each pass's centre correction is clipped to this (m, per axis).
    max_turn: each pass's heading correction is clipped to this (rad).
    repeat_shift: a pass after the first only where the last one moved the centre at least
        this far (m, in the ground plane).
    repeat_min_points: ... and the frame has at least this many points.
    repeat_min_length: ... and the estimate is at least this long (m, its extents).
    points: points fed per frame (a seeded subset of a larger frame; a smaller one repeated),
        the refiner's arithmetic; the shipped refiner was trained with 256.
    size: apply a size head's correction of the shape's length and width (refiners trained
        with ``--size``; a refiner without one changes no size).
    size_width: with ``size``, correct the width too (False: the length only).
    max_resize: the size correction's log ratio is clipped to this (0.3: x0.74 to x1.35).
    """

    iterations: int = 3
    min_points: int = 1
    max_shift: float = 1.5
    max_turn: float = 0.35
    repeat_shift: float = 0.0
    repeat_min_points: int = 1
    repeat_min_length: float = 6.0
    points: int = NUM_POINTS
    size: bool = True
    size_width: bool = False
    max_resize: float = 0.3

    def __post_init__(self):
        if self.points < 1:
            raise ConfigError(f"RefinerConfig.points must be >= 1, got {self.points}")
        if self.iterations < 0:
            raise ConfigError(f"RefinerConfig.iterations must be >= 0, got {self.iterations}")
        if not self.repeat_shift >= 0:
            raise ConfigError(f"RefinerConfig.repeat_shift must be >= 0, got "
                              f"{self.repeat_shift}")


class PlacementRefiner:
    """Applies a trained :class:`RefinerNet` to estimates (:meth:`refine`)."""

    def __init__(self, net, config: RefinerConfig | None = None, seed: int = 0,
                 meta: dict | None = None):
        self.net = net.eval()
        self.config = config or RefinerConfig()
        self.seed = int(seed)
        self.meta = dict(meta or {})
        self._layers: list[tuple[np.ndarray, np.ndarray]] | None = None

    @classmethod
    def load(cls, path: str | Path, config: RefinerConfig | None = None) -> PlacementRefiner:
        torch = _torch()
        path = Path(path)
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise DataError(path, "no such refiner file") from None
        except Exception as exc:  # noqa: BLE001 (a corrupt or foreign file)
            raise DataError(path, f"not a readable refiner file ({exc})") from None
        if not isinstance(payload, dict) or payload.get("format") != FORMAT:
            raise DataError(path, f"not a {FORMAT} file")
        net = build_net(int(payload.get("width", WIDTH)), int(payload.get("outputs", 4)))
        try:
            net.load_state_dict(payload["state_dict"])
        except (KeyError, RuntimeError) as exc:
            raise DataError(path, f"refiner weights do not fit ({exc})") from None
        return cls(net, config, meta=payload.get("meta"))

    def save(self, path: str | Path) -> None:
        torch = _torch()
        import io

        from seqshape._io import atomic_write_bytes

        buf = io.BytesIO()
        torch.save({"format": FORMAT, "width": self.net.width, "outputs": self.net.outputs,
                    "state_dict": self.net.state_dict(), "meta": self.meta}, buf)
        atomic_write_bytes(Path(path), buf.getvalue())

    def corrections(self, points: Sequence[np.ndarray], poses: np.ndarray,
                    extents: np.ndarray, seeds: Sequence[int],
                    reference: bool = False, run: Forward | None = None) -> np.ndarray:
        """``(F, 4)`` corrections ``(dx, dy, dz, dyaw)`` in each pose's box frame (m, rad),
        ``(F, 6)`` with the size head's log ratios of length and width.

        The network runs in numpy (:meth:`forward`: a few small matrix products, no framework
        overhead on a one-track step), or in ``run`` (the same function on an inference
        engine's threads: ``Estimator`` passes its engine's, see
        :meth:`seqshape.model.engine.OnnxEngine.refiner`); ``reference``: in PyTorch, the
        module itself."""
        xyz, cond, scales = refine_inputs_batch(points, poses, extents, seeds,
                                                n=self.config.points)
        if reference:
            torch = _torch()
            with torch.no_grad():
                out = self.net(torch.from_numpy(xyz), torch.from_numpy(cond)).double().numpy()
        else:
            out = (run or self.forward)(xyz, cond).astype(np.float64)
        out[:, :3] *= scales[:, None]
        return out

    def forward(self, xyz: np.ndarray, cond: np.ndarray) -> np.ndarray:
        """:class:`RefinerNet`'s forward pass in numpy float32: ``xyz (B, n, 3)``, ``cond
        (B, C)`` -> ``(B, 4)`` (equal to the module's within float32 rounding; tested)."""
        if self._layers is None:
            self._layers = [(m.weight.detach().numpy().T.astype(np.float32).copy(),
                             m.bias.detach().numpy().astype(np.float32).copy())
                            for m in (*self.net.mlp1[::2], *self.net.mlp2[::2],
                                      *self.net.head[::2])]
        (w1, b1), (w2, b2), (w3, b3), (w4, b4), *head = self._layers
        b, n, _ = xyz.shape
        x = np.maximum(xyz.reshape(b * n, 3) @ w1 + b1, 0.0) @ w2 + b2  # (B n, 64)
        c = x.shape[1]
        g = x.reshape(b, n, c).max(axis=1)  # (B, 64)
        # mlp2's first layer on [x, g]: the global half once per frame
        y = (x @ w3[:c]).reshape(b, n, -1) + (g @ w3[c:] + b3)[:, None, :]
        y = np.maximum(y, 0.0).reshape(b * n, -1) @ w4 + b4
        h = np.concatenate([y.reshape(b, n, -1).max(axis=1), cond], axis=1)
        for i, (w, bias) in enumerate(head):
            h = h @ w + bias
            if i < len(head) - 1:
                h = np.maximum(h, 0.0)
        return h

    def refine_poses(self, points: Sequence[np.ndarray], poses: np.ndarray,
                     extents: np.ndarray, seeds: Sequence[int] | None = None,
                     run: Forward | None = None) -> np.ndarray:
        """Refined copies of ``poses (F, 4)`` (sensor frame) from each frame's points; frames
        with fewer than ``min_points`` points or a non-finite pose are returned unchanged
        (``run``: as in :meth:`corrections`)."""
        return self.refine(points, poses, extents, seeds, run)[0]

    def refine(self, points: Sequence[np.ndarray], poses: np.ndarray, extents: np.ndarray,
               seeds: Sequence[int] | None = None, run: Forward | None = None,
               first: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`refine_poses` and the size corrections ``(F, 2)``: the log ratios of the
        shape's length and width (the first pass's, clipped to ``max_resize``; 0 without a
        size head, with ``config.size`` off, or for a frame left alone). ``first``: the
        passes before it are done already (``poses`` are their outcome; the inference
        engine's refined graphs run the first pass, :class:`~seqshape.model.engine.
        RefinedStepGraph`)."""
        cfg = self.config
        poses = np.array(poses, dtype=np.float64).reshape(-1, 4)
        sizes = np.zeros((len(poses), 2))
        seeds = list(range(len(poses))) if seeds is None else list(seeds)
        ok = [i for i, p in enumerate(points) if len(p) >= max(cfg.min_points, 1)
              and np.all(np.isfinite(poses[i])) and np.all(np.isfinite(extents[i][:1]))]
        for it in range(first, cfg.iterations):
            if not ok:
                break
            d = self.corrections([points[i] for i in ok], poses[ok], np.asarray(extents)[ok],
                                 [self.seed + 1000003 * it + seeds[i] for i in ok], run=run)
            if it == 0 and cfg.size and d.shape[1] >= SIZE_OUTPUTS:
                sizes[ok] = np.clip(d[:, 4:6], -cfg.max_resize, cfg.max_resize)
                if not cfg.size_width:
                    sizes[ok, 1] = 0.0
            shift = np.clip(d[:, :3], -cfg.max_shift, cfg.max_shift)
            turn = np.clip(d[:, 3], -cfg.max_turn, cfg.max_turn)
            yaw = poses[ok, 3]
            c, s = np.cos(yaw), np.sin(yaw)
            poses[ok, 0] += c * shift[:, 0] - s * shift[:, 1]
            poses[ok, 1] += s * shift[:, 0] + c * shift[:, 1]
            poses[ok, 2] += shift[:, 2]
            poses[ok, 3] = yaw + turn
            moved = np.hypot(shift[:, 0], shift[:, 1])
            ok = [i for i, m in zip(ok, moved, strict=True)
                  if m >= cfg.repeat_shift and len(points[i]) >= cfg.repeat_min_points
                  and extents[i][0] >= cfg.repeat_min_length]
        return poses, sizes

    def corrections_of(self, frames: Sequence[np.ndarray], complete: np.ndarray,
                       poses: np.ndarray, seeds: Sequence[int] | None = None,
                       run: Forward | None = None) -> np.ndarray:
        """``(F, 6)`` corrections of independent frames (:data:`CORRECTION_FIELDS`: the pose's,
        :func:`delta`, and the shape's size), one batched pass; NaN rows for the frames left
        alone (fewer than ``min_points`` points, a non-finite pose). ``frames``: per frame
        the points the network got; ``complete`` (F, K, 3) and ``poses`` (F, 4) its
        estimates; ``seeds``: per frame, the seed of the points' subset (when a frame has more
        than ``config.points``); ``run``: as in :meth:`corrections`."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
        corr = np.full((len(poses), len(CORRECTION_FIELDS)), np.nan)
        idx = [i for i, f in enumerate(frames) if len(f) >= max(self.config.min_points, 1)
               and np.all(np.isfinite(poses[i]))]
        if idx:
            complete = np.asarray(complete)
            new, sizes = self.refine([frames[i] for i in idx], poses[idx],
                                     extents_batch(complete[idx], poses[idx]),
                                     None if seeds is None else [seeds[i] for i in idx], run)
            corr[idx, :4] = delta(poses[idx], new)
            corr[idx, 4:] = sizes
        return corr

    def refine_sequence(self, frames: Sequence[np.ndarray], complete: np.ndarray,
                        poses: np.ndarray, last: np.ndarray | None = None,
                        seeds: Sequence[int] | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Refine the estimates of consecutive frames of one track.

        Args:
            frames, complete, poses, seeds: as in :meth:`corrections_of`.
            last: the correction of the frame before, carried over empty frames (None: empty
                frames before the first refined one are left alone).

        Returns ``(complete, poses, last)``: new arrays (the shapes moved rigidly with their
        poses) and the correction of the last frame with points. A frame with points is
        refined; an empty one (the estimate carried forward from the state) gets the last
        correction, as the estimate it repeats did.
        """
        corr = self.corrections_of(frames, complete, poses, seeds)
        for i in range(len(corr)):
            if np.isfinite(corr[i, 0]):
                last = corr[i]
            elif not len(frames[i]) and last is not None:
                corr[i] = last
        complete, poses = apply_corrections(complete, poses, corr)
        return complete, poses, last


def apply_corrections(complete: np.ndarray, poses: np.ndarray, corr: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Copies of ``complete`` (F, K, 3) and ``poses`` (F, 4) moved by the corrections ``corr``
    (F, 4) (:func:`delta`) or (F, 6) (:data:`CORRECTION_FIELDS`; a NaN row, or a non-finite
    pose: left as it is; an all-zero row: bit for bit as it is), each shape moved rigidly
    with its pose and, with size columns, stretched along its box axes about its centre by
    their exponentials."""
    complete = np.asarray(complete)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    out_c, out_p = np.array(complete, copy=True), poses.copy()
    moved = [i for i in range(len(poses)) if np.isfinite(corr[i, 0]) and np.any(corr[i])
             and np.all(np.isfinite(poses[i]))]
    if moved:
        for i in moved:
            out_p[i] = apply_delta(poses[i], corr[i])
        scale = np.exp(corr[moved, 4:6]) if corr.shape[1] > 4 else None
        out_c[moved] = _move_batch(complete[moved], poses[moved], out_p[moved],
                                   scale).astype(complete.dtype)
    return out_c, out_p


def extents_of(complete: np.ndarray, pose) -> np.ndarray:
    """``(length, width, height)`` of a placed complete shape in its pose's box frame: the
    spread between the 1st and 99th percentiles (as
    :func:`seqshape.evaluation.runner.estimate_extents`); NaN without points."""
    pts = np.asarray(complete, dtype=np.float64).reshape(-1, 3)
    if not len(pts):
        return np.full(3, np.nan)
    lo, hi = np.percentile(box_frame(pts, pose), [1, 99], axis=0)
    return hi - lo


def extents_batch(complete: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """:func:`extents_of` of ``complete (B, K, 3)`` placed with ``poses (B, 4)``: ``(B, 3)``."""
    complete = np.asarray(complete, dtype=np.float64)
    if complete.shape[1] == 0:
        return np.full((len(complete), 3), np.nan)
    lo, hi = percentiles_1_99(_to_box(complete, poses))
    return hi - lo


def percentiles_1_99(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.percentile(q, [1, 99], axis=1)`` of float64 ``q (B, K, C)``, bit for bit (numpy's
    default linear method: the virtual index ``(K - 1) p``, its two neighbours after a
    partition, numpy's interpolation), without the general function's fixed cost (about 0.1
    ms, most of a one-track refinement's extents). Non-finite input takes numpy's own path."""
    k = q.shape[1]
    if k < 2 or q.dtype != np.float64 or not np.isfinite(q).all():
        lo, hi = np.percentile(q, [1, 99], axis=1)
        return lo, hi
    virtual = (k - 1) * (np.array([1.0, 99.0]) / 100)
    below = np.floor(virtual).astype(np.intp)
    gamma = virtual - below
    part = np.partition(q, np.unique(np.r_[below, below + 1]), axis=1)
    out = []
    for i in range(2):
        a, b, t = part[:, below[i]], part[:, below[i] + 1], gamma[i]
        d = b - a
        out.append(b - d * (1 - t) if t >= 0.5 else a + d * t)
    return out[0], out[1]


def _to_box(points: np.ndarray, poses: np.ndarray, c: np.ndarray | None = None,
            s: np.ndarray | None = None) -> np.ndarray:
    """``points (B, K, 3)`` in the box frames of ``poses (B, 4)``, as :func:`box_frame` (a new
    float64 array; ``c``, ``s``: the yaws' (B, 1) cosines and sines, when at hand)."""
    poses = np.asarray(poses, dtype=np.float64)
    if c is None:
        c, s = np.cos(poses[:, 3])[:, None], np.sin(poses[:, 3])[:, None]
    d = points - poses[:, None, :3]
    q = np.empty(d.shape)
    q[..., 0] = c * d[..., 0] + s * d[..., 1]
    q[..., 1] = -s * d[..., 0] + c * d[..., 1]
    q[..., 2] = d[..., 2]
    return q


def _move_batch(points: np.ndarray, old: np.ndarray, new: np.ndarray,
                scale: np.ndarray | None = None) -> np.ndarray:
    """``points (B, K, 3)`` placed with poses ``old (B, 4)`` re-placed with ``new`` (each
    cloud moved rigidly, as :func:`_move`; ``scale`` (B, 2): first stretched by these factors
    along its box's x and y axes, about the box centre; rows of exactly 1 are left as they
    are)."""
    q = _to_box(np.asarray(points, dtype=np.float64), old)
    if scale is not None:
        q[..., :2] *= scale[:, None, :]
    c, s = np.cos(new[:, 3])[:, None], np.sin(new[:, 3])[:, None]
    out = np.empty(q.shape)
    out[..., 0] = c * q[..., 0] - s * q[..., 1] + new[:, None, 0]
    out[..., 1] = s * q[..., 0] + c * q[..., 1] + new[:, None, 1]
    out[..., 2] = q[..., 2] + new[:, None, 2]
    return out


def delta(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """``(F, 4)``: pose ``new`` relative to pose ``old`` (the centre's move in ``old``'s box
    frame, and the turn), so that ``apply_delta(old, delta(old, new)) == new``."""
    old = np.asarray(old, dtype=np.float64).reshape(-1, 4)
    new = np.asarray(new, dtype=np.float64).reshape(-1, 4)
    c, s = np.cos(old[:, 3]), np.sin(old[:, 3])
    d = new[:, :3] - old[:, :3]
    return np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2],
                 new[:, 3] - old[:, 3]]


def apply_delta(pose, d) -> np.ndarray:
    """Pose ``pose (4,)`` moved by a correction ``d (4,)`` of :func:`delta`."""
    pose = np.asarray(pose, dtype=np.float64)
    c, s = math.cos(pose[3]), math.sin(pose[3])
    return np.array([pose[0] + c * d[0] - s * d[1], pose[1] + s * d[0] + c * d[1],
                     pose[2] + d[2], pose[3] + d[3]])


def pretrained_refiner_path() -> Path:
    """The shipped refiner's file."""
    return Path(__file__).resolve().parent.parent / "pretrained" / "refiner.pt"


def load_refiner(spec: str | Path | None, config: RefinerConfig | None = None
                 ) -> PlacementRefiner | None:
    """The refiner named by ``spec``: ``"none"`` / None (no refinement), ``"pretrained"`` (the
    shipped file) or the path of a refiner file."""
    if spec is None or str(spec) == "none":
        return None
    path = pretrained_refiner_path() if str(spec) == "pretrained" else Path(spec)
    return PlacementRefiner.load(path, config)


def _move(points: np.ndarray, old, new) -> np.ndarray:
    """Points placed with pose ``old`` re-placed with pose ``new`` (the same canonical cloud);
    the one-cloud reference of :func:`_move_batch` (tests)."""
    from seqshape.geometry import canonical_to_sensor, sensor_to_canonical

    return canonical_to_sensor(sensor_to_canonical(points, old), new)


def targets(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Training targets ``(F, 4)``: the true centre in each estimate's box frame and the yaw
    correction of the heading axis, wrapped to [-pi/2, pi/2)."""
    est = np.asarray(est, dtype=np.float64).reshape(-1, 4)
    true = np.asarray(true, dtype=np.float64).reshape(-1, 4)
    c, s = np.cos(est[:, 3]), np.sin(est[:, 3])
    d = true[:, :3] - est[:, :3]
    dyaw = (true[:, 3] - est[:, 3] + math.pi / 2) % math.pi - math.pi / 2
    return np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2], dyaw]
