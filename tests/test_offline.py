"""Offline (whole-track) estimation on a tiny random network: its relation to the online
estimator, the two passes, the whole-track heading, ``evaluate --offline`` and the labeller."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from _model_data import box_track, make_dataset, write_checkpoint

torch = pytest.importorskip("torch")

from seqshape.errors import ConfigError  # noqa: E402
from seqshape.geometry import sensor_to_canonical, wrap_angle  # noqa: E402
from seqshape.model import Estimator, ModelConfig, ShapePoseNet  # noqa: E402
from seqshape.model.offline import (  # noqa: E402
    OfflineConfig,
    OfflineEstimator,
    chunk_tracks,
    consistent_flips,
    estimate_track,
    estimate_tracks,
)

CFG = ModelConfig(num_points=32, encoder1=(16, 32), encoder2=(32, 32), hidden=24,
                  shape_decoder=(32,), pose_decoder=(32,), num_complete=64,
                  shape_frame="canonical")


def _estimator(recurrent=True, seed=0, cfg=CFG) -> Estimator:
    torch.manual_seed(seed)
    return Estimator(ShapePoseNet(cfg, recurrent=recurrent), threads=1)


def _track(frames=8, empty=3, seed=1):
    """Points per frame (frame ``empty`` has none; some frames have more than N = 32 points)
    and identity-free ego poses (a sensor driving and turning)."""
    tr = box_track("t", "val", np.random.default_rng(seed), frames, empty)
    egos = []
    for k in range(frames):
        e = np.eye(4)
        c, s = math.cos(0.05 * k), math.sin(0.05 * k)
        e[:2, :2] = [[c, -s], [s, c]]
        e[:3, 3] = [1.5 * k, 0.2 * k, 0.0]
        egos.append(e)
    return tr.points, egos


def _step_all(est, points, egos=None, times=None):
    est.reset()
    out = [est.step(["t"], [p], ego_poses=None if egos is None else [egos[k]],
                    timestamps=None if times is None else [times[k]])[0]
           for k, p in enumerate(points)]
    est.reset()
    return out


def _close(a, b, atol=1e-5):
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x.pose, y.pose, atol=atol)
        np.testing.assert_allclose(x.complete, y.complete, atol=atol)
        assert x.flipped == y.flipped and x.num_points == y.num_points


@pytest.mark.parametrize("motion", [False, True])
def test_online_mode_equals_stepping_frame_by_frame(motion):
    cfg = ModelConfig(**{**CFG.to_dict(), "motion_input": motion})
    est = _estimator(cfg=cfg)
    if motion:  # the motion columns start at zero: make them count
        with torch.no_grad():
            for p in est.model.parameters():
                p.add_(0.05 * torch.randn_like(p))
    points, egos = _track()
    times = 100.0 + 0.1 * np.arange(len(points)) + 0.02 * (np.arange(len(points)) == 5)
    assert max(len(p) for p in points) > CFG.num_points  # exercises the random subsets
    timed = estimate_track(est, points, ego_poses=egos, timestamps=times, mode="online",
                           track_id="t")
    _close(timed, _step_all(est, points, egos, times))
    untimed = estimate_track(est, points, mode="online", track_id="t")
    _close(untimed, _step_all(est, points))
    if motion:  # the time steps reached the network
        assert not np.allclose(timed[6].complete, untimed[6].complete, atol=1e-5)


CONFIGS = [OfflineConfig(),
           OfflineConfig(shape="two-pass", pose="two-pass", smooth=False, heading=False),
           OfflineConfig(shape="final", pose="online", smooth=False),
           OfflineConfig(shape="bidirectional", pose="bidirectional"),
           OfflineConfig(shape="final", pose="two-pass", heading=False),
           OfflineConfig(shape="average", shape_decay=1.0)]


@pytest.mark.parametrize("cfg", CONFIGS, ids=lambda c: c.name)
def test_offline_equals_online_on_one_frame(cfg):
    est = _estimator()
    points, egos = _track()
    online = _step_all(est, points[:1], egos[:1])
    _close(estimate_track(est, points[:1], ego_poses=egos[:1], config=cfg, track_id="t"),
           online)
    _close(estimate_track(est, points[:1], config=cfg, track_id="t"), _step_all(est, points[:1]))


def test_baseline_offline_is_its_online_estimate():
    est = _estimator(recurrent=False)
    points, egos = _track()
    _close(estimate_track(est, points, ego_poses=egos, track_id="t"),
           _step_all(est, points, egos))


def _manual(model, frames, hidden=None):
    """Frame-by-frame forward passes from ``hidden``: per-frame poses and the final state."""
    poses = []
    mean, seen = torch.zeros(1, 3), torch.zeros(1, dtype=torch.bool)
    h = torch.zeros(1, model.state_size) if hidden is None else hidden
    with torch.inference_mode():
        for f in frames:
            pts = torch.zeros(1, 1, max(len(f), 1), 3)
            if len(f):
                pts[0, 0] = torch.from_numpy(f)
            out = model(pts, torch.tensor([[len(f)]]), h, mean, seen)
            h, mean, seen = out["hidden"], out["mean"], out["seen"][:, -1]
            poses.append(out["pose"][0, 0].double().numpy())
    return np.array(poses), h


def test_two_pass_starts_every_frame_from_the_final_state():
    """By hand: pass 1 over the whole track from zeros, then pass 2 from its final state;
    frame t < last takes pass 2's estimate, frames from the last detection on pass 1's."""
    est = _estimator()
    points, _ = _track(frames=6, empty=5)  # the last frame is empty: last detection = 4
    points = [p[:20] for p in points]  # no random subsets: the hand check feeds them as is
    first, h_final = _manual(est.model, points)
    second, _ = _manual(est.model, points, h_final)
    cfg = OfflineConfig(shape="two-pass", pose="two-pass", smooth=False, heading=False)
    got = np.array([e.pose for e in estimate_track(est, points, config=cfg)])
    np.testing.assert_allclose(got[:4], second[:4], atol=1e-5)
    np.testing.assert_allclose(got[4:], first[4:], atol=1e-5)
    assert np.abs(second[:4] - first[:4]).max() > 1e-3  # the final state made a difference


def test_final_shape_is_the_last_detections_shape_in_every_frame():
    est = _estimator()
    points, egos = _track()
    cfg = OfflineConfig(shape="final", pose="online", smooth=False, heading=False)
    out = estimate_track(est, points, config=cfg, track_id="t")
    online = estimate_track(est, points, mode="online", track_id="t")
    ref = sensor_to_canonical(online[-1].complete, online[-1].pose)
    for e, o in zip(out, online, strict=True):
        np.testing.assert_allclose(e.pose, o.pose, atol=1e-6)
        np.testing.assert_allclose(sensor_to_canonical(e.complete, e.pose), ref, atol=1e-4)


def _in_sensor(world_xy, world_yaw, egos):
    """Poses (T, 4) in each frame's sensor frame from fixed-frame centres and yaws."""
    out = []
    for (x, y), yaw, e in zip(world_xy, world_yaw, egos, strict=True):
        inv = np.linalg.inv(e)
        c = inv[:3, :3] @ np.array([x, y, 0.0]) + inv[:3, 3]
        out.append([c[0], c[1], c[2], yaw - math.atan2(e[1, 0], e[0, 0])])
    return np.array(out)


