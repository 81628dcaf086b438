"""Overlays of amodal instance masks on a camera image: the one drawing behind the labeller's
overlay PNGs (``seqshape label --overlays``, the demo) and ``seqshape show-scene``'s image.

Per instance (an :class:`~seqshape.amodal.masks.InstanceMask` or an :class:`OverlayInstance`):
its visible mask tinted and its amodal mask outlined in the colour of its track, and a tag with
the track id. The colour is a function of the track id alone (:func:`track_colour`), so a
vehicle keeps its colour across frames, labelling modes and pictures. Tags are placed by
:func:`place_tags`: near their instance, inside the image, never over another tag (a thin line
joins a tag pushed away from its instance). A legend strip under the image explains them, one
entry per instance in depth order: ``track 3, depth rank 0`` (depth rank: the instance's place
in the image's occlusion order, 0 = nearest). An instance without a track (a mask-only label)
is grey, tagged ``m1``, ``m2``... Pixel coordinates are OpenCV's (x right, y down); images are
BGR ``uint8``.
"""

from __future__ import annotations

import colorsys
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seqshape._io import atomic_write_bytes, contained_path, safe_stem
from seqshape.errors import DataError

NO_TRACK_COLOUR = (150, 150, 150)  #: BGR of instances without a track
_FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX (cv2 is imported lazily)
_PAD = 2  # pixels between a tag's text and its box
_MAX_RINGS = 40  # how far (in tag heights) a tag may be pushed from its instance
_LEGEND_BG = (38, 38, 38)
_LEGEND_FG = (235, 235, 235)
_LEGEND_TITLE = ("tag = track id, colour = track;", "fill: visible mask, outline: amodal mask;",
                 "depth rank 0 = nearest")

Rect = tuple[int, int, int, int]  # x0, y0, x1, y1 (pixels, x1/y1 exclusive)


@dataclass
class OverlayInstance:
    """What :func:`draw_overlay` draws of one instance; an
    :class:`~seqshape.amodal.masks.InstanceMask` has these fields too. (This module does not
    import :mod:`~seqshape.amodal.masks`, whose scipy and networkx the viewers do not need.)

    ``amodal``/``visible``: ``(h, w)`` bool; ``order``: depth rank (0 = nearest).
    """

    track_id: str
    amodal: np.ndarray
    visible: np.ndarray
    order: int = 0


def track_colour(track: int | str | None) -> tuple[int, int, int]:
    """The BGR colour of ``track`` (an integer id, a string id, or None for no track).

    Integer ids (and strings of digits, so ``3`` and ``"0003"`` agree) take golden-ratio
    hues of the id, so consecutive ids differ strongly; other strings use their CRC-32.
    Deterministic: the same id has the same colour in every frame, run and picture.

    >>> track_colour(3) == track_colour("0003") != track_colour(4)
    True
    >>> track_colour(None)
    (150, 150, 150)
    """
    if track is None:
        return NO_TRACK_COLOUR
    text = str(track)
    key = int(text) if text.isdigit() else zlib.crc32(text.encode("utf-8", "surrogatepass"))
    r, g, b = colorsys.hsv_to_rgb((key * 0.618034) % 1.0, 0.85, 1.0)
    return int(255 * b), int(255 * g), int(255 * r)


def tag_label(track_id: str) -> str:
    """The short tag of a seqshape track id: its last ``_`` part, without leading zeros when
    it is a number, else its first 8 characters (``"0000_0003"`` -> ``"3"``).

    >>> tag_label("0000_0003"), tag_label("log_7fab2350-7eaf-3b7e")
    ('3', '7fab2350')
    """
    last = str(track_id).rsplit("_", 1)[-1]
    return str(int(last)) if last.isdigit() else last[:8]


def _font_scale(width: int) -> float:
    """Text scale for an image ``width`` pixels wide (0.45 at KITTI's 1242, larger above)."""
    return 0.45 * max(1.0, width / 1400.0)


