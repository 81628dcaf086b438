"""Masks as COCO RLE, and the KINS (amodal) and COCO (instance) JSON files of a sequence.

Masks are boolean ``(H, W)`` arrays (row = image v, column = image u). RLEs are COCO compressed
RLE dicts ``{"size": [H, W], "counts": str}`` (``counts`` decoded to ASCII so that they go into
JSON as they are).

KINS file (``amodal/SSSS.json``), one per sequence::

    {"images": [{"id", "file_name": "SSSS/FFFFFF.png", "height", "width", "frame"}],
     "categories": [{"id", "name"}],
     "annotations": [{"id", "image_id", "category_id", "track_id",
                      "a_segm", "i_segm",      # amodal / visible (inmodal) mask, RLE or polygons
                      "a_bbox", "i_bbox",      # [x, y, w, h] of those masks, pixels
                      "a_area", "i_area",      # pixel counts of those masks
                      "oco_id", "ico_id",      # occlusion cluster and order, see below
                      "iscrowd"}]}

Occlusion order (:func:`occlusion_order`), the KINS definitions (Qi et al., CVPR 2019,
Sec. 3: "occlusion clusters" and the "relative occlusion order" inside them): in one image, two
instances are linked when their amodal masks overlap (the nearer one hides the other there);
the connected components with two or more instances are the occlusion clusters.

* ``oco_id``: the 1-based id of the instance's cluster, clusters numbered by the depth of their
  nearest member (front first); an instance that overlaps no other instance is in no cluster
  and gets ``oco_id`` 0 **and** ``ico_id`` 0.
* ``ico_id``: the occlusion order inside the cluster: 1 for an instance that nothing hides
  (the front-most), and one more than the largest order among the instances that hide it
  (``1 + max(ico of its occluders)``), so it rises by one each time an instance is occluded:
  A hides B hides C gives 1, 2, 3; A hiding both B and C (which do not touch) gives 1, 2, 2.

Of two overlapping instances the one with the smaller depth hides the other; depth is whatever
the producer sorts by (the labeller: the rank of its per-pixel occlusion order; the scene
writer: the distance of each vehicle's nearest visible point); ties are broken by annotation
order.

Segmentations are read as COCO RLE or polygons everywhere (:func:`segm_to_mask`; the KINS
release uses polygons); they are written as RLE, or as polygons with ``polygons=True``
(:func:`mask_to_polygons`: the outer contours of the mask's connected parts, so a hole inside a
mask is filled, and a round trip is exact otherwise).

COCO instance file (``instances_2d/SSSS.json``): ``images`` and ``categories`` as above and
``annotations`` with ``id``, ``image_id``, ``category_id``, ``segmentation`` (RLE, or polygons
``[[x1, y1, x2, y2, ...], ...]`` when read), ``bbox`` ``[x, y, w, h]``, ``area``, ``score``,
``iscrowd`` and an optional ``track_id``.

The category list (:data:`~seqshape.data.categories.KINS_CATEGORIES`, the default
``categories`` of every file written) comes from :mod:`seqshape.data.categories`.
"""

from __future__ import annotations

import graphlib
import json
import math
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from seqshape._io import atomic_write_json, read_bytes
from seqshape.data.categories import KINS_CATEGORIES
from seqshape.errors import DataError, require

IMAGE_KEYS = ("id", "file_name", "height", "width")
KINS_KEYS = ("id", "image_id", "category_id", "a_segm", "i_segm", "a_bbox", "i_bbox",
             "a_area", "i_area", "oco_id", "ico_id")
COCO_KEYS = ("id", "image_id", "category_id", "segmentation")
#: the largest image (height x width pixels) a file may declare: a bound against absurd sizes
#: that would allocate gigabytes (8192 x 8192 fits)
MAX_IMAGE_PIXELS = 1 << 26
_MAX_GROUPS = 7  # 5-bit groups in one compressed run: 35 bits hold any difference of two runs


class SegmentationError(ValueError):
    """A malformed COCO segmentation (RLE or polygons); the readers turn it into a
    :class:`~seqshape.errors.DataError` naming the file and the annotation."""


def _mask_api():
    return require("pycocotools.mask", "COCO RLE masks", "pycocotools")


# ----------------------------------------------------------------------------- masks