def test_consistent_flips_on_a_reversed_track():
    """A vehicle driving towards -x in the fixed frame while the network says it faces +x
    (all but two frames): every frame but those two is flipped; the sensor moves and turns."""
    n = 14
    _, egos = _track(frames=n)
    world = np.c_[30.0 - 1.0 * np.arange(n), np.full(n, 4.0)]
    yaw = np.zeros(n)
    yaw[[4, 9]] = math.pi  # the two right ones
    poses = _in_sensor(world, yaw, egos)
    flips = consistent_flips(poses, egos, np.ones(n, bool))
    assert flips.tolist() == [k not in (4, 9) for k in range(n)]
    # the same track in time order reversed (now driving towards +x): only those two flip
    back = consistent_flips(_in_sensor(world[::-1], yaw, egos), egos, np.ones(n, bool))
    assert back.tolist() == [k in (4, 9) for k in range(n)]
    # no fixed frame, no evidence: nothing flips
    assert not consistent_flips(poses, None, np.ones(n, bool)).any()


def test_consistent_flips_of_a_parked_vehicle_follow_the_track_majority():
    n = 12
    _, egos = _track(frames=n)
    world = np.tile([[20.0, -5.0]], (n, 1))
    yaw = np.full(n, 0.3)
    yaw[[0, 1, 11]] += math.pi  # a minority, at both ends of the track
    has = np.ones(n, bool)
    has[6] = False  # an empty frame takes part in nothing but is still decided
    flips = consistent_flips(_in_sensor(world, yaw, egos), egos, has)
    assert flips.tolist() == [k in (0, 1, 11) for k in range(n)]


def test_offline_heading_flips_the_yaw_and_keeps_the_shape():
    est = _estimator()
    points, egos = _track()
    cfg = OfflineConfig(shape="online", smooth=False, heading=True)
    online = estimate_track(est, points, mode="online", track_id="t",
                            config=OfflineConfig(heading=False))
    out = estimate_track(est, points, ego_poses=egos, config=cfg, track_id="t")
    flips = consistent_flips(np.array([o.pose for o in online]), egos,
                             np.array([len(p) > 0 for p in points]), est.heading)
    for e, o, f in zip(out, online, flips, strict=True):
        assert e.flipped == f
        d = (e.pose[3] - o.pose[3] - (math.pi if f else 0.0) + math.pi) % (2 * math.pi)
        assert abs(d - math.pi) < 1e-9
        np.testing.assert_allclose(e.complete, o.complete, atol=1e-6)


def test_offline_smoothing_weighs_frames_as_configured():
    """With frame weights configured, the offline poses are the whole-track smoother of the
    online poses with :func:`frame_weights` of the points the network got (at most N per
    frame); by default the weights are equal (off, as measured)."""
    from seqshape.model.smooth import frame_weights, limit_shift, smooth_track_poses

    est = _estimator()
    points, egos = _track(frames=14, empty=6, seed=3)
    points = [p[:k] for p, k in zip(points, [40, 5, 9, 40, 12, 40, 0, 7, 40, 40, 3, 40, 20, 40],
                                    strict=True)]  # sparse frames among full ones
    online = estimate_track(est, points, mode="online", track_id="t")
    poses = np.array([o.pose for o in online])
    counts = np.array([min(len(p), est.max_points) for p in points])
    assert len(set(counts.tolist())) > 2  # the frames weigh differently
    got = {}
    for name, cfg_kw in (("weighted", {"full_points": 30, "ramp": 4}), ("default", {})):
        cfg = OfflineConfig(heading=False, **cfg_kw)
        got[name] = np.array([o.pose for o in estimate_track(est, points, ego_poses=egos,
                                                             config=cfg, track_id="t")])
        weights = frame_weights(counts, cfg.full_points, cfg.ramp)
        want = limit_shift(smooth_track_poses(poses, np.arange(14.0), np.stack(egos),
                                              weights=weights), poses, counts > 0)
        np.testing.assert_allclose(got[name], want, atol=1e-5)
    assert np.abs(got["weighted"][:, :2] - got["default"][:, :2]).max() > 1e-3
    plain = OfflineConfig(heading=False)
    assert plain.full_points is None and plain.ramp is None
    with pytest.raises(ConfigError, match="OfflineConfig ramp"):
        OfflineConfig(ramp=0)


