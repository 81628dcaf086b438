"""Per-pixel occlusion with pruned depth queries against a brute-force reference (issue 17).

``_owners`` asks an instance for its local depth only where it can be the nearest (its least
point depth not beyond the smallest largest depth of the instances there); the reference here
computes every covering instance's local depth at every overlap pixel by brute force (sorted
distances to all its points, no KD-tree) and takes the argmin.
"""

import numpy as np
import pytest

from seqshape.amodal.masks import (
    _K_LOCAL,
    InstanceMask,
    _owners,
    _resolve_pixel,
    instance_from_projection,
)


def _brute_local_depth(inst, pix):
    if len(inst.z) == 0:
        return np.full(len(pix), np.inf)
    out = np.empty(len(pix))
    for p, (u, v) in enumerate(pix):
        d2 = (inst.uv[:, 0] - u) ** 2 + (inst.uv[:, 1] - v) ** 2
        near = np.argsort(d2, kind="stable")[:min(_K_LOCAL, len(d2))]
        out[p] = inst.z[near].min()
    return out


def _reference(insts):
    """``(wins, visible masks)`` pixel by pixel: every instance asked everywhere it covers."""
    n = len(insts)
    h, w = insts[0].amodal.shape
    stack = np.stack([m.amodal for m in insts])
    visible = [m.amodal.copy() for m in insts]
    wins = np.zeros((n, n), dtype=np.int64)
    rows, cols = np.nonzero(stack.sum(0) >= 2)
    for r, c in zip(rows, cols, strict=True):
        depth = [(_brute_local_depth(m, np.array([[c, r]], float))[0] if stack[i, r, c]
                  else np.inf) for i, m in enumerate(insts)]
        owner = int(np.argmin(depth))
        for i in range(n):
            if stack[i, r, c] and i != owner:
                visible[i][r, c] = False
                if stack[owner, r, c]:
                    wins[owner, i] += 1
    return wins, visible


def _blobs(seed, n, size=(50, 70), depth_spread=1.0, empty_last=False):
    rng = np.random.default_rng(seed)
    insts = []
    for k in range(n):
        centre = rng.uniform([10, 10], [size[1] - 10, size[0] - 10])
        uv = centre + rng.normal(0, rng.uniform(4, 12), (150, 2))
        z = rng.uniform(5, 40) + rng.normal(0, depth_spread, 150)
        insts.append(instance_from_projection(f"t{k}", uv, z, size))
    if empty_last:
        insts[-1].z, insts[-1].uv = np.zeros(0), np.zeros((0, 2))
    return insts


def _check(insts):
    wins_ref, vis_ref = _reference(insts)
    wins = _resolve_pixel(insts)
    assert np.array_equal(wins, wins_ref)
    for m, v in zip(insts, vis_ref, strict=True):
        assert np.array_equal(m.visible, v)
    return wins


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("spread", [0.3, 8.0])
def test_owners_equal_the_brute_force_reference(seed, spread):
    # spread 0.3: depth ranges mostly apart (most pixels decided without a query);
    # 8.0: ranges overlap (most pixels asked)
    wins = _check(_blobs(seed, 3 + seed % 3, depth_spread=spread, empty_last=seed % 2 == 1))
    assert wins.sum() > 0


def _flat(track, uv, z, size=(20, 20)):
    uv = np.asarray(uv, float)
    return instance_from_projection(track, uv, np.full(len(uv), z) if np.isscalar(z) else z,
                                    size)


def test_hand_made_cases():
    square = [[2, 2], [14, 2], [14, 14], [2, 14], [8, 8], [5, 11], [11, 5]]
    shifted = [[u + 3, v + 3] for u, v in square]
    # apart in depth: the near one owns every overlap pixel, no query needed
    a, b = _flat("a", square, 5.0), _flat("b", shifted, 9.0)
    cover = np.stack([a.amodal, b.amodal])
    rows, cols = np.nonzero(cover.sum(0) >= 2)
    pix = np.c_[cols, rows].astype(float)
    assert (_owners([b, a], cover[::-1][:, rows, cols], pix) == 1).all()
    _check([_flat("a", square, 5.0), _flat("b", shifted, 9.0)])
    # equal constant depths: a tie everywhere, the lower index wins (as np.argmin)
    wins = _check([_flat("a", square, 7.0), _flat("b", shifted, 7.0)])
    assert wins[0, 1] > 0 and wins[1, 0] == 0
    # overlapping ranges: a slanted instance in front on one side, behind on the other
    z = np.array([4.0, 4.0, 12.0, 12.0, 8.0, 10.0, 6.0])
    _check([_flat("a", square, z), _flat("b", shifted, 8.0), _flat("c", square[:5], 20.0)])
    # an instance without depth samples never owns a pixel (inf), except against another one
    empty = _flat("e", shifted, 3.0)
    empty.z, empty.uv = np.zeros(0), np.zeros((0, 2))
    _check([empty, _flat("a", square, 5.0)])
    e2 = _flat("f", square, 3.0)
    e2.z, e2.uv = np.zeros(0), np.zeros((0, 2))
    empty = _flat("e", shifted, 3.0)
    empty.z, empty.uv = np.zeros(0), np.zeros((0, 2))
    _check([e2, empty])


def test_no_overlap_and_single_instance():
    a = _flat("a", [[1, 1], [5, 1], [1, 5]], 5.0)
    b = _flat("b", [[12, 12], [18, 12], [12, 18]], 5.0)
    assert _resolve_pixel([a, b]).sum() == 0
    assert isinstance(a, InstanceMask) and _resolve_pixel([a]).sum() == 0
