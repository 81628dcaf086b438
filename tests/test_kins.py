import json

import numpy as np
import pytest
from pycocotools import mask as coco_mask

from seqshape.data.kins import (
    KINS_CATEGORIES,
    SegmentationError,
    annotation_mask,
    annotations_by_image,
    bbox_of_mask,
    coco_annotation,
    image_entry,
    kins_annotation,
    mask_to_polygons,
    mask_to_rle,
    occlusion_order,
    read_coco_instances,
    read_kins,
    rle_runs,
    rle_to_mask,
    segm_to_mask,
    write_coco_instances,
    write_kins,
)
from seqshape.errors import DataError


def _rect(h, w, x0, y0, x1, y1):
    m = np.zeros((h, w), dtype=bool)
    m[y0:y1, x0:x1] = True
    return m


def test_rle_round_trip_random_masks():
    rng = np.random.default_rng(0)
    for shape, p in [((375, 1242), 0.3), ((7, 5), 0.5), ((1, 1), 1.0), ((20, 30), 0.0)]:
        mask = rng.random(shape) < p
        rle = mask_to_rle(mask)
        assert isinstance(rle["counts"], str) and rle["size"] == list(shape)
        json.dumps(rle)
        back = rle_to_mask(rle)
        assert back.dtype == bool and back.shape == shape
        np.testing.assert_array_equal(back, mask)


def test_uncompressed_rle_and_polygon():
    # uncompressed RLE: column-major run lengths starting with zeros
    m = rle_to_mask({"size": [2, 3], "counts": [1, 2, 3]})
    np.testing.assert_array_equal(m, np.array([[0, 1, 0], [1, 0, 0]], dtype=bool))
    # a polygon covering pixel columns 2..5, rows 1..3 (pycocotools rasterises edges inclusive)
    poly = segm_to_mask([[2, 1, 6, 1, 6, 4, 2, 4]], 8, 10)
    assert bbox_of_mask(poly)[:2] == [2.0, 1.0] and 9 <= poly.sum() <= 20


def test_bbox_of_mask():
    assert bbox_of_mask(_rect(10, 12, 3, 2, 7, 9)) == [3.0, 2.0, 4.0, 7.0]
    assert bbox_of_mask(np.zeros((4, 4), bool)) == [0.0, 0.0, 0.0, 0.0]


def test_occlusion_order_clusters_and_ranks():
    h, w = 20, 40
    masks = [_rect(h, w, 0, 0, 10, 10),    # A: overlaps B
             _rect(h, w, 5, 5, 15, 15),    # B: overlaps A and C
             _rect(h, w, 14, 0, 20, 6),    # C: overlaps B only
             _rect(h, w, 30, 0, 35, 5)]    # D: alone
    depths = [12.0, 8.0, 20.0, 5.0]
    oco, ico = occlusion_order(depths, masks)
    # D overlaps nobody: 0, 0 although it is the nearest. {A, B, C} is cluster 1: B (8 m) is
    # hidden by nobody (1); A and C are each hidden by B only (2), they do not touch
    assert oco == [1, 1, 1, 0]
    assert ico == [2, 1, 2, 0]
    assert occlusion_order([], []) == ([], [])


def test_occlusion_order_isolated_instance_is_zero():
    assert occlusion_order([7.0], [_rect(10, 10, 2, 2, 5, 5)]) == ([0], [0])
    # two instances that do not touch (adjacent pixels are not an overlap)
    oco, ico = occlusion_order([3.0, 4.0], [_rect(10, 10, 0, 0, 5, 5),
                                            _rect(10, 10, 5, 0, 9, 5)])
    assert (oco, ico) == ([0, 0], [0, 0])


def test_occlusion_order_chain_rises_by_one_per_occlusion():
    h, w = 10, 40
    a, b, c = _rect(h, w, 0, 0, 10, 8), _rect(h, w, 8, 0, 20, 8), _rect(h, w, 18, 0, 30, 8)
    # A (front) hides B, B hides C; A and C do not touch. Given in shuffled order.
    oco, ico = occlusion_order([30.0, 10.0, 20.0], [c, a, b])
    assert oco == [1, 1, 1] and ico == [3, 1, 2]
    # C also reaching under A changes nothing: C is still hidden by B (order 2) -> 3
    c2 = _rect(h, w, 5, 0, 30, 3)
    assert occlusion_order([10.0, 20.0, 30.0], [a, b, c2]) == ([1, 1, 1], [1, 2, 3])


