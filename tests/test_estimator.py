"""Estimator: batched == per-track, empty frames, any point count, weight files."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from seqshape.data.windows import points_length, points_lengths
from seqshape.errors import ConfigError, DataError
from seqshape.model import Estimator, ModelConfig, ShapePoseNet
from seqshape.model import estimator as estimator_module
from seqshape.model import weights as weights_module
from seqshape.train.checkpoint import model_payload, save_payload

TINY = ModelConfig(num_points=64, encoder1=(8, 16), encoder2=(16, 24), hidden=20,
                   shape_decoder=(32,), pose_decoder=(16,), num_complete=40)


def _model(recurrent=True):
    torch.manual_seed(0)
    return ShapePoseNet(TINY, recurrent=recurrent)


def _frames(rng, n_tracks, n_frames):
    sizes = [0, 1, 5, 64, 200, 10_000]
    return [[(rng.normal(size=(sizes[(i + t) % len(sizes)], 3)) + [10 + i, -i, 0])
             .astype(np.float32) for i in range(n_tracks)] for t in range(n_frames)]


@pytest.mark.parametrize("recurrent", [True, False])
def test_batched_equals_per_track(recurrent):
    frames = _frames(np.random.default_rng(0), 5, 4)
    ids = [f"t{i}" for i in range(5)]
    batched, single = Estimator(_model(recurrent)), Estimator(_model(recurrent))
    for pts in frames:
        out_b = batched.step(ids, pts)
        out_s = [single.step([tid], [p])[0] for tid, p in zip(ids, pts, strict=True)]
        for a, b in zip(out_b, out_s, strict=True):
            assert a.track_id == b.track_id and a.num_points == b.num_points
            np.testing.assert_allclose(a.complete, b.complete, atol=2e-5)
            np.testing.assert_allclose(a.pose, b.pose, atol=2e-5)


def test_estimate_types_and_point_counts():
    est = Estimator(_model())
    rng = np.random.default_rng(1)
    pts = [np.zeros((0, 3), np.float32), rng.normal(size=(1, 3)),
           rng.normal(size=(10_000, 3)) + 5]
    out = est.step(["a", "b", "c"], pts)
    assert [o.num_points for o in out] == [0, 1, 64]
    for o in out:
        assert o.complete.shape == (40, 3) and o.complete.dtype == np.float32
        assert o.pose.shape == (4,) and o.pose.dtype == np.float64
        assert np.all(np.isfinite(o.complete)) and np.all(np.isfinite(o.pose))
    # a track with no points yet is decoded around the origin (no known mean): not valid
    assert np.linalg.norm(out[0].complete.mean(0)) < np.linalg.norm(out[2].complete.mean(0))
    assert [o.valid for o in out] == [False, True, True]


def test_empty_frame_does_not_corrupt_state():
    rng = np.random.default_rng(2)
    f1, f2 = (rng.normal(size=(50, 3)) + 8).astype(np.float32), \
        (rng.normal(size=(40, 3)) + 8).astype(np.float32)
    a, b = Estimator(_model()), Estimator(_model())
    first = a.step(["x"], [f1])[0]
    carried = a.step(["x"], [np.zeros((0, 3), np.float32)])[0]
    np.testing.assert_array_equal(carried.complete, first.complete)
    np.testing.assert_array_equal(carried.pose, first.pose)
    with_gap = a.step(["x"], [f2])[0]
    b.step(["x"], [f1])
    without_gap = b.step(["x"], [f2])[0]
    np.testing.assert_array_equal(with_gap.complete, without_gap.complete)
    nan = f2.copy()
    nan[:5] = np.nan  # non-finite rows (a sensor's no-returns) are dropped with a warning
    with pytest.warns(UserWarning, match=r"track 'y'.*dropped 5 of 40 points that are not fin"):
        dropped = Estimator(_model()).step(["y"], [nan])[0]
    alone = Estimator(_model()).step(["y"], [f2[5:]])[0]
    assert dropped.num_points == 35
    np.testing.assert_array_equal(dropped.complete, alone.complete)
    with pytest.warns(UserWarning), pytest.raises(ConfigError, match="more than 1000 m"):
        b.step(["y"], [np.concatenate([nan, [[2000.0, 0.0, 0.0]]])])  # NaN does not hide range


def test_reset():
    est = Estimator(_model())
    pts = [np.ones((3, 3), np.float32)] * 2
    first = est.step(["a", "b"], pts)
    est.step(["a", "b"], pts)
    est.reset("a")
    assert est.track_ids == ["b"]
    again = est.step(["a"], pts[:1])[0]  # a fresh state again (batch of 1 vs 2: rounding)
    np.testing.assert_allclose(again.complete, first[0].complete, atol=1e-6)
    est.reset()
    assert est.track_ids == []
    with pytest.raises(Exception, match="twice"):
        est.step(["a", "a"], pts)


def test_checkpoint_round_trip(tmp_path):
    model = _model(recurrent=False)
    path = tmp_path / "model.pt"
    save_payload(path, model_payload(model, {}, {"val_cd_m": 0.05}))
    est = Estimator.from_checkpoint(path)
    assert not est.recurrent and est.kind == "baseline" and est.metrics["val_cd_m"] == 0.05
    pts = np.random.default_rng(3).normal(size=(30, 3)).astype(np.float32)
    ref = Estimator(model).step(["a"], [pts])[0]
    # the reference, bit for bit (the network's own placement: the loaders' default refiner
    # was trained on the shipped networks, not on this one)
    exact = Estimator.from_checkpoint(path, backend="torch", refiner="none")
    np.testing.assert_array_equal(exact.step(["a"], [pts])[0].complete, ref.complete)
    # the float32 fast backends: the same arithmetic in another order
    fl = Estimator.from_checkpoint(path, backend="auto-float", refiner="none")
    np.testing.assert_allclose(fl.step(["a"], [pts])[0].complete, ref.complete, atol=1e-5)
    # the loaders' default, "auto": int8 where its check passes (these random weights may not)
    assert est.backend in ("onnx-int8", "onnx")


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_corrupt_and_foreign_files(tmp_path):
    good = tmp_path / "good.pt"
    save_payload(good, model_payload(_model(), {}, {}))
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:1000])
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(np.random.default_rng(0).bytes(5000))
    foreign = tmp_path / "foreign.pt"
    torch.save({"model": torch.zeros(3)}, foreign)
    pickled = tmp_path / "pickled.pt"
    pickled.write_bytes(pickle.dumps(np.random.default_rng))  # code, not weights
    wrong = tmp_path / "wrong.pt"
    payload = model_payload(_model(), {}, {})
    payload["model_config"]["hidden"] = 99
    torch.save(payload, wrong)
    newer = tmp_path / "newer.pt"
    torch.save({**model_payload(_model(), {}, {}), "version": 99}, newer)
    for path, msg in ((truncated, "not a readable"), (garbage, "not a readable"),
                      (foreign, "not a seqshape checkpoint"), (pickled, "not a readable"),
                      (wrong, "do not fit"), (newer, "newer"),
                      (tmp_path / "missing.pt", "not found")):
        with pytest.raises(DataError, match=msg) as info:
            Estimator.from_checkpoint(path)
        assert str(path) in str(info.value)


def test_from_pretrained_missing_is_clear(tmp_path, monkeypatch):
    monkeypatch.setattr(weights_module, "PRETRAINED_DIR", tmp_path)
    with pytest.raises(DataError, match="seqshape train --model baseline"):
        Estimator.from_pretrained("baseline")
    save_payload(tmp_path / "sequential.pt", model_payload(_model(), {}, {}))
    assert Estimator.from_pretrained("sequential").recurrent


def _state_equal(a: Estimator, b: Estimator) -> bool:
    sa, sb = a.model.state_dict(), b.model.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_load_resolves_names_and_paths(tmp_path, monkeypatch):
    monkeypatch.setattr(weights_module, "PRETRAINED_DIR", tmp_path)
    save_payload(tmp_path / "sequential.pt", model_payload(_model(), {}, {}))
    save_payload(tmp_path / "baseline.pt", model_payload(_model(False), {}, {}))
    run = tmp_path / "run"
    run.mkdir()
    save_payload(run / "model.pt", model_payload(_model(False), {}, {"cd": 0.5}))
    assert Estimator.load("sequential").recurrent
    assert Estimator.load("pretrained").kind == "sequential"
    base = Estimator.load("pretrained", kind="baseline", threads=1)
    assert base.kind == "baseline" and _state_equal(base, Estimator.from_pretrained("baseline"))
    own = Estimator.load(run / "model.pt")
    assert own.metrics == {"cd": 0.5}
    assert _state_equal(own, Estimator.from_checkpoint(str(run / "model.pt")))
    assert Estimator.load(str(run / "model.pt"), kind="baseline").kind == "baseline"
    with pytest.raises(ConfigError, match="holds a baseline model, not a sequential one"):
        Estimator.load(run / "model.pt", kind="sequential")
    with pytest.raises(DataError, match="weights file not found"):
        Estimator.load(tmp_path / "none.pt")
    with pytest.raises(ConfigError, match="unknown pretrained model 'big'"):
        Estimator.load("pretrained", kind="big")
    with pytest.raises(ConfigError, match="CPU"):
        Estimator.load("sequential", device="cuda")
    (tmp_path / "baseline.pt").unlink()
    with pytest.raises(DataError, match="baseline.pt: shipped baseline weights are missing"):
        Estimator.load("baseline")


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_load_refuses_pickles(tmp_path):
    pickled = tmp_path / "pickled.pt"
    pickled.write_bytes(pickle.dumps(np.random.default_rng))  # code, not weights
    with pytest.raises(DataError, match="not a readable"):
        Estimator.load(pickled)


def test_resolve_weights_is_shared_with_training(tmp_path, monkeypatch):
    from seqshape.train.checkpoint import resolve_init

    monkeypatch.setattr(weights_module, "PRETRAINED_DIR", tmp_path)
    save_payload(tmp_path / "baseline.pt", model_payload(_model(False), {}, {}))
    assert resolve_init("pretrained", "baseline") == tmp_path / "baseline.pt"
    assert estimator_module.resolve_weights("baseline") == tmp_path / "baseline.pt"
    assert resolve_init(tmp_path / "baseline.pt", "sequential") == tmp_path / "baseline.pt"
    with pytest.raises(DataError, match="sequential weights are missing"):
        resolve_init("pretrained", "sequential")


# ---------------------------------------------------------------------- issue 15: scale, heading
SCALED = ModelConfig(**{**TINY.to_dict(), "scale_norm": "length", "shape_frame": "canonical"})


def _scaled_pair(recurrent=True):
    """The same weights without and with ``scale_norm="length"``."""
    torch.manual_seed(0)
    plain = ShapePoseNet(ModelConfig(**{**SCALED.to_dict(), "scale_norm": "none"}), recurrent)
    scaled = ShapePoseNet(SCALED, recurrent)
    scaled.load_state_dict(plain.state_dict())
    return plain, scaled


def _car(rng, n=50, length=4.4, centre=(10.0, 2.0, -0.8)):
    """Points of a car-sized box side (well under scale_ref = 6 m)."""
    return (rng.uniform(-0.5, 0.5, (n, 3)) * [length, 1.8, 1.4] + centre).astype(np.float32)


@pytest.mark.parametrize("recurrent", [True, False])
def test_scaled_model_equals_plain_model_on_cars(recurrent):
    rng = np.random.default_rng(1)
    plain, scaled = (Estimator(m) for m in _scaled_pair(recurrent))
    for _ in range(3):
        pts = [_car(rng), _car(rng, 30, 3.8, (5.0, -4.0, -1.0))]
        for a, b in zip(plain.step(["a", "b"], pts), scaled.step(["a", "b"], pts), strict=True):
            assert b.scale == a.scale == 1.0
            assert np.array_equal(a.complete, b.complete) and np.array_equal(a.pose, b.pose)


def test_scale_hints_override_the_points_estimate():
    rng = np.random.default_rng(2)
    _, net = _scaled_pair()
    pts = [_car(rng, 60, 4.0)]
    est = Estimator(net)
    assert est.step(["a"], pts)[0].scale == 1.0                        # from the points
    assert est.step(["a"], pts, sizes=[(12.0, 2.5, 3.0)])[0].scale == 2.0   # box hint
    assert est.step(["a"], pts, sizes=[18.0])[0].scale == 3.0            # length hint
    assert est.step(["a"], pts, classes=["bus"])[0].scale == pytest.approx(10.0 / 6.0)
    assert est.step(["a"], pts, classes=["car"])[0].scale == 1.0
    assert est.step(["a"], pts, sizes=[None], classes=[None])[0].scale == 1.0
    # what the hint does is exactly the network run at that scale
    ref = Estimator(net)
    direct = net.eval()(torch.from_numpy(pts[0])[None, None], torch.tensor([[60]]),
                        scale=torch.tensor([[2.0]]))
    out = ref.step(["a"], pts, sizes=[12.0])[0]
    np.testing.assert_allclose(out.complete, direct["complete"][0, 0].detach().numpy(),
                               atol=1e-5)
    with pytest.raises(ConfigError):
        est.step(["a"], pts, classes=["tank"])
    with pytest.raises(ConfigError):
        est.step(["a"], pts, sizes=[-3.0])
    with pytest.raises(ConfigError):
        est.step(["a"], pts, sizes=[4.0, 5.0])


def test_points_length_running_max_for_the_sequential_model_only():
    """A long vehicle first seen end-on: the sequential estimator keeps the largest extent
    seen so far, the per-frame baseline uses each frame's own."""
    # a 12 m side and an end-on view, turned by 30 degrees: 101 evenly spaced points per edge,
    # so the 1st-99th percentile extent along the vehicle is 0.98 of it
    u = np.linspace(-0.5, 0.5, 101)
    side = np.c_[12.0 * u, np.full(101, 1.25), np.zeros(101)]
    end = np.c_[np.full(101, 6.0), 2.5 * u, np.zeros(101)]
    turn = _rz(np.radians(30.0))[:3, :3]
    long_side, end_on = ((p @ turn.T + [15.0, 4.0, -0.5]).astype(np.float32) for p in (side, end))
    assert points_length(long_side) == pytest.approx(0.98 * 12.0, rel=0.01)
    assert points_length(end_on) == pytest.approx(0.98 * 2.5, rel=0.01)
    torch.manual_seed(0)
    cfg = ModelConfig(**{**SCALED.to_dict(), "num_points": 128})
    for recurrent, expected in ((True, 12.0), (False, 2.5)):
        est = Estimator(ShapePoseNet(cfg, recurrent))
        first = est.step(["bus"], [long_side])[0].scale
        assert first == pytest.approx(0.98 * 12.0 / 6.0, rel=0.01)
        later = est.step(["bus"], [end_on])[0].scale
        assert later == pytest.approx(max(1.0, 0.98 * expected / 6.0), rel=0.01)
        assert est.step(["bus"], [np.zeros((0, 3), np.float32)])[0].scale == later


