"""Tracks as a tracker delivers them: holes in time and identity switches (issue 44).

The smoothers (causal and whole-track), the shape average and the heading vote split a track
into segments at a hole longer than ``MAX_GAP`` or at a jump no vehicle makes, and never move
an estimate with points further than ``MAX_SHIFT``. References: a fresh smoother fed the
segment alone, sums by hand, and the truth of hand-made drives.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from seqshape.errors import ConfigError
from seqshape.model.smooth import (
    MAX_GAP,
    MAX_SHIFT,
    CausalSmoother,
    average_shapes,
    frame_numbers,
    limit_shift,
    smooth_track_poses,
    track_segments,
)


def _drive(times, seed=0, noise=0.15, speed=8.0, turn=0.05):
    """Poses of a car driving a circle arc at ``speed`` m/s (yaw rate ``turn`` rad/s), seen by
    a sensor driving straight at 5 m/s: truth and noisy estimates in the sensor frames, and the
    ego poses (sensor -> world)."""
    rng = np.random.default_rng(seed)
    t = np.asarray(times, dtype=np.float64)
    heading = 0.3 + turn * t
    r = speed / turn
    world = np.c_[30 + r * (np.sin(heading) - np.sin(0.3)),
                  -r * (np.cos(heading) - np.cos(0.3)), np.full(len(t), -0.9), heading]
    egos = []
    for ti in t:
        e = np.eye(4)
        e[0, 3] = 5.0 * ti
        egos.append(e)
    truth = world.copy()
    truth[:, 0] -= 5.0 * t
    est = truth + np.c_[rng.normal(0, noise, (len(t), 2)), np.zeros(len(t)),
                        rng.normal(0, 0.05, len(t))]
    return truth, est, egos


def _hole_times():
    """Frames 0-19 and 124-153 at 10 Hz: a track lost for 10.4 s and found again."""
    return np.r_[np.arange(20), np.arange(124, 154)] * 0.1


def test_frame_numbers_count_the_hole():
    f = frame_numbers(_hole_times(), 50)
    np.testing.assert_array_equal(f, np.r_[np.arange(20), np.arange(124, 154)])
    # jitter rounds away; equal times still advance one frame; no times: the index
    jitter = np.array([0.0, 0.101, 0.199, 0.3, 0.3, 0.52])
    np.testing.assert_array_equal(frame_numbers(jitter, 6), [0, 1, 2, 3, 4, 5])
    np.testing.assert_array_equal(frame_numbers(None, 3), [0, 1, 2])


def test_track_segments_split_at_holes_and_jumps():
    times = np.arange(8) * 0.1
    valid = np.ones(8, bool)
    assert track_segments(times, valid).tolist() == [0] * 8
    gap = times.copy()
    gap[5:] += MAX_GAP + 0.05
    assert track_segments(gap, valid).tolist() == [0] * 5 + [1] * 3
    centres = np.c_[np.arange(8) * 0.8, np.zeros(8)]  # 8 m/s
    assert track_segments(times, valid, centres).tolist() == [0] * 8
    centres[4:, 1] += 12.0  # another vehicle, 12 m to the side
    assert track_segments(times, valid, centres).tolist() == [0] * 4 + [1] * 4
    # a frame without points belongs to the detection before it
    valid[5] = False
    assert track_segments(gap, valid).tolist() == [0] * 6 + [1] * 2


def test_segment_rule_catches_a_switch_to_the_next_lane_not_noise_or_braking():
    """A vehicle 3.5 m to the side under the same id (the next lane) starts a segment; a
    track's noisy estimates (0.3 m) over 60 s, and a car braking at 7 m/s^2, do not."""
    rng = np.random.default_rng(0)
    times = np.arange(600) * 0.1
    centres = np.c_[15.0 * times, np.zeros(600)] + rng.normal(0, 0.3, (600, 2))
    assert track_segments(times, np.ones(600, bool), centres).max() == 0
    switched = centres.copy()
    switched[300:, 1] += 3.5
    seg = track_segments(times, np.ones(600, bool), switched)
    assert seg[299] == 0 and seg[300] == 1 and seg.max() == 1
    t = np.arange(40) * 0.1
    braking = np.c_[20.0 * t - 3.5 * t ** 2, np.zeros(40)]  # 20 m/s to a stop in 2.9 s
    braking[29:, 0] = braking[28, 0]
    assert track_segments(t, np.ones(40, bool), braking).max() == 0
    # holes within MAX_GAP keep the segment; the prediction spans them
    holes = np.ones(600, bool)
    holes[100:108] = False
    assert track_segments(times, holes, centres).max() == 0


