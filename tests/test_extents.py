"""Track extents bounded by the observed points (seqshape.model.extents, issue 44): hand-made
boxes seen from known sides, with the expected boxes worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest

from seqshape.errors import ConfigError
from seqshape.geometry import box_surface, sensor_to_canonical
from seqshape.model.extents import bound_extents


def _visible(points: np.ndarray, pose, size) -> np.ndarray:
    """The points of a posed box's surface on the faces that face the sensor (origin)."""
    local = sensor_to_canonical(points, pose)
    sensor = sensor_to_canonical(np.zeros((1, 3)), pose)[0]
    half = np.asarray(size) / 2
    keep = np.zeros(len(local), bool)
    for a in range(2):
        keep |= (np.abs(local[:, a] - half[a]) < 1e-6) & (sensor[a] > half[a])
        keep |= (np.abs(local[:, a] + half[a]) < 1e-6) & (sensor[a] < -half[a])
    return points[keep]


def _track(poses, truth=(4.6, 1.8, 1.5), net=(4.0, 1.8, 1.5), net_offset=(0.0, 0.0)):
    """Visible points of a ``truth`` box at ``poses`` and the network's shapes: a ``net`` box
    whose centre is ``net_offset`` (box frame) from the truth's, and the network's poses."""
    poses = np.asarray(poses, dtype=np.float64)
    pts, shapes, est = [], [], []
    for k, p in enumerate(poses):
        pts.append(_visible(box_surface(4000, k, truth, pose=tuple(p)), p, truth))
        c, s = np.cos(p[3]), np.sin(p[3])
        q = p.copy()
        q[:2] += [c * net_offset[0] - s * net_offset[1], s * net_offset[0] + c * net_offset[1]]
        est.append(q)
        shapes.append(box_surface(2000, 100 + k, net, pose=tuple(q)).astype(np.float32))
    return pts, np.stack(shapes), np.stack(est)


def _box(complete, pose):
    local = sensor_to_canonical(np.asarray(complete, np.float64), pose)
    lo, hi = np.percentile(local[:, :2], (1, 99), axis=0)
    return lo, hi


def test_both_ends_seen_give_the_observed_length_and_centre():
    # a parked car passed by the ego: seen from behind (car ahead), then from the front
    poses = [[8.0, 3.0, -0.9, 0.0], [6.0, 3.0, -0.9, 0.0], [-6.0, 3.0, -0.9, 0.0],
             [-8.0, 3.0, -0.9, 0.0]]
    pts, shapes, est = _track(poses, net_offset=(0.2, 0.0))
    out_c, out_p = bound_extents(pts, shapes, est)
    for c, p, truth in zip(out_c, out_p, np.asarray(poses), strict=True):
        lo, hi = _box(c, p)
        assert hi[0] - lo[0] == pytest.approx(4.6, abs=0.05)  # the observed length
        assert np.linalg.norm(p[:2] - truth[:2]) < 0.05  # centred between the faces
        assert hi[1] - lo[1] == pytest.approx(1.8, abs=0.05)  # width: one side seen, kept


def test_one_end_seen_keeps_a_longer_prior_and_extends_a_shorter_one():
    # seen from behind and the left only: the front is never seen
    poses = [[8.0, -3.0, -0.9, 0.0], [9.0, -3.0, -0.9, 0.0], [10.0, -3.0, -0.9, 0.0]]
    pts, shapes, est = _track(poses, net=(5.0, 1.8, 1.5))  # the prior longer than the car
    out_c, out_p = bound_extents(pts, shapes, est)
    np.testing.assert_allclose(out_p, est)  # nothing observed contradicts it
    np.testing.assert_allclose(out_c, shapes, atol=1e-5)
    # a prior shorter than the side seen: the box reaches the observed points, back fixed
    pts, shapes, est = _track(poses, net=(4.0, 1.8, 1.5), net_offset=(-0.3, 0.0))
    out_c, out_p = bound_extents(pts, shapes, est)
    for c, p, e in zip(out_c, out_p, est, strict=True):
        lo, hi = _box(c, p)
        lo_e = _box(c, e)[0]
        assert lo_e[0] == pytest.approx(-2.0, abs=0.03)  # the network's back stays
        assert hi[0] - lo[0] == pytest.approx(4.55, abs=0.05)  # up to the side's far end


def test_anchor_moves_the_seen_face_to_the_points():
    poses = [[8.0, -3.0, -0.9, 0.0], [9.0, -3.0, -0.9, 0.0]]
    pts, shapes, est = _track(poses, truth=(4.5, 1.8, 1.5), net=(4.5, 1.8, 1.5),
                              net_offset=(0.25, 0.1))
    # without the anchor the box only grows to hold the back seen 0.25 m behind it
    grown, kept = bound_extents(pts, shapes, est)
    lo, hi = _box(grown[0], kept[0])
    assert hi[0] - lo[0] == pytest.approx(4.75, abs=0.03)
    np.testing.assert_allclose(kept[:, 0], est[:, 0] - 0.125, atol=0.02)
    _, moved = bound_extents(pts, shapes, est, anchor=True)
    # seen: the back (x) and the right side (y): both faces put back where they are
    np.testing.assert_allclose(moved[:, :2], np.asarray(poses)[:, :2], atol=0.03)


def test_segments_are_bounded_on_their_own_and_bad_input_refused():
    poses = [[8.0, 3.0, -0.9, 0.0], [7.0, 3.0, -0.9, 0.0], [-7.0, 3.0, -0.9, 0.0],
             [-8.0, 3.0, -0.9, 0.0], [8.0, 3.0, -0.9, 0.0], [9.0, 3.0, -0.9, 0.0]]
    pts, shapes, est = _track(poses, net=(5.0, 1.8, 1.5))
    out_c, out_p = bound_extents(pts, shapes, est, segments=[0, 0, 0, 0, 1, 1])
    lo, hi = _box(out_c[0], out_p[0])
    assert hi[0] - lo[0] == pytest.approx(4.6, abs=0.05)  # both ends seen in segment 0
    np.testing.assert_allclose(out_c[4:], shapes[4:], atol=1e-5)  # segment 1 saw one end
    out_c, out_p = bound_extents(pts, shapes, est)  # one segment: all six frames
    lo, hi = _box(out_c[5], out_p[5])
    assert hi[0] - lo[0] == pytest.approx(4.6, abs=0.05)
    with pytest.raises(ValueError, match="one track"):
        bound_extents(pts[:2], shapes, est)


def test_offline_config_extents_checked():
    from seqshape.model.offline import OfflineConfig

    assert OfflineConfig().extents in ("none", "bound", "anchor")
    with pytest.raises(ConfigError, match="extents"):
        OfflineConfig(extents="stretch")