def test_scaled_estimator_is_equivariant():
    """Twice the points and twice the hinted length: exactly twice the shape and centre."""
    rng = np.random.default_rng(4)
    pts = [_car(rng, 40, 7.0) for _ in range(3)]
    a, b = Estimator(_scaled_pair()[1]), Estimator(_scaled_pair()[1])
    for p in pts:
        ea = a.step(["t"], [p], sizes=[8.0])[0]
        eb = b.step(["t"], [2 * p], sizes=[16.0])[0]
        assert eb.scale == 2 * ea.scale == pytest.approx(16.0 / 6.0)
        assert np.array_equal(eb.complete, 2 * ea.complete)
        assert np.array_equal(eb.pose[:3], 2 * ea.pose[:3]) and eb.pose[3] == ea.pose[3]


def _fixed_yaw_model(yaw: float) -> ShapePoseNet:
    """A network whose pose is (frame mean, ``yaw``) whatever it sees."""
    net = _model()
    with torch.no_grad():
        net.pose_decoder[-1].weight.zero_()
        net.pose_decoder[-1].bias.copy_(torch.tensor([0, 0, 0, np.cos(yaw), np.sin(yaw)]))
    return net


def _rz(a: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    m[:3, 3] = t
    return m


def _drive(speed: float, frames: int = 8):
    """A vehicle driving at ``speed`` m/frame along 40 degrees in a fixed frame, seen from an
    ego that drives along x at 0.5 m/frame with a 30 degree yaw: sensor-frame points and the
    ego poses (sensor -> fixed)."""
    rng = np.random.default_rng(5)
    heading = np.radians(40.0)
    out = []
    for t in range(frames):
        centre = np.array([20.0, 5.0, -0.5]) + speed * t * np.array([np.cos(heading),
                                                                    np.sin(heading), 0])
        world = _car(rng, 50, 4.4, centre)
        ego = _rz(np.radians(30.0), (0.5 * t, 0.0, 0.0))
        sensor = (np.linalg.inv(ego) @ np.c_[world, np.ones(len(world))].T).T[:, :3]
        out.append((sensor.astype(np.float32), ego))
    return out


def test_moving_track_estimated_backwards_comes_out_forwards():
    from seqshape.geometry import sensor_to_canonical

    backwards = np.radians(40.0 + 180.0 - 30.0)  # sensor-frame yaw = fixed-frame 220 deg
    flt, raw = Estimator(_fixed_yaw_model(backwards)), Estimator(_fixed_yaw_model(backwards))
    flips = []
    for pts, ego in _drive(speed=1.0):
        e = flt.step(["v"], [pts], ego_poses=[ego])[0]
        r = raw.step(["v"], [pts])[0]  # no ego poses: nothing known about motion
        assert not r.flipped and r.pose[3] == pytest.approx(wrap(backwards))
        flips.append(e.flipped)
        if e.flipped:  # forwards in the fixed frame = 40 deg - 30 deg of the ego in sensor
            assert e.pose[3] == pytest.approx(np.radians(10.0))
            # same placed point set, the canonical shape turned by pi; same centre
            assert np.array_equal(e.complete, r.complete)
            np.testing.assert_array_equal(e.pose[:3], r.pose[:3])
            turned = sensor_to_canonical(r.complete, r.pose) * [-1, -1, 1]
            np.testing.assert_allclose(sensor_to_canonical(e.complete, e.pose), turned,
                                       atol=1e-5)
    # 2 m of fitted travel needs 3 frames at 1 m/frame: from then on every frame is fixed
    assert flips == [False, False] + [True] * 6


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_parked_and_forward_tracks_are_left_alone():
    backwards = np.radians(40.0 + 180.0 - 30.0)
    for yaw, speed in ((backwards, 0.0), (backwards, 0.1), (np.radians(10.0), 1.0)):
        est = Estimator(_fixed_yaw_model(yaw))
        for pts, ego in _drive(speed):
            e = est.step(["v"], [pts], ego_poses=[ego])[0]
            assert not e.flipped and e.pose[3] == pytest.approx(wrap(yaw))


def test_static_sensor_uses_sensor_frame_motion():
    from seqshape.model import HeadingConfig

    rng = np.random.default_rng(6)
    frames = [_car(rng, 50, 4.4, (10.0 + t, 3.0, -0.5)) for t in range(5)]  # drives along +x
    est = Estimator(_fixed_yaw_model(np.pi), heading=HeadingConfig(static_sensor=True))
    out = [est.step(["v"], [p])[0] for p in frames]
    assert [e.flipped for e in out] == [False, False, True, True, True]
    assert out[-1].pose[3] == pytest.approx(0.0, abs=1e-6)


def _yaw_pose(yaw):
    t = np.eye(4)
    t[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    return t


def test_heading_vote_and_motion_line():
    from seqshape.model.heading import HeadingConfig, HeadingFilter, motion_direction

    yaws = [0.1, 0.1, 0.1, 0.1 + np.pi, 0.1, 0.1]
    flt = HeadingFilter(HeadingConfig(vote_fixed_only=False))  # the sensor frame votes too
    flips = [flt.update(np.array([5.0, 0, 0, y]), None, True) for y in yaws]
    assert flips == [False, False, False, True, False, False]
    # by default the vote needs a fixed frame: nothing without ego poses ...
    flt = HeadingFilter(HeadingConfig())
    assert [flt.update(np.array([5.0, 0, 0, y]), None, True) for y in yaws] == [False] * 6
    # ... and, with them, votes in the fixed frame: the ego turned by 90 degrees between
    # frames 2 and 3, so a parked car's sensor-frame yaw falls by 90 degrees there (the car
    # sits at the sensor's origin, so that turning the ego does not move it)
    ego = [np.eye(4)] * 3 + [_yaw_pose(np.pi / 2)] * 3
    sensor_yaws = [0.1, 0.1, 0.1, 0.1 - np.pi / 2 + np.pi, 0.1 - np.pi / 2, 0.1 - np.pi / 2]
    flt = HeadingFilter(HeadingConfig())
    assert [flt.update(np.array([0.0, 0, 0, y]), e, True)
            for y, e in zip(sensor_yaws, ego, strict=True)] == [False, False, False, True,
                                                                False, False]
    assert not HeadingConfig().active_without_poses
    assert HeadingConfig(vote_fixed_only=False).active_without_poses
    assert not HeadingFilter(HeadingConfig(vote=False)).update(
        np.array([5.0, 0, 0, 3.0]), np.eye(4), True)
    line = np.c_[np.arange(6) * 0.5, np.arange(6) * -0.5]
    assert motion_direction(line, 1.5, 0.8) == pytest.approx(-np.pi / 4)
    assert motion_direction(line[:3], 1.5, 0.8) is None  # 1.41 m: not enough travel
    jitter = np.random.default_rng(0).normal(scale=1.0, size=(10, 2))
    assert motion_direction(jitter, 1.5, 0.8) is None


def test_bad_ego_pose_is_a_clear_error():
    est = Estimator(_model())
    with pytest.raises(ConfigError, match="ego_poses"):
        est.step(["a"], [np.zeros((3, 3), np.float32)], ego_poses=[np.eye(3)])


def test_points_length_matches_numpy_percentiles():
    rng = np.random.default_rng(7)
    angles = np.arange(8) * np.pi / 8
    for n in (2, 3, 17, 256):
        p = rng.normal(size=(n, 3)).astype(np.float32) * [5.0, 1.0, 1.0]
        proj = p[:, :2] @ np.stack([np.cos(angles), np.sin(angles)])
        ref = np.percentile(proj, 99, axis=0) - np.percentile(proj, 1, axis=0)
        assert points_length(p) == pytest.approx(ref.max(), rel=1e-5)
    assert points_length(np.zeros((1, 3))) == 0.0


def test_points_lengths_equal_points_length_frame_by_frame():
    """The batched lengths of a step are the per-frame ones bit for bit: frames of 0-400
    points, float32 and float64, repeated points (ties in the sort), one batch of one frame."""
    rng = np.random.default_rng(3)
    for _ in range(100):
        frames = []
        for _ in range(int(rng.integers(1, 40))):
            n = int(rng.choice([0, 1, 2, 3, int(rng.integers(2, 400))]))
            f = rng.normal(size=(n, 3)) * rng.uniform(0.1, 5.0, 3) + rng.uniform(-50, 50, 3)
            if n > 3 and rng.random() < 0.3:
                f[: n // 2] = f[0]
            frames.append(f.astype(np.float32) if rng.random() < 0.5 else f)
        expected = np.array([points_length(f) for f in frames])
        np.testing.assert_array_equal(points_lengths(frames), expected)
    assert points_lengths([]).shape == (0,)


# ------------------------------------------------------------- issue 18: estimator semantics
BACKENDS = ["torch", "torch-lean", "onnx"]


def _backend(name: str) -> str:
    if name == "onnx":
        pytest.importorskip("onnxruntime")
        pytest.importorskip("onnx")
    return name


def _box_cloud(rng, n, centre=(12.0, -3.0, -0.8)):
    return (rng.uniform(-0.5, 0.5, (n, 3)) * [4.4, 1.8, 1.4] + centre).astype(np.float32)


@pytest.mark.parametrize("backend", BACKENDS)
def test_estimates_are_not_valid_until_a_track_has_points(backend):
    est = Estimator(_model(), backend=_backend(backend))
    rng = np.random.default_rng(11)
    empty = np.zeros((0, 3), np.float32)
    flags = []
    for k in range(5):
        a = [empty, [], _box_cloud(rng, 30), empty, _box_cloud(rng, 20)][k]
        out = est.step(["a", "b"], [a, _box_cloud(rng, 25, (8.0, 4.0, -0.8))])
        flags.append((out[0].valid, out[1].valid))
        assert all(np.all(np.isfinite(o.complete)) and np.all(np.isfinite(o.pose)) for o in out)
    assert flags == [(False, True), (False, True), (True, True), (True, True), (True, True)]
    est.reset("a")  # a reset track is new again
    assert [o.valid for o in est.step(["a", "b"], [empty, empty])] == [False, True]


def test_an_estimate_without_a_finite_pose_is_not_valid():
    from seqshape.model.estimator import Estimate

    assert not Estimate("a", np.zeros((0, 3), np.float32), np.full(4, np.nan), 0).valid
    assert Estimate("a", np.zeros((5, 3), np.float32), np.zeros(4), 5).valid


def test_an_empty_list_is_zero_points():
    rng = np.random.default_rng(12)
    pts = _box_cloud(rng, 30)
    outs = []
    for empty in ([], np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3), np.int32)):
        est = Estimator(_model())
        first = est.step(["a"], [empty])[0]
        assert first.num_points == 0 and not first.valid
        outs.append((first, est.step(["a"], [pts])[0]))
    for first, second in outs[1:]:
        for a, b in ((first, outs[0][0]), (second, outs[0][1])):
            assert np.array_equal(a.complete, b.complete) and np.array_equal(a.pose, b.pose)


@pytest.mark.parametrize(("points", "message"), [
    (np.ones((4, 3), bool), "dtype bool \\(booleans\\)"),
    (np.ones((4, 3), complex), "dtype complex128 \\(complex numbers\\)"),
    (np.full((4, 3), "1.0"), "dtype <U3 \\(strings\\)"),
    (np.array([[1.0, 2.0, None]]), "dtype object \\(Python objects\\)"),
    (None, "dtype object"),
    ([[1.0, 2.0, 3.0], [1.0, 2.0]], "not an \\(N, 3\\) array"),
    (np.ones((4, 2)), "shape \\(N, 3\\), got \\(4, 2\\)"),
    ([[]], "shape \\(N, 3\\), got \\(1, 0\\)"),
    (np.ones(3), "shape \\(N, 3\\), got \\(3,\\)"),
    (np.array([[800.0, 700.0, 0.0]]), "point 0 at \\(800.0, 700.0, 0.0\\) is more than 1000 m"),
    (np.array([[5.0, 0, 0], [0, 0, -1e300]]), "point 1 .* more than 1000 m"),
    (np.array([[5, 0, 0], [2 ** 40, 0, 0]], np.int64), "point 1 .* more than 1000 m"),
])
def test_refused_points_name_the_track_and_change_no_state(points, message):
    est = Estimator(_model())
    good = _box_cloud(np.random.default_rng(13), 20)
    with pytest.raises(ConfigError, match=f"point_lists\\[1\\] \\(track 'car9'\\): .*{message}"):
        est.step(["car7", "car9"], [good, points])
    assert est.track_ids == []  # the good track of the refused step did not advance either
    fresh = Estimator(_model())
    a, b = est.step(["car7"], [good])[0], fresh.step(["car7"], [good])[0]
    assert np.array_equal(a.complete, b.complete)


def test_refused_hints_change_no_state():
    est = Estimator(_model())
    good = _box_cloud(np.random.default_rng(14), 20)
    with pytest.raises(ConfigError, match="timestamps\\[1\\]"):
        est.step(["a", "b"], [good, good], timestamps=[0.0, "noon"])
    assert est.track_ids == []


def test_numbers_of_any_real_dtype_within_range_are_accepted():
    rng = np.random.default_rng(15)
    ints = rng.integers(-30, 30, size=(40, 3))
    ref = Estimator(_model()).step(["a"], [ints.astype(np.float32)])[0]
    for pts in (ints, ints.astype(np.uint8) if ints.min() >= 0 else ints.astype(np.int16),
                ints.astype(np.float16), ints.tolist()):
        out = Estimator(_model()).step(["a"], [pts])[0]
        assert np.array_equal(out.complete, ref.complete) and np.array_equal(out.pose, ref.pose)
    far = np.array([[999.0, 0.0, 0.0], [0.0, -700.0, 700.0]])  # 999 m and 989.9 m: accepted
    assert Estimator(_model()).step(["a"], [far])[0].num_points == 2


@pytest.mark.parametrize("recurrent", [True, False])
def test_valid_outputs_are_the_network_step_by_step_bit_for_bit(recurrent):
    """The reference backend's estimates on a normal track (float32 and float64 input, an
    empty frame in the middle) are the network's own forward pass, one frame at a time with
    the state carried, exactly."""
    model = _model(recurrent)
    rng = np.random.default_rng(16)
    frames = [_box_cloud(rng, n, (10.0 + 0.5 * t, 2.0, -0.8))
              for t, n in enumerate([30, 64, 0, 5, 50])]
    est32, est64 = Estimator(model), Estimator(model)
    hidden, mean = torch.zeros(1, model.state_size), torch.zeros(1, 3)
    seen = torch.zeros(1, dtype=torch.bool)
    for f in frames:
        n = max(1, len(f))
        batch = np.zeros((1, 1, n, 3), np.float32)
        batch[0, 0, :len(f)] = f
        with torch.inference_mode():
            ref = model(torch.from_numpy(batch), torch.tensor([[len(f)]]), hidden, mean, seen)
        hidden, mean, seen = ref["hidden"], ref["mean"], ref["seen"][:, 0]
        a = est32.step(["t"], [f])[0]
        b = est64.step(["t"], [f.astype(np.float64)])[0]
        for out in (a, b):
            assert out.valid
            np.testing.assert_array_equal(out.complete, ref["complete"][0, 0].numpy())
            np.testing.assert_array_equal(out.pose, ref["pose"][0, 0].double().numpy())


@pytest.mark.parametrize("recurrent", [True, False])
def test_max_points_equals_a_model_trained_for_that_many(recurrent, tmp_path):
    """``max_points=N`` cuts every frame to at most N points: step by step the very estimates
    of the same weights saved with ``num_points=N`` (the option is only the input cut), and
    the whole-track path cuts alike."""
    import dataclasses

    from seqshape.model.offline import estimate_track

    model = _model(recurrent)
    cut = ShapePoseNet(dataclasses.replace(TINY, num_points=16), recurrent=recurrent)
    cut.load_state_dict(model.state_dict())
    frames = _frames(np.random.default_rng(3), 3, 4)
    ids = ["a", "b", "c"]
    opt, ref = Estimator(model, max_points=16), Estimator(cut)
    assert (opt.max_points, Estimator(_model(recurrent)).max_points) == (16, TINY.num_points)
    for pts in frames:
        for a, b, p in zip(opt.step(ids, pts), ref.step(ids, pts), pts, strict=True):
            assert a.num_points == b.num_points == min(len(p), 16)
            assert np.array_equal(a.complete, b.complete) and np.array_equal(a.pose, b.pose)
    track = [f[0] for f in frames]
    whole = estimate_track(Estimator(_model(recurrent), max_points=16), track, mode="online",
                           track_id="a")
    again = Estimator(_model(recurrent), max_points=16)
    for t, p in enumerate(track):
        (e,) = again.step(["a"], [p])
        np.testing.assert_allclose(whole[t].pose, e.pose, atol=1e-5)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ConfigError, match="max_points"):
            Estimator(_model(recurrent), max_points=bad)