def test_bad_arguments_are_config_errors():
    est = _estimator()
    points, egos = _track()
    with pytest.raises(ConfigError, match="mode"):
        estimate_track(est, points, mode="both")
    with pytest.raises(ConfigError, match="shape"):
        OfflineConfig(shape="mean")
    with pytest.raises(ConfigError, match="ego poses"):
        estimate_track(est, points, ego_poses=egos[:2])
    with pytest.raises(ConfigError, match="timestamps"):
        estimate_track(est, points, timestamps=[0.0])
    assert estimate_track(est, []) == []


def _checkpoint(path, kind):
    return write_checkpoint(path, kind, CFG)


def test_evaluate_offline_end_to_end(tmp_path):
    from seqshape.cli import main

    data = make_dataset(tmp_path / "ds", n_train=1, n_val=2, frames=6)
    seq, base = _checkpoint(tmp_path / "s.pt", "sequential"), _checkpoint(tmp_path / "b.pt",
                                                                          "baseline")
    runs = {}
    for flag in ([], ["--offline"]):
        out = tmp_path / ("off" if flag else "on")
        assert main(["evaluate", "--data", str(data.path), "--checkpoint", seq, "--baseline",
                     base, "--out", str(out), "--emd-every", "2", "--emd-points", "32",
                     "--workers", "0", "--view", "auto" if flag else "none", "--refiner", "none",
                     *flag]) == 0
        runs[bool(flag)] = json.loads((out / "metrics.json").read_text())
    assert (tmp_path / "off" / "track_view.html").stat().st_size > 0
    assert runs[True]["settings"]["modes"] == {"sequential": "offline", "baseline": "online"}
    assert runs[False]["settings"]["modes"]["sequential"] == "online"
    assert "Mode: sequential offline, baseline online" in (tmp_path / "off" /
                                                            "metrics.md").read_text()
    assert runs[True]["baseline"] == runs[False]["baseline"]  # the baseline is per frame
    assert runs[True]["sequential"] != runs[False]["sequential"]


def test_evaluate_causal_smoothing_moves_the_sequential_model_only(tmp_path, capsys):
    from seqshape.cli import main

    data = make_dataset(tmp_path / "ds", n_train=1, n_val=2, frames=9)
    seq, base = _checkpoint(tmp_path / "s.pt", "sequential"), _checkpoint(tmp_path / "b.pt",
                                                                          "baseline")
    common = ["evaluate", "--data", str(data.path), "--checkpoint", seq, "--baseline", base,
              "--emd-every", "0", "--workers", "0", "--view", "none", "--refiner", "none"]
    runs = {}
    for mode in ("none", "causal"):
        assert main([*common, "--out", str(tmp_path / mode), "--smoothing", mode]) == 0
        runs[mode] = json.loads((tmp_path / mode / "metrics.json").read_text())
    assert runs["causal"]["baseline"] == runs["none"]["baseline"]  # the baseline is per frame
    assert runs["causal"]["sequential"] != runs["none"]["sequential"]
    assert runs["causal"]["settings"]["modes"] == {"sequential": "online + causal smoothing",
                                                   "baseline": "online"}
    assert runs["none"]["settings"]["modes"]["sequential"] == "online"
    capsys.readouterr()
    assert main([*common, "--out", str(tmp_path / "x"), "--offline", "--smoothing",
                 "causal"]) == 1
    assert "--smoothing is for the online mode" in capsys.readouterr().err
    assert not (tmp_path / "x" / "metrics.json").exists()


def test_labeller_replays_the_offline_estimates():
    from seqshape.amodal.labeler import LabelConfig, offline_replay
    from seqshape.amodal.refine import TrackInput, complete_tracks

    assert LabelConfig().online is False
    est = _estimator()
    inputs = []
    for k in range(2):
        points, egos = _track(frames=5 + k, seed=k)
        inputs.append(TrackInput(f"v{k}", list(range(k, 5 + 2 * k)), points, ego=np.stack(egos)))
    for refine in ("none", "bidirectional"):
        got = complete_tracks(offline_replay(est, inputs), inputs, refine)
        for inp, comp in zip(inputs, got, strict=True):
            ref = estimate_track(est, inp.points, ego_poses=list(inp.ego),
                                 track_id=inp.track_id)
            np.testing.assert_allclose(comp.poses, [e.pose for e in ref])
            for c, e in zip(comp.clouds, ref, strict=True):
                np.testing.assert_array_equal(c, e.complete)


def test_offline_estimator_wraps_an_estimator():
    est = _estimator()
    off = OfflineEstimator(est, OfflineConfig(smooth=False))
    points, _ = _track()
    assert off.recurrent and off.kind == "sequential"
    _close(off.estimate_track(points, track_id="t"),
           estimate_track(est, points, config=OfflineConfig(smooth=False), track_id="t"))


def test_predict_track_passes_timestamps_to_a_step_that_takes_them():
    from seqshape.evaluation.runner import predict_track

    track = box_track("t", "val", np.random.default_rng(3), 5)
    seen = []

    class Timed:
        recurrent = True

        def reset(self, track_id=None):
            pass

        def step(self, track_ids, point_lists, timestamps=None):
            seen.append(timestamps)
            return [None] * len(track_ids)

    predict_track(Timed(), track)
    assert seen == [[t] for t in track.timestamps.tolist()]


def test_label_cli_flag_selects_online():
    import argparse

    from seqshape.scripts.label import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert parser.parse_args(["--sequence", "0"]).online is False
    assert parser.parse_args(["--sequence", "0", "--online"]).online is True


