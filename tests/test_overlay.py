"""Overlays of amodal masks (seqshape.amodal.overlay): one colour per track, tags that stay in
the image and avoid each other, a legend; the labeller's overlay files."""

import colorsys
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from seqshape.amodal import labeler
from seqshape.amodal.labeler import LabelResult
from seqshape.amodal.masks import InstanceMask
from seqshape.amodal.overlay import (
    NO_TRACK_COLOUR,
    draw_overlay,
    frame_tracks,
    overlay_layout,
    place_tags,
    track_colour,
    write_overlays,
)
from seqshape.data.kins import kins_annotation

H, W = 120, 320
GREY = 90


def box_mask(x0, y0, x1, y1, h=H, w=W):
    m = np.zeros((h, w), bool)
    m[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = True
    return m


def inst(track_id, rect, order, visible=None):
    a = box_mask(*rect)
    return InstanceMask(track_id, a, a.copy() if visible is None else visible, float(order),
                        order)


def hsv_bgr(h):
    """The documented colour rule by hand: hue h, saturation 0.85, value 1, as BGR."""
    r, g, b = colorsys.hsv_to_rgb(h, 0.85, 1.0)
    return int(255 * b), int(255 * g), int(255 * r)


def test_track_colour_rule_and_stability():
    assert track_colour(3) == hsv_bgr((3 * 0.618034) % 1.0) == track_colour("0003")
    assert track_colour(None) == NO_TRACK_COLOUR
    assert track_colour("7fab2350-uuid") == track_colour("7fab2350-uuid")  # no salted hash
    assert len({track_colour(k) for k in range(12)}) == 12


def test_one_colour_per_track_across_frames():
    """Track 3 is in front in one frame and behind in the next: its tint is the same; a
    different track has a different tint (before, the colour followed the depth rank)."""
    img = np.full((H, W, 3), GREY, np.uint8)
    f1 = [inst("0000_0003", (20, 30, 90, 80), 0), inst("0000_0005", (150, 30, 220, 80), 1)]
    f2 = [inst("0000_0005", (30, 40, 100, 90), 0), inst("0000_0003", (200, 20, 260, 60), 1)]
    o1, o2 = draw_overlay(img, f1, legend=False), draw_overlay(img, f2, legend=False)
    expect = (0.55 * GREY + 0.45 * np.array(track_colour(3))).astype(np.uint8)
    # inside the visible masks, away from outlines and tags
    assert (o1[60, 50] == expect).all() and (o2[50, 240] == expect).all()
    assert (o1[60, 180] != expect).any() and (o1[60, 180] == o2[70, 60]).all()


def test_tags_inside_image_and_apart_on_a_crowded_frame():
    rng = np.random.default_rng(0)
    insts = []
    for k in range(25):  # many overlapping instances, some cut by every border
        x0, y0 = int(rng.integers(-40, W - 10)), int(rng.integers(-20, H - 8))
        rect = (x0, y0, x0 + int(rng.integers(12, 90)), y0 + int(rng.integers(10, 50)))
        if not box_mask(*rect).any():
            rect = (0, 0, 5, 5)
        insts.append(inst(f"0000_{k:04d}", rect, k))
    rects = overlay_layout(insts)
    assert all(r is not None for r in rects)
    for i, (x0, y0, x1, y1) in enumerate(rects):
        assert 0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H, (i, rects[i])
        for x2, y2, x3, y3 in rects[i + 1:]:
            assert min(x1, x3) <= max(x0, x2) or min(y1, y3) <= max(y0, y2)
    out = draw_overlay(np.full((H, W, 3), GREY, np.uint8), insts, legend=False)
    for m, (x0, y0, _, _) in zip(insts, rects, strict=True):  # each tag box is drawn there
        assert tuple(out[y0, x0]) == track_colour(m.track_id.split("_")[-1])


def test_place_tags_keeps_clear_of_occupied_and_survives_no_room():
    rects = place_tags([(10, 10, 40, 30)] * 2, [(20, 12)] * 2, (100, 60),
                       occupied=[(0, 0, 100, 10)])
    assert rects[0][1] >= 10 and rects[1][1] >= 10 and rects[0] != rects[1]
    crowd = place_tags([(0, 0, 10, 10)] * 20, [(30, 15)] * 20, (40, 20))  # no room at all
    assert all(0 <= x0 and x1 <= 40 and 0 <= y0 and y1 <= 20 for x0, y0, x1, y1 in crowd)


def test_legend_explains_every_tag_in_depth_order():
    img = np.full((H, W, 3), GREY, np.uint8)
    insts = [inst("0000_0009", (200, 30, 260, 80), 1), inst("0000_0002", (20, 30, 90, 80), 0),
             inst("log_mask000001_0", (120, 40, 160, 70), 2)]
    out = draw_overlay(img, insts, tracks=[9, 2, None])  # the last one has no track
    assert out.shape[1] == W and out.shape[0] > H
    assert draw_overlay(img, insts, legend=False).shape == img.shape
    strip = out[H:]
    first = {}
    for track in (2, 9, None):  # a swatch per instance, nearest first (left to right)
        ys, xs = np.nonzero(np.all(strip == track_colour(track), axis=2))
        assert len(xs) > 100, track
        first[track] = (np.median(ys) // 10, np.median(xs))  # the swatch, not stray pixels
    assert sorted(first, key=lambda t: first[t]) == [2, 9, None]


def test_given_track_ids_override_the_names():
    img = np.full((H, W, 3), GREY, np.uint8)
    insts = [inst("log_7fab2350-aaaa", (20, 30, 90, 80), 0)]
    out = draw_overlay(img, insts, tracks=[12], legend=False)
    x0, y0, _, _ = overlay_layout(insts, [12])[0]
    assert tuple(out[y0, x0]) == track_colour(12)
    with pytest.raises(ValueError, match="track ids"):
        draw_overlay(img, insts, tracks=[1, 2])


def test_frame_tracks_matches_annotations_by_area():
    insts = [inst("a_1", (0, 0, 10, 10), 0), inst("a_2", (20, 0, 25, 10), 1)]
    anns = [kins_annotation(1, 0, 4, m.amodal, m.visible, 0, 0, t)
            for m, t in zip(insts, (7, None), strict=True)]
    assert frame_tracks(insts, anns) == [7, None]
    assert frame_tracks(insts, anns[::-1]) is None and frame_tracks(insts, anns[:1]) is None


class FakeLog:
    """A log with two frames, no images (overlays on black) and an unsafe name."""

    name = "../../up"
    frames = [0, 1]
    default_camera = "cam"

    def image_path(self, frame, camera=None):
        return None

    def camera(self, name=None, frame=None):
        return SimpleNamespace(height=H, width=W)


def test_write_overlays_uses_kins_track_ids_and_stays_in_folder(tmp_path):
    masks = {0: [inst("x_0001", (20, 30, 90, 80), 0)], 1: [inst("x_0001", (150, 30, 220, 80), 0)]}
    images = [{"id": f, "frame": f} for f in (0, 1)]
    anns = [kins_annotation(f + 1, f, 4, m[0].amodal, m[0].visible, 0, 0, 42)
            for f, m in masks.items()]
    result = LabelResult(images, anns, masks, camera="cam")
    out = tmp_path / "deep" / "ov"
    paths = write_overlays(FakeLog(), result, out)
    assert [p.name for p in paths] == ["_.._up_000000.png", "_.._up_000001.png"]
    assert sorted(p.name for p in out.iterdir()) == [p.name for p in paths]
    assert not (tmp_path / "up_000000.png").exists()
    for p, m in zip(paths, (masks[0][0], masks[1][0]), strict=True):
        img = cv2.imread(str(p))
        assert img.shape[0] > H and img.shape[1] == W  # legend strip under the image
        x0, y0, _, _ = overlay_layout([m], [42])[0]
        assert tuple(img[y0, x0]) == track_colour(42)  # tag = the KINS track id 42, not 1


def test_labeler_keeps_the_old_names():
    assert labeler.draw_overlay is draw_overlay and labeler.write_overlays is write_overlays
