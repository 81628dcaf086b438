"""Mask-guided placement (seqshape.amodal.align) against brute-force and hand-built cases."""

import numpy as np
import pytest

from seqshape.amodal.align import AlignConfig, align_instances, best_shift, shift_ious, shift_mask
from seqshape.amodal.masks import InstanceMask, resolve_occlusion
from seqshape.errors import ConfigError

H, W = 60, 80


def rect(y0, y1, x0, x1):
    m = np.zeros((H, W), dtype=bool)
    m[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = True
    return m


def brute_ious(amodal, guide, occluder, ry, rx):
    out = np.zeros((2 * ry + 1, 2 * rx + 1))
    for dy in range(-ry, ry + 1):
        for dx in range(-rx, rx + 1):
            vis = shift_mask(amodal, dy, dx) & ~occluder
            union = (vis | guide).sum()
            out[dy + ry, dx + rx] = (vis & guide).sum() / union if union else 0.0
    return out


def test_shift_mask_moves_and_clips():
    m = rect(10, 20, 70, 80)
    s = shift_mask(m, 3, 5)
    assert s.sum() == 10 * 5  # half of the 10 columns left the image
    assert s[13:23, 75:80].all() and not s[:13].any()
    assert np.array_equal(shift_mask(m, 0, 0), m)
    assert np.array_equal(shift_mask(shift_mask(m, -4, -6), 4, 6), m)


@pytest.mark.parametrize("seed", range(4))
def test_shift_ious_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    amodal = rng.random((H, W)) < 0.05
    amodal |= rect(20, 35, 30, 55)
    guide = rect(22, 36, 34 + seed, 56 + seed) & (rng.random((H, W)) < 0.9)
    occluder = rect(0, H, 0, 38) if seed % 2 else np.zeros((H, W), bool)
    ry, rx = 5, 7
    np.testing.assert_allclose(shift_ious(amodal, guide, occluder, ry, rx),
                               brute_ious(amodal, guide, occluder, ry, rx), atol=1e-9)


def test_shift_ious_near_the_border_count_nothing_outside_the_image():
    amodal = rect(0, 10, 0, 12)
    guide = rect(0, 10, 0, 12)
    ious = shift_ious(amodal, guide, np.zeros((H, W), bool), 3, 3)
    np.testing.assert_allclose(ious, brute_ious(amodal, guide, np.zeros((H, W), bool), 3, 3))
    assert ious[3, 3] == 1.0


def test_best_shift_recovers_a_misplaced_occluded_car():
    # a car 30 px wide of which only its right 8 px show beside an occluder ending at x = 40;
    # the estimate sits 6 px too far right, so its visible strip is 14 px wide, not 8
    truth = rect(20, 35, 18, 48)
    occluder = rect(0, H, 0, 40)
    guide = truth & ~occluder
    estimate = shift_mask(truth, 0, 6)
    dy, dx, iou, base = best_shift(estimate, guide, occluder)
    assert (dy, dx) == (0, -6)
    assert iou == 1.0 and base < 0.6


def test_best_shift_stays_put_without_a_real_gain():
    truth = rect(20, 35, 18, 48)
    guide = truth.copy()
    guide[20, 18:48] = False  # a one-row segmentation error
    dy, dx, iou, base = best_shift(truth, guide, np.zeros((H, W), bool))
    assert (dy, dx) == (0, 0) and iou == base
    # the search range follows the mask size: 40 % of a 30 px wide mask is 12 px
    far = shift_mask(truth, 0, 20)
    assert best_shift(far, truth, np.zeros((H, W), bool))[:2] == (0, -12)
    assert best_shift(shift_mask(truth, 0, 10), truth, np.zeros((H, W), bool))[:2] == (0, -10)
    assert best_shift(shift_mask(truth, 0, 10), truth, np.zeros((H, W), bool),
                      AlignConfig(max_px=4))[:2] == (0, -4)


def test_align_instances_front_to_back():
    # the front car is right, the back car is 5 px off; only the back one moves, and its
    # visible mask ends up equal to its guide once the occlusion is resolved again
    front = rect(25, 45, 10, 40)
    back_truth = rect(20, 35, 30, 60)
    guides = {"front": front, "back": back_truth & ~front}
    insts = [InstanceMask("front", front, front.copy(), 10.0),
             InstanceMask("back", shift_mask(back_truth, 0, 5), back_truth.copy(), 30.0)]
    resolve_occlusion(insts, order="median")
    moved = align_instances(insts, guides)
    assert moved == {"back": (0, -5)}
    resolve_occlusion(insts, order="median")
    assert np.array_equal(insts[1].amodal, back_truth)
    assert np.array_equal(insts[1].visible, guides["back"])
    assert np.array_equal(insts[0].amodal, front)


def test_align_config_rejects_bad_values():
    with pytest.raises(ConfigError):
        AlignConfig(max_shift=-1)
    with pytest.raises(ConfigError):
        AlignConfig(min_gain=2)
    with pytest.raises(ConfigError):
        AlignConfig(max_px=-3)


def test_points_inside_matches_brute_force():
    from seqshape.amodal.align import points_inside, shift_scores

    amodal = rect(20, 35, 30, 55)
    rng = np.random.default_rng(3)
    uv = np.c_[rng.uniform(25, 60, 40), rng.uniform(15, 40, 40)]
    uv = np.r_[uv, [[-5.0, 10.0], [200.0, 3.0]]]  # outside the image: not counted
    px = np.floor(uv[:40]).astype(int)
    ry, rx = 4, 6
    want = np.zeros((2 * ry + 1, 2 * rx + 1))
    for dy in range(-ry, ry + 1):
        for dx in range(-rx, rx + 1):
            s = shift_mask(amodal, dy, dx)
            want[dy + ry, dx + rx] = s[px[:, 1], px[:, 0]].mean()
    np.testing.assert_allclose(points_inside(amodal, uv, ry, rx), want, atol=1e-12)
    # the batched call gives the same IoUs as without points
    guide, occ = rect(22, 36, 33, 57), rect(0, H, 0, 35)
    ious, inside = shift_scores(amodal, guide, occ, ry, rx, uv)
    np.testing.assert_allclose(ious, brute_ious(amodal, guide, occ, ry, rx), atol=1e-9)
    np.testing.assert_allclose(inside, want, atol=1e-12)
    assert np.all(points_inside(amodal, np.zeros((0, 2)), 2, 2) == 1.0)