def _overlap(a: Rect, b: Rect) -> int:
    """Area in pixels shared by rectangles ``a`` and ``b``."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return max(w, 0) * max(h, 0)


def _candidates(box: Rect, size: tuple[int, int], image: tuple[int, int]) -> np.ndarray:
    """Tag positions ``(C, 4)`` around an instance's bounding ``box``, best first, moved
    inside the image: above it, inside its top, beside it, below it; then rings of growing
    distance (up to :data:`_MAX_RINGS` tag heights away)."""
    (tw, th), (width, height) = size, image
    x0, y0, x1, y1 = box
    cx, cy = (x0 + x1 - tw) / 2, (y0 + y1 - th) / 2
    spots = [np.array([[x0, y0 - th - 1], [x1 - tw, y0 - th - 1], [x0, y0], [cx, cy],
                       [x1 + 1, y0], [x0 - tw - 1, y0], [x0, y1 + 1], [x1 - tw, y1 - th]])]
    step = th + 1
    for ring in range(1, _MAX_RINGS + 1):
        d = ring * step
        k = np.arange(-ring, ring + 1) * step
        one = np.ones_like(k)
        spots += [np.c_[x0 + k, (y0 - th - 1 - d) * one], np.c_[x0 + k, (y1 + d) * one],
                  np.c_[(x0 - tw - d) * one, y0 + k], np.c_[(x1 + d) * one, y0 + k]]
    xy = np.concatenate(spots).astype(np.float64)  # (C, 2) top-left corners
    xy[:, 0] = np.clip(xy[:, 0], 0, max(width - tw, 0))
    xy[:, 1] = np.clip(xy[:, 1], 0, max(height - th, 0))
    xy = np.round(xy).astype(np.int64)
    return np.c_[xy, xy[:, 0] + tw, xy[:, 1] + th]


def place_tags(boxes: Sequence[Rect], sizes: Sequence[tuple[int, int]],
               image_size: tuple[int, int], occupied: Sequence[Rect] = ()) -> list[Rect]:
    """Greedy tag placement: one rectangle per tag, inside the image and over no other tag.

    ``boxes``: each instance's bounding box ``(x0, y0, x1, y1)``; ``sizes``: each tag's
    ``(width, height)``; ``image_size``: ``(width, height)``; ``occupied``: rectangles to keep
    clear. Tags are placed in the given order, each at the first free position of
    :func:`_candidates` (above its box, inside it, beside it, below it, then further away).
    When no position is free (more tag area than image) a tag goes where it overlaps least.
    """
    placed: list[Rect] = []
    taken = np.array(list(occupied), dtype=np.int64).reshape(-1, 4)
    for box, size in zip(boxes, sizes, strict=True):
        cand = _candidates(box, size, image_size)  # (C, 4)
        w = (np.minimum(cand[:, None, 2], taken[None, :, 2])
             - np.maximum(cand[:, None, 0], taken[None, :, 0])).clip(0)
        h = (np.minimum(cand[:, None, 3], taken[None, :, 3])
             - np.maximum(cand[:, None, 1], taken[None, :, 1])).clip(0)
        cost = (w * h).sum(axis=1)  # (C,) pixels shared with the tags placed so far
        free = np.flatnonzero(cost == 0)
        best = cand[free[0] if len(free) else int(np.argmin(cost))]
        placed.append(tuple(int(v) for v in best))
        taken = np.vstack([taken, best])
    return placed


def _tag_texts(insts: Sequence[OverlayInstance], tracks) -> tuple[list, list[str]]:
    """``(track per instance, tag text per instance)``; instances without a track get
    ``m1``, ``m2``... in order."""
    if tracks is None:
        tracks = [tag_label(m.track_id) for m in insts]
    tracks = list(tracks)
    if len(tracks) != len(insts):
        raise ValueError(f"{len(tracks)} track ids for {len(insts)} instances")
    texts, k = [], 0
    for t in tracks:
        if t is None:
            k += 1
            texts.append(f"m{k}")
        else:
            texts.append(str(t))
    return tracks, texts


def _text_colour(bgr: tuple[int, int, int]) -> tuple[int, int, int]:
    """Black on light colours, white on dark ones."""
    b, g, r = bgr
    return (0, 0, 0) if 0.299 * r + 0.587 * g + 0.114 * b > 120 else (255, 255, 255)


def _draw_tag(cv2, img: np.ndarray, rect: Rect, text: str, colour, scale: float) -> None:
    cv2.rectangle(img, rect[:2], (rect[2] - 1, rect[3] - 1), colour, -1)
    base = cv2.getTextSize(text, _FONT, scale, 1)[1]
    cv2.putText(img, text, (rect[0] + _PAD, rect[3] - _PAD - base + 1), _FONT, scale,
                _text_colour(colour), 1, cv2.LINE_AA)


def overlay_layout(insts: Sequence[OverlayInstance], tracks=None, image_size=None
                   ) -> list[Rect | None]:
    """Where :func:`draw_overlay` puts each instance's tag (None: empty amodal mask, no tag).

    ``tracks`` and the tag order are :func:`draw_overlay`'s; ``image_size`` ``(width,
    height)`` defaults to the masks' size.
    """
    import cv2  # lazy: OpenCV is heavy and only the overlays need it

    _, texts = _tag_texts(insts, tracks)
    if image_size is None:
        h, w = insts[0].amodal.shape if insts else (1, 1)
        image_size = (w, h)
    scale = _font_scale(image_size[0])
    order = sorted(range(len(insts)), key=lambda i: insts[i].order)  # front first
    boxes, sizes, who = [], [], []
    for i in order:
        ys, xs = np.nonzero(insts[i].amodal)
        if not len(xs):
            continue
        (tw, th), base = cv2.getTextSize(texts[i], _FONT, scale, 1)
        boxes.append((int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1))
        sizes.append((tw + 2 * _PAD, th + base + 2 * _PAD))
        who.append(i)
    out: list[Rect | None] = [None] * len(insts)
    for i, rect in zip(who, place_tags(boxes, sizes, image_size), strict=True):
        out[i] = rect
    return out


def _legend(cv2, width: int, entries: list[tuple[str | None, str, tuple]],
            scale: float) -> np.ndarray:
    """The legend strip ``(H, width, 3)``: the title's parts, then ``[tag] text`` entries,
    flowing left to right and wrapping at the image width."""
    (_, th), base = cv2.getTextSize("Ag", _FONT, scale, 1)
    line = th + base + 2 * _PAD + 4
    items = [(None, part, _LEGEND_FG) for part in _LEGEND_TITLE] + [None] + list(entries)
    rows: list[list[tuple[int, str | None, str, tuple]]] = [[]]
    x = 6
    for item in items:
        if item is None:  # the entries start on a new line
            rows.append([])
            x = 6
            continue
        tag, text, colour = item
        tw = cv2.getTextSize(tag, _FONT, scale, 1)[0][0] + 2 * _PAD + 4 if tag else 0
        need = tw + cv2.getTextSize(text, _FONT, scale, 1)[0][0] + 14
        if x + need > width and rows[-1]:
            rows.append([])
            x = 6
        rows[-1].append((x, tag, text, colour))
        x += need
    strip = np.empty((len(rows) * line + 4, width, 3), np.uint8)
    strip[:] = _LEGEND_BG
    for r, row in enumerate(rows):
        y0 = r * line + 2
        for x0, tag, text, colour in row:
            if tag:
                tw = cv2.getTextSize(tag, _FONT, scale, 1)[0][0] + 2 * _PAD
                _draw_tag(cv2, strip, (x0, y0, x0 + tw, y0 + line - 4), tag, colour, scale)
                x0 += tw + 4
            cv2.putText(strip, text, (x0, y0 + line - 4 - _PAD - base + 1), _FONT, scale,
                        _LEGEND_FG, 1, cv2.LINE_AA)
    return strip


def _legend_entries(insts, tracks, texts) -> list[tuple[str, str, tuple]]:
    entries = []
    for i in sorted(range(len(insts)), key=lambda i: insts[i].order):
        what = f"track {texts[i]}" if tracks[i] is not None else "mask only (no track)"
        entries.append((texts[i], f"{what}, depth rank {insts[i].order}",
                        track_colour(tracks[i])))
    return entries


def draw_overlay(image: np.ndarray, insts: Sequence[OverlayInstance], tracks=None,
                 legend: bool = True) -> np.ndarray:
    """The BGR ``image (h, w, 3)`` with the instances drawn on it (module doc).

    ``tracks``: the track id shown and coloured for each instance (an int, a string, or None
    for an instance without a track); default :func:`tag_label` of each ``track_id``.
    ``legend``: add the legend strip under the image (the result is then taller than
    ``image``; without it the result has ``image``'s shape).
    """
    import cv2  # lazy: OpenCV is heavy and only the overlays need it

    tracks, texts = _tag_texts(insts, tracks)
    out = image.copy()
    h, w = out.shape[:2]
    scale = _font_scale(w)
    for i in sorted(range(len(insts)), key=lambda i: -insts[i].order):  # back to front
        m, col = insts[i], track_colour(tracks[i])
        out[m.visible] = (0.55 * out[m.visible] + 0.45 * np.array(col)).astype(np.uint8)
        contours, _ = cv2.findContours(m.amodal.astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, col, 1)
    for i, rect in enumerate(overlay_layout(insts, tracks, (w, h))):
        if rect is None:
            continue
        _leader(cv2, out, insts[i].amodal, rect, track_colour(tracks[i]))
        _draw_tag(cv2, out, rect, texts[i], track_colour(tracks[i]), scale)
    if legend:
        out = np.vstack([out, _legend(cv2, w, _legend_entries(insts, tracks, texts), scale)])
    return out


def _leader(cv2, img: np.ndarray, amodal: np.ndarray, rect: Rect, colour) -> None:
    """A line from a tag to its instance when the tag does not touch the instance's box."""
    ys, xs = np.nonzero(amodal)
    box = (int(xs.min()) - 2, int(ys.min()) - 2, int(xs.max()) + 3, int(ys.max()) + 3)
    if _overlap(rect, box):
        return
    tag_c = ((rect[0] + rect[2]) // 2, (rect[1] + rect[3]) // 2)
    k = int(np.argmin(np.hypot(xs - tag_c[0], ys - tag_c[1])))
    cv2.line(img, tag_c, (int(xs[k]), int(ys[k])), colour, 1, cv2.LINE_AA)


def frame_tracks(insts: Sequence[OverlayInstance], anns: Sequence[dict]) -> list | None:
    """The KINS ``track_id`` of each instance of one frame of a labelling result (None for
    the mask-only labels), or None when ``anns`` (that image's annotations, in the order the
    labeller wrote them) do not match ``insts`` one to one by amodal area."""
    if len(anns) != len(insts):
        return None
    for m, ann in zip(insts, anns, strict=True):
        if int(ann.get("a_area", -1)) != int(np.count_nonzero(m.amodal)):
            return None
    return [ann.get("track_id") for ann in anns]


def overlay_path(out_dir, log_name: str, frame) -> Path:
    """The overlay PNG of ``frame`` of the log ``log_name`` in ``out_dir``:
    ``OUT/<log>_FFFFFF.png``, the log name made file-name safe, kept inside ``out_dir``."""
    return contained_path(Path(out_dir), f"{safe_stem(log_name)}_{int(frame):06d}.png")


def write_overlays(log, result, out_dir, frames=None) -> list[Path]:
    """Overlay PNGs ``OUT/<log>_FFFFFF.png`` (:func:`draw_overlay`, with the legend) of a
    :class:`~seqshape.amodal.labeler.LabelResult` in its camera, on the camera image (black
    when absent); returns the paths.

    Tags show each instance's KINS ``track_id`` (the one in the label file); the log name is
    made file-name safe (:func:`seqshape._io.safe_stem`).
    """
    import cv2  # lazy: OpenCV is heavy and only the overlays need it

    out_dir = Path(out_dir)
    camera = result.camera or log.default_camera
    image_ids = {img.get("frame", img["id"]): img["id"] for img in result.images}
    anns: dict[int, list[dict]] = {}
    for ann in result.annotations:
        anns.setdefault(ann["image_id"], []).append(ann)
    paths = []
    for frame in (log.frames if frames is None else frames):
        img_path = log.image_path(frame, camera)
        img = (cv2.imread(str(img_path), cv2.IMREAD_COLOR)
               if img_path is not None and Path(img_path).is_file() else None)
        if img is None:
            cam = log.camera(camera, frame)
            img = np.zeros((cam.height, cam.width, 3), np.uint8)
        insts = result.masks.get(frame, [])
        tracks = frame_tracks(insts, anns.get(image_ids.get(frame), []))
        ok, buf = cv2.imencode(".png", draw_overlay(img, insts, tracks))
        if not ok:
            raise DataError(out_dir, f"could not encode the overlay of frame {frame}")
        path = overlay_path(out_dir, log.name, frame)
        atomic_write_bytes(path, buf.tobytes())
        paths.append(path)
    return paths