def mask_to_rle(mask) -> dict:
    """COCO compressed RLE ``{"size": [H, W], "counts": str}`` of a boolean (H, W) mask.

    The same string as ``pycocotools.mask.encode`` of the whole mask in column-major order
    (a mask of other values: of the mask as uint8), made from the mask's bounding box only.

    >>> m = np.zeros((3, 4), dtype=bool); m[1, 1:3] = True
    >>> rle = mask_to_rle(m); rle["size"], bool((rle_to_mask(rle) == m).all())
    ([3, 4], True)
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must be 2-D (H, W), got shape {mask.shape}")
    binary = _binary(mask)
    if binary is None:  # values other than 0 and 1: pycocotools on the whole mask as before
        rle = _mask_api().encode(np.asfortranarray(mask.astype(np.uint8)))
        return {"size": [int(rle["size"][0]), int(rle["size"][1])],
                "counts": rle["counts"].decode("ascii")}
    return _rle_from_box(binary, _mask_box(binary))


def _binary(mask: np.ndarray) -> np.ndarray | None:
    """``mask`` as bool when it is bool or its uint8 conversion holds only 0 and 1, else None."""
    if mask.dtype == bool:
        return mask
    data = mask.astype(np.uint8)
    return data.view(bool) if data.size == 0 or int(data.max()) <= 1 else None


def _mask_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(r0, r1, c0, c1)``, the half-open rows and columns of a boolean mask's true pixels,
    or None when it has none."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask[rows[0]:rows[-1] + 1].any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _box_runs(crop: np.ndarray | None, box, height: int, width: int) -> np.ndarray:
    """The uncompressed COCO RLE counts (alternating runs of zeros and ones from a run of
    zeros, column-major; no trailing empty run) of the ``height x width`` boolean mask that is
    ``crop`` inside ``box`` (:func:`_mask_box`) and false elsewhere."""
    total = height * width
    if box is None:
        return np.array([total], dtype=np.uint64)
    r0, r1, c0, c1 = box
    cols = np.zeros((c1 - c0, r1 - r0 + 2), dtype=np.int8)  # each column, a zero above, below
    cols[:, 1:-1] = crop.T
    step = np.diff(cols, axis=1)  # +1 where a run of ones starts, -1 where it ends
    sj, si = np.nonzero(step == 1)  # column-major order of the whole mask
    ej, ei = np.nonzero(step == -1)
    starts = (c0 + sj) * height + r0 + si
    ends = (c0 + ej) * height + r0 + ei
    joined = starts[1:] == ends[:-1]  # a run through the bottom row into the next column's top
    starts, ends = starts[np.r_[True, ~joined]], ends[np.r_[~joined, True]]
    runs = np.empty(2 * len(starts) + 1, dtype=np.int64)
    runs[0] = starts[0]
    runs[1::2] = ends - starts
    runs[2:-1:2] = starts[1:] - ends[:-1]
    runs[-1] = total - ends[-1]
    return (runs if runs[-1] else runs[:-1]).astype(np.uint64)


def _rle_from_box(mask: np.ndarray, box) -> dict:
    """:func:`mask_to_rle` of the boolean ``mask`` whose :func:`_mask_box` is ``box``."""
    h, w = (int(v) for v in mask.shape)
    crop = None if box is None else mask[box[0]:box[1], box[2]:box[3]]
    runs = _box_runs(crop, box, h, w)
    rle = _mask_api().frPyObjects({"size": [h, w], "counts": runs.tolist()}, h, w)
    return {"size": [h, w], "counts": rle["counts"].decode("ascii")}


def rle_to_mask(rle: dict) -> np.ndarray:
    """Boolean (H, W) mask of a COCO RLE (compressed ``str``/``bytes`` or uncompressed list).

    The RLE is checked first (:func:`rle_runs`): a malformed one raises
    :class:`SegmentationError` (a ``ValueError``), never decodes to garbage.
    """
    runs = rle_runs(rle)
    h, w = _rle_size(rle)
    counts = rle["counts"]
    if isinstance(counts, list):
        obj = _mask_api().frPyObjects({"size": [h, w], "counts": runs.tolist()}, h, w)
    else:
        obj = {"size": [h, w], "counts": counts.encode("ascii") if isinstance(counts, str)
               else bytes(counts)}
    return _decode(obj)


def rle_runs(rle) -> np.ndarray:
    """The run lengths ``(R,)`` int64 of a COCO RLE dict, checked.

    ``counts`` is a list of non-negative integers (uncompressed RLE) or a COCO compressed
    string (``str`` or ``bytes``, the LEB128-like code of ``pycocotools``' ``rleToString``);
    the runs must add up to ``height * width`` exactly. Anything else raises
    :class:`SegmentationError` saying what is wrong.

    >>> rle_runs({"size": [2, 3], "counts": [1, 2, 3]}).tolist()
    [1, 2, 3]
    >>> rle_runs(mask_to_rle(np.eye(2, dtype=bool))).tolist()
    [0, 1, 2, 1]
    """
    if not isinstance(rle, dict) or "size" not in rle or "counts" not in rle:
        raise SegmentationError("an RLE is a dict with 'size' and 'counts'")
    h, w = _rle_size(rle)
    counts = rle["counts"]
    if isinstance(counts, list):
        runs = _list_runs(counts)
    elif isinstance(counts, (str, bytes)):
        runs = _string_runs(counts)
    else:
        raise SegmentationError(f"RLE counts must be a string or a list of integers, "
                                f"got {type(counts).__name__}")
    total = int(runs.sum()) if runs.size else 0
    if total != h * w:
        raise SegmentationError(f"RLE counts cover {total} pixels, its size {[h, w]} has "
                                f"{h * w}")
    return runs


def _rle_size(rle: dict) -> tuple[int, int]:
    """``(h, w)`` of an RLE's ``size``, checked (:func:`_image_size`)."""
    size = rle.get("size") if isinstance(rle, dict) else None
    if not isinstance(size, (list, tuple)) or len(size) != 2:
        raise SegmentationError(f"RLE size must be [height, width], got {size!r}")
    return _image_size(size[0], size[1], "RLE size", allow_empty=True)


def _image_size(height, width, what: str, allow_empty: bool = False) -> tuple[int, int]:
    """``(height, width)`` as ints: non-negative (positive unless ``allow_empty``) integers of
    at most :data:`MAX_IMAGE_PIXELS` pixels together, else :class:`SegmentationError`."""
    h, w = _integer(height), _integer(width)
    low = 0 if allow_empty else 1
    if h is None or w is None or h < low or w < low:
        raise SegmentationError(f"{what} must be {'non-negative' if allow_empty else 'positive'}"
                                f" integers, got {[height, width]!r}")
    if h * w > MAX_IMAGE_PIXELS:
        raise SegmentationError(f"{what} {[h, w]} is over {MAX_IMAGE_PIXELS} pixels")
    return h, w


def _integer(value) -> int | None:
    """``value`` as an int when it is an integer (a JSON number without a fraction; not a
    bool), else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return None


def _list_runs(counts: list) -> np.ndarray:
    """Runs of uncompressed RLE counts: non-negative integers (sum checked by the caller)."""
    runs = [_integer(c) for c in counts]
    bad = next((i for i, r in enumerate(runs) if r is None or r < 0), None)
    if bad is not None:
        raise SegmentationError(f"RLE counts[{bad}] = {counts[bad]!r}: run lengths are "
                                "non-negative integers")
    if any(r > MAX_IMAGE_PIXELS for r in runs):
        raise SegmentationError(f"RLE run longer than {MAX_IMAGE_PIXELS} pixels")
    return np.asarray(runs, dtype=np.int64)


def _string_runs(counts: str | bytes) -> np.ndarray:
    """Runs of a COCO compressed RLE string (``pycocotools`` ``rleFrString``, vectorised).

    Each run is 5-bit groups, least significant first, in characters ``48 + group`` with bit
    0x20 saying "more groups follow"; the last group's bit 0x10 is the sign. From the fourth
    run on, a run is stored as the difference to the run two before it.
    """
    if isinstance(counts, str):
        if not counts.isascii():
            raise SegmentationError("RLE counts string is not ASCII")
        counts = counts.encode("ascii")
    c = np.frombuffer(counts, dtype=np.uint8).astype(np.int64) - 48
    if c.size == 0:
        return np.zeros(0, dtype=np.int64)
    if c.min() < 0 or c.max() > 63:
        raise SegmentationError("RLE counts string holds characters outside '0'..'o'")
    more = (c & 0x20) != 0
    if more[-1]:
        raise SegmentationError("RLE counts string is truncated (its last run is unfinished)")
    ends = np.flatnonzero(~more)  # the last character of each run
    starts = np.r_[0, ends[:-1] + 1]
    length = ends - starts + 1
    if length.max() > _MAX_GROUPS:
        raise SegmentationError("RLE counts string holds a run too long to be a pixel count")
    k = np.arange(c.size) - np.repeat(starts, length)  # group index inside its run
    x = np.add.reduceat((c & 0x1F) << (5 * k), starts)
    x = np.where((c[ends] & 0x10) != 0, x - (1 << (5 * length)), x)  # sign extension
    runs = x.copy()
    runs[1::2] = np.cumsum(x[1::2])  # odd runs from the 4th (index 3) on: + run two before
    runs[2::2] = np.cumsum(x[2::2])  # even runs from index 4 on likewise; run 0 stays alone
    if runs.min() < 0 or runs.max() > MAX_IMAGE_PIXELS:
        bad = int(np.flatnonzero((runs < 0) | (runs > MAX_IMAGE_PIXELS))[0])
        raise SegmentationError(f"RLE counts string decodes to run {bad} of length "
                                f"{int(runs[bad])}")
    return runs


def _decode(rle: dict) -> np.ndarray:
    with warnings.catch_warnings():  # pycocotools' __array__ is not numpy-2 clean
        warnings.simplefilter("ignore", DeprecationWarning)
        return _mask_api().decode(rle).astype(bool)


def segm_to_mask(segm, height: int, width: int) -> np.ndarray:
    """Boolean (height, width) mask of a COCO segmentation: RLE dict or list of polygons.

    Polygons are lists ``[x1, y1, x2, y2, ...]`` (pixels, at least three points) of finite
    numbers no further than one image size outside the image; they are rasterised as
    ``pycocotools`` does (``frPyObjects``, the polygons merged into one mask). A malformed
    segmentation raises :class:`SegmentationError` (a ``ValueError``).

    A pixel ``(u, v)`` is the unit square from ``(u, v)`` to ``(u + 1, v + 1)``, so a polygon
    along pixel edges covers exactly the pixels inside it:

    >>> segm_to_mask([[1, 1, 4, 1, 4, 3, 1, 3]], 4, 5).astype(int)
    array([[0, 0, 0, 0, 0],
           [0, 1, 1, 1, 0],
           [0, 1, 1, 1, 0],
           [0, 0, 0, 0, 0]])
    """
    height, width = _image_size(height, width, "image size")
    if isinstance(segm, dict):
        mask = rle_to_mask(segm)
        if mask.shape != (height, width):
            raise SegmentationError(f"RLE size {list(mask.shape)} != image size "
                                    f"{[height, width]}")
        return mask
    polys = _polygons(segm, height, width)
    if not polys:
        return np.zeros((height, width), dtype=bool)
    mu = _mask_api()
    rles = mu.frPyObjects(polys, height, width)
    return _decode(mu.merge(rles))


def _polygons(segm, height: int, width: int) -> list[list[float]]:
    """The polygons of a segmentation as lists of floats, checked (:func:`segm_to_mask`)."""
    if not isinstance(segm, list):
        raise SegmentationError(f"a segmentation is an RLE dict or a list of polygons, got "
                                f"{type(segm).__name__}")
    out = []
    for i, poly in enumerate(segm):
        if not isinstance(poly, list) or not all(_is_number(v) for v in poly):
            raise SegmentationError(f"polygon {i}: a polygon is a flat list of numbers "
                                    "[x1, y1, x2, y2, ...]")
        if len(poly) < 6 or len(poly) % 2:
            raise SegmentationError(f"polygon {i}: {len(poly)} coordinates; polygons need an "
                                    "even number (>= 6) of coordinates")
        finite = all(_is_finite(v) for v in poly)
        xy = np.asarray(poly if finite else [], dtype=np.float64).reshape(-1, 2)
        lim = np.array([width, height], dtype=np.float64)
        if not (finite and np.all(xy >= -lim) and np.all(xy <= 2 * lim)):
            raise SegmentationError(f"polygon {i}: coordinates must be finite and within one "
                                    f"image size of the {width}x{height} image")
        out.append([float(v) for v in poly])
    return out


def _is_number(value) -> bool:
    """A JSON number: int or float, not a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value,
                                                                                        bool)