def _many_tracks(seed: int = 5) -> list[dict]:
    """Tracks of 1 to 12 frames (some over N points, one with an empty frame, one with only
    empty frames, one with none), with timestamps, hints and ego poses on some."""
    rng = np.random.default_rng(seed)
    out = []
    for i, n in enumerate([12, 1, 7, 12, 3, 9, 5]):
        tr = box_track(f"m{i}", "val", rng, n, 2 if i == 2 else None)
        item = {"points": tr.points} if i in (1, 5) else {"points": tr.points,
                                                         "track_id": tr.track_id}
        if i % 2 == 0:
            item["timestamps"] = 50.0 + tr.timestamps + 0.03 * (np.arange(n) % 2)
        if i % 3 == 0:
            item["size"] = tuple(tr.size)
        if i == 4:
            item["cls"] = "truck"
        if i == 3:
            item["ego_poses"] = _track(frames=n)[1]
        out.append(item)
    out.append({"points": [np.zeros((0, 3), np.float32)] * 4, "track_id": "blank"})
    out.append({"points": [], "track_id": "none"})
    return out


@pytest.mark.parametrize("mode,cfg", [("online", None)] + [("offline", c) for c in CONFIGS],
                         ids=lambda c: c if isinstance(c, str) else getattr(c, "name", "-"))
def test_estimate_tracks_equals_estimate_track_per_track(mode, cfg):
    """Batched passes (chunks of several tracks padded to the longest, a chunk bound that
    splits them) give each track what its own pass gives, to float rounding (1e-5 m / rad:
    the batched products may sum in another order; a wrong padding, state or time step moves
    estimates by centimetres); with every model option on, and the shipped default."""
    net_cfg = ModelConfig(**{**CFG.to_dict(), "motion_input": True, "scale_norm": "length",
                             "frame_skip": True})
    est = _estimator(cfg=net_cfg)
    with torch.no_grad():  # the zero-initialised extensions get weights, so they matter
        for p in est.model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    tracks = _many_tracks()
    for chunk in (24, 10_000):
        batched = estimate_tracks(est, tracks, mode=mode, config=cfg, chunk_frames=chunk)
        assert len(batched) == len(tracks)
        for tr, got in zip(tracks, batched, strict=True):
            own = estimate_track(est, mode=mode, config=cfg, **tr)
            ids = [tr.get("track_id", "track")] * len(tr["points"])  # two share the default
            assert [e.track_id for e in got] == ids
            _close(got, own)
            for a, b in zip(got, own, strict=True):
                assert a.scale == b.scale


def test_chunk_tracks_takes_each_track_once_longest_first_within_the_bound():
    rng = np.random.default_rng(0)
    for _ in range(50):
        lengths = rng.integers(1, 40, size=rng.integers(1, 30)).tolist()
        bound = int(rng.integers(1, 200))
        chunks = chunk_tracks(lengths, bound)
        assert sorted(i for c in chunks for i in c) == list(range(len(lengths)))
        firsts = [lengths[c[0]] for c in chunks]
        assert firsts == sorted(firsts, reverse=True)
        for c in chunks:
            assert lengths[c[0]] == max(lengths[i] for i in c)
            assert len(c) == 1 or len(c) * lengths[c[0]] <= bound
    assert chunk_tracks([], 10) == []


def test_estimate_tracks_rejects_bad_tracks():
    est = _estimator()
    points, _ = _track(frames=3)
    for bad in ([points], [{"timestamps": [0.0]}], [{"points": points, "colour": "red"}]):
        with pytest.raises(ConfigError, match=r"tracks\[0\]"):
            estimate_tracks(est, bad)
    with pytest.raises(ConfigError, match="chunk_frames"):
        estimate_tracks(est, [{"points": points}], chunk_frames=0)
    with pytest.raises(ConfigError, match="mode"):
        estimate_tracks(est, [{"points": points}], mode="sideways")
    with pytest.raises(ConfigError, match="timestamps"):
        estimate_tracks(est, [{"points": points}, {"points": points, "timestamps": [0.0]}])
    assert estimate_tracks(est, []) == []


def test_offline_estimator_estimates_many_tracks():
    est = _estimator()
    off = OfflineEstimator(est, OfflineConfig(shape="two-pass", pose="online"))
    tracks = _many_tracks()[:3]
    for tr, got in zip(tracks, off.estimate_tracks(tracks), strict=True):
        _close(got, off.estimate_track(**tr))


def test_offline_estimates_are_valid_from_the_first_detection_and_drop_nan_rows():
    """Frames before a track's first points are marked not valid in both modes, as
    Estimator.step marks them; NaN rows are dropped with a warning, as step drops them."""
    est = _estimator()
    rng = np.random.default_rng(5)
    pts = [np.zeros((0, 3), np.float32)] * 2 + [
        (rng.normal(size=(30, 3)) + [8, 0, 0]).astype(np.float32) for _ in range(3)]
    for mode in ("online", "offline"):
        out = estimate_track(est, pts, mode=mode)
        assert [e.valid for e in out] == [False, False, True, True, True]
    nan = [p.copy() for p in pts]
    nan[3][:4] = np.nan
    with pytest.warns(UserWarning, match=r"points\[3\] \(track 'car'\): dropped 4 of 30"):
        out = estimate_track(est, nan, mode="online", track_id="car")
    assert [e.num_points for e in out] == [0, 0, 30, 26, 30]


