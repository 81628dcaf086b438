"""Amodal and visible masks of one image from completed point clouds, and the occlusion order.

Per instance: the completed cloud (``(K, 3)`` in the LiDAR/sensor frame) is projected with the
camera (a :class:`seqshape.camera.PinholeCamera`, any dataset; a KITTI calibration is taken as
its camera 2); points less than ``min_depth`` in front of the
camera are dropped; the amodal mask is the filled alpha shape of the rest
(:mod:`seqshape.amodal.alpha`), clipped to the image.

Occlusion, two rules (``order=``):

* ``"pixel"`` (default): where amodal masks overlap, each pixel goes to the instance whose
  completed surface is nearest there: the local depth of an instance at a pixel is the minimum
  depth of its ``k`` projected points nearest to that pixel (its front surface). The visible
  mask is the amodal mask minus the pixels won by others. The total order (for the KINS ids) is
  a topological sort of the pairwise "in front of" relation (who wins most of the pair's overlap),
  ties and cycles broken by median depth. Only the instances that can be nearest at a pixel (by the
  depth ranges of their points) are asked for their local depth there (:func:`_owners`).
* ``"median"``: instances are ordered by the median depth of their projected points; the visible
  mask is the amodal mask minus the amodal masks of all instances in front.

The per-pixel rule is right where the median is wrong (a long vehicle beside a short one, a
vehicle partly ahead of another); ``benchmarks/bm_labelling.py`` measures both (docs/amodal.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree

from seqshape.amodal.align import align_instances
from seqshape.amodal.alpha import alpha_shape_mask
from seqshape.camera import as_camera

ORDERS = ("pixel", "median")
MIN_DEPTH = 0.5  # m in front of the camera; nearer points are dropped before projecting
_K_LOCAL = 6


@dataclass
class InstanceMask:
    """One instance of one image.

    ``amodal``/``visible``: ``(h, w)`` bool; ``depth``: median depth (m) of the projected
    points; ``order``: rank in the occlusion order (0 = front-most).
    """

    track_id: str
    amodal: np.ndarray
    visible: np.ndarray
    depth: float
    order: int = 0
    uv: np.ndarray = field(default=None, repr=False)  # (M, 2) projected points
    z: np.ndarray = field(default=None, repr=False)  # (M,) their depths


def project_cloud(points, camera, image_size=None, min_depth: float = MIN_DEPTH):
    """Project ``points (N, 3)`` (sensor frame) with ``camera`` (a PinholeCamera);
    ``(uv (M, 2), depth (M,))``.

    Points nearer than ``min_depth`` metres in front of the camera are dropped.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    uv, depth = as_camera(camera).project(points)
    uv, depth = np.asarray(uv, dtype=np.float64), np.asarray(depth, dtype=np.float64)
    keep = np.isfinite(depth) & (depth > min_depth) & np.all(np.isfinite(uv), axis=1)
    return uv[keep], depth[keep]