def test_occlusion_order_two_clusters_front_first():
    h, w = 10, 60
    far = [_rect(h, w, 0, 0, 10, 8), _rect(h, w, 5, 0, 15, 8)]       # 30 m and 40 m
    near = [_rect(h, w, 40, 0, 50, 8), _rect(h, w, 45, 0, 55, 8)]    # 10 m and 12 m
    alone = _rect(h, w, 25, 0, 30, 8)                                 # 5 m, touches nobody
    oco, ico = occlusion_order([30.0, 40.0, 12.0, 10.0, 5.0], far + near[::-1] + [alone])
    assert oco == [2, 2, 1, 1, 0] and ico == [1, 2, 2, 1, 0]


def test_mask_to_polygons_round_trip():
    import cv2

    h, w = 60, 80
    mask = np.zeros((h, w), np.uint8)
    cv2.circle(mask, (40, 30), 15, 1, -1)
    cv2.fillConvexPoly(mask, np.array([[2, 50], [20, 44], [30, 58]], np.int32), 1)
    mask = mask.astype(bool)
    mask[5:8, 5:20] = True   # a thin bar
    mask[50, 70] = True      # a single pixel
    polys = mask_to_polygons(mask)
    assert len(polys) == 4 and all(len(p) >= 6 and len(p) % 2 == 0 for p in polys)
    json.dumps(polys)
    back = segm_to_mask(polys, h, w)
    iou = (back & mask).sum() / (back | mask).sum()
    assert iou > 0.97
    # holes: polygons are the outer contours, so a ring comes back filled
    ring = _rect(h, w, 10, 10, 30, 30) & ~_rect(h, w, 15, 15, 25, 25)
    np.testing.assert_array_equal(segm_to_mask(mask_to_polygons(ring), h, w),
                                  _rect(h, w, 10, 10, 30, 30))
    assert mask_to_polygons(np.zeros((4, 4), bool)) == []


def test_kins_polygons_read_and_scored(tmp_path):
    from seqshape.amodal.evaluate import evaluate_files

    images, anns, (a0, v0, a1, v1) = _scene()
    write_kins(tmp_path / "rle.json", images, anns)
    poly = [kins_annotation(a["id"], a["image_id"], a["category_id"],
                            rle_to_mask(a["a_segm"]), rle_to_mask(a["i_segm"]),
                            a["oco_id"], a["ico_id"], polygons=True) for a in anns]
    assert isinstance(poly[1]["a_segm"], list) and poly[1]["a_area"] == a1.sum()
    write_kins(tmp_path / "poly.json", images, poly)
    doc = read_kins(tmp_path / "poly.json")
    np.testing.assert_array_equal(annotation_mask(doc["annotations"][1], "a_segm",
                                                  doc["images"][0]), a1)
    np.testing.assert_array_equal(annotation_mask(doc["annotations"][1], "i_segm",
                                                  doc["images"][0]), v1)
    # polygons scored against RLE: every instance matched with IoU 1
    for segm in ("a_segm", "i_segm"):
        results, unmatched = evaluate_files([(tmp_path / "poly.json", tmp_path / "rle.json")],
                                            segm=segm)
        assert unmatched == 0 and [r.iou for r in results] == [1.0, 1.0, 1.0]


def _scene():
    h, w = 30, 50
    images = [image_entry(i, "0003", f, h, w) for i, f in enumerate([0, 1])]
    a0, a1 = _rect(h, w, 2, 2, 20, 15), _rect(h, w, 10, 5, 40, 25)
    v0 = a0.copy()
    v1 = a1 & ~a0
    oco, ico = occlusion_order([5.0, 9.0], [a0, a1])
    anns = [kins_annotation(1, 0, 4, a0, v0, oco[0], ico[0], track_id=3),
            kins_annotation(2, 0, 7, a1, v1, oco[1], ico[1], track_id=8),
            kins_annotation(3, 1, 4, a0, v0, 1, 1)]
    return images, anns, (a0, v0, a1, v1)


