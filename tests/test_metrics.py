"""Metrics against slow, obviously-correct references and hand-computed cases."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from seqshape.evaluation.metrics import (
    cd_floor,
    chamfer_distance,
    earth_movers_distance,
    emd_floor,
    emd_floor_pair,
    emd_sampling_law,
    emd_subsampled,
    nearest_distances,
    pose_errors,
    rotation_error,
    subsample,
    subsample_pair,
    translation_error,
)
from seqshape.testing import box_surface


def chamfer_brute(a, b) -> float:
    ab = [min(np.sqrt(((p - q) ** 2).sum()) for q in b) for p in a]
    ba = [min(np.sqrt(((q - p) ** 2).sum()) for p in a) for q in b]
    return float(np.mean(ab) + np.mean(ba))


def emd_brute(a, b) -> float:
    best = np.inf
    for perm in itertools.permutations(range(len(b))):
        best = min(best, np.mean([np.linalg.norm(a[i] - b[j]) for i, j in enumerate(perm)]))
    return float(best)


@pytest.mark.parametrize("n,m", [(1, 1), (5, 9), (23, 7), (40, 40)])
def test_chamfer_matches_double_loop(n, m):
    rng = np.random.default_rng(n * 100 + m)
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(m, 3)) + 0.3
    assert chamfer_distance(a, b) == pytest.approx(chamfer_brute(a, b), rel=1e-12, abs=1e-12)


def test_chamfer_properties():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 3)).astype(np.float32)
    assert chamfer_distance(a, a) == 0.0
    b = rng.normal(size=(30, 3))
    assert chamfer_distance(a, b) == pytest.approx(chamfer_distance(b, a))
    # not squared: scaling the clouds by s scales CD by s
    assert chamfer_distance(3 * a, 3 * b) == pytest.approx(3 * chamfer_distance(a, b))
    # a single point shifted by d: d one way plus d the other
    assert chamfer_distance([[0, 0, 0]], [[0, 0.25, 0]]) == pytest.approx(0.5)
    assert nearest_distances(a, a).max() == 0.0


def test_chamfer_rejects_bad_input():
    with pytest.raises(ValueError, match="empty"):
        chamfer_distance(np.zeros((0, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        chamfer_distance(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="NaN"):
        chamfer_distance(np.full((2, 3), np.nan), np.zeros((4, 3)))


@pytest.mark.parametrize("n,seed", [(6, 0), (7, 1), (8, 2)])
def test_emd_matches_all_permutations(n, seed):
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    assert earth_movers_distance(a, b) == pytest.approx(emd_brute(a, b), rel=1e-12)


def test_emd_hand_computed_shift():
    rng = np.random.default_rng(3)
    a = rng.uniform(-2, 2, size=(200, 3))
    d = 0.07
    direction = np.array([1.0, 2.0, -2.0]) / 3.0
    # a small shift of a spread-out cloud: the identity matching is optimal, EMD = d
    assert earth_movers_distance(a, a + d * direction) == pytest.approx(d, rel=1e-9)
    # order of points does not matter
    assert earth_movers_distance(a, (a + d * direction)[::-1]) == pytest.approx(d, rel=1e-9)
    # EMD >= CD/2-style lower bound: every matched distance >= nearest distance
    b = rng.normal(size=(200, 3))
    assert earth_movers_distance(a, b) >= nearest_distances(a, b).mean() - 1e-12


def test_emd_unequal_sizes_is_a_clear_error():
    with pytest.raises(ValueError, match="equal-size.*subsample"):
        earth_movers_distance(np.zeros((5, 3)), np.zeros((6, 3)))


def test_subsample_deterministic_and_distinct():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(300, 3))
    s1, s2 = subsample(a, 100, seed=5), subsample(a, 100, seed=5)
    assert np.array_equal(s1, s2)
    assert len(np.unique(s1, axis=0)) == 100
    assert not np.array_equal(s1, subsample(a, 100, seed=6))
    assert subsample(a, 300) is a
    with pytest.raises(ValueError):
        subsample(a, 301)
    pa, pb = subsample_pair(a, rng.normal(size=(120, 3)), n=1024, seed=1)
    assert len(pa) == len(pb) == 120
    qa, qb = subsample_pair(a, a, n=50, seed=1)
    assert len(qa) == 50 and np.array_equal(qa, subsample_pair(a, a, n=50, seed=1)[0])
    assert emd_subsampled(a, a + [0.1, 0, 0], n=64, seed=2) >= 0.0


def test_rotation_error_wraps():
    deg = np.radians
    assert rotation_error(deg(359.0), deg(1.0)) == pytest.approx(deg(2.0))
    assert rotation_error(deg(1.0), deg(359.0)) == pytest.approx(deg(2.0))
    assert rotation_error(deg(-179.0), deg(179.0)) == pytest.approx(deg(2.0))
    assert rotation_error(deg(90.0), deg(-90.0)) == pytest.approx(np.pi)
    assert rotation_error(7 * np.pi + 0.1, 0.1) == pytest.approx(np.pi)
    many = rotation_error(np.linspace(-20, 20, 1001), 0.3)
    assert many.shape == (1001,) and many.min() >= 0 and many.max() <= np.pi + 1e-12


def test_translation_error_is_planar():
    assert translation_error([3.0, 4.0, 10.0, 1.0], [0.0, 0.0, -5.0, 0.0]) == pytest.approx(5.0)
    p = np.array([[1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, np.pi]])
    t, r = pose_errors(p, np.zeros((2, 4)))
    np.testing.assert_allclose(t, [np.sqrt(2), 0.0])
    np.testing.assert_allclose(r, [0.0, np.pi])


def test_cd_floor_resample_is_exact_definition():
    gt = box_surface(2048, 0)
    floor, method = cd_floor(gt, 1024, seed=3, resample=lambda n, s: box_surface(n, s))
    assert method == "resample"
    assert floor == pytest.approx(chamfer_distance(box_surface(1024, 3), gt))


@pytest.mark.parametrize("m,k", [(2048, 1024), (2048, 2048), (4096, 1024)])
def test_cd_floor_split_estimate_matches_true_resampling(m, k):
    gt = box_surface(m, 0)
    truth = np.mean([chamfer_distance(box_surface(k, s), gt) for s in range(1, 5)])
    est = np.mean([cd_floor(gt, k, seed=s)[0] for s in range(4)])
    assert cd_floor(gt, k)[1] == "split"
    assert est == pytest.approx(truth, rel=0.06)


def test_emd_sampling_law_predicts_smaller_samplings():
    """EMD of two independent n-point samplings of a car-sized box, 128-512 points, predicted
    from the 1024-point one by sqrt(log n / n) (measured within 9 %)."""
    def emd(n):
        return np.mean([earth_movers_distance(box_surface(n, s), box_surface(n, s + 100))
                        for s in range(3)])

    ref = emd(1024)
    for n in (128, 256, 512):
        assert emd(n) == pytest.approx(ref * emd_sampling_law(n) / emd_sampling_law(1024),
                                       rel=0.12)
    assert emd_sampling_law(1024) < emd_sampling_law(512)


def test_emd_floor_resample_is_exact_definition():
    gt = box_surface(2048, 0)
    floor, method = emd_floor(gt, 256, seed=3, resample=lambda n, s: box_surface(n, s))
    a, b, factor, how = emd_floor_pair(gt, 256, seed=3, resample=lambda n, s: box_surface(n, s))
    assert method == how == "resample" and factor == 1.0 and len(a) == len(b) == 256
    assert floor == pytest.approx(earth_movers_distance(a, b))
    np.testing.assert_array_equal(a, box_surface(256, int(np.random.default_rng(3).integers(
        0, 2**31, size=2)[0])))


@pytest.mark.parametrize("m,n", [(2048, 512), (512, 512)])
def test_emd_floor_split_estimate_matches_true_resampling(m, n):
    """Two halves of the stored points: exact in distribution when M >= 2n, else rescaled by
    the sampling law (512 stored points, halves of 256, for a 512-point EMD)."""
    gt = box_surface(m, 0)
    truth = np.mean([earth_movers_distance(box_surface(n, s), box_surface(n, s + 50))
                     for s in range(1, 4)])
    est = np.mean([emd_floor(gt, n, seed=s)[0] for s in range(3)])
    assert emd_floor(gt, n)[1] == "split"
    assert est == pytest.approx(truth, rel=0.12)
    with pytest.raises(ValueError, match="too few"):
        emd_floor(gt[:6], n)
