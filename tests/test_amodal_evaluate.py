"""Mask evaluation against hand-computed IoUs and misses."""

import numpy as np
import pytest

from seqshape.amodal.evaluate import (
    breakdown,
    evaluate_image,
    mask_iou_matrix,
    match_masks,
    summarise,
)


def box(y0, x0, h, w, size=(100, 100)):
    m = np.zeros(size, bool)
    m[y0:y0 + h, x0:x0 + w] = True
    return m


def test_iou_matrix_hand_computed():
    a, b = box(0, 0, 10, 10), box(0, 2, 10, 10)  # overlap 8 x 10 = 80, union 120
    iou = mask_iou_matrix([a, b], [a])
    assert iou.shape == (2, 1)
    assert iou[0, 0] == pytest.approx(1.0) and iou[1, 0] == pytest.approx(80 / 120)
    assert mask_iou_matrix([], [a]).shape == (0, 1)


def test_hungarian_beats_greedy():
    # greedy would give g0 its best (p0, IoU .8) and leave g1 with nothing;
    # the optimum pairs p0-g1 and p1-g0
    g0, g1 = box(0, 0, 10, 10), box(0, 6, 10, 10)
    p0 = box(0, 2, 10, 10)  # IoU(g0) = 80/120, IoU(g1) = 60/140
    p1 = box(0, 0, 10, 6)   # IoU(g0) = 60/100, IoU(g1) = 0
    pred_of_gt, iou = match_masks([p0, p1], [g0, g1])
    assert pred_of_gt.tolist() == [1, 0]
    assert iou == pytest.approx([0.6, 60 / 140])


def test_misses_unmatched_prediction_and_low_iou():
    g = [box(0, 0, 10, 10), box(50, 50, 10, 10), box(80, 80, 10, 10)]
    p = [box(0, 2, 10, 10),          # IoU 2/3 with g0: a match
         box(50, 50, 10, 4),         # IoU 0.4 with g1: a miss
         box(30, 0, 5, 5)]           # overlaps nothing: unmatched prediction; g2: no partner
    res, unmatched = evaluate_image(7, p, g, gt_visible_area=[100, 50, 100],
                                    gt_distance=[10, 20, 60])
    assert [r.missed for r in res] == [False, True, True]
    assert [r.pred_index for r in res] == [0, 1, -1]
    assert unmatched == 2
    m = summarise(res, unmatched)
    assert m["n"] == 3 and m["misses"] == 2
    assert m["miss_pct"] == pytest.approx(200 / 3)
    assert m["miou"] == pytest.approx(2 / 3)
    assert m["miou_with_misses"] == pytest.approx((2 / 3) / 3)
    assert m["unmatched_predictions"] == 2
    assert res[1].occlusion == pytest.approx(0.5)
    bd = breakdown(res)
    assert bd["occlusion"]["none (<1%)"]["n"] == 2
    assert bd["occlusion"]["largely (30-70%)"]["misses"] == 1
    assert bd["distance"]["50-80 m"]["miss_pct"] == pytest.approx(100.0)


def test_empty_image_and_no_predictions():
    res, unmatched = evaluate_image(0, [], [])
    assert res == [] and unmatched == 0
    res, unmatched = evaluate_image(0, [box(0, 0, 3, 3)], [])
    assert unmatched == 1
    res, _ = evaluate_image(0, [], [box(0, 0, 3, 3)])
    assert summarise(res)["miss_pct"] == 100.0 and np.isnan(summarise(res)["miou"])


def test_within_distance_keeps_near_instances_only():
    from seqshape.amodal.evaluate import within_distance

    g = [np.zeros((4, 4), bool) for _ in range(3)]
    for k, m in enumerate(g):
        m[k, :] = True
    res, _ = evaluate_image(0, [g[0]], g, gt_distance=[10.0, 90.0, float("nan")])
    near = within_distance(res, 80.0)
    assert [r.gt_index for r in near] == [0]
    assert summarise(near)["miss_pct"] == 0.0 and summarise(res)["misses"] == 2
