"""The placement refiner (seqshape.model.placement): its inputs and targets on hand-made
cases, the corrections' algebra, the rigid move of the shape, file round trip and errors, and
one refinement in the streaming and the whole-track paths."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _model_data import box_track, write_checkpoint

torch = pytest.importorskip("torch")

from seqshape.errors import ConfigError, DataError  # noqa: E402
from seqshape.geometry import sensor_to_canonical  # noqa: E402
from seqshape.model import Estimator, ModelConfig, ShapePoseNet  # noqa: E402
from seqshape.model import placement as P  # noqa: E402
from seqshape.model.offline import estimate_track  # noqa: E402

CFG = ModelConfig(num_points=32, encoder1=(16, 32), encoder2=(32, 32), hidden=24,
                  shape_decoder=(32,), pose_decoder=(32,), num_complete=64,
                  shape_frame="canonical")


def _shift_refiner(dx=0.5, dy=-0.2, dz=0.0, dyaw=0.1, random_head=False):
    """A refiner whose correction is a constant (the head's last bias), optionally plus a
    data-dependent part (random last-layer weights)."""
    torch.manual_seed(0)
    net = P.build_net(16)
    with torch.no_grad():
        net.head[-1].bias.copy_(torch.tensor([dx, dy, dz, dyaw]))
        if random_head:
            net.head[-1].weight.normal_(0, 0.05)
    return P.PlacementRefiner(net)


def test_refine_inputs_hand_case():
    pose = np.array([10.0, 0.0, -1.0, math.pi / 2])  # heading +y
    pts = np.array([[10.0, 1.0, -1.0], [9.0, 0.0, -0.5]])  # 1 m ahead; 1 m to the right
    xyz, count, cond, s = P.refine_inputs(pts, pose, (4.0, 1.8, 1.5), np.random.default_rng(0),
                                          n=5)
    assert count == 2 and s == 1.0 and xyz.shape == (5, 3)
    np.testing.assert_allclose(xyz[0], [1.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(xyz[1], [0.0, 1.0, 0.5], atol=1e-6)
    np.testing.assert_array_equal(xyz[2:], xyz[[0, 1, 0]])  # cyclic padding
    # the sensor (origin) seen from the box: 10 m along -x of the world = box +y... (-10, 0)
    # in the world is (0, +10) in a frame turned by +90 degrees: direction (0, 1)
    np.testing.assert_allclose(cond[3:5], [0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(cond[:3], [4.0, 1.8, 1.5], atol=1e-6)
    assert cond[5] == pytest.approx(math.log1p(10.0) / 4)
    assert cond[6] == pytest.approx(math.log1p(2) / 7)


def test_refine_inputs_scales_long_vehicles_and_subsets_many_points():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(1000, 3)) + [20, 0, 0]
    xyz, count, cond, s = P.refine_inputs(pts, [20, 0, 0, 0], (9.0, 2.5, 3.0), rng, n=64)
    assert s == pytest.approx(2.0) and count == 64
    np.testing.assert_allclose(cond[:3], [4.5, 1.25, 1.5], atol=1e-6)
    from scipy.spatial import cKDTree
    d, _ = cKDTree(pts).query(xyz.astype(np.float64) * 2 + [20, 0, 0])
    assert d.max() < 1e-5  # each fed point is one of the frame's


def test_targets_hand_cases():
    est = np.array([[0.0, 0.0, 0.0, math.pi / 2]])
    true = np.array([[0.0, 1.0, 0.2, math.pi / 2 + 0.1]])
    np.testing.assert_allclose(P.targets(est, true), [[1.0, 0.0, 0.2, 0.1]], atol=1e-12)
    flipped = true.copy()
    flipped[0, 3] += math.pi  # the axis correction ignores which end is the front
    np.testing.assert_allclose(P.targets(est, flipped), [[1.0, 0.0, 0.2, 0.1]], atol=1e-12)


def test_delta_round_trip():
    rng = np.random.default_rng(3)
    old = np.c_[rng.normal(0, 10, (20, 3)), rng.uniform(-4, 4, 20)]
    new = old + np.c_[rng.normal(0, 0.5, (20, 3)), rng.normal(0, 0.2, 20)]
    d = P.delta(old, new)
    for i in range(20):
        np.testing.assert_allclose(P.apply_delta(old[i], d[i]), new[i], atol=1e-12)
    np.testing.assert_allclose(P.targets(old, new)[:, :3], d[:, :3], atol=1e-12)


def test_untrained_refiner_is_the_identity():
    ref = P.PlacementRefiner(P.build_net())
    rng = np.random.default_rng(0)
    poses = np.array([[12.0, -3.0, -0.9, 0.3], [25.0, 5.0, -1.0, -2.0]])
    complete = rng.normal(size=(2, 50, 3)).astype(np.float32) + poses[:, None, :3]
    frames = [rng.normal(size=(40, 3)) + poses[0, :3], np.zeros((0, 3))]
    c, p, last = ref.refine_sequence(frames, complete, poses)
    np.testing.assert_array_equal(p, poses)
    np.testing.assert_array_equal(c, complete)
    np.testing.assert_array_equal(last, 0.0)


def test_correction_moves_pose_along_its_axes_and_shape_rigidly():
    ref = _shift_refiner(dx=0.5, dy=-0.2, dz=0.1, dyaw=0.1)
    ref.config = P.RefinerConfig(iterations=1)  # one pass, also for the 9 m vehicle below
    pose = np.array([[10.0, 4.0, -1.0, math.pi / 2]])
    canon = np.random.default_rng(1).uniform(-1, 1, size=(200, 3)) * [2, 0.9, 0.7]  # 4 m
    from seqshape.geometry import canonical_to_sensor
    complete = canonical_to_sensor(canon, pose[0])[None].astype(np.float32)
    frames = [canonical_to_sensor(canon[:10], pose[0])]
    c, p, last = ref.refine_sequence(frames, complete, pose)
    # heading +y: 0.5 m ahead is +y, 0.2 m to the right is +x
    np.testing.assert_allclose(p[0], [10.2, 4.5, -0.9, math.pi / 2 + 0.1], atol=1e-5)
    np.testing.assert_allclose(sensor_to_canonical(c[0], p[0]), canon, atol=1e-5)
    np.testing.assert_allclose(last, [0.5, -0.2, 0.1, 0.1, 0.0, 0.0], atol=1e-5)
    # a vehicle twice as long as SCALE_REF: the shift is in units of the input scale
    long = canonical_to_sensor(canon * [2 * P.SCALE_REF / 4.0, 1, 1], pose[0])
    _, p2, _ = ref.refine_sequence(frames, long[None].astype(np.float32), pose)
    s = P.scale_of(P.extents_of(long, pose[0])[0])
    assert 1.9 < s < 2.1
    np.testing.assert_allclose(p2[0], [10.0 + 0.2 * s, 4.0 + 0.5 * s, -1.0 + 0.1 * s,
                                       math.pi / 2 + 0.1], atol=1e-5)


def test_corrections_are_clipped_and_sparse_frames_left_alone():
    ref = _shift_refiner(dx=5.0, dy=0.0, dz=0.0, dyaw=1.0)
    ref.config = P.RefinerConfig(min_points=5)
    pose = np.array([[10.0, 0.0, 0.0, 0.0], [10.0, 0.0, 0.0, 0.0]])
    frames = [np.full((8, 3), [10.0, 0, 0]), np.full((3, 3), [10.0, 0, 0])]
    _, p, _ = ref.refine_sequence(frames, np.zeros((2, 4, 3), np.float32), pose)
    np.testing.assert_allclose(p[0], [11.5, 0.0, 0.0, 0.35], atol=1e-6)
    np.testing.assert_array_equal(p[1], pose[1])


def test_further_passes_only_where_the_last_one_moved_far_enough():
    """A constant 0.5 m forward correction (0.5 m x s for a long vehicle), three passes at
    most, again only where the previous pass moved the centre >= 0.3 m with >= 6 points."""
    ref = _shift_refiner(dx=0.5, dy=0.0, dz=0.0, dyaw=0.0)
    ref.config = P.RefinerConfig(iterations=3, repeat_shift=0.3, repeat_min_points=6,
                                 repeat_min_length=0.0)
    poses = np.array([[10.0, 0, 0, 0], [10.0, 0, 0, 0], [10.0, 0, 0, 0]])
    frames = [np.full((8, 3), [10.0, 0, 0]), np.full((4, 3), [10.0, 0, 0]),
              np.full((8, 3), [10.0, 0, 0])]
    extents = np.array([[4.0, 1.8, 1.5], [4.0, 1.8, 1.5], [4.0, 1.8, 1.5]])
    p = ref.refine_poses(frames, poses, extents)
    np.testing.assert_allclose(p[:, 0], [11.5, 10.5, 11.5], atol=1e-6)  # 4 points: one pass
    ref.config = P.RefinerConfig(iterations=3, repeat_shift=0.6, repeat_min_points=6,
                                 repeat_min_length=0.0)
    np.testing.assert_allclose(ref.refine_poses(frames, poses, extents)[:, 0],
                               [10.5, 10.5, 10.5], atol=1e-6)  # 0.5 m < 0.6 m: converged
    # repeat_shift 0, repeat_min_points 1: every pass on every frame, as passes applied one
    # after the other with their seeds
    ref2 = _shift_refiner(dx=0.5, dy=0.0, dz=0.0, dyaw=0.0, random_head=True)
    ref2.config = P.RefinerConfig(iterations=2, repeat_shift=0.0, repeat_min_points=1,
                                  repeat_min_length=0.0)
    both = ref2.refine_poses(frames, poses, extents, seeds=[4, 5, 6])
    step = poses.copy()
    for it in range(2):
        ref2.config = P.RefinerConfig(iterations=1, repeat_min_length=0.0)
        ref2.seed = 1000003 * it
        step = ref2.refine_poses(frames, step, extents, seeds=[4, 5, 6])
    np.testing.assert_array_equal(both, step)
    # the defaults: three passes for an estimate of 6 m or more, one below
    ref.config = P.RefinerConfig()
    long = extents * [[1.0, 1, 1], [2.0, 1, 1], [1.5, 1, 1]]  # 4, 8 and 6 m
    frames8 = [np.full((8, 3), [10.0, 0, 0])] * 3
    moved = ref.refine_poses(frames8, poses, long)[:, 0] - poses[:, 0]
    s8, s6 = P.scale_of(8.0), P.scale_of(6.0)  # the correction is in units of the scale
    np.testing.assert_allclose(moved, [0.5, 3 * 0.5 * s8, 3 * 0.5 * s6], atol=1e-6)
    with pytest.raises(P.ConfigError, match="repeat_shift"):
        P.RefinerConfig(repeat_shift=-1.0)


def test_empty_frames_carry_the_last_correction():
    ref = _shift_refiner(dx=0.3, dy=0.0, dz=0.0, dyaw=0.0)
    poses = np.array([[10.0, 0, 0, 0], [11.0, 0, 0, 0], [12.0, 0, 0, math.pi / 2]])
    frames = [np.zeros((0, 3)), np.full((6, 3), [11.0, 0, 0]), np.zeros((0, 3))]
    _, p, _ = ref.refine_sequence(frames, np.zeros((3, 4, 3), np.float32), poses)
    np.testing.assert_array_equal(p[0], poses[0])  # before any refined frame: as it was
    np.testing.assert_allclose(p[1], [11.3, 0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(p[2], [12.0, 0.3, 0, math.pi / 2], atol=1e-6)


def test_file_round_trip_and_errors(tmp_path):
    ref = _shift_refiner(random_head=True)
    path = tmp_path / "refiner.pt"
    ref.save(path)
    back = P.PlacementRefiner.load(path)
    rng = np.random.default_rng(0)
    frames = [rng.normal(size=(20, 3)) + [8, 2, -1]]
    poses = np.array([[8.0, 2.0, -1.0, 0.4]])
    complete = rng.normal(size=(1, 16, 3)).astype(np.float32) + [8, 2, -1]
    np.testing.assert_array_equal(ref.refine_sequence(frames, complete, poses)[1],
                                  back.refine_sequence(frames, complete, poses)[1])
    assert P.load_refiner("none") is None
    with pytest.raises(DataError, match="no such refiner file"):
        P.load_refiner(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(DataError, match="bad.pt"):
        P.PlacementRefiner.load(bad)
    torch.save({"format": "something else"}, tmp_path / "other.pt")
    with pytest.raises(DataError, match="not a seqshape-placement-refiner file"):
        P.PlacementRefiner.load(tmp_path / "other.pt")


@pytest.mark.parametrize("recurrent", [True, False])
def test_streaming_and_whole_track_paths_refine_alike(recurrent):
    torch.manual_seed(0)
    est = Estimator(ShapePoseNet(CFG, recurrent=recurrent), threads=1)
    tr = box_track("t", "val", np.random.default_rng(1), 8, 3)  # frame 3 empty
    est.refiner = _shift_refiner(random_head=True)
    est.reset()
    stepped = [est.step(["t"], [p])[0] for p in tr.points]
    est.reset()
    whole = estimate_track(est, tr.points, mode="online", track_id="t")
    for a, b in zip(stepped, whole, strict=True):
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-5)
        np.testing.assert_allclose(a.complete, b.complete, atol=1e-5)
    est.refiner = None
    est.reset()
    plain = [est.step(["t"], [p])[0] for p in tr.points]
    moved = [np.linalg.norm(a.pose[:2] - b.pose[:2]) for a, b in zip(stepped, plain, strict=True)]
    assert min(moved) > 0.1  # every frame, the empty one too, carries a correction
    offline = estimate_track(est, tr.points, track_id="t")
    est.refiner = _shift_refiner(random_head=True)
    refined_offline = estimate_track(est, tr.points, track_id="t")
    assert all(np.linalg.norm(a.pose[:2] - b.pose[:2]) > 0.1
               for a, b in zip(offline, refined_offline, strict=True))


def test_numpy_forward_equals_the_module():
    ref = _shift_refiner(random_head=True)
    torch.manual_seed(1)
    with torch.no_grad():
        for p in ref.net.parameters():
            p.add_(0.1 * torch.randn_like(p))
    rng = np.random.default_rng(0)
    frames = [rng.normal(size=(k, 3)) * [2, 1, 0.7] + [15, -3, -1] for k in (1, 7, 300, 256)]
    poses = np.array([[15.0, -3.0, -1.0, 0.2 * i] for i in range(4)])
    ext = np.array([[4.2, 1.8, 1.5], [3.0, 1.6, 1.4], [9.0, 2.5, 3.2], [12.0, 2.6, 3.5]])
    fast = ref.corrections(frames, poses, ext, seeds=[0, 1, 2, 3])
    slow = ref.corrections(frames, poses, ext, seeds=[0, 1, 2, 3], reference=True)
    assert np.abs(slow).max() > 0.05  # a network that does something
    np.testing.assert_allclose(fast, slow, rtol=1e-4, atol=1e-5)


def test_batched_inputs_equal_the_single_frame_inputs():
    rng = np.random.default_rng(5)
    frames = [rng.normal(size=(k, 3)) * [2, 1, 0.7] + [12, 4, -1] for k in (1, 5, 256, 700)]
    poses = np.c_[np.full((4, 3), [12.0, 4.0, -1.0]) + rng.normal(0, 0.3, (4, 3)),
                  rng.uniform(-3, 3, 4)]
    ext = np.array([[4.0, 1.8, 1.5], [np.nan, 1.7, 1.4], [10.0, 2.5, 3.0], [5.0, 2.0, 1.6]])
    xyz, cond, scales = P.refine_inputs_batch(frames, poses, ext, seeds=[7, 8, 9, 10], n=256)
    for i in range(4):
        a, _, c, s = P.refine_inputs(frames[i], poses[i], ext[i],
                                     np.random.default_rng(7 + i), n=256)
        np.testing.assert_allclose(xyz[i], a, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(cond[i], c, rtol=1e-6, atol=1e-7)
        assert scales[i] == s


def test_batched_extents_and_moves_equal_the_single_frame_ones():
    rng = np.random.default_rng(2)
    clouds = rng.normal(size=(3, 100, 3)) * [2, 0.9, 0.7] + [10, -5, -1]
    old = np.c_[rng.normal(0, 5, (3, 3)), rng.uniform(-3, 3, 3)]
    new = old + np.c_[rng.normal(0, 0.4, (3, 3)), rng.normal(0, 0.2, 3)]
    ext = P.extents_batch(clouds, old)
    moved = P._move_batch(clouds, old, new)
    for i in range(3):
        np.testing.assert_allclose(ext[i], P.extents_of(clouds[i], old[i]), atol=1e-12)
        np.testing.assert_allclose(moved[i], P._move(clouds[i], old[i], new[i]), atol=1e-9)


def _checkpoint(path, kind):
    return write_checkpoint(path, kind, CFG)


def test_evaluate_with_a_refiner_file(tmp_path):
    import json

    from _model_data import make_dataset

    from seqshape.cli import main

    data = make_dataset(tmp_path / "ds", n_train=1, n_val=2, frames=5)
    seq, base = _checkpoint(tmp_path / "s.pt", "sequential"), _checkpoint(tmp_path / "b.pt",
                                                                          "baseline")
    _shift_refiner(dx=0.4).save(tmp_path / "r.pt")
    runs = {}
    for name, extra in (("plain", []), ("refined", ["--refiner", str(tmp_path / "r.pt")]),
                        ("none", ["--refiner", "none"]),
                        ("seq only", ["--refiner", str(tmp_path / "r.pt"),
                                      "--baseline-refiner", "none"])):
        out = tmp_path / name
        assert main(["evaluate", "--data", str(data.path), "--checkpoint", seq, "--baseline",
                     base, "--out", str(out), "--emd-every", "0", "--workers", "0", "--view",
                     "none", "--offline", *extra]) == 0
        runs[name] = json.loads((out / "metrics.json").read_text())
    assert runs["refined"]["settings"]["modes"] == {
        "sequential": "offline + placement refiner", "baseline": "online + placement refiner"}
    for m in ("sequential", "baseline"):  # every estimate moved 0.4 m along its axis
        assert runs["refined"][m]["trans_cm"] != runs["plain"][m]["trans_cm"]
        assert runs["refined"][m]["cd_cm"] != runs["plain"][m]["cd_cm"]
    # --baseline-refiner none: the baseline keeps its own placement, the sequential model not
    assert runs["seq only"]["settings"]["modes"] == {
        "sequential": "offline + placement refiner", "baseline": "online"}
    assert runs["seq only"]["baseline"]["trans_cm"] == runs["none"]["baseline"]["trans_cm"]
    assert runs["seq only"]["sequential"]["trans_cm"] == runs["refined"]["sequential"]["trans_cm"]
    assert main(["evaluate", "--data", str(data.path), "--checkpoint", seq, "--baseline", base,
                 "--out", str(tmp_path / "x"), "--refiner", str(tmp_path / "nope.pt")]) == 1


def test_a_steps_tracks_carry_their_own_corrections():
    """In one step of several tracks, an empty frame gets its own track's last correction,
    never another track's: a track without points yet is left as the network gives it."""
    torch.manual_seed(0)
    est = Estimator(ShapePoseNet(CFG), threads=1)
    tr = box_track("t", "val", np.random.default_rng(1), 3, None)
    plain = est.step(["a", "new"], [tr.points[0], np.zeros((0, 3))])
    est.reset()
    est.refiner = _shift_refiner(dx=0.5, dy=0.0, dz=0.0, dyaw=0.0)
    refined = est.step(["a", "new"], [tr.points[0], np.zeros((0, 3))])
    np.testing.assert_array_equal(refined[1].pose, plain[1].pose)  # no correction of its own
    np.testing.assert_array_equal(refined[1].complete, plain[1].complete)
    assert np.linalg.norm(refined[0].pose[:2] - plain[0].pose[:2]) == pytest.approx(0.5)
    # "a" empty next step: its carried estimate keeps a's correction
    est.refiner = None
    carried_plain = est.step(["a", "b"], [np.zeros((0, 3)), tr.points[1]])[0]
    est.reset()
    est.refiner = _shift_refiner(dx=0.5, dy=0.0, dz=0.0, dyaw=0.0)
    est.step(["a", "new"], [tr.points[0], np.zeros((0, 3))])
    carried = est.step(["a", "b"], [np.zeros((0, 3)), tr.points[1]])[0]
    assert np.linalg.norm(carried.pose[:2] - carried_plain.pose[:2]) == pytest.approx(0.5)


def test_points_option_sets_the_input_size():
    """``RefinerConfig.points``: a frame larger than it is read through a seeded subset of that
    many points, the same one :func:`refine_inputs` draws; a smaller frame is unchanged, as the
    max-pools see each real point whatever the padding."""
    ref = _shift_refiner(random_head=True)
    rng = np.random.default_rng(2)
    frames = [rng.normal(size=(k, 3)) * [2, 1, 0.7] + [15, -3, -1] for k in (20, 300)]
    poses = np.array([[15.0, -3.0, -1.0, 0.3], [15.0, -3.0, -1.0, -0.4]])
    ext = np.array([[4.2, 1.8, 1.5], [4.6, 1.9, 1.5]])
    wide = ref.corrections(frames, poses, ext, seeds=[0, 1])
    ref.config = P.RefinerConfig(points=64)
    narrow = ref.corrections(frames, poses, ext, seeds=[0, 1])
    np.testing.assert_allclose(narrow[0], wide[0], rtol=1e-5, atol=1e-6)  # 20 points: as before
    assert np.abs(narrow[1] - wide[1]).max() > 1e-4  # 300 points: another subset, another answer
    for i in range(2):
        xyz, _, cond, s = P.refine_inputs(frames[i], poses[i], ext[i], np.random.default_rng(i),
                                          n=64)
        out = ref.forward(xyz[None], cond[None])[0].astype(np.float64)
        out[:3] *= s
        np.testing.assert_allclose(narrow[i], out, rtol=1e-5, atol=1e-6)
    with pytest.raises(ConfigError, match="points"):
        P.RefinerConfig(points=0)


def test_percentiles_1_99_equal_numpys_bit_for_bit():
    rng = np.random.default_rng(3)
    for k in (2, 3, 7, 100, 101, 1024, 2048):
        for q in (rng.normal(size=(3, k, 3)) * 5, np.round(rng.normal(size=(2, k, 3)), 1)):
            lo, hi = P.percentiles_1_99(q)
            ref_lo, ref_hi = np.percentile(q, [1, 99], axis=1)
            assert np.array_equal(lo, ref_lo) and np.array_equal(hi, ref_hi)
    q = rng.normal(size=(2, 50, 3))
    q[1, 4, 2] = np.nan  # numpy's own path: NaN where a column holds one
    lo, _ = P.percentiles_1_99(q)
    assert np.isnan(lo[1, 2]) and np.isfinite(lo[0]).all()


@pytest.mark.parametrize("backend", ["torch-lean", "onnx"])
def test_engine_refiner_equals_the_module(backend):
    if backend == "onnx":
        pytest.importorskip("onnxruntime")
        pytest.importorskip("onnx")
    ref = _shift_refiner(random_head=True)
    torch.manual_seed(2)
    with torch.no_grad():
        for p in ref.net.parameters():
            p.add_(0.1 * torch.randn_like(p))
    torch.manual_seed(0)
    est = Estimator(ShapePoseNet(CFG), threads=1, backend=backend, refiner=ref)
    run = est._refiner_run()
    assert run is not None
    rng = np.random.default_rng(4)
    for b, n in ((1, 256), (1, 1), (7, 64), (40, 256)):  # 40 x 256 rows: the two-thread pass
        xyz = rng.normal(size=(b, n, 3)).astype(np.float32)
        cond = rng.normal(size=(b, len(P.COND_FIELDS))).astype(np.float32)
        with torch.no_grad():
            slow = ref.net(torch.from_numpy(xyz), torch.from_numpy(cond)).numpy()
        np.testing.assert_allclose(run(xyz, cond), slow, rtol=1e-4, atol=1e-5)


def test_refined_steps_agree_across_backends():
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from seqshape.model.engine import TOLERANCE

    torch.manual_seed(0)
    model = ShapePoseNet(CFG)
    tracks = [box_track(f"t{i}", "val", np.random.default_rng(10 + i), 5, 2) for i in range(6)]
    out = {}
    for backend in ("torch", "onnx"):
        est = Estimator(model, threads=1, backend=backend, refiner=_shift_refiner(random_head=True))
        assert (est._refiner_run() is None) == (backend == "torch")
        out[backend] = [est.step([t.track_id for t in tracks], [t.points[k] for t in tracks])
                        for k in range(5)]
    for a_step, b_step in zip(out["torch"], out["onnx"], strict=True):
        for a, b in zip(a_step, b_step, strict=True):
            np.testing.assert_allclose(b.pose[:3], a.pose[:3], atol=TOLERANCE[1] * 5)
            np.testing.assert_allclose(b.complete, a.complete, atol=TOLERANCE[0])


def test_size_corrections_stretch_the_shape_about_its_centre():
    rng = np.random.default_rng(0)
    canon = rng.uniform(-1, 1, size=(400, 3)) * [2.2, 0.9, 0.7]
    pose = np.array([10.0, 4.0, -0.9, 0.6])
    placed = P._move(canon, np.zeros(4), pose)[None].astype(np.float32)
    corr = np.array([[0.2, -0.1, 0.0, 0.05, math.log(1.1), math.log(0.9)]])
    c, p = P.apply_corrections(placed, pose[None], corr)
    np.testing.assert_allclose(p[0], P.apply_delta(pose, corr[0]), atol=1e-12)
    q = sensor_to_canonical(c[0], p[0])
    np.testing.assert_allclose(q, canon * [1.1, 0.9, 1.0], atol=1e-4)  # float32 shape
    ext = P.extents_of(c[0], p[0]) / P.extents_of(placed[0], pose)
    np.testing.assert_allclose(ext, [1.1, 0.9, 1.0], rtol=1e-4)
    same = P.apply_corrections(placed, pose[None], np.r_[corr[0, :4], 0, 0][None])
    moved = P.apply_corrections(placed, pose[None], corr[:, :4])
    assert np.array_equal(same[0], moved[0])  # zero size columns: the rigid move, bit for bit


def test_size_head_is_applied_once_clipped_and_can_be_turned_off():
    torch.manual_seed(0)
    net = P.build_net(16, outputs=6)
    with torch.no_grad():
        net.head[-1].bias.copy_(torch.tensor([0.1, 0.0, 0.0, 0.0, 0.05, 0.9]))
    frames = [np.random.default_rng(1).normal(size=(50, 3)) + [12, 0, -1]]
    pose = np.array([[12.0, 0.0, -1.0, 0.0]])
    ext = np.array([[7.0, 2.5, 3.0]])  # 6 m and more: three passes
    poses, sizes = P.PlacementRefiner(net, P.RefinerConfig(size_width=True)).refine(frames, pose,
                                                                                      ext)
    np.testing.assert_allclose(sizes, [[0.05, 0.3]])  # the first pass's, clipped to max_resize
    default = P.PlacementRefiner(net).refine(frames, pose, ext)
    np.testing.assert_allclose(default[1], [[0.05, 0.0]])  # by default the length only
    np.testing.assert_array_equal(default[0], poses)
    assert poses[0, 0] > 12.0 + 0.25  # the pose took every pass
    off = P.PlacementRefiner(net, P.RefinerConfig(size=False)).refine(frames, pose, ext)[1]
    assert np.all(off == 0)
    old = P.PlacementRefiner(P.build_net(16))  # no size head: zero size columns
    assert np.all(old.corrections_of(frames, np.zeros((1, 10, 3)) + [12, 0, -1], pose)[:, 4:] == 0)


def test_size_head_file_round_trip_and_engine(tmp_path):
    torch.manual_seed(3)
    ref = P.PlacementRefiner(P.build_net(16, outputs=6))
    with torch.no_grad():
        for p in ref.net.parameters():
            p.add_(0.1 * torch.randn_like(p))
    ref.save(tmp_path / "r.pt")
    back = P.PlacementRefiner.load(tmp_path / "r.pt")
    assert back.net.outputs == 6
    xyz = np.random.default_rng(0).normal(size=(3, 40, 3)).astype(np.float32)
    cond = np.random.default_rng(1).normal(size=(3, len(P.COND_FIELDS))).astype(np.float32)
    np.testing.assert_allclose(back.forward(xyz, cond), ref.forward(xyz, cond), rtol=1e-6)
    est = Estimator(ShapePoseNet(CFG), threads=1, backend="torch-lean", refiner=back)
    np.testing.assert_allclose(est._refiner_run()(xyz, cond), ref.forward(xyz, cond),
                               rtol=1e-4, atol=1e-5)
    with pytest.raises(ConfigError, match="4 or 6 outputs"):
        P.build_net(16, outputs=5)
