"""The track memory of parked vehicles (``Estimator(track_memory="parked")``,
:mod:`seqshape.model.track_memory`): when it feeds a frame, with what, and that it changes
nothing where it does not apply."""

import numpy as np
import pytest
import torch

from seqshape.errors import ConfigError
from seqshape.model import Estimator, ModelConfig, ShapePoseNet
from seqshape.model import track_memory as tm
from seqshape.model.offline import estimate_tracks
from seqshape.testing import box_surface

CAR = (4.5, 1.8, 1.5)


def _ego(x: float) -> np.ndarray:
    """The sensor at (x, 0, 0) of the fixed frame, axes aligned."""
    e = np.eye(4)
    e[0, 3] = x
    return e


def _drive_by(n: int, step: float = 0.7, car_speed: float = 0.0, seed: int = 0):
    """A car at (20, 6) in the fixed frame (moving along x at ``car_speed`` m/frame) seen by
    an ego driving along x by ``step`` m a frame: per frame the points in the sensor frame and
    the ego pose."""
    rng = np.random.default_rng(seed)
    frames, egos = [], []
    for k in range(n):
        ego = _ego(step * k)
        centre = np.array([20.0 + car_speed * k, 6.0, -0.9])
        world = box_surface(300, rng, CAR, pose=(*centre, 0.0))
        frames.append((world - ego[:3, 3]).astype(np.float32))
        egos.append(ego)
    return frames, egos


def _memory_after(frames, egos, centres) -> tm.TrackMemory:
    mem = tm.TrackMemory(np.random.default_rng(0))
    for f, e, c in zip(frames, egos, centres, strict=True):
        mem.record(f, e, np.array([c[0] - e[0, 3], c[1], -0.9, 0.0]))
    return mem


def test_a_parked_car_passed_by_gets_its_earlier_points():
    frames, egos = _drive_by(tm.MIN_DETECTIONS + 1)
    mem = _memory_after(frames[:-1], egos[:-1], [(20.0, 6.0)] * (len(frames) - 1))
    assert mem.parked(egos[-1][:3, 3])
    n = 64
    mixed = mem.frame_input(frames[-1], egos[-1], n)
    assert mixed is not None and mixed.dtype == np.float32 and len(mixed) == n
    cur = int(n * tm.CURRENT_SHARE)
    # the first half: points of the new frame itself
    assert np.isin(mixed[:cur].view("V12"), frames[-1].view("V12")).all()
    # the rest: earlier frames' points, in the new sensor frame: on the parked car's surface
    world = mixed[cur:] + egos[-1][:3, 3]
    assert np.abs(world[:, 0] - 20.0).max() <= CAR[0] / 2 + 1e-4
    assert np.abs(world[:, 1] - 6.0).max() <= CAR[1] / 2 + 1e-4
    assert not np.isin(mixed[cur:].view("V12"), frames[-1].view("V12")).any()


def test_the_memory_stays_out_of_a_moving_vehicle_a_static_sensor_and_a_first_frame():
    n = tm.MIN_DETECTIONS + 3
    # a car at 8 m/s (0.8 m a frame): its estimates leave the parked circle
    frames, egos = _drive_by(n, car_speed=0.8)
    mem = _memory_after(frames[:-1], egos[:-1], [(20.0 + 0.8 * k, 6.0) for k in range(n - 1)])
    assert not mem.parked(egos[-1][:3, 3]) and mem.frame_input(frames[-1], egos[-1], 64) is None
    # a parked car and a sensor that does not move: one view repeated, nothing to add
    frames, egos = _drive_by(n, step=0.0)
    mem = _memory_after(frames[:-1], egos[:-1], [(20.0, 6.0)] * (n - 1))
    assert mem.frame_input(frames[-1], egos[-1], 64) is None
    # too few earlier estimates
    frames, egos = _drive_by(tm.MIN_DETECTIONS)
    mem = _memory_after(frames[:-1], egos[:-1], [(20.0, 6.0)] * (tm.MIN_DETECTIONS - 1))
    assert mem.frame_input(frames[-1], egos[-1], 64) is None
    # an empty frame gets nothing
    frames, egos = _drive_by(n)
    mem = _memory_after(frames[:-1], egos[:-1], [(20.0, 6.0)] * (n - 1))
    assert mem.frame_input(np.zeros((0, 3), np.float32), egos[-1], 64) is None