def test_heading_filter_gets_each_frames_points_and_class_online_and_in_online_mode(monkeypatch):
    """The opt-in shape evidence of the heading step needs the frame's points and the class:
    Estimator.step and estimate_track(mode="online") hand the filter the same ones."""
    from seqshape.model import heading as heading_mod

    seen = []
    update = heading_mod.HeadingFilter.update

    def spy(self, pose, ego, has_points, points=None, cls=None, time=None):
        seen.append((None if points is None else len(points), cls, time))
        return update(self, pose, ego, has_points, points, cls, time)

    monkeypatch.setattr(heading_mod.HeadingFilter, "update", spy)
    est = _estimator()
    points, egos = _track()
    times = 0.1 * np.arange(len(points))
    for t in range(len(points)):
        est.step(["t"], [points[t]], classes=["car"], ego_poses=[egos[t]],
                 timestamps=[times[t]])
    stepped, seen[:] = list(seen), []
    estimate_track(est, points, ego_poses=egos, timestamps=times, mode="online",
                   track_id="t", cls="car")
    assert seen == stepped and len(seen) == len(points)
    assert [n for n, _, _ in seen] == [min(len(p), CFG.num_points) for p in points]
    assert {c for _, c, _ in seen} == {"car"}
    np.testing.assert_allclose([s for _, _, s in seen], times)  # the holes' clock


@pytest.mark.parametrize("online", [True, False])
def test_labeller_places_a_known_box_seen_before_its_first_points(online):
    """sc-gt: a box annotated in frames before its first LiDAR points gets the network's prior
    shape at its true pose, not an estimate from nothing placed around the sensor origin."""
    from seqshape.amodal.labeler import offline_replay
    from seqshape.amodal.refine import TrackInput, complete_tracks

    est = _estimator()
    rng = np.random.default_rng(3)
    gt = np.array([[12.0 + 0.5 * t, 3.0, -0.8, 0.2] for t in range(5)])
    points = [np.zeros((0, 3), np.float32)] * 2 + [
        (rng.normal(scale=0.5, size=(40, 3)) + gt[t, :3]).astype(np.float32) for t in (2, 3, 4)]
    inputs = [TrackInput("v", list(range(5)), points, poses=gt)]
    runner = est if online else offline_replay(est, inputs)
    (comp,) = complete_tracks(runner, inputs, "none")
    for i in (0, 1):
        np.testing.assert_array_equal(comp.poses[i], gt[i])
        assert np.linalg.norm(comp.clouds[i].mean(axis=0)[:2] - gt[i, :2]) < 1.0


# ----------------------------------------------------------------- shapes moved to new poses


def _place_reference(complete, own, poses):
    """``smooth.place_shapes`` frame by frame with the geometry functions (the code before it was
    vectorised): the reference it must equal bit for bit."""
    from seqshape.geometry import canonical_to_sensor, wrap_angle

    out = np.array(complete, dtype=np.float32)
    for t in range(len(poses)):
        if np.array_equal(own[t], poses[t]):
            continue
        mine = np.array(own[t], dtype=np.float64)
        if abs(wrap_angle(mine[3] - poses[t, 3])) > math.pi / 2:
            mine[3] = wrap_angle(mine[3] + math.pi)
        out[t] = canonical_to_sensor(sensor_to_canonical(complete[t], mine), poses[t])
    return out


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_place_shapes_moves_each_shape_as_frame_by_frame(dtype):
    from seqshape.model.smooth import place_shapes as _place

    rng = np.random.default_rng(5)
    t, k = 12, 50
    own = np.c_[rng.normal(0, 20, (t, 3)), rng.uniform(-math.pi, math.pi, t)]
    poses = own + np.c_[rng.normal(0, 0.3, (t, 3)), rng.normal(0, 0.2, t)]
    poses[[1, 4], 3] = own[[1, 4], 3] + math.pi + 0.1  # flipped: the shape's front relabelled
    poses[[0, 7]] = own[[0, 7]]  # unchanged frames keep their shape as it is
    complete = (own[:, None, :3] + rng.normal(0, 2, (t, k, 3))).astype(dtype)
    got = _place(complete, own, poses)
    want = _place_reference(complete, own, poses)
    assert got.dtype == np.float32 and np.array_equal(got, want)
    assert np.array_equal(got[[0, 7]], complete[[0, 7]].astype(np.float32))
    # the shape stays where it was estimated when only the heading turned by pi
    turned = own.copy()
    turned[:, 3] += math.pi
    assert np.allclose(_place(complete, own, turned), complete, atol=1e-4)
    # a broadcast (read-only) shape, as the "final" shape source gives it
    final = np.broadcast_to(complete[3], complete.shape)
    assert np.array_equal(_place(final, own, poses), _place_reference(final, own, poses))
    assert _place(complete[:0], own[:0], poses[:0]).shape == (0, k, 3)


# --------------------------------------------------------------- the smoothing's local fits


def _local_fit_reference(t, y, window, iterations, scale, max_deg=2, query=None, prior=None):
    """The robust local polynomial fit of ``seqshape.model.smooth`` query by query, with
    ``numpy.linalg.lstsq`` on each query's own window (the code before it was batched), the
    samples' ``prior`` weights times the Tukey weights (the prior alone where Tukey rejects
    all)."""
    prior = np.ones(len(t)) if prior is None else prior
    query = t if query is None else query
    val, slope = np.empty((len(query), y.shape[1])), np.zeros((len(query), y.shape[1]))
    for i, tq in enumerate(query):
        sel = np.flatnonzero(np.abs(t - tq) <= window)
        if len(sel) < 2:  # at most one sample: the nearest sample's window
            sel = np.flatnonzero(np.abs(t - t[np.argmin(np.abs(t - tq))]) <= window)
        dt = t[sel] - tq
        deg = min(max_deg, len(np.unique(dt)) - 1)
        if min(np.count_nonzero(dt < 0), np.count_nonzero(dt > 0)) < window / 2:
            deg = min(deg, 1)
        a = np.vander(dt, deg + 1, increasing=True)
        w = prior[sel]
        for _ in range(iterations + 1):
            sw = np.sqrt(w)[:, None]
            coef = np.linalg.lstsq(a * sw, y[sel] * sw, rcond=None)[0]
            u = np.linalg.norm(y[sel] - a @ coef, axis=1) / (4.685 * scale)
            w = np.where(u < 1, (1 - u ** 2) ** 2, 0.0)
            w = prior[sel] if w.sum() < deg + 1 else w * prior[sel]
        val[i] = coef[0]
        slope[i] = coef[1] if deg >= 1 else 0.0
    return val, slope