def test_kins_write_read_round_trip(tmp_path):
    images, anns, (a0, v0, a1, v1) = _scene()
    assert images[1]["file_name"] == "0003/000001.png"
    write_kins(tmp_path / "k.json", images, anns)
    doc = read_kins(tmp_path / "k.json")
    assert doc["images"] == images and doc["categories"] == KINS_CATEGORIES
    assert doc["annotations"] == anns
    got = annotations_by_image(doc)
    assert [a["id"] for a in got[0]] == [1, 2] and [a["id"] for a in got[1]] == [3]
    ann = doc["annotations"][1]
    np.testing.assert_array_equal(rle_to_mask(ann["a_segm"]), a1)
    np.testing.assert_array_equal(rle_to_mask(ann["i_segm"]), v1)
    assert ann["a_area"] == a1.sum() and ann["i_area"] == v1.sum()
    assert ann["a_bbox"] == [10.0, 5.0, 30.0, 20.0] and ann["track_id"] == 8
    assert (ann["oco_id"], ann["ico_id"]) == (1, 2)


def test_read_kins_errors(tmp_path):
    images, anns, _ = _scene()
    p = tmp_path / "k.json"
    bad = [dict(a) for a in anns]
    del bad[1]["ico_id"]
    p.write_text(json.dumps({"images": images, "categories": KINS_CATEGORIES,
                             "annotations": bad}))
    with pytest.raises(DataError, match=r"k\.json: annotations\[1\]: missing key\(s\) \['ico_id'\]"):
        read_kins(p)
    bad = [dict(a) for a in anns]
    bad[2]["image_id"] = 99
    p.write_text(json.dumps({"images": images, "categories": KINS_CATEGORIES,
                             "annotations": bad}))
    with pytest.raises(DataError, match=r"annotations\[2\]: unknown image_id 99"):
        read_kins(p)
    p.write_text(json.dumps({"images": images, "annotations": anns}))
    with pytest.raises(DataError, match="categories"):
        read_kins(p)
    p.write_text("{not json")
    with pytest.raises(DataError, match="invalid JSON"):
        read_kins(p)
    bad = [dict(a) for a in anns]
    bad[0]["a_segm"] = mask_to_rle(np.zeros((4, 4), bool))
    with pytest.raises(ValueError, match="RLE size"):
        write_kins(tmp_path / "w.json", images, bad)
    assert not (tmp_path / "w.json").exists()


def test_coco_instances_round_trip_and_polygons(tmp_path):
    images, _, (a0, v0, a1, v1) = _scene()
    anns = [coco_annotation(1, 0, 4, v0, score=0.9, track_id=3),
            coco_annotation(2, 0, 7, v1, score=0.75)]
    write_coco_instances(tmp_path / "c.json", images, anns)
    doc = read_coco_instances(tmp_path / "c.json")
    assert doc["annotations"] == anns
    np.testing.assert_array_equal(rle_to_mask(doc["annotations"][1]["segmentation"]), v1)
    # a segmenter's output with polygons and no area/bbox/score
    raw = {"images": images, "categories": KINS_CATEGORIES,
           "annotations": [{"id": 5, "image_id": 1, "category_id": 4,
                            "segmentation": [[2, 2, 12, 2, 12, 8, 2, 8]]}]}
    (tmp_path / "p.json").write_text(json.dumps(raw))
    ann = read_coco_instances(tmp_path / "p.json")["annotations"][0]
    m = rle_to_mask(ann["segmentation"])
    assert m.shape == (30, 50) and ann["area"] == m.sum() and ann["score"] == 1.0
    assert ann["bbox"][:2] == [2.0, 2.0]
    raw["annotations"][0]["segmentation"] = [[1, 2, 3]]
    (tmp_path / "p.json").write_text(json.dumps(raw))
    with pytest.raises(DataError, match=r"annotations\[0\]\.segmentation"):
        read_coco_instances(tmp_path / "p.json")