def _is_finite(value) -> bool:
    """A JSON number that is finite as a float (an integer too large for a float is not)."""
    if not _is_number(value):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def mask_to_polygons(mask) -> list[list[float]]:
    """COCO polygons ``[[x1, y1, x2, y2, ...], ...]`` of a boolean (H, W) mask: the outer
    contour of each connected part (``cv2.findContours``, ``RETR_EXTERNAL``).

    The contours are traced on the mask upsampled 2x, so they run along pixel edges and a
    single pixel or a one-pixel line still gives a valid polygon; :func:`segm_to_mask` of the
    result gives back the mask exactly, except that holes are filled (outer contours only).

    >>> m = np.zeros((4, 5), dtype=bool); m[1:3, 1:4] = True
    >>> bool((segm_to_mask(mask_to_polygons(m), 4, 5) == m).all())
    True
    """
    import cv2  # lazy: OpenCV is heavy and only the polygon output needs it

    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"mask must be 2-D (H, W), got shape {mask.shape}")
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if rows.size == 0:
        return []
    r0, c0 = rows[0], cols[0]
    box = mask[r0:rows[-1] + 1, c0:cols[-1] + 1].astype(np.uint8)  # only the mask's box
    up = np.repeat(np.repeat(box, 2, axis=0), 2, axis=1)
    contours, _ = cv2.findContours(up, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        xy = (c.reshape(-1, 2).astype(np.float64) + 0.5) / 2 + [c0, r0]
        if len(xy) < 3:  # cannot happen on the 2x grid; guard the COCO minimum anyway
            continue
        out.append([round(float(v), 2) for v in xy.ravel()])
    return out


def encode_segm(mask, polygons: bool = False):
    """A boolean (H, W) mask as a COCO segmentation: RLE, or polygons (module doc)."""
    return mask_to_polygons(mask) if polygons else mask_to_rle(mask)


def bbox_of_mask(mask) -> list[float]:
    """COCO box ``[x, y, w, h]`` (pixels, x = column) of a boolean mask; zeros when empty."""
    mask = np.asarray(mask, dtype=bool)
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return [0.0, 0.0, 0.0, 0.0]
    cols = np.flatnonzero(mask.any(axis=0))
    return [float(cols[0]), float(rows[0]), float(cols[-1] - cols[0] + 1),
            float(rows[-1] - rows[0] + 1)]


# ----------------------------------------------------------------------------- occlusion


def _mask_overlaps(masks: Sequence[np.ndarray]) -> np.ndarray:
    """``(K, K)`` bool: do masks i and j share a pixel (compared inside their common box)."""
    k = len(masks)
    boxes = [_mask_box(m) for m in masks]
    out = np.zeros((k, k), dtype=bool)
    for i in range(k):
        for j in range(i + 1, k):
            if boxes[i] is None or boxes[j] is None:
                continue
            r0, r1 = max(boxes[i][0], boxes[j][0]), min(boxes[i][1], boxes[j][1])
            c0, c1 = max(boxes[i][2], boxes[j][2]), min(boxes[i][3], boxes[j][3])
            if r0 < r1 and c0 < c1 and np.any(masks[i][r0:r1, c0:c1] & masks[j][r0:r1, c0:c1]):
                out[i, j] = out[j, i] = True
    return out


def occlusion_order(depths: Sequence[float], amodal_masks: Sequence[np.ndarray],
                    hides=None) -> tuple[list[int], list[int]]:
    """KINS ``(oco_id, ico_id)`` per instance of one image (definitions in the module doc).

    ``depths`` (K,) sort front (small) to back; ``amodal_masks`` K boolean (H, W) masks.
    ``hides``: optional ``(K, K)`` bool, ``hides[i, j]`` when instance i covers pixels of j's
    amodal mask (an exact relation, e.g. a renderer's); for an overlapping pair it decides who
    is in front where it is one-sided, the depths decide otherwise (and everywhere when the
    relation has a cycle). Isolated instances get ``(0, 0)``.
    """
    k = len(depths)
    if len(amodal_masks) != k:
        raise ValueError(f"{k} depths but {len(amodal_masks)} masks")
    if k == 0:
        return [], []
    overlap = _mask_overlaps([np.asarray(m, dtype=bool) for m in amodal_masks])
    parent = list(range(k))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*np.nonzero(np.triu(overlap, 1)), strict=True):
        parent[find(int(i))] = find(int(j))
    order = _front_to_back(depths, overlap, hides)
    cluster_ids: dict[int, int] = {}
    oco, ico = [0] * k, [0] * k
    done: list[int] = []
    for i in order:
        if not overlap[i].any():
            continue  # in no cluster: 0, 0
        root = find(i)
        cluster_ids.setdefault(root, len(cluster_ids) + 1)
        oco[i] = cluster_ids[root]
        # everything overlapping i and already placed is in front of it
        ico[i] = 1 + max((ico[j] for j in done if overlap[i, j]), default=0)
        done.append(i)
    return oco, ico


