"""Mask-guided placement for sc-seg: move each completed vehicle in the image so that its
predicted visible mask best matches its own 2D instance mask.

sc-seg segments the LiDAR points of a frame with the frame's 2D instance masks, so every
vehicle it labels from a detection also has the mask its points came from. That mask is
evidence the completed shape ignores: a heavily occluded car seen through a gap by a handful of
LiDAR returns is placed by the estimator from those few points, and the hidden part can end
up on the wrong side, leaving the predicted visible part (the amodal mask minus what the
vehicles in front cover) beside the segmenter's mask. This step searches the image shifts
``s = (dy, dx)`` of an instance's amodal mask, each axis within ``max_shift`` of the mask's
own extent (at most ``max_px``), for the one maximising

    IoU( shift(amodal, s) minus occluders,  instance mask ),

the occluders being the amodal masks of the vehicles already placed in front of it. Every
shift is scored at once by cross-correlating the amodal mask's bounding box with the window
it can reach (intersection, visible area, and the vehicle's own LiDAR pixels; OpenCV's
``matchTemplate``), so the cost per instance is a few correlations of its bounding box. The
best shift is applied only when it improves that IoU by at least ``min_gain`` and keeps
``min_inside`` of the vehicle's own LiDAR returns inside the moved mask (measured surface
outranks a segmenter's outline); vehicles are handled front to back, and the occlusion order
is resolved again afterwards. A pure image shift keeps the depth (the occlusion order stays
the estimator's), which matches a lateral or vertical placement error of a small, far
vehicle. Measured effect and the choice of the defaults: docs/results.md (amodal labels).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from seqshape.errors import ConfigError


@dataclass(frozen=True)
class AlignConfig:
    """``max_shift``: search range per axis as a fraction of the amodal mask's width/height;
    ``max_px``: cap of that range (pixels); ``min_gain``: IoU gain needed to move;
    ``min_inside``: share of the vehicle's own LiDAR returns that must stay inside the moved
    mask; ``max_points``: only vehicles with fewer own returns in the frame are moved (0, the
    default: no limit; a cap lost mIoU, docs/results.md, "Amodal labels")."""

    max_shift: float = 0.4
    max_px: int = 40
    min_gain: float = 0.05
    min_inside: float = 0.9
    max_points: int = 0

    def __post_init__(self):
        if not 0.0 <= self.max_shift <= 2.0:
            raise ConfigError(f"align max_shift must be in [0, 2], got {self.max_shift}")
        if self.max_px < 0:
            raise ConfigError(f"align max_px must be >= 0, got {self.max_px}")
        if not 0.0 <= self.min_gain <= 1.0:
            raise ConfigError(f"align min_gain must be in [0, 1], got {self.min_gain}")
        if self.max_points < 0:
            raise ConfigError(f"align max_points must be >= 0, got {self.max_points}")
        if not 0.0 <= self.min_inside <= 1.0:
            raise ConfigError(f"align min_inside must be in [0, 1], got {self.min_inside}")


def _crop(mask: np.ndarray, y0: int, x0: int, h: int, w: int) -> np.ndarray:
    """``mask[y0:y0+h, x0:x0+w]`` with the part outside the image False."""
    out = np.zeros((h, w), dtype=bool)
    H, W = mask.shape
    ya, yb, xa, xb = max(y0, 0), min(y0 + h, H), max(x0, 0), min(x0 + w, W)
    if ya < yb and xa < xb:
        out[ya - y0:yb - y0, xa - x0:xb - x0] = mask[ya:yb, xa:xb]
    return out


def _pixels(uv, shape: tuple[int, int]) -> np.ndarray:
    """Integer ``(M, 2)`` (u, v) pixels of the image points ``uv`` that fall inside it."""
    H, W = shape
    if uv is None:
        return np.zeros((0, 2), dtype=np.int64)
    px = np.floor(np.asarray(uv, dtype=np.float64).reshape(-1, 2)).astype(np.int64)
    return px[(px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)]


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(y0, y1, x0, x1)`` (end exclusive) of a bool mask's pixels, None when empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return None
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def shift_scores(amodal: np.ndarray, guide: np.ndarray, occluder: np.ndarray, ry: int,
                 rx: int, uv=None, box=None) -> tuple[np.ndarray, np.ndarray | None]:
    """For every shift ``(dy, dx)``, ``|dy| <= ry``, ``|dx| <= rx``, as arrays ``(2 ry + 1,
    2 rx + 1)`` indexed ``[dy + ry, dx + rx]``:

    * the IoU of ``shift(amodal) & ~occluder`` (inside the image) with ``guide``;
    * with ``uv`` ``(M, 2)`` image points, the share of those inside the image that lie in
      ``shift(amodal)`` (else None).

    All masks are ``(h, w)`` bool of one image; ``box``: the amodal mask's :func:`_bbox` when
    already known. Each sum is a cross-correlation of the amodal mask's bounding box with the
    window that box can reach (OpenCV's ``matchTemplate``).
    """
    ones = np.ones((2 * ry + 1, 2 * rx + 1))
    px = _pixels(uv, amodal.shape)
    box = _bbox(amodal) if box is None else box
    if box is None:
        return np.zeros_like(ones), (None if uv is None else ones)
    ay0, ay1, ax0, ax1 = box
    templ = amodal[ay0:ay1, ax0:ax1].astype(np.float32)
    y0, x0, h, w = ay0 - ry, ax0 - rx, ay1 - ay0 + 2 * ry, ax1 - ax0 + 2 * rx

    def corr(layer: np.ndarray) -> np.ndarray:
        return np.rint(cv2.matchTemplate(layer.astype(np.float32), templ, cv2.TM_CCORR))

    free = _crop(~occluder, y0, x0, h, w)  # False outside the image too
    inter = corr(_crop(guide, y0, x0, h, w) & free)
    visible = corr(free)
    union = visible + float(np.count_nonzero(guide)) - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        ious = np.where(union > 0, inter / union, 0.0)
    if uv is None:
        return ious, None
    if len(px) == 0:
        return ious, ones
    hits = np.zeros((h, w), dtype=np.float32)
    u, v = px[:, 0] - x0, px[:, 1] - y0
    near = (u >= 0) & (u < w) & (v >= 0) & (v < h)  # the others never meet a shifted mask
    np.add.at(hits, (v[near], u[near]), 1.0)
    return ious, corr(hits) / len(px)


def shift_ious(amodal: np.ndarray, guide: np.ndarray, occluder: np.ndarray, ry: int,
               rx: int) -> np.ndarray:
    """The IoU part of :func:`shift_scores`."""
    return shift_scores(amodal, guide, occluder, ry, rx)[0]


def points_inside(amodal: np.ndarray, uv: np.ndarray, ry: int, rx: int) -> np.ndarray:
    """The share of the image points ``uv`` inside ``shift(amodal)`` for every shift
    (:func:`shift_scores`; 1 when none of them is in the image)."""
    empty = np.zeros_like(amodal)
    return shift_scores(amodal, empty, empty, ry, rx, uv)[1]


def shift_mask(mask: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``mask`` moved by ``(dy, dx)`` pixels; what leaves the image is lost."""
    out = np.zeros_like(mask)
    H, W = mask.shape
    src = mask[max(0, -dy):H - max(0, dy), max(0, -dx):W - max(0, dx)]
    out[max(0, dy):max(0, dy) + src.shape[0], max(0, dx):max(0, dx) + src.shape[1]] = src
    return out


def best_shift(amodal: np.ndarray, guide: np.ndarray, occluder: np.ndarray,
               cfg: AlignConfig = AlignConfig(), points=None) -> tuple[int, int, float, float]:
    """``(dy, dx, iou_at_shift, iou_unshifted)``: the shift within the search range with the
    highest IoU (the smallest such shift on ties), or ``(0, 0, iou, iou)`` when no shift
    gains ``min_gain``. ``points`` ``(M, 2)``: the pixels of the vehicle's own LiDAR returns;
    shifts that leave more than ``1 - min_inside`` of them outside the mask are not taken
    (the returns are measured surface, the 2D mask only a segmenter's guess)."""
    box = _bbox(amodal)
    if box is None or not guide.any():
        return 0, 0, 0.0, 0.0
    ry = min(cfg.max_px, int(np.ceil(cfg.max_shift * (box[1] - box[0]))))
    rx = min(cfg.max_px, int(np.ceil(cfg.max_shift * (box[3] - box[2]))))
    has_points = points is not None and len(points) > 0
    ious, inside = shift_scores(amodal, guide, occluder, ry, rx,
                                points if has_points else None, box)
    base = float(ious[ry, rx])
    if inside is not None:
        ok = inside >= min(cfg.min_inside, float(inside[ry, rx]))
        ious = np.where(ok, ious, -1.0)
    dy, dx = np.mgrid[-ry:ry + 1, -rx:rx + 1]
    key = np.lexsort(((dy ** 2 + dx ** 2).ravel(), -np.round(ious, 9).ravel()))[0]
    by, bx = int(dy.ravel()[key]), int(dx.ravel()[key])
    best = float(ious.ravel()[key])
    if best - base < cfg.min_gain:
        return 0, 0, base, base
    return by, bx, best, base


def align_instances(insts: list, guides: Mapping[str, np.ndarray],
                    cfg: AlignConfig = AlignConfig(),
                    points: Mapping[str, np.ndarray] | None = None) -> dict[str, tuple[int, int]]:
    """Shift, in place, the amodal masks (and projected points) of the instances that have a
    guide mask (``{track_id: (h, w) bool}``), front to back by their current ``order``;
    returns the applied ``{track_id: (dy, dx)}``. ``points``: ``{track_id: (M, 2)}`` pixels
    of each vehicle's own LiDAR returns (:func:`best_shift`). The caller re-resolves the
    occlusion."""
    if not insts:
        return {}
    moved: dict[str, tuple[int, int]] = {}
    covered = np.zeros_like(insts[0].amodal)
    for m in sorted(insts, key=lambda m: m.order):
        guide = guides.get(m.track_id)
        pts = None if points is None else points.get(m.track_id)
        if cfg.max_points and pts is not None and len(pts) >= cfg.max_points:
            guide = None
        if guide is not None:
            dy, dx, _, _ = best_shift(m.amodal, guide, covered, cfg, pts)
            if dy or dx:
                m.amodal = shift_mask(m.amodal, dy, dx)
                if m.uv is not None:
                    m.uv = m.uv + np.array([dx, dy], dtype=np.float64)
                moved[m.track_id] = (dy, dx)
        covered |= m.amodal
    return moved