def test_occlusion_order_exact_relation_overrides_depth():
    h, w = 10, 40
    long_, short = _rect(h, w, 0, 0, 30, 8), _rect(h, w, 20, 0, 36, 8)
    # a long vehicle whose nearest point is nearer (8 m) although the short one (9 m) covers
    # part of it: the exact relation puts the short one in front
    assert occlusion_order([8.0, 9.0], [long_, short]) == ([1, 1], [1, 2])
    hides = np.array([[False, False], [True, False]])
    assert occlusion_order([8.0, 9.0], [long_, short], hides=hides) == ([1, 1], [2, 1])
    # a cycle (each covers some of the other) is no order: depth decides
    both = np.ones((2, 2), bool)
    assert occlusion_order([8.0, 9.0], [long_, short], hides=both) == ([1, 1], [1, 2])
    three = [_rect(h, w, 0, 0, 10, 8), _rect(h, w, 8, 0, 20, 8), _rect(h, w, 18, 0, 30, 8)]
    chain = np.zeros((3, 3), bool)
    chain[2, 1] = chain[1, 0] = True
    # C hides B hides A per the relation (reverse of depth): orders 3, 2, 1
    assert occlusion_order([1.0, 2.0, 3.0], three, hides=chain) == ([1, 1, 1], [3, 2, 1])
    # a cycle over three mutually overlapping instances: depth alone
    wide = [_rect(h, w, 0, 0, 20, 8), _rect(h, w, 5, 0, 25, 8), _rect(h, w, 10, 0, 30, 8)]
    cycle = np.zeros((3, 3), bool)
    cycle[0, 1] = cycle[1, 2] = cycle[2, 0] = True
    assert occlusion_order([1.0, 2.0, 3.0], wide, hides=cycle) == ([1, 1, 1], [1, 2, 3])


def _reference_rle(mask) -> dict:
    """The former mask_to_rle: pycocotools on a Fortran copy of the whole mask."""
    mask = np.asarray(mask)
    data = mask.view(np.uint8) if mask.dtype == bool else mask.astype(np.uint8)
    rle = coco_mask.encode(np.asfortranarray(data))
    return {"size": [int(rle["size"][0]), int(rle["size"][1])],
            "counts": rle["counts"].decode("ascii")}


def _masks(seed: int):
    """Masks of every kind: random small ones (runs through the bottom row into the next
    column, full columns, full, empty), blobs in a KITTI-size image, at its borders."""
    rng = np.random.default_rng(seed)
    for k in range(400):
        h, w = (int(v) for v in rng.integers(1, 9, 2))
        m = rng.random((h, w)) < rng.random()
        if k % 9 == 0:
            m[:] = k % 2 == 0
        if k % 5 == 0:
            m[:, rng.integers(0, w)] = True
        yield m
    for r0, r1, c0, c1 in [(0, 375, 0, 30), (300, 375, 1200, 1242), (0, 1, 0, 1242),
                           (120, 240, 500, 640), (374, 375, 1241, 1242)]:
        m = np.zeros((375, 1242), dtype=bool)
        m[r0:r1, c0:c1] = rng.random((r1 - r0, c1 - c0)) < 0.97
        yield m
        yield np.asfortranarray(m)
        yield m[::-1, ::-1]  # not contiguous


@pytest.mark.parametrize("seed", [0, 1])
def test_rle_from_the_bounding_box_is_byte_identical(seed):
    for m in _masks(seed):
        assert mask_to_rle(m) == _reference_rle(m)


def test_rle_of_other_dtypes_is_byte_identical():
    rng = np.random.default_rng(2)
    for dtype in (np.uint8, np.int64, np.float32):
        for vmax in (1, 2):
            m = rng.integers(0, vmax + 1, (6, 7)).astype(dtype)
            assert mask_to_rle(m) == _reference_rle(m)
    assert mask_to_rle(np.zeros((0, 3), np.uint8)) == _reference_rle(np.zeros((0, 3), np.uint8))
    with pytest.raises(ValueError):
        mask_to_rle(np.zeros((2, 2, 2), bool))


def test_annotations_equal_the_whole_mask_composition():
    masks = list(_masks(3))
    for a, v in zip(masks[::2], masks[1::2], strict=False):
        if a.shape != v.shape:
            continue
        ann = kins_annotation(1, 2, 1, a, v & a, 1, 2, track_id=5)
        for key, m in (("a", a), ("i", v & a)):
            assert ann[f"{key}_segm"] == _reference_rle(m)
            assert ann[f"{key}_bbox"] == bbox_of_mask(m)
            assert ann[f"{key}_area"] == int(np.count_nonzero(m))
        coco = coco_annotation(1, 2, 1, a, score=0.5)
        assert (coco["segmentation"], coco["bbox"], coco["area"]) == (
            _reference_rle(a), bbox_of_mask(a), int(np.count_nonzero(a)))
    poly = kins_annotation(1, 1, 1, masks[-3], masks[-3], 0, 0, polygons=True)
    assert poly["a_segm"] == mask_to_polygons(masks[-3])
    assert poly["a_area"] == int(masks[-3].sum())