def _front_to_back(depths, overlap: np.ndarray, hides) -> list[int]:
    """Instance indices front to back: by depth, or a topological order of ``hides`` on the
    overlapping pairs where it is one-sided (depth breaking ties; depth alone on a cycle)."""
    k = len(depths)
    by_depth = sorted(range(k), key=lambda i: (float(depths[i]), i))
    if hides is None:
        return by_depth
    hides = np.asarray(hides, dtype=bool).reshape(k, k)
    rank = {i: r for r, i in enumerate(by_depth)}
    # each pair gets one direction: the one-sided relation where there is one, else depth
    front = {j: set() for j in range(k)}
    for i, j in zip(*np.nonzero(np.triu(overlap, 1)), strict=True):
        i, j = int(i), int(j)
        if hides[i, j] != hides[j, i]:
            a, b = (i, j) if hides[i, j] else (j, i)
        else:
            a, b = (i, j) if rank[i] < rank[j] else (j, i)
        front[b].add(a)
    sorter = graphlib.TopologicalSorter(front)
    try:
        sorter.prepare()
    except graphlib.CycleError:
        return by_depth
    out = []
    while sorter.is_active():
        ready = sorted(sorter.get_ready(), key=rank.get)
        out.extend(ready)
        sorter.done(*ready)
    return out


