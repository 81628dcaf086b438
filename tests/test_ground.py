"""The sweep ground plane (seqshape.data.ground): the fast RANSAC equals the former one exactly.

The former implementation is kept below as the slow reference: the plane hypotheses drawn one
``rng.choice`` at a time, the whole sweep converted to float64, the candidates copied out.
"""

import numpy as np
import pytest

from seqshape.data.ground import (
    _BLOCK,
    _column_counts,
    _cross,
    _fit_plane,
    _inlier_counts,
    _minus,
    _quantile,
    _ransac_plane,
    _triples,
    ground_plane,
)


def _reference_ransac(cand, rng, iterations, threshold, max_tilt_deg):
    if len(cand) < 3 or iterations < 1:
        return None, 0
    tri = cand[np.stack([rng.choice(len(cand), 3, replace=False) for _ in range(iterations)])]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = (norm >= 1e-9) & (np.abs(n[:, 2]) >= np.cos(np.radians(max_tilt_deg)) * norm)
    if not ok.any():
        return None, 0
    n, tri = n[ok] / norm[ok, None] * np.sign(n[ok, 2])[:, None], tri[ok]
    offs = np.einsum("ij,ij->i", n, tri[:, 0])
    counts = np.count_nonzero(np.abs(cand @ n.T - offs) < threshold, axis=0)
    i = int(np.argmax(counts))
    if counts[i] <= 0:
        return None, 0
    return (n[i], float(-offs[i])), int(counts[i])


def _reference_ground_plane(points, threshold=0.2, sensor_height=1.73, iterations=100,
                            max_tilt_deg=10.0, low_quantile=0.3, seed=0, max_candidates=5000):
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    flat = (np.array([0.0, 0.0, 1.0]), float(sensor_height))
    if len(points) == 0:
        return flat
    z_lo = np.quantile(points[:, 2], low_quantile) + 0.5
    cand = points[points[:, 2] <= z_lo]
    rng = np.random.default_rng(seed)
    if len(cand) > max_candidates:
        cand = cand[rng.choice(len(cand), max_candidates, replace=False)]
    best, best_count = _reference_ransac(cand, rng, iterations, threshold, max_tilt_deg)
    if best is None or best_count < 3:
        return flat
    n, d = best
    n2, d2 = _fit_plane(cand[np.abs(cand @ n + d) < threshold])
    if n2[2] < np.cos(np.radians(max_tilt_deg)):
        return n, d
    return n2, d2