# ----------------------------------------------------------------------------- validation (issue 18)


def _pixel_runs(mask) -> list[int]:
    """Uncompressed COCO counts of a mask by a plain loop over its column-major pixels."""
    runs, value, n = [], False, 0
    for v in np.asarray(mask, dtype=bool).T.ravel():
        if v != value:
            runs.append(n)
            value, n = v, 0
        n += 1
    return runs + [n]


def test_rle_runs_of_compressed_strings_match_a_pixel_loop():
    for m in _masks(4):
        if m.size <= 5000:
            assert rle_runs(mask_to_rle(m)).tolist() == _pixel_runs(m)
    # long runs (several 5-bit groups, negative differences) in a KITTI-size mask
    big = np.zeros((375, 1242), bool)
    big[10:370, 3:1200:7] = True
    big[100:101, :] = True
    assert rle_runs(mask_to_rle(big)).tolist() == _pixel_runs(big)
    assert rle_runs({"size": [0, 3], "counts": ""}).tolist() == []


@pytest.mark.parametrize("rle,message", [
    ({"size": [4, 5], "counts": ""}, "cover 0 pixels, its size \\[4, 5\\] has 20"),
    ({"size": [4, 5], "counts": "1"}, "cover 1 pixels"),
    ({"size": [4, 5], "counts": [1, 2]}, "cover 3 pixels"),
    ({"size": [4, 5], "counts": [100]}, "cover 100 pixels"),
    ({"size": [4, 5], "counts": [-3, 23]}, "counts\\[0\\] = -3"),
    ({"size": [4, 5], "counts": [1.5, 18.5]}, "counts\\[0\\] = 1.5"),
    ({"size": [4, 5], "counts": [True, 19]}, "counts\\[0\\] = True"),
    ({"size": [4, 5], "counts": None}, "string or a list"),
    ({"size": [-4, 5], "counts": []}, "non-negative integers"),
    ({"size": [4], "counts": ""}, "\\[height, width\\]"),
    ({"size": [1 << 20, 1 << 20], "counts": []}, "over"),
    ({"size": [4, 5], "counts": "\x80"}, "not ASCII"),
    ({"size": [4, 5], "counts": "zz"}, "characters outside"),
    ({"size": [4, 5], "counts": "0h"}, "truncated"),  # 'h' = 56: a group with 'more' set
    ({"size": [4, 5], "counts": "0L"}, "run 1 of length -4"),  # 'L': 0x1c, sign set: 28 - 32
    ({"counts": ""}, "'size' and 'counts'"),
])
def test_malformed_rles_are_refused(rle, message):
    with pytest.raises(SegmentationError, match=message):
        rle_to_mask(rle)


def test_uncompressed_rle_of_integral_floats_and_bytes_counts():
    np.testing.assert_array_equal(rle_to_mask({"size": [2, 3], "counts": [1.0, 2, 3]}),
                                  rle_to_mask({"size": [2, 3], "counts": [1, 2, 3]}))
    rle = mask_to_rle(_rect(4, 5, 1, 1, 3, 3))
    np.testing.assert_array_equal(rle_to_mask({**rle, "counts": rle["counts"].encode()}),
                                  _rect(4, 5, 1, 1, 3, 3))


def test_hand_drawn_polygon_round_trip(tmp_path):
    # an L drawn along pixel edges: rows 1-2 columns 1-4, rows 3-5 columns 1-2, and a second
    # polygon, the square of pixel (5, 5)
    poly = [[1, 1, 5, 1, 5, 3, 3, 3, 3, 6, 1, 6], [5, 5, 6, 5, 6, 6, 5, 6]]
    expected = np.zeros((7, 6), bool)
    expected[1:3, 1:5] = True
    expected[3:6, 1:3] = True
    expected[5, 5] = True
    np.testing.assert_array_equal(segm_to_mask(poly, 7, 6), expected)
    # through a KINS file, as the KINS release stores them (a_segm polygons)
    images = [image_entry(0, "0000", 0, 7, 6)]
    ann = kins_annotation(1, 0, 4, expected, expected, 0, 0)
    ann["a_segm"] = ann["i_segm"] = poly
    write_kins(tmp_path / "poly.json", images, [ann])
    doc = read_kins(tmp_path / "poly.json")
    np.testing.assert_array_equal(annotation_mask(doc["annotations"][0], "a_segm", images[0]),
                                  expected)
    # and back: the polygons of the mask give the mask again
    np.testing.assert_array_equal(segm_to_mask(mask_to_polygons(expected), 7, 6), expected)