def project_clouds(clouds: dict[str, np.ndarray], camera, min_depth: float = MIN_DEPTH
                   ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """:func:`project_cloud` of every cloud ``{track_id: (K, 3)}`` of one image in one
    projection (the clouds concatenated): ``{track_id: (uv (M, 2), depth (M,))}``."""
    arrays = [np.asarray(c, dtype=np.float64).reshape(-1, 3) for c in clouds.values()]
    if not arrays:
        return {}
    uv, depth = as_camera(camera).project(np.concatenate(arrays))  # (N, 2), (N,)
    keep = np.isfinite(depth) & (depth > min_depth) & np.all(np.isfinite(uv), axis=1)
    ends = np.cumsum([len(a) for a in arrays])
    out = {}
    for tid, a, b in zip(clouds, ends - [len(x) for x in arrays], ends, strict=True):
        k = keep[a:b]
        out[tid] = (uv[a:b][k], depth[a:b][k])
    return out


def instance_from_projection(track_id: str, uv, depth, image_size,
                             alpha: float | None = None) -> InstanceMask:
    """An :class:`InstanceMask` (visible mask not yet resolved) from projected points."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    amodal = alpha_shape_mask(uv, image_size, alpha=alpha)
    med = float(np.median(depth)) if len(depth) else np.inf
    return InstanceMask(str(track_id), amodal, amodal.copy(), med, 0, uv, depth)


def _local_depth(inst: InstanceMask, pix_uv: np.ndarray) -> np.ndarray:
    """Front-surface depth of ``inst`` at pixels ``pix_uv (P, 2)`` -> ``(P,)``."""
    if len(inst.z) == 0:
        return np.full(len(pix_uv), np.inf)
    k = min(_K_LOCAL, len(inst.z))
    _, idx = cKDTree(inst.uv).query(pix_uv, k=k)  # (P, k) or (P,)
    return inst.z[idx.reshape(len(pix_uv), -1)].min(axis=1)


def _box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)`` (end exclusive) of a non-empty bool mask's pixels."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _overlap_pixels(insts: list[InstanceMask]) -> tuple[np.ndarray, np.ndarray]:
    """``(rows (P,), cols (P,))`` of the pixels covered by two or more amodal masks, row-major
    (each mask is counted inside its own bounding box only)."""
    h, w = insts[0].amodal.shape
    boxes = [_box(m.amodal) if m.amodal.any() else (0, 0, 0, 0) for m in insts]
    count = np.zeros((h, w), dtype=np.int32)
    for m, (y0, y1, x0, x1) in zip(insts, boxes, strict=True):
        count[y0:y1, x0:x1] += m.amodal[y0:y1, x0:x1]
    return np.nonzero(count >= 2)


def _depth_range(inst: InstanceMask) -> tuple[float, float]:
    """``(min, max)`` depth of the projected points of ``inst``: bounds of its
    :func:`_local_depth` at any pixel (``inf`` for none; ``(-inf, inf)`` when unknown)."""
    if inst.z is None:
        return -np.inf, np.inf
    if len(inst.z) == 0:
        return np.inf, np.inf
    return float(np.min(inst.z)), float(np.max(inst.z))


def _owners(insts: list[InstanceMask], cover: np.ndarray, pix: np.ndarray) -> np.ndarray:
    """``(P,)`` the instance nearest in front at each overlap pixel: the argmin over the
    instances of their :func:`_local_depth` there (``inf`` where an instance does not cover
    the pixel; ties to the lower index), ``cover (n, P)``, ``pix (P, 2)`` as ``(u, v)``.

    The local depth of an instance lies between the least and the largest depth of its points
    (:func:`_depth_range`), so an instance whose least depth exceeds the smallest largest
    depth of the instances covering a pixel cannot be nearest there (some instance is nearer
    by a strict margin). Only the others, the candidates, are asked for their local depth, and
    only at the pixels with two candidates or more; a pixel with one candidate is its.
    The argmin is that of the full comparison, ties included.
    """
    n, p = cover.shape
    ranges = np.array([_depth_range(m) for m in insts], dtype=np.float64).reshape(n, 2)
    lo, hi = ranges[:, 0], ranges[:, 1]
    best_hi = np.where(cover, hi[:, None], np.inf).min(axis=0)  # (P,)
    cand = cover & (lo[:, None] <= best_hi[None, :])  # (n, P)
    count = cand.sum(axis=0)
    owner = np.argmax(cand, axis=0)  # the single candidate (first one where several)
    ask = np.flatnonzero(count >= 2)
    if len(ask) == 0:
        return owner
    cand = cand[:, ask]
    depth = np.full(cand.shape, np.inf)
    for i in range(n):
        sel = cand[i]
        if sel.any():
            depth[i, sel] = _local_depth(insts[i], pix[ask[sel]])
    owner[ask] = np.argmin(depth, axis=0)
    return owner


def _resolve_pixel(insts: list[InstanceMask]) -> np.ndarray:
    """Per-pixel ownership; returns ``wins (n, n)``: pixels of overlap i-vs-j won by i."""
    n = len(insts)
    wins = np.zeros((n, n), dtype=np.int64)
    rows, cols = _overlap_pixels(insts)
    if len(rows) == 0:
        return wins
    pix = np.c_[cols, rows].astype(np.float64)  # (P, 2) as (u, v)
    cover = np.stack([m.amodal[rows, cols] for m in insts])  # (n, P)
    owner = _owners(insts, cover, pix)  # (P,)
    own = np.zeros(cover.shape, dtype=np.float64)  # (n, P): the owner, where it covers
    own[owner, np.arange(len(owner))] = cover[owner, np.arange(len(owner))]
    wins = np.rint(own @ cover.T.astype(np.float64)).astype(np.int64)  # won by i over j
    np.fill_diagonal(wins, 0)
    for i in range(n):
        lose = cover[i] & (owner != i)
        insts[i].visible[rows[lose], cols[lose]] = False
    return wins


def _order_from_wins(wins: np.ndarray, depths: Sequence[float]) -> list[int]:
    """Indices front to back: topological order of "i in front of j", median depth as tiebreak."""
    n = len(depths)
    g = nx.DiGraph()
    g.add_nodes_from(range(n))
    for i in range(n):
        for j in range(i + 1, n):
            if wins[i, j] > wins[j, i]:
                g.add_edge(i, j)
            elif wins[j, i] > wins[i, j]:
                g.add_edge(j, i)
    try:
        return list(nx.lexicographical_topological_sort(g, key=lambda i: (depths[i], i)))
    except nx.NetworkXUnfeasible:  # a cycle: no consistent order, fall back to depth
        return sorted(range(n), key=lambda i: (depths[i], i))


def resolve_occlusion(insts: list[InstanceMask], order: str = "pixel") -> list[InstanceMask]:
    """Fill ``visible`` and ``order`` of every instance of one image, in place; returns them."""
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    if not insts:
        return insts
    for m in insts:
        m.visible = m.amodal.copy()
    depths = [m.depth for m in insts]
    if order == "pixel":
        ranking = _order_from_wins(_resolve_pixel(insts), depths)
    else:
        ranking = sorted(range(len(insts)), key=lambda i: (depths[i], i))
        covered = np.zeros_like(insts[0].amodal)
        for i in ranking:
            insts[i].visible = insts[i].amodal & ~covered
            covered |= insts[i].amodal
    for rank, i in enumerate(ranking):
        insts[i].order = rank
    return insts


def frame_masks(clouds: dict[str, np.ndarray], camera, image_size: tuple[int, int],
                alpha: float | None = None, order: str = "pixel",
                min_depth: float = MIN_DEPTH, extra=(),
                max_covered: float = 0.9, guides=None, align=None,
                guide_points=None) -> list[InstanceMask]:
    """Masks of one ``(h, w)`` image of ``camera`` (a PinholeCamera) from completed clouds
    ``{track_id: (K, 3) sensor frame}``.

    Instances whose amodal mask is empty (behind the camera, outside the image) are left out.
    ``extra``: instances made otherwise (mask-only labels, :mod:`seqshape.amodal.fallback`),
    ordered with the others; one whose mask lies more than ``max_covered`` inside the
    union of the clouds' amodal masks is left out (a vehicle already labelled).
    ``guides``: ``{track_id: (h, w) bool}`` 2D instance masks; with ``align`` (an
    :class:`~seqshape.amodal.align.AlignConfig`) those instances are moved in the image to
    match them (:mod:`seqshape.amodal.align`) and the occlusion is resolved again;
    ``guide_points`` ``{track_id: (M, 3) sensor frame}``, each vehicle's own LiDAR returns of
    this frame, keep it from moving off them.
    """
    insts = []
    for tid, (uv, depth) in project_clouds(clouds, camera, min_depth=min_depth).items():
        if len(uv) == 0:
            continue
        inst = instance_from_projection(tid, uv, depth, image_size, alpha=alpha)
        if inst.amodal.any():
            insts.append(inst)
    if len(extra):
        covered = np.zeros(image_size, dtype=bool)
        for m in insts:
            covered |= m.amodal
        for m in extra:
            area = np.count_nonzero(m.amodal)
            if area and np.count_nonzero(m.amodal & covered) <= max_covered * area:
                insts.append(m)
    insts = resolve_occlusion(insts, order=order)
    if align is not None and guides:
        pix = {tid: uv for tid, (uv, _) in
               project_clouds(guide_points or {}, camera, min_depth=min_depth).items()}
        if align_instances(insts, guides, align, pix):
            insts = resolve_occlusion(insts, order=order)
    return insts