def kins_annotation(ann_id: int, image_id: int, category_id: int, amodal_mask, visible_mask,
                    oco_id: int, ico_id: int, track_id: int | None = None,
                    polygons: bool = False) -> dict:
    """One KINS annotation dict from boolean (H, W) amodal and visible masks (segmentations
    as RLE, or as polygons with ``polygons``)."""
    a = np.asarray(amodal_mask, dtype=bool)
    v = np.asarray(visible_mask, dtype=bool)
    if a.shape != v.shape:
        raise ValueError(f"amodal mask {a.shape} and visible mask {v.shape} differ in size")
    a_segm, a_bbox, a_area = _described(a, polygons)
    i_segm, i_bbox, i_area = _described(v, polygons)
    ann = {"id": int(ann_id), "image_id": int(image_id), "category_id": int(category_id),
           "a_segm": a_segm, "i_segm": i_segm, "a_bbox": a_bbox, "i_bbox": i_bbox,
           "a_area": a_area, "i_area": i_area,
           "oco_id": int(oco_id), "ico_id": int(ico_id), "iscrowd": 0}
    if track_id is not None:
        ann["track_id"] = int(track_id)
    return ann


def _described(mask: np.ndarray, polygons: bool) -> tuple[Any, list[float], int]:
    """``(segmentation, bbox, area)`` of a boolean (H, W) mask: :func:`encode_segm`,
    :func:`bbox_of_mask` and its pixel count, from one search for its bounding box."""
    if mask.ndim != 2:
        raise ValueError(f"mask must be 2-D (H, W), got shape {mask.shape}")
    box = _mask_box(mask)
    segm = mask_to_polygons(mask) if polygons else _rle_from_box(mask, box)
    if box is None:
        return segm, [0.0, 0.0, 0.0, 0.0], 0
    r0, r1, c0, c1 = box
    area = int(np.count_nonzero(mask[r0:r1, c0:c1]))
    return segm, [float(c0), float(r0), float(c1 - c0), float(r1 - r0)], area