def test_limit_shift_puts_back_far_frames_with_points_only():
    poses = np.zeros((3, 4))
    smoothed = np.array([[0.3, 0, 0, 0.1], [MAX_SHIFT + 0.1, 0, 0, 0.2], [5.0, 0, 0, 0.0]])
    got = limit_shift(smoothed, poses, [True, True, False])
    np.testing.assert_array_equal(got, [[0.3, 0, 0, 0.1], [0, 0, 0, 0], [5.0, 0, 0, 0.0]])


def test_causal_smoother_after_a_hole_is_a_fresh_one():
    """Across a 10.4 s hole the causal smoother forgets the track: after it, its poses equal
    those of a new smoother fed the frames after the hole alone, and they stay near the
    truth (before segments, the fit over frame indices put the car tens of metres off)."""
    times = _hole_times()
    truth, est, egos = _drive(times)
    # the frame weights' ramp counts the track's detections, not the segment's: off here
    sm, fresh = CausalSmoother(ramp=None), CausalSmoother(ramp=None)
    out = np.array([sm.update(est[t], True, egos[t], times[t]) for t in range(50)])
    again = np.array([fresh.update(est[t], True, egos[t], times[t]) for t in range(20, 50)])
    np.testing.assert_allclose(out[20:], again, atol=1e-9)
    assert sm.segments == 1
    err = np.linalg.norm(out[:, :2] - truth[:, :2], axis=1)
    assert err.max() < 0.6, err.max()
    # the frames' times count: the old rule (one frame per update) is what the hole broke
    old = np.array([smooth_track_poses(est[max(0, t - 63):t + 1],
                                       np.arange(min(t, 63) + 1.0), np.stack(
                                           egos[max(0, t - 63):t + 1]), window=5)[-1]
                    for t in range(50)])
    assert np.linalg.norm(old[20:, :2] - truth[20:, :2], axis=1).max() > 2 * err.max()


def test_causal_smoother_identity_switch_is_a_new_segment():
    """A different vehicle under the same id (12 m away): a new segment; the shape average
    and the poses after it owe nothing to the first vehicle."""
    times = np.arange(30) * 0.1
    truth, est, egos = _drive(times, seed=1)
    est[15:, 1] += 12.0

    class E:  # an estimate as update_estimate takes it
        def __init__(self, pose, complete):
            self.pose, self.complete, self.num_points, self.flipped = pose, complete, 200, False

    rng = np.random.default_rng(3)
    shapes = [rng.normal(0, 1, (16, 3)).astype(np.float32) + est[t, :3].astype(np.float32)
              for t in range(30)]
    sm, fresh = CausalSmoother(ramp=None), CausalSmoother(ramp=None)
    got = []
    for t in range(30):
        e = E(est[t].copy(), shapes[t].copy())
        sm.update_estimate(e, egos[t], times[t])
        got.append(e)
    for t in range(15, 30):
        e = E(est[t].copy(), shapes[t].copy())
        fresh.update_estimate(e, egos[t], times[t])
        np.testing.assert_allclose(got[t].pose, e.pose, atol=1e-9)
        np.testing.assert_allclose(got[t].complete, e.complete, atol=1e-5)
    assert sm.segments == 1
    shift = np.linalg.norm(np.array([g.pose[:2] for g in got]) - est[:, :2], axis=1)
    assert shift.max() <= MAX_SHIFT


def test_causal_smoother_does_not_carry_a_fit_through_a_long_run_without_points():
    times = np.arange(40) * 0.1
    truth, est, egos = _drive(times, seed=2)
    has = np.ones(40, bool)
    has[12:40] = False  # the tracker coasts the track for 2.8 s
    sm = CausalSmoother()
    out = np.array([sm.update(est[t], has[t], egos[t], times[t]) for t in range(40)])
    late = times - times[11] > MAX_GAP
    np.testing.assert_array_equal(out[late], est[late])  # the stale estimate, not a guess
    assert np.all(np.linalg.norm(out[~late & ~has, :2] - truth[~late & ~has, :2], axis=1)
                  < 1.5)


def test_causal_smoother_refuses_bad_limits():
    for bad in ({"max_gap": 0}, {"max_speed": -1.0}, {"max_shift": True}, {"max_gap": "1"}):
        with pytest.raises(ConfigError, match="CausalSmoother"):
            CausalSmoother(**bad)