@pytest.mark.parametrize("segm,message", [
    ([[[1, 2], [3, 4], [5, 6]]], "flat list of numbers"),
    ([["a", "b", 1, 2, 3, 4]], "flat list of numbers"),
    ([[1, 2, 3, 4]], "even number \\(>= 6\\)"),
    ([[1, 2, 3, 4, 5, 6, 7]], "even number"),
    ([[float("nan"), 0, 1, 1, 2, 2]], "finite"),
    ([[1e300, 0, 1, 1, 2, 2]], "within one image size"),
    ([[10**400, 0, 1, 1, 2, 2]], "finite"),
    ([[-11, 0, 1, 1, 2, 2]], "within one image size"),
    ([[True, 0, 1, 1, 2, 2]], "flat list"),
    ("polygon", "RLE dict or a list"),
])
def test_malformed_polygons_are_refused(segm, message):
    with pytest.raises(SegmentationError, match=message):
        segm_to_mask(segm, 10, 10)


def _doc_with(tmp_path, change):
    images, anns, _ = _scene()
    doc = {"images": images, "categories": KINS_CATEGORIES, "annotations": anns}
    doc = json.loads(json.dumps(doc))
    change(doc)
    path = tmp_path / "k.json"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("change,message", [
    (lambda d: d["images"][0].update(height="375"), r"images\[0\]: height, width must be"),
    (lambda d: d["images"][0].update(width=0), r"images\[0\]: height, width must be positive"),
    (lambda d: d["images"][0].update(id=[1]), r"images\[0\]\.id: expected a non-negative"),
    (lambda d: d["images"][0].update(file_name=3), r"images\[0\]\.file_name"),
    (lambda d: d["images"].__setitem__(0, "x"), r"images\[0\]: expected an object"),
    (lambda d: d["annotations"][0].update(id={"a": 1}), r"annotations\[0\]\.id"),
    (lambda d: d["annotations"][0].update(category_id=None), r"annotations\[0\]\.category_id"),
    (lambda d: d["annotations"][1].update(a_bbox=[1, 2, 3]), r"annotations\[1\]\.a_bbox"),
    (lambda d: d["annotations"][1].update(i_area=-1), r"annotations\[1\]\.i_area"),
    (lambda d: d["annotations"][1].update(ico_id=1.5), r"annotations\[1\]\.ico_id"),
    (lambda d: d["annotations"][1].update(distance="far"), r"annotations\[1\]\.distance"),
    (lambda d: d["annotations"][1].update(track_id=[3]), r"annotations\[1\]\.track_id"),
    (lambda d: d["annotations"][1]["a_segm"].update(counts=""),
     r"annotations\[1\]\.a_segm: RLE counts cover 0 pixels"),
    (lambda d: d["annotations"][1].update(i_segm=[[1, 2, 3]]),
     r"annotations\[1\]\.i_segm: polygon 0: 3 coordinates"),
    (lambda d: d["annotations"].__setitem__(2, None), r"annotations\[2\]: expected an object"),
])
def test_read_kins_refuses_wrong_types_naming_the_file(tmp_path, change, message):
    path = _doc_with(tmp_path, change)
    with pytest.raises(DataError, match=message) as info:
        read_kins(path)
    assert info.value.path == str(path)


def test_read_kins_files_of_other_encodings(tmp_path):
    path = tmp_path / "k.json"
    images, anns, _ = _scene()
    text = json.dumps({"images": images, "categories": KINS_CATEGORIES, "annotations": anns})
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())  # a UTF-8 BOM is fine
    assert read_kins(path)["annotations"] == anns
    path.write_bytes(text.encode("utf-16"))
    with pytest.raises(DataError, match="not UTF-8"):
        read_kins(path)
    path.write_text(json.dumps([1, 2]))
    with pytest.raises(DataError, match="got a JSON array"):
        read_coco_instances(path)