def coco_annotation(ann_id: int, image_id: int, category_id: int, mask, score: float = 1.0,
                    track_id: int | None = None, polygons: bool = False) -> dict:
    """One COCO instance annotation dict from a boolean (H, W) mask (``segmentation`` RLE, or
    polygons with ``polygons``)."""
    segm, bbox, area = _described(np.asarray(mask, dtype=bool), polygons)
    ann = {"id": int(ann_id), "image_id": int(image_id), "category_id": int(category_id),
           "segmentation": segm, "bbox": bbox, "area": area, "score": float(score),
           "iscrowd": 0}
    if track_id is not None:
        ann["track_id"] = int(track_id)
    return ann


def image_entry(image_id: int, sequence: str, frame: int, height: int, width: int,
                file_name: str | None = None) -> dict:
    """An ``images`` entry; ``file_name`` defaults to KITTI's ``SSSS/FFFFFF.png``."""
    name = file_name if file_name is not None else f"{sequence}/{int(frame):06d}.png"
    return {"id": int(image_id), "file_name": name,
            "height": int(height), "width": int(width), "frame": int(frame)}


# ----------------------------------------------------------------------------- files


def write_kins(path: str | Path, images: list[dict], annotations: list[dict],
               categories: list[dict] | None = None, info: dict | None = None) -> None:
    """Write a KINS-format JSON file atomically (categories default to :data:`KINS_CATEGORIES`;
    ``info``, when given, is written as the file's first key, as COCO's ``info`` block).

    The content is validated first (as :func:`read_kins` does), so an invalid annotation
    raises ``ValueError`` and nothing is written.
    """
    doc = {} if info is None else {"info": dict(info)}
    doc.update({"images": list(images), "categories": list(categories or KINS_CATEGORIES),
                "annotations": list(annotations)})
    try:
        _validate(doc, KINS_KEYS, ("a_segm", "i_segm"))
    except _Invalid as exc:
        raise ValueError(f"invalid KINS content: {exc}") from None
    atomic_write_json(path, doc, indent=None)


def read_kins(path: str | Path) -> dict[str, list[dict]]:
    """Read and validate a KINS JSON file; returns ``{"images", "categories", "annotations"}``.

    Every annotation must have :data:`KINS_KEYS`, refer to an existing image and category, and
    carry masks (RLE or polygons) of its image's size. ``track_id`` and ``iscrowd`` are
    optional (``iscrowd`` defaults to 0). Problems raise :class:`DataError` naming the file and
    the annotation index.
    """
    doc = _load(path)
    try:
        _validate(doc, KINS_KEYS, ("a_segm", "i_segm"))
    except _Invalid as exc:
        raise DataError(path, str(exc)) from None
    for ann in doc["annotations"]:
        ann.setdefault("iscrowd", 0)
    return doc