def test_average_shapes_decay_by_frames_and_stop_at_segments():
    """The decay counts frame numbers (a frame after a hole of k frames weighs its past
    decay^k), and no average crosses a segment: by hand on a 4-frame track."""
    c = np.array([1.0, 2.0, 4.0, 8.0])
    complete = np.zeros((4, 2, 3), np.float32)
    complete[:, :, 0] = c[:, None]
    poses = np.zeros((4, 4))
    w = np.ones(4)
    d = 0.5
    got = average_shapes(complete, poses, w, d, frames=[0, 1, 4, 5])[:, 0, 0]
    s1 = 2 + d * 1
    s2 = 4 + d ** 3 * s1
    m2 = 1 + d ** 3 * (1 + d)
    want = [1.0, s1 / (1 + d), s2 / m2, (8 + d * s2) / (1 + d * m2)]
    np.testing.assert_allclose(got, want, rtol=1e-6)
    got = average_shapes(complete, poses, w, d, causal=False, segments=[0, 0, 1, 1])[:, 0, 0]
    want = [(1 + d * 2) / (1 + d), (2 + d * 1) / (1 + d), (4 + d * 8) / (1 + d),
            (8 + d * 4) / (1 + d)]
    np.testing.assert_allclose(got, want, rtol=1e-6)
    # decay 1 (no forgetting) still stops at a segment
    got = average_shapes(complete, poses, w, 1.0, segments=[0, 0, 1, 1])[:, 0, 0]
    np.testing.assert_allclose(got, [1, 1.5, 4, 6], rtol=1e-6)


def test_offline_track_with_a_hole_stays_near_its_estimates():
    """The whole-track mode on a track lost for 10.4 s: the smoothed poses of each segment are
    the smoother over that segment alone (frame numbers from the timestamps), every frame
    within MAX_SHIFT of the online estimate, and the heading of each segment its own."""
    import torch

    from seqshape.model import Estimator, ModelConfig, ShapePoseNet
    from seqshape.model.offline import OfflineConfig, estimate_track
    from seqshape.testing import box_surface

    torch.manual_seed(0)
    cfg = ModelConfig(num_points=32, encoder1=(16, 32), encoder2=(32, 32), hidden=24,
                      shape_decoder=(32,), pose_decoder=(32,), num_complete=64,
                      shape_frame="canonical")
    est = Estimator(ShapePoseNet(cfg, recurrent=True), threads=1, track_memory="none")
    times = _hole_times()
    truth, _, egos = _drive(times, noise=0.0)
    points = [box_surface(40, k, pose=tuple(truth[k]), dtype=np.float32) for k in range(50)]
    online = estimate_track(est, points, timestamps=times, ego_poses=egos, mode="online")
    offline = estimate_track(est, points, timestamps=times, ego_poses=egos,
                             config=OfflineConfig(heading=False))
    on = np.array([o.pose for o in online])
    off = np.array([o.pose for o in offline])
    assert np.linalg.norm(off[:, :2] - on[:, :2], axis=1).max() <= MAX_SHIFT + 1e-9
    frames = frame_numbers(times, 50)
    for part in (slice(0, 20), slice(20, 50)):
        want = limit_shift(smooth_track_poses(on[part], frames[part], np.stack(egos[part])),
                           on[part])
        np.testing.assert_allclose(off[part], want, atol=1e-6)
    assert math.isfinite(off.sum())


def test_heading_filter_forgets_its_evidence_after_a_hole():
    """The online heading step starts afresh after a hole over MAX_GAP (as a new filter fed
    the frames after it), and keeps its evidence across a shorter one."""
    from seqshape.model.heading import HeadingConfig, HeadingFilter

    times = _hole_times()
    truth, est, egos = _drive(times, seed=4)
    est[20:, 3] += math.pi  # after the hole the estimates point backwards
    cfg = HeadingConfig()
    whole, fresh = HeadingFilter(cfg), HeadingFilter(cfg)
    got = [whole.update(est[t], egos[t], True, time=times[t]) for t in range(50)]
    want = [fresh.update(est[t], egos[t], True, time=times[t]) for t in range(20, 50)]
    assert got[20:] == want
    blind = HeadingFilter(cfg)  # without times the hole is not seen: the old evidence stays
    flips = [blind.update(est[t], egos[t], True) for t in range(50)]
    assert flips[20:] != want
    short = HeadingFilter(cfg)
    t2 = np.arange(50) * 0.1
    t2[20:] += MAX_GAP - 0.15
    kept = [short.update(est[t], egos[t], True, time=t2[t]) for t in range(50)]
    assert kept == flips