def test_local_fit_equals_the_per_query_least_squares():
    from seqshape.model.smooth import _local_fit

    rng = np.random.default_rng(11)
    for case in range(40):
        n = int(rng.integers(1, 60))
        t = np.sort(rng.choice(np.arange(120), n, replace=False)).astype(np.float64)
        y = np.cumsum(rng.normal(0, 0.5, (n, 3)), axis=0)
        bad = rng.random(n) < 0.15  # outliers the robust weights reject
        y[bad] += rng.normal(0, 4, (int(bad.sum()), 3))
        query = None if case % 2 else np.arange(t[0] - 12, t[-1] + 12)  # queries off the ends
        prior = None if case % 3 else rng.uniform(0.01, 1.0, n)  # the frames' weights
        for window, deg in ((8, 2), (np.inf, 1), (2, 2)):
            got = _local_fit(t, y, window, 3, 0.3, deg, query, prior)
            want = _local_fit_reference(t, y, window, 3, 0.3, deg, query, prior)
            for g, w_ in zip(got, want, strict=True):
                assert g.shape == w_.shape
                np.testing.assert_allclose(g, w_, rtol=0, atol=1e-9)


# ------------------------------------------------------------ causal (online) smoothing


def _noisy_drive(n=30, seed=3, noise=0.3):
    """True and noisy estimated poses of a car driving at 8 m/s along a gentle curve, seen by
    a sensor that drives too (ego poses), in each frame's sensor frame."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    world = np.c_[20 + 0.8 * k, 5 + 0.004 * k ** 2, np.zeros(n), np.arctan2(0.008 * k, 0.8)]
    egos = []
    for j in range(n):
        e = np.eye(4)
        e[:3, 3] = [0.6 * j, 0.0, 0.0]
        egos.append(e)
    truth = world.copy()
    truth[:, 0] -= 0.6 * k  # the sensor frames moved by the ego
    est = truth + np.c_[rng.normal(0, noise, (n, 2)), np.zeros(n), rng.normal(0, 0.08, n)]
    return truth, est, egos


def test_causal_smoother_is_the_smoother_over_the_past_with_the_estimates_front():
    from seqshape.geometry import wrap_angle
    from seqshape.model.smooth import CausalSmoother, frame_weights, smooth_track_poses

    truth, est, egos = _noisy_drive()
    est[12, 3] += math.pi  # one estimate turned around: its front must stay as estimated
    valid = np.ones(len(est), bool)
    valid[8] = False  # a frame without points: not fitted, it gets the fit's value
    counts = np.where(valid, 100 + 10 * np.arange(len(est)), 0)  # points per frame
    weights = frame_weights(counts)  # as the smoother weighs them
    sm = CausalSmoother(window=5, history=64, min_frames=5)
    out = np.array([sm.update(est[t], valid[t], egos[t], 0.1 * t, num_points=counts[t])
                    for t in range(len(est))])
    # before the fifth frame with points the estimates pass through unchanged
    assert np.array_equal(out[:4], est[:4])
    for t in range(4, len(est)):  # after that: the whole-track smoother over frames <= t
        want = smooth_track_poses(est[:t + 1], np.arange(t + 1.0), np.stack(egos[:t + 1]),
                                  window=5, valid=valid[:t + 1], weights=weights[:t + 1])[-1]
        if abs(wrap_angle(want[3] - est[t, 3])) > math.pi / 2:
            want[3] = wrap_angle(want[3] + math.pi)
        np.testing.assert_allclose(out[t], want, atol=1e-9)
    assert abs(wrap_angle(out[12, 3] - est[12, 3])) < math.pi / 2
    # the smoother's own heading instead, with equal weights (the smoother without them)
    own = CausalSmoother(window=5, keep_front=False, full_points=None, ramp=None)
    mine = [own.update(est[t], valid[t], egos[t], 0.1 * t) for t in range(13)][-1]
    np.testing.assert_allclose(mine, smooth_track_poses(est[:13], np.arange(13.0),
                                                        np.stack(egos[:13]), window=5,
                                                        valid=valid[:13])[-1], atol=1e-9)
    assert abs(wrap_angle(mine[3] - est[12, 3])) > math.pi / 2  # the flip is not kept
    # and it pays: the centres' error falls by a fifth or more once it acts (0.36 -> 0.26 m)
    raw = np.linalg.norm(est[10:, :2] - truth[10:, :2], axis=1).mean()
    smooth = np.linalg.norm(out[10:, :2] - truth[10:, :2], axis=1).mean()
    assert smooth < 0.8 * raw


def test_frame_weights_by_hand():
    from seqshape.model.smooth import frame_weights

    counts = [0, 40, 320, 0, 80, 160]
    # points: (n / 160)^2 up to 1; ramp 4: the k-th detection min(1, k / 4); none: 0
    want = [0.0, (40 / 160) ** 2 * 1 / 4, 1.0 * 2 / 4, 0.0, (80 / 160) ** 2 * 3 / 4, 1.0]
    np.testing.assert_allclose(frame_weights(counts, 160, 4), want, rtol=1e-12)
    np.testing.assert_allclose(frame_weights(counts, None, None), [0, 1, 1, 0, 1, 1])
    np.testing.assert_allclose(frame_weights(counts, 160, None)[[1, 2]], [1 / 16, 1.0])
    with pytest.raises(ConfigError, match="frame_weights full_points"):
        frame_weights(counts, 0)


def test_smoother_weights_pull_the_fit_towards_the_dense_frames():
    """A stretch of frames with few points whose estimates are off by 25 cm (not far enough
    for the robust weights to reject them): weighted, the fit stays near the dense frames;
    weight 0 is a frame left out (as an invalid one); bad weights are refused."""
    from seqshape.model.smooth import frame_weights, smooth_track_poses

    n = 30
    truth = np.c_[10 + 0.8 * np.arange(n), np.full(n, 4.0), np.zeros(n), np.zeros(n)]
    est = truth.copy()
    est[10:16, 1] += 0.25  # the sparse frames' estimates, biased sideways
    counts = np.full(n, 400)
    counts[10:16] = 16
    eye = np.broadcast_to(np.eye(4), (n, 4, 4))
    plain = smooth_track_poses(est, np.arange(n), eye)
    weighted = smooth_track_poses(est, np.arange(n), eye, weights=frame_weights(counts))
    # unweighted the bias comes through; weighted (1/100 of a dense frame) almost none of it
    assert np.abs(plain[12, 1] - 4.0) > 0.1
    assert np.abs(weighted[12, 1] - 4.0) < 0.02
    keep = np.ones(n, bool)
    keep[10:16] = False
    zero = np.where(keep, 1.0, 0.0)
    np.testing.assert_allclose(smooth_track_poses(est, np.arange(n), eye, weights=zero),
                               smooth_track_poses(est, np.arange(n), eye, valid=keep),
                               atol=1e-12)
    for bad in (np.ones(n - 1), np.r_[np.ones(n - 1), -1.0], np.r_[np.ones(n - 1), np.nan]):
        with pytest.raises(ValueError, match="weights"):
            smooth_track_poses(est, np.arange(n), eye, weights=bad)


def _shapes_track(n=12, k=40, seed=0, noise=0.05):
    """A canonical shape, and per frame: poses, that shape plus i.i.d. noise placed with them
    (in the sensor frame), and random weights with some zeros."""
    from seqshape.geometry import canonical_to_sensor

    rng = np.random.default_rng(seed)
    truth = rng.uniform(-1, 1, (k, 3)) * [2.2, 0.9, 0.7]
    poses = np.c_[rng.uniform(5, 30, (n, 2)), rng.normal(0, 0.1, n), rng.uniform(-3, 3, n)]
    noisy = truth + rng.normal(0, noise, (n, k, 3))
    complete = np.stack([canonical_to_sensor(c, p) for c, p in zip(noisy, poses, strict=True)])
    weights = rng.uniform(0.1, 1.0, n)
    weights[[0, 5, 6]] = 0.0
    return truth, poses, complete.astype(np.float32), weights


def test_average_shapes_equals_the_weighted_sum_by_hand():
    from seqshape.model.smooth import average_shapes

    truth, poses, complete, weights = _shapes_track()
    can = np.stack([sensor_to_canonical(c.astype(np.float64), p)
                    for c, p in zip(complete, poses, strict=True)])
    n = len(poses)
    for causal in (True, False):
        for decay in (0.7, 1.0):
            got = average_shapes(complete, poses, weights, decay, causal=causal)
            for t in range(n):
                j = np.arange(n) if not causal else np.arange(t + 1)
                w = weights[j] * decay ** np.abs(t - j)
                if w.sum() == 0:  # frame 0: nothing weighed yet, its own shape
                    np.testing.assert_array_equal(got[t], complete[t])
                    continue
                want = np.tensordot(w / w.sum(), can[j], axes=1)
                np.testing.assert_allclose(sensor_to_canonical(got[t], poses[t]), want,
                                           atol=1e-5)
    # the average is nearer the true shape than the frames are (i.i.d. noise: about
    # 1 / sqrt(frames) of it)
    own = np.abs(can[1:] - truth).mean()
    mean = np.abs(np.stack([sensor_to_canonical(g, p) for g, p in zip(
        average_shapes(complete, poses, weights, 1.0, causal=False), poses, strict=True)])
        - truth).mean()
    assert mean < 0.45 * own
    with pytest.raises(ConfigError, match="shape_decay"):
        average_shapes(complete, poses, weights, 0.0)
    with pytest.raises(ValueError, match="one track"):
        average_shapes(complete, poses[:-1], weights)


def test_causal_smoother_shape_average_and_rigid_shapes_without_it():
    """``update_estimate`` replaces the shape by the causal :func:`average_shapes` of the
    track (in the decoder's frames: a flipped estimate's yaw is turned back first), placed
    with the smoothed pose; with ``shape_decay=None`` the shape only moves with the pose."""
    from types import SimpleNamespace

    from seqshape.model.smooth import CausalSmoother, average_shapes, frame_weights

    _, poses, complete, weights = _shapes_track(n=10, seed=2)
    counts = np.where(weights > 0, (weights * 300).astype(int), 0)
    flipped = np.zeros(10, bool)
    flipped[7] = True  # the heading step turned this yaw and kept the shape
    est_poses = poses.copy()
    est_poses[7, 3] = wrap_angle(est_poses[7, 3] + math.pi)
    mean = average_shapes(complete, poses, frame_weights(counts), 0.8)
    for decay in (0.8, None):
        sm = CausalSmoother(min_frames=50, shape_decay=decay)  # poses left as they are
        for t in range(10):
            e = SimpleNamespace(pose=est_poses[t].copy(), complete=complete[t].copy(),
                                num_points=int(counts[t]), flipped=bool(flipped[t]))
            sm.update_estimate(e)
            np.testing.assert_array_equal(e.pose, est_poses[t])
            want = complete[t] if decay is None else mean[t]
            np.testing.assert_allclose(e.complete, want, atol=1e-5)
    with pytest.raises(ConfigError, match="shape_decay"):
        CausalSmoother(shape_decay=1.5)


def test_causal_smoother_history_is_bounded_and_arguments_checked():
    from seqshape.model.smooth import CausalSmoother, frame_weights, smooth_track_poses

    _, est, egos = _noisy_drive(n=20)
    sm = CausalSmoother(window=3, history=8, min_frames=2)
    for t in range(20):
        got = sm.update(est[t], True, egos[t])
    # the ramp's weights count the track's detections, not the history's
    want = smooth_track_poses(est[12:], np.arange(8.0), np.stack(egos[12:]), window=3,
                              weights=frame_weights(np.ones(20))[12:])[-1]
    np.testing.assert_allclose(got, want, atol=1e-9)
    for bad in ({"window": 0}, {"history": 1}, {"min_frames": 0.5}, {"window": True},
                {"full_points": 0}, {"ramp": -1.0}, {"ramp": float("nan")},
                {"full_points": "160"}):
        with pytest.raises(ConfigError, match="CausalSmoother"):
            CausalSmoother(**bad)
    for bad in (-1, 2.5, True):
        with pytest.raises(ConfigError, match="num_points"):
            sm.update(est[0], True, egos[0], num_points=bad)


def test_causal_smoother_kept_fits_equal_the_smoother_over_its_history():
    """The local fits the causal smoother keeps between frames (those whose window is
    complete) give, at every frame, the smoother's own result over the remembered history:
    through the history's bound, runs of frames without points, a parked stretch and a frame
    without an ego pose (the fit moves to the sensor frames, then back)."""
    from seqshape.model.smooth import CausalSmoother, frame_weights, smooth_track_poses

    _, est, egos = _noisy_drive(n=90, seed=5)
    est[40:60, :2] = est[40, :2] + np.random.default_rng(2).normal(0, 0.2, (20, 2))  # parked
    valid = np.ones(len(est), bool)
    valid[[9, 10, 11, 12, 13, 14, 15, 30, 71]] = False
    egos = list(egos)
    egos[50] = None
    counts = np.where(valid, np.random.default_rng(4).integers(5, 400, len(est)), 0)
    weights = frame_weights(counts, full_points=160, ramp=8)
    # the parked stretch's ends are jumps no vehicle makes: no segment or shift limit here
    sm = CausalSmoother(window=3, history=16, min_frames=2, full_points=160, ramp=8,
                        max_speed=np.inf, max_shift=np.inf)
    kept = 0
    for t in range(len(est)):
        got = sm.update(est[t], valid[t], egos[t], 0.1 * t, num_points=counts[t])
        lo = max(0, t - 15)
        if valid[: t + 1].sum() < 2:
            np.testing.assert_array_equal(got, est[t])
            continue
        frames = egos[lo:t + 1]
        ego = None if any(e is None for e in frames) else np.stack(frames)
        want = smooth_track_poses(est[lo:t + 1], np.arange(t + 1.0 - lo), ego, window=3,
                                  valid=valid[lo:t + 1], weights=weights[lo:t + 1])[-1]
        if abs(wrap_angle(want[3] - est[t, 3])) > math.pi / 2:
            want[3] = wrap_angle(want[3] + math.pi)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        kept = max(kept, len(sm._fits))
    assert 0 < kept <= 16  # fits are kept, never more than the history holds


def test_causal_smoothing_online_mode_equals_stepping():
    est = _estimator()
    est.smoothing = "causal"
    points, egos = _track(frames=14, empty=6)
    times = 50.0 + 0.1 * np.arange(len(points))
    stepped = _step_all(est, points, egos, times)
    _close(estimate_track(est, points, ego_poses=egos, timestamps=times, mode="online",
                          track_id="t"), stepped)
    est.smoothing = "none"
    plain = _step_all(est, points, egos, times)
    moved = [not np.allclose(a.pose, b.pose) for a, b in zip(stepped, plain, strict=True)]
    assert not any(moved[:4]) and any(moved[4:])  # from the fifth frame with points on
    # the shape: the track's causal shape average (in the decoder's frames: a heading flip
    # turned the yaw and kept the shape), moved rigidly with the smoothed pose
    from seqshape.model.smooth import SHAPE_DECAY, average_shapes, frame_weights

    def decoder_frame(e):
        return e.pose + np.array([0.0, 0.0, 0.0, math.pi if e.flipped else 0.0])

    counts = [min(len(p), est.max_points) for p in points]
    mean = average_shapes(np.stack([b.complete for b in plain]),
                          np.stack([decoder_frame(b) for b in plain]), frame_weights(counts),
                          SHAPE_DECAY)
    for a, b, m in zip(stepped, plain, mean, strict=True):
        np.testing.assert_allclose(sensor_to_canonical(a.complete, decoder_frame(a)),
                                   sensor_to_canonical(m, decoder_frame(b)), atol=1e-4)
    assert not np.allclose(stepped[-1].complete, plain[-1].complete, atol=1e-3)
    with pytest.raises(ConfigError, match="smoothing"):
        est.smoothing = "kalman"


def test_window_median_equals_numpy_nanmedian():
    from seqshape.model.smooth import _window_median, _windows

    rng = np.random.default_rng(1)
    for _ in range(200):
        t = np.sort(rng.choice(200, rng.integers(1, 80), replace=False)).astype(float)
        values = rng.normal(0, 1, len(t))
        query = np.sort(rng.uniform(-10, 210, rng.integers(1, 50)))
        idx, inside = _windows(t, query, rng.uniform(0.5, 8))
        want = np.zeros(len(query))
        some = inside.any(axis=1)
        want[some] = np.nanmedian(np.where(inside[some], values[idx[some]], np.nan), axis=1)
        assert np.array_equal(_window_median(values, idx, inside), want)