def write_coco_instances(path: str | Path, images: list[dict], annotations: list[dict],
                         categories: list[dict] | None = None) -> None:
    """Write COCO instance-format JSON (visible 2D masks, as a segmenter outputs) atomically."""
    doc = {"images": list(images), "categories": list(categories or KINS_CATEGORIES),
           "annotations": list(annotations)}
    try:
        _validate(doc, COCO_KEYS, ("segmentation",))
    except _Invalid as exc:
        raise ValueError(f"invalid COCO content: {exc}") from None
    atomic_write_json(path, doc, indent=None)


def read_coco_instances(path: str | Path) -> dict[str, list[dict]]:
    """Read COCO instance-format JSON; polygon segmentations are converted to RLE.

    Returns ``{"images", "categories", "annotations"}``; every annotation ends with an RLE
    ``segmentation`` plus ``bbox``, ``area`` (computed when absent), ``score`` (1.0 when
    absent) and ``iscrowd`` (0 when absent).
    """
    doc = _load(path)
    try:
        _validate(doc, COCO_KEYS, ("segmentation",))
    except _Invalid as exc:
        raise DataError(path, str(exc)) from None
    sizes = {img["id"]: (int(img["height"]), int(img["width"])) for img in doc["images"]}
    for i, ann in enumerate(doc["annotations"]):
        if isinstance(ann["segmentation"], dict) and "area" in ann and "bbox" in ann:
            mask = None
        else:
            try:
                mask = segm_to_mask(ann["segmentation"], *sizes[ann["image_id"]])
            except (ValueError, TypeError) as exc:
                raise DataError(path, f"annotations[{i}].segmentation: {exc}") from None
            ann["segmentation"] = mask_to_rle(mask)
            ann.setdefault("area", int(mask.sum()))
            ann.setdefault("bbox", bbox_of_mask(mask))
        ann.setdefault("score", 1.0)
        ann.setdefault("iscrowd", 0)
    return doc


def annotation_mask(ann: dict, key: str, image: dict) -> np.ndarray:
    """The boolean (H, W) mask of ``ann[key]`` (RLE or polygons) on its ``image`` entry."""
    return segm_to_mask(ann[key], int(image["height"]), int(image["width"]))


def annotations_by_image(doc: dict[str, list[dict]]) -> dict[int, list[dict]]:
    """Annotations grouped by ``image_id`` (every image present, possibly with an empty list)."""
    out: dict[int, list[dict]] = {img["id"]: [] for img in doc["images"]}
    for ann in doc["annotations"]:
        out[ann["image_id"]].append(ann)
    return out


class _Invalid(Exception):
    pass


def _load(path: str | Path) -> dict[str, Any]:
    """The JSON object in ``path``; :class:`DataError` naming the file on any problem."""
    path = Path(path)
    data = read_bytes(path, "file", "json")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text (byte {exc.start}): not a JSON file") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(path, f"invalid JSON ({exc})") from None
    except (ValueError, RecursionError) as exc:  # digits over Python's limit, deep nesting
        raise DataError(path, f"invalid JSON ({type(exc).__name__}: {exc})") from None
    if not isinstance(doc, dict):
        raise DataError(path, "expected a JSON object with images, categories, annotations, "
                              f"got a JSON {_json_type(doc)}")
    return doc


def _json_type(value) -> str:
    """The JSON name of a parsed value's type, for messages."""
    for kind, name in ((dict, "object"), (list, "array"), (str, "string"), (bool, "boolean"),
                       (int, "number"), (float, "number")):
        if isinstance(value, kind):
            return name
    return "null" if value is None else type(value).__name__


def _validate(doc: dict, ann_keys: Sequence[str], segm_keys: Sequence[str]) -> None:
    """Check a KINS / COCO document (keys, types, ids, segmentations); raises ``_Invalid``."""
    for key in ("images", "categories", "annotations"):
        if not isinstance(doc.get(key), list):
            raise _Invalid(f"missing or non-list top-level key '{key}'")
    sizes = _check_images(doc["images"])
    cats = set()
    for i, cat in enumerate(doc["categories"]):
        if not isinstance(cat, dict) or "id" not in cat or "name" not in cat:
            raise _Invalid(f"categories[{i}]: needs 'id' and 'name'")
        cat_id = _id(cat["id"], f"categories[{i}].id")
        if cat_id in cats:
            raise _Invalid(f"categories[{i}]: duplicate category id {cat_id}")
        cats.add(cat_id)
    ids = set()
    for i, ann in enumerate(doc["annotations"]):
        where = f"annotations[{i}]"
        _check_object(ann, ann_keys, where)
        ann_id = _id(ann["id"], f"{where}.id")
        if ann_id in ids:
            raise _Invalid(f"{where}: duplicate annotation id {ann_id}")
        ids.add(ann_id)
        if _id(ann["image_id"], f"{where}.image_id") not in sizes:
            raise _Invalid(f"{where}: unknown image_id {ann['image_id']}")
        if _id(ann["category_id"], f"{where}.category_id") not in cats:
            raise _Invalid(f"{where}: unknown category_id {ann['category_id']}")
        _check_fields(ann, where)
        for key in segm_keys:
            _check_segm(ann[key], sizes[ann["image_id"]], f"{where}.{key}")


