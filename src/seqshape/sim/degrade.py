"""Degrade exact 2D instance masks into what a decent instance segmenter would output.

Applied per image to the exact visible masks of a scene, in this order:

1. **missed instances**: each instance is dropped with probability ``miss_rate_small`` when
   its area is below ``small_area`` pixels (COCO's "small", 32 x 32) and ``miss_rate``
   otherwise;
2. **erosion / dilation**: ``dilate_px`` > 0 dilates, < 0 erodes, by that many pixels
   (3 x 3 cross structuring element, iterated);
3. **boundary noise**: the mask's signed distance to its boundary is perturbed by a smooth
   random field whose amplitude is drawn per instance uniformly in ``jitter_px`` (pixels),
   then re-thresholded: the outline moves in and out by up to that many pixels;
4. **false instances**: ``Poisson(false_rate * n_true)`` random blobs (ellipses of 200 to
   4000 px, jittered like the others) are added with low scores.

Defaults resemble a decent Mask R-CNN on KITTI cars (1-3 px boundary jitter, 5% of small
instances missed, 2% false positives per true instance). :data:`NO_DEGRADE` (all zero) returns
the input masks unchanged. Scores: kept instances ``U(0.7, 1.0)``, false ones ``U(0.3, 0.7)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seqshape.errors import ConfigError


@dataclass(frozen=True)
class DegradeConfig:
    """Rates and magnitudes of the degradations (see the module docstring).

    miss_rate_small: probability of missing a small instance (area below ``small_area`` px).
    miss_rate: probability of missing a larger instance.
    small_area: area (px) below which an instance is small (32 x 32, COCO's small).
    dilate_px: dilate (>0) or erode (<0) every mask by this many px.
    jitter_px: boundary noise amplitude range, px (per instance, uniform in [min, max]).
    false_rate: false instances per true instance (Poisson mean).
    """

    miss_rate_small: float = 0.05
    miss_rate: float = 0.0
    small_area: int = 32 * 32
    dilate_px: int = 0
    jitter_px: tuple[float, float] = (1.0, 3.0)
    false_rate: float = 0.02

    def __post_init__(self):
        for name in ("miss_rate_small", "miss_rate", "false_rate"):
            v = getattr(self, name)
            if not 0.0 <= v <= (1.0 if name != "false_rate" else 100.0):
                raise ConfigError(f"degradation {name} must be a rate >= 0 (<= 1 for misses), "
                                  f"got {v}")
        lo, hi = self.jitter_px
        if not 0.0 <= lo <= hi:
            raise ConfigError(f"jitter_px must be (min, max) with 0 <= min <= max, got "
                              f"{self.jitter_px}")

    @property
    def is_identity(self) -> bool:
        return (self.miss_rate_small == 0 and self.miss_rate == 0 and self.dilate_px == 0
                and self.jitter_px[1] == 0 and self.false_rate == 0)


NO_DEGRADE = DegradeConfig(miss_rate_small=0.0, miss_rate=0.0, dilate_px=0,
                           jitter_px=(0.0, 0.0), false_rate=0.0)


@dataclass
class Instance2D:
    """A 2D instance: ``mask`` (H, W) bool, ``score``, ``category_id`` and ``track_id``
    (-1 for a false positive)."""

    mask: np.ndarray
    score: float
    category_id: int
    track_id: int


def erode_dilate(mask: np.ndarray, px: int) -> np.ndarray:
    """Dilate (``px`` > 0) or erode (``px`` < 0) a bool (H, W) mask by ``|px|`` pixels."""
    import cv2  # heavy optional import (~0.3 s): only the 2D mask work needs OpenCV

    if px == 0:
        return mask.copy()
    kernel = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    op = cv2.dilate if px > 0 else cv2.erode
    return op(mask.astype(np.uint8), kernel, iterations=abs(int(px))).astype(bool)


def _signed_distance(mask: np.ndarray) -> np.ndarray:
    """Signed distance (pixels) to the boundary, positive inside; the boundary (0) lies half
    way between an inside and an outside pixel."""
    import cv2  # heavy optional import (~0.3 s): only the 2D mask work needs OpenCV

    m = mask.astype(np.uint8)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, 3)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, 3)
    return np.where(m > 0, inside - 0.5, 0.5 - outside)


def jitter_boundary(mask: np.ndarray, amplitude: float, rng: np.random.Generator,
                    scale_px: float = 12.0) -> np.ndarray:
    """Move the outline of a bool (H, W) mask in and out by up to ``amplitude`` pixels.

    The noise is a smooth field (random values on a grid of ``scale_px`` spacing, bicubically
    upsampled) in [-amplitude, amplitude], added to the signed distance. Only a window around
    the mask is processed.
    """
    import cv2  # heavy optional import (~0.3 s): only the 2D mask work needs OpenCV

    if amplitude <= 0 or not mask.any():
        return mask.copy()
    h, w = mask.shape
    pad = int(np.ceil(amplitude)) + 2
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, h)
    c0, c1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, w)
    win = mask[r0:r1, c0:c1]
    sd = _signed_distance(win)
    gh = max(int(np.ceil((r1 - r0) / scale_px)) + 2, 2)
    gw = max(int(np.ceil((c1 - c0) / scale_px)) + 2, 2)
    grid = rng.uniform(-1.0, 1.0, (gh, gw)).astype(np.float32)
    field = cv2.resize(grid, (c1 - c0, r1 - r0), interpolation=cv2.INTER_CUBIC)
    field = np.clip(field, -1.0, 1.0) * amplitude
    out = mask.copy()
    out[r0:r1, c0:c1] = (sd + field) > 0
    return out


def _false_blob(shape, rng: np.random.Generator) -> np.ndarray:
    import cv2  # heavy optional import (~0.3 s): only the 2D mask work needs OpenCV

    h, w = shape
    area = rng.uniform(200, 4000)
    aspect = rng.uniform(1.0, 2.5)
    ax = (int(max(np.sqrt(area * aspect / np.pi), 2)), int(max(np.sqrt(area / aspect / np.pi), 2)))
    centre = (int(rng.integers(0, w)), int(rng.integers(h // 3, h)))
    m = np.zeros((h, w), np.uint8)
    cv2.ellipse(m, centre, ax, float(rng.uniform(-15, 15)), 0, 360, 1, -1)
    return m.astype(bool)


def degrade_instances(instances: list[Instance2D], cfg: DegradeConfig,
                      rng: np.random.Generator, shape: tuple[int, int] | None = None
                      ) -> list[Instance2D]:
    """Apply the degradations of ``cfg`` to one image's instances (see the module doc).

    ``shape`` (H, W) is needed only when ``instances`` is empty and false positives are on.
    Returns new :class:`Instance2D` objects; empty masks after erosion are dropped. With
    :data:`NO_DEGRADE` the result equals the input (same masks, scores and ids).
    """
    if cfg.is_identity:
        return [Instance2D(i.mask.copy(), i.score, i.category_id, i.track_id) for i in instances]
    out = []
    for inst in instances:
        area = int(inst.mask.sum())
        p_miss = cfg.miss_rate_small if area < cfg.small_area else cfg.miss_rate
        if rng.random() < p_miss:
            continue
        m = erode_dilate(inst.mask, cfg.dilate_px)
        m = jitter_boundary(m, rng.uniform(*cfg.jitter_px), rng)
        if m.any():
            out.append(Instance2D(m, float(rng.uniform(0.7, 1.0)), inst.category_id,
                                  inst.track_id))
    if shape is None and instances:
        shape = instances[0].mask.shape
    n_false = int(rng.poisson(cfg.false_rate * len(instances))) if cfg.false_rate > 0 else 0
    cats = [i.category_id for i in instances] or [4]
    for _ in range(n_false if shape is not None else 0):
        m = jitter_boundary(_false_blob(shape, rng), rng.uniform(*cfg.jitter_px), rng)
        out.append(Instance2D(m, float(rng.uniform(0.3, 0.7)), int(rng.choice(cats)), -1))
    return out