def test_only_frames_within_reach_of_the_ego_feed_the_memory():
    step = 1.0
    n = int(2 * tm.MEMORY_REACH / step) + 3
    frames, egos = _drive_by(n, step=step)
    for k, f in enumerate(frames):  # tag each frame's points by its height
        f[:, 2] = 0.01 * k
    mem = _memory_after(frames[:-1], egos[:-1], [(20.0, 6.0)] * (n - 1))
    mixed = mem.frame_input(frames[-1], egos[-1], 256)
    tags = np.round(mixed[int(256 * tm.CURRENT_SHARE):, 2] / 0.01).astype(int)
    reach = int(tm.MEMORY_REACH / step)
    assert set(tags) == set(range(n - 1 - reach, n - 1))


def test_a_parked_centre_far_from_the_others_ends_the_memory():
    frames, egos = _drive_by(tm.MIN_DETECTIONS + 2)
    centres = [(20.0, 6.0)] * (len(frames) - 2) + [(20.0 + 2 * tm.PARK_RADIUS + 0.1, 6.0)]
    mem = _memory_after(frames[:-1], egos[:-1], centres)
    assert mem.frame_input(frames[-1], egos[-1], 64) is None


def test_frames_are_stored_capped_and_the_newest_kept():
    rng = np.random.default_rng(1)
    mem = tm.TrackMemory(np.random.default_rng(0))
    for k in range(tm.MEMORY_FRAMES + 5):
        mem.record(rng.normal(size=(tm.FRAME_POINTS * 2, 3)), _ego(float(k)), np.zeros(4))
    assert len(mem) == tm.MEMORY_FRAMES
    assert (mem._counts == tm.FRAME_POINTS).all()
    assert sorted(mem._egos[:, 0]) == list(range(5, tm.MEMORY_FRAMES + 5))


def _net(seed: int = 0) -> ShapePoseNet:
    torch.manual_seed(seed)
    cfg = ModelConfig(num_points=32, encoder1=(16, 32), encoder2=(32, 32), hidden=24,
                      shape_decoder=(32,), pose_decoder=(32,), num_complete=64,
                      shape_frame="canonical")
    return ShapePoseNet(cfg, recurrent=True)


def _run(est: Estimator, frames, egos, track_id="a"):
    est.reset()
    return [est.step([track_id], [f], ego_poses=[e])[0] for f, e in zip(frames, egos,
                                                                           strict=True)]


def test_the_estimator_default_is_the_memory_for_the_sequential_model_only():
    assert Estimator(_net(), threads=1).track_memory == "parked"
    base = ShapePoseNet(_net().cfg, recurrent=False)
    assert Estimator(base, threads=1).track_memory == "none"
    with pytest.raises(ConfigError, match="track_memory"):
        Estimator(_net(), threads=1, track_memory="always")
    est = Estimator(_net(), threads=1)
    with pytest.raises(ConfigError, match="track_memory"):
        est.track_memory = "yes"


def test_where_it_does_not_apply_the_estimates_are_those_without_it():
    net = _net()
    on = Estimator(net, threads=1, track_memory="parked")
    off = Estimator(net, threads=1, track_memory="none")
    # a moving car (its own estimates are not those of a parked one: the memory never feeds)
    frames, egos = _drive_by(12, car_speed=1.5)
    with_memory = _run(on, frames, egos)
    assert not on._states["a"].memory.parked(egos[-1][:3, 3])
    for a, b in zip(with_memory, _run(off, frames, egos), strict=True):
        np.testing.assert_array_equal(a.pose, b.pose)
        np.testing.assert_array_equal(a.complete, b.complete)
    # no ego poses at all
    on.reset()
    off.reset()
    frames, _ = _drive_by(12)
    for f in frames:
        a, b = on.step(["a"], [f])[0], off.step(["a"], [f])[0]
        np.testing.assert_array_equal(a.pose, b.pose)
    assert on._states["a"].memory is None


def test_a_parked_track_is_fed_its_memory_and_estimate_tracks_steps_it():
    net = _net()
    on = Estimator(net, threads=1, track_memory="parked")
    frames, egos = _drive_by(12)
    stepped = _run(on, frames, egos)
    off = _run(Estimator(net, threads=1, track_memory="none"), frames, egos)
    changed = [not np.array_equal(a.pose, b.pose) for a, b in zip(stepped, off, strict=True)]
    # this network's estimates stay within the parked circle: fed from the 6th frame on
    assert changed == [False] * tm.MIN_DETECTIONS + [True] * (12 - tm.MIN_DETECTIONS)
    assert len(on._states["a"].memory) == 12
    # estimate_tracks (online) equals stepping, for tracks sharing an id too
    other, other_egos = _drive_by(9, seed=3)
    tracks = [{"points": frames, "ego_poses": egos, "track_id": "a"},
              {"points": other, "ego_poses": other_egos, "track_id": "a"},
              {"points": other, "track_id": "b"}]
    out = estimate_tracks(on, tracks, "online")
    for a, b in zip(out[0], stepped, strict=True):
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-5)
    for a, b in zip(out[1], _run(on, other, other_egos), strict=True):
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-5)
    alone = estimate_tracks(on, tracks[2:], "online")[0]
    for a, b in zip(out[2], alone, strict=True):
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-5)
    assert on.track_ids == ["a"]  # estimate_tracks left the live states alone
    # offline: the memory's stream is the first pass of a track with ego poses
    plain = Estimator(net, threads=1, track_memory="none")
    fed, unfed = (estimate_tracks(e, tracks, "offline") for e in (on, plain))
    assert max(np.abs(a.pose - b.pose).max() for a, b in zip(fed[0], unfed[0], strict=True)) > 1e-4
    for a, b in zip(fed[2], unfed[2], strict=True):  # no ego poses: no memory
        np.testing.assert_array_equal(a.pose, b.pose)