def _check_object(obj, keys, where: str) -> None:
    """``obj`` must be a JSON object holding every one of ``keys``."""
    if not isinstance(obj, dict):
        raise _Invalid(f"{where}: expected an object, got a JSON {_json_type(obj)}")
    missing = [k for k in keys if k not in obj]
    if missing:
        raise _Invalid(f"{where}: missing key(s) {missing}")


def _check_images(images: list) -> dict[int, tuple[int, int]]:
    """``{image id: (height, width)}`` of checked ``images`` entries."""
    sizes = {}
    names: dict[str, int] = {}
    for i, img in enumerate(images):
        _check_object(img, IMAGE_KEYS, f"images[{i}]")
        image_id = _id(img["id"], f"images[{i}].id")
        if image_id in sizes:
            raise _Invalid(f"images[{i}]: duplicate image id {image_id}")
        if not isinstance(img["file_name"], str) or not img["file_name"]:
            raise _Invalid(f"images[{i}].file_name: expected a non-empty string")
        first = names.setdefault(img["file_name"], i)
        if first != i:
            raise _Invalid(f"images[{i}]: file_name {img['file_name']!r} is also images[{first}]"
                           " (one entry per image: its annotations would be split or counted "
                           "twice)")
        if "frame" in img:
            _id(img["frame"], f"images[{i}].frame")
        try:
            sizes[image_id] = _image_size(img["height"], img["width"], "height, width")
        except SegmentationError as exc:
            raise _Invalid(f"images[{i}]: {exc}") from None
    return sizes


def _id(value, where: str) -> int:
    """An id: a non-negative integer (``_Invalid`` otherwise)."""
    out = _integer(value)
    if out is None or out < 0:
        raise _Invalid(f"{where}: expected a non-negative integer, got {value!r}")
    return out


#: optional or required annotation fields and their check: "box" [x, y, w, h] finite with
#: w, h >= 0; "count" a finite number >= 0; "order" an integer >= 0; "number" any number
#: (NaN for unknown); "finite" a finite number; "flag" 0 or 1; "track" an integer or string
_FIELDS = {"a_bbox": "box", "i_bbox": "box", "bbox": "box", "a_area": "count",
           "i_area": "count", "area": "count", "oco_id": "order", "ico_id": "order",
           "iscrowd": "flag", "score": "finite", "distance": "number",
           "lidar_points": "number", "track_id": "track"}


def _check_fields(ann: dict, where: str) -> None:
    """Check the annotation's known non-segmentation fields (:data:`_FIELDS`)."""
    for key, kind in _FIELDS.items():
        if key not in ann:
            continue
        v = ann[key]
        if kind == "box":
            ok = (isinstance(v, list) and len(v) == 4 and all(_is_finite(x) for x in v)
                  and v[2] >= 0 and v[3] >= 0)
            want = "[x, y, w, h]: four finite numbers, w and h >= 0"
        elif kind in ("count", "finite", "number"):
            ok = _is_finite(v) if kind != "number" else _is_number(v)
            ok = ok and (kind != "count" or v >= 0)
            want = {"count": "a finite number >= 0", "finite": "a finite number",
                    "number": "a number"}[kind]
        elif kind in ("order", "flag"):
            n = _integer(v)
            ok = n is not None and (0 <= n if kind == "order" else n in (0, 1))
            want = "an integer >= 0" if kind == "order" else "0 or 1"
        else:
            ok = v is None or isinstance(v, str) or _integer(v) is not None
            want = "an integer or a string"
        if not ok:
            raise _Invalid(f"{where}.{key}: expected {want}, got {v!r}")


def _check_segm(segm, size: tuple[int, int], where: str) -> None:
    """Check one segmentation completely (RLE runs or polygon coordinates) against its image's
    ``(height, width)``, so that decoding it later cannot fail."""
    try:
        if isinstance(segm, dict):
            rle_runs(segm)
            rle_size = _rle_size(segm)
            if rle_size != size:
                raise SegmentationError(f"RLE size {list(rle_size)} != image size {list(size)}")
        else:
            _polygons(segm, *size)
    except SegmentationError as exc:
        raise _Invalid(f"{where}: {exc}") from None
