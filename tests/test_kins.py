import doctest
import json

import numpy as np
import pytest

from seqshape.amodal.kins import (
    KINS_CATEGORIES,
    annotations_by_image,
    bbox_of_mask,
    coco_annotation,
    image_entry,
    kins_annotation,
    mask_to_rle,
    occlusion_order,
    read_coco_instances,
    read_kins,
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
    # D (5 m) is the nearest -> cluster 1; {A, B, C} cluster 2 ordered B (8), A (12), C (20)
    assert oco == [2, 2, 2, 1]
    assert ico == [2, 1, 3, 1]
    assert occlusion_order([], []) == ([], [])


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


def test_docstring_examples():
    import seqshape.amodal.kins as mod

    result = doctest.testmod(mod)
    assert result.attempted > 0 and result.failed == 0