def test_the_memory_moves_a_parked_estimate_and_is_repeatable():
    """With the memory fed, the network sees more of the car: a frame's estimate differs from
    the one without it, and the same seed gives the same estimates."""
    net = _net(1)
    frames, egos = _drive_by(14)
    # pin the track's estimates to the parked circle, so that the memory always applies
    a = Estimator(net, threads=1, track_memory="parked")
    runs = []
    for _ in range(2):
        a.reset()
        out = []
        for f, e in zip(frames, egos, strict=True):
            out.append(a.step(["a"], [f], ego_poses=[e])[0])
            a._states["a"].memory._centres[-1] = np.array([20.0, 6.0])
        runs.append(np.array([o.pose for o in out]))
    np.testing.assert_array_equal(runs[0], runs[1])
    plain = np.array([o.pose for o in _run(Estimator(net, threads=1, track_memory="none"),
                                             frames, egos)])
    k = tm.MIN_DETECTIONS
    np.testing.assert_array_equal(runs[0][:k], plain[:k])
    assert np.abs(runs[0][k:] - plain[k:]).max() > 1e-4


def test_evaluate_refuses_the_memory_offline():
    from seqshape.evaluation.evaluate import EvaluateConfig

    with pytest.raises(ConfigError, match="track-memory"):
        EvaluateConfig(offline=True, track_memory="parked")
    with pytest.raises(ConfigError, match="track-memory"):
        EvaluateConfig(track_memory="sometimes")
    assert EvaluateConfig(offline=True).track_memory == "auto"


def test_an_identity_switch_ends_the_memory():
    """A tracker hands another vehicle (3 m away) the same id: its estimates leave the parked
    circle, and no earlier points of the first vehicle are fed to it."""
    n = tm.MIN_DETECTIONS + 4
    frames, egos = _drive_by(n)
    centres = [(20.0, 6.0)] * (n - 2) + [(23.0, 6.0)]
    mem = _memory_after(frames[:-1], egos[:-1], centres)
    assert mem.frame_input(frames[-1], egos[-1], 64) is None
    # and it stays off while the first vehicle's positions are in the memory
    mem.record(frames[-1], egos[-1], np.array([23.0 - egos[-1][0, 3], 6.0, -0.9, 0.0]))
    assert mem.frame_input(frames[-1], egos[-1], 64) is None


def test_a_refused_step_leaves_the_memory_as_it_was(monkeypatch):
    """A step refused for lack of memory (the engine's allocation failed) draws nothing from
    the track memory: the step after it gives what it would have given without the refusal."""
    pytest.importorskip("onnxruntime")
    from onnxruntime.capi.onnxruntime_pybind11_state import Fail

    net = _net()
    frames, egos = _drive_by(9)
    a, b = (Estimator(net, backend="onnx", threads=1, track_memory="parked") for _ in range(2))
    for f, e in zip(frames[:-1], egos[:-1], strict=True):
        a.step(["a"], [f], ego_poses=[e])
        b.step(["a"], [f], ego_poses=[e])
    assert a._states["a"].memory.parked(egos[-1][:3, 3])  # the last frame is fed

    def fail(inputs):
        raise Fail("[ONNXRuntimeError] : 1 : FAIL : BFCArena::AllocateRawInternal Failed to "
                   "allocate memory for requested buffer of size 8589934592")

    with monkeypatch.context() as m:
        m.setattr(a._engine, "_run", fail)
        with pytest.raises(ConfigError, match="not enough memory"):
            a.step(["a"], [frames[-1]], ego_poses=[egos[-1]])
    got = a.step(["a"], [frames[-1]], ego_poses=[egos[-1]])[0]
    want = b.step(["a"], [frames[-1]], ego_poses=[egos[-1]])[0]
    np.testing.assert_array_equal(got.pose, want.pose)