def _sweep(n: int, seed: int, slope: float = 0.02) -> np.ndarray:
    """A float32 (n, 4) sweep: a sloped noisy road, walls and vehicles above it."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-40, 40, (n, 2))
    z = -1.73 + slope * xy[:, 0] + rng.normal(0, 0.03, n)
    up = rng.random(n) < 0.35
    z[up] += rng.uniform(0.2, 3.0, up.sum())
    return np.c_[xy, z, rng.random(n)].astype(np.float32)


@pytest.mark.parametrize("m", [3, 4, 5, 7, 16, 101, 5000, 2**31 + 5, 2**33])
def test_triples_are_the_draws_of_one_choice_at_a_time(m):
    for seed in range(40):
        a, b = np.random.default_rng(seed), np.random.default_rng(seed)
        want = np.stack([a.choice(m, 3, replace=False) for _ in range(60)])
        np.testing.assert_array_equal(_triples(b, m, 60), want)
        assert a.bit_generator.state == b.bit_generator.state  # the same draws, no more


def test_ransac_equals_the_reference_exactly():
    rng = np.random.default_rng(3)
    for trial in range(30):
        m = int(rng.integers(3, 400))
        cand = rng.normal(size=(m, 3)) * [5, 5, 0.05 + 0.5 * (trial % 3)]
        if trial % 4 == 0:
            cand = cand.astype(np.float32)
        if trial % 7 == 0:
            cand[: m // 2] = cand[0]  # many degenerate triples
        for tilt in (10.0, 1.0):
            got = _ransac_plane(cand, np.random.default_rng(trial), 60, 0.08, tilt)
            want = _reference_ransac(cand, np.random.default_rng(trial), 60, 0.08, tilt)
            assert got[1] == want[1]
            if want[0] is None:
                assert got[0] is None
            else:
                np.testing.assert_array_equal(got[0][0], want[0][0])
                assert got[0][1] == want[0][1]


@pytest.mark.parametrize("n", [0, 1, 2, 3, 50, 3000, 40000])
def test_ground_plane_equals_the_reference_exactly(n):
    for seed in range(3):
        sweep = _sweep(n, seed, slope=0.02 * seed)
        for pts in (sweep[:, :3], sweep[:, :3].astype(np.float64), sweep[:, :3].tolist()):
            got = ground_plane(pts, seed=seed)
            want = _reference_ground_plane(pts, seed=seed)
            np.testing.assert_array_equal(got[0], want[0])
            assert got[1] == want[1]


def test_ground_plane_fallback_and_small_candidate_sets():
    wall = np.c_[np.zeros(200), np.random.default_rng(0).uniform(-5, 5, (200, 2))]
    n, d = ground_plane(wall.astype(np.float32))  # a vertical wall: no horizontal plane
    np.testing.assert_array_equal(n, [0.0, 0.0, 1.0])
    assert d == 1.73
    sweep = _sweep(8000, 5)[:, :3]
    for kw in ({"max_candidates": 10**6}, {"iterations": 1}, {"low_quantile": 0.9}):
        got, want = ground_plane(sweep, **kw), _reference_ground_plane(sweep, **kw)
        np.testing.assert_array_equal(got[0], want[0])
        assert got[1] == want[1]


@pytest.mark.parametrize("m", [1, 2, _BLOCK - 1, _BLOCK, _BLOCK + 1, 3 * _BLOCK + 7, 15000])
def test_inlier_counts_by_blocks_equal_one_product(m):
    rng = np.random.default_rng(m)
    cand = rng.normal(size=(m, 3)) * [8, 8, 0.1]
    n = rng.normal(size=(57, 3)) * [0.05, 0.05, 1]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    offs = rng.normal(0, 0.05, 57)
    want = np.count_nonzero(np.abs(cand @ n.T - offs) < 0.08, axis=0)
    for block in (1, 7, _BLOCK, 10**6):
        np.testing.assert_array_equal(_inlier_counts(cand, n, offs, 0.08, block), want)
    assert want.min() < want.max()  # the planes differ: a swapped column would show


@pytest.mark.parametrize("m", [_BLOCK + 1, 4000, 15000])
def test_ransac_equals_the_reference_on_many_candidates(m):
    for trial in range(3):
        cand = _sweep(m, trial, slope=0.03)[:, :3].astype(np.float64)
        got = _ransac_plane(cand, np.random.default_rng(trial), 60, 0.08, 10.0)
        want = _reference_ransac(cand, np.random.default_rng(trial), 60, 0.08, 10.0)
        assert got[1] == want[1] > 0
        np.testing.assert_array_equal(got[0][0], want[0][0])
        assert got[0][1] == want[0][1]


# --- the faster steps, each against the numpy call it replaces -----------------------------


def _quantile_cases():
    """1-D float64 arrays with ties, signed zeros, infinities, NaNs, one or two values."""
    rng = np.random.default_rng(9)
    cases = [np.array([0.5]), np.array([1.0, -1.0]), np.array([-0.0, 0.0, -0.0]),
             np.array([np.inf, np.inf, 1.0]), np.array([-np.inf, np.inf]),
             np.array([np.nan]), np.array([1.0, np.nan, 2.0]), np.full(7, 3.25),
             np.array([1e308, -1e308, 1e308]), np.array([5e-324, -5e-324, 0.0])]
    for trial in range(300):
        n = int(rng.integers(1, 40 if trial % 3 else 5000))
        z = [rng.normal(size=n), rng.integers(-3, 3, n).astype(float),
             rng.normal(size=n).astype(np.float32).astype(float) * 100][trial % 3]
        if trial % 5 == 0:
            z[rng.random(n) < 0.2] = np.inf
            z[rng.random(n) < 0.2] = -np.inf
        if trial % 7 == 0:
            z[rng.random(n) < 0.05] = np.nan
        cases.append(z)
    return cases


def test_quantile_equals_numpys():
    qs = (0.3, 0.0, 1.0, 0.5, 0.1, 0.9999, 1 - 1e-16, 1e-9, 1 / 3)
    with np.errstate(all="ignore"):
        for z in _quantile_cases():
            for q in qs:
                got, want = _quantile(z, q), np.quantile(z, q)
                assert type(got) is type(want) is np.float64
                assert np.array_equal(got, want, equal_nan=True)
                assert np.isnan(want) or got + 0.5 == want + 0.5  # how ground_plane uses it
            # other kinds of q go to np.quantile itself
            for q in (np.float32(0.3), np.float64(0.3), 0, 1, [0.3]):
                np.testing.assert_array_equal(_quantile(z, q), np.quantile(z, q))
    with pytest.raises(ValueError):
        _quantile(np.ones(3), 1.5)


def test_cross_and_minus_equal_the_broadcasts():
    rng = np.random.default_rng(10)
    for dtype in (np.float64, np.float32):
        u, v = (rng.normal(size=(60, 3)) * 10).astype(dtype), rng.normal(size=(60, 3)).astype(dtype)
        u[:5] = v[:5]  # parallel
        u[5:8] = 0.0
        got = _cross(u, v)
        assert got.dtype == dtype and got.tobytes() == np.cross(u, v).tobytes()
        p, c = rng.normal(size=(501, 3)).astype(dtype), rng.normal(size=3).astype(dtype)
        assert _minus(p, c).tobytes() == (p - c).tobytes() and _minus(p, c).flags.c_contiguous
    ints = rng.integers(-9, 9, (40, 3))
    assert _minus(ints, np.array([0.5, 1.5, -2.0])).tobytes() == (ints - [0.5, 1.5, -2.0]).tobytes()


def _former_fit_plane(p):
    c = p.mean(0)
    n = np.linalg.svd(p - c, full_matrices=False)[2][-1]
    n = n if n[2] >= 0 else -n
    return n, float(-n @ c)


def test_fit_plane_equals_the_former_one():
    rng = np.random.default_rng(12)
    for m in (3, 4, 50, 3000, 20000):
        for dtype in (np.float64, np.float32):
            p = (rng.normal(size=(m, 3)) * [8, 8, 0.05] + [0, 0, -1.7]).astype(dtype)
            (n, d), (n0, d0) = _fit_plane(p), _former_fit_plane(p)
            assert n.tobytes() == n0.tobytes() and d == d0


@pytest.mark.parametrize("m", [1, 254, 255, 256, 511, 512, 513])
def test_column_counts_are_exact_sums(m):
    mask = (np.random.default_rng(m).random((m, 9)) < 0.7).astype(np.uint8)
    mask[:, 0], mask[:, 1] = 1, 0  # all rows, no row
    counts = _column_counts(mask)
    assert counts.dtype == np.int64
    np.testing.assert_array_equal(counts, mask.sum(0, dtype=np.int64))


@pytest.mark.parametrize("block", [1, 2, 3, _BLOCK])
def test_inlier_counts_when_every_point_is_an_inlier_of_many_blocks(block):
    """The byte tally is emptied every 255 blocks: counts far above 255 stay exact."""
    m = 1200
    cand = np.zeros((m, 3))
    cand[::3, 2] = 1.0  # a third of the points off the planes z = 0 and z = 0.01
    n = np.array([[0.0, 0.0, 1.0]] * 3)
    offs = np.array([0.0, 0.01, 5.0])
    want = np.count_nonzero(np.abs(cand @ n.T - offs) < 0.08, axis=0)
    np.testing.assert_array_equal(_inlier_counts(cand, n, offs, 0.08, block), want)
    np.testing.assert_array_equal(want, [800, 800, 0])


def test_ground_plane_equals_the_reference_with_non_finite_rows():
    sweep = _sweep(6000, 7)[:, :3].astype(np.float64)
    for rows, col in ((slice(None, None, 37), 2), (slice(None, None, 41), 0), (slice(5, 6), 1)):
        bad = sweep.copy()
        bad[rows, col] = np.nan
        for pts in (bad, np.where(np.isnan(bad), np.inf, bad)):
            with np.errstate(invalid="ignore"):
                got, want = ground_plane(pts), _reference_ground_plane(pts)
            np.testing.assert_array_equal(got[0], want[0])
            assert got[1] == want[1]
