"""The evaluation runner, report files, plots and HTML view on fake estimators."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest

from seqshape.data import Track, TrackDataset, write_dataset
from seqshape.evaluation.metrics import chamfer_distance, earth_movers_distance
from seqshape.evaluation.runner import FIELDS, detection_span, evaluate_tracks, predict_track
from seqshape.geometry import canonical_to_sensor, sensor_to_canonical
from seqshape.testing import box_surface as _box_surface

SIZE = (4.5, 1.8, 1.5)


def box_surface(n: int, seed: int, size=SIZE) -> np.ndarray:
    return _box_surface(n, seed, size, dtype=np.float32)


def make_track(i: int, n_frames: int = 12) -> Track:
    """A box driving past the sensor; frames 0, 1 and the last are empty, one in the middle too."""
    rng = np.random.default_rng(i)
    complete = box_surface(2048, 1000 + i)
    t = np.arange(n_frames)
    poses = np.c_[8.0 + 0.5 * t, -3.0 + 0.4 * t + i, np.full(n_frames, -1.25),
                  0.1 * t + 0.5 * i]
    points = []
    for f in range(n_frames):
        gt = canonical_to_sensor(complete, poses[f])
        visible = gt[np.linalg.norm(gt, axis=1) < np.linalg.norm(poses[f, :3])]
        k = 0 if f in (0, 1, n_frames - 1, 5) else min(len(visible), 20 + 10 * f)
        points.append(visible[rng.choice(len(visible), k, replace=False)])
    return Track(f"trk{i:02d}", points, poses, complete, SIZE, 0.1 * t,
                 {"split": "val", "mesh": f"box:{i}"})


@dataclass
class Estimate:
    track_id: str
    complete: np.ndarray
    pose: np.ndarray
    num_points: int


class OracleEstimator:
    """Returns a fresh K-point sampling of the true surface at the true pose (+ optional noise);
    stateful like the real one: it counts frames per track since its last reset."""

    recurrent = True

    def __init__(self, tracks, k=1024, pose_noise=0.0, seed=0):
        self.tracks = {tr.track_id: tr for tr in tracks}
        self.k, self.noise = k, pose_noise
        self.rng = np.random.default_rng(seed)
        self.frame: dict[str, int] = {}
        self.calls: list[int] = []

    def reset(self, track_id=None):
        if track_id is None:
            self.frame.clear()
        else:
            self.frame.pop(track_id, None)

    def step(self, track_ids, point_lists):
        self.calls.append(len(track_ids))
        out = []
        for tid, pts in zip(track_ids, point_lists, strict=True):
            tr = self.tracks[tid]
            t = self.frame.get(tid, detection_span(tr)[0])
            self.frame[tid] = t + 1
            assert len(pts) == len(tr.points[t])
            pose = tr.poses[t] + self.rng.normal(0, self.noise, 4) * [1, 1, 0, 1]
            shape = canonical_to_sensor(box_surface(self.k, int(self.rng.integers(1 << 30))),
                                        pose)
            out.append(Estimate(tid, shape, pose, len(pts)))
        return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    tracks = [make_track(i, 10 + i) for i in range(4)]
    tracks.append(Track("train0", tracks[0].points, tracks[0].poses, tracks[0].complete, SIZE,
                        tracks[0].timestamps, {"split": "train"}))
    return write_dataset(root, tracks)


def test_runner_oracle_scores_floor_and_zero_pose_error(dataset):
    val = dataset.split("val")
    tracks = list(val)
    est = OracleEstimator(tracks)
    res = evaluate_tracks({"sequential": est}, val, emd_points=256, emd_every=3,
                          batch_tracks=2, workers=0)
    rec = res.records
    assert set(rec) == set(FIELDS)
    # frames from first to last detection: 2 .. n-2 inclusive, the empty middle frame included
    expected = sum(len(tr) - 3 for tr in tracks)
    assert len(rec["frame"]) == expected
    assert max(est.calls) == 2  # tracks are stepped together
    np.testing.assert_allclose(rec["trans_m"], 0.0, atol=1e-12)
    np.testing.assert_allclose(rec["rot_rad"], 0.0, atol=1e-12)
    floor = np.average(res.floors["floor_m"])
    assert np.mean(rec["cd_m"]) == pytest.approx(floor, rel=0.05)
    assert set(res.floors["method"]) == {"split"}
    # EMD on every 3rd frame of each track counted from its first detection
    has_emd = np.isfinite(rec["emd_m"])
    for tr in tracks:
        first = detection_span(tr)[0]
        sel = rec["track_id"] == tr.track_id
        assert np.array_equal(has_emd[sel], (rec["frame"][sel] - first) % 3 == 0)
    # EMD of two independent 256-point samplings of the same surface, measured directly
    ref = np.mean([earth_movers_distance(box_surface(256, s), box_surface(256, s + 50))
                   for s in range(6)])
    assert np.mean(rec["emd_m"][has_emd]) == pytest.approx(ref, rel=0.15)
    # ... which is the EMD floor: per track, two halves of its stored sampling
    emd_floor = np.average(res.floors["emd_floor_m"])
    assert np.isfinite(res.floors["emd_floor_m"]).all()
    assert emd_floor == pytest.approx(ref, rel=0.15)
    assert np.mean(rec["emd_m"][has_emd]) == pytest.approx(emd_floor, rel=0.15)


def test_runner_records_detections_points_and_distance(dataset):
    val = dataset.split("val")
    tr = val[1]
    res = evaluate_tracks({"sequential": OracleEstimator([tr])}, [tr], emd_every=0, workers=0)
    rec = res.records
    first, stop = detection_span(tr)
    np.testing.assert_array_equal(rec["frame"], np.arange(first, stop))
    np.testing.assert_array_equal(rec["n_points"], tr.num_points[first:stop])
    np.testing.assert_array_equal(rec["n_det"], np.cumsum(tr.num_points[first:stop] > 0))
    np.testing.assert_allclose(rec["distance_m"], np.hypot(*tr.poses[first:stop, :2].T))
    assert np.all(np.isnan(rec["emd_m"]))
    # CD is computed against the ground truth placed in each frame
    est = OracleEstimator([tr], seed=5)
    frames, estimates = predict_track(est, tr)
    t = frames[3]
    assert chamfer_distance(estimates[3].complete, tr.complete_in_frame(t)) < 0.3


def test_runner_pose_errors_and_process_pool(dataset):
    val = dataset.split("val")
    tracks = list(val)[:2]
    ests = {"sequential": OracleEstimator(tracks, pose_noise=0.01, seed=1),
            "baseline": OracleEstimator(tracks, pose_noise=0.2, seed=2)}
    res = evaluate_tracks(ests, tracks, emd_points=128, emd_every=4, workers=2)
    inline = evaluate_tracks({"sequential": OracleEstimator(tracks, pose_noise=0.01, seed=1),
                              "baseline": OracleEstimator(tracks, pose_noise=0.2, seed=2)},
                             tracks, emd_points=128, emd_every=4, workers=0)
    np.testing.assert_allclose(res.records["emd_m"], inline.records["emd_m"], equal_nan=True)
    seq, base = res.of("sequential"), res.of("baseline")
    assert np.mean(seq["trans_m"]) < np.mean(base["trans_m"])
    assert np.mean(seq["rot_rad"]) < np.mean(base["rot_rad"])
    assert np.all(base["rot_rad"] <= np.pi)
    assert res.settings["n_pred_points"] == {"sequential": 1024, "baseline": 1024}
    # the shape-only diagnostic: the true shape at a noisy pose, moved to the true pose, is
    # as good as the oracle's CD without noise (the floor); its placed CD is much worse
    floor = np.average(res.floors["floor_m"])
    assert np.mean(base["cd_true_pose_m"]) == pytest.approx(floor, rel=0.05)
    assert np.mean(base["cd_m"]) > 1.5 * np.mean(base["cd_true_pose_m"])


def test_unknown_pose_frames_get_nan_metrics(tmp_path):
    tr = make_track(7)
    tr.poses[4] = np.nan
    res = evaluate_tracks({"sequential": OracleEstimator([make_track(7)])}, [tr],
                          emd_every=1, emd_points=64, workers=0)
    row = res.records["frame"] == 4
    for k in ("cd_m", "emd_m", "trans_m", "rot_rad"):
        assert np.isnan(res.records[k][row]).all()
    assert np.isfinite(res.records["cd_m"][~row]).all()


def test_sensor_to_canonical_of_oracle_is_box():
    tr = make_track(0)
    est = OracleEstimator([tr])
    _, estimates = predict_track(est, tr)
    can = sensor_to_canonical(estimates[0].complete, estimates[0].pose)
    np.testing.assert_allclose(np.abs(can).max(0), np.array(SIZE) / 2, atol=1e-4)


def test_report_files_plots_and_html(dataset, tmp_path):
    from seqshape.evaluation.html import write_track_html
    from seqshape.evaluation.plots import write_plots
    from seqshape.evaluation.report import PAPER_TABLE, write_metrics

    val = dataset.split("val")
    tracks = list(val)
    ests = {"sequential": OracleEstimator(tracks, pose_noise=0.01, seed=1),
            "baseline": OracleEstimator(tracks, pose_noise=0.1, seed=2)}
    res = evaluate_tracks(ests, val, emd_points=64, emd_every=2, workers=0)
    summary = write_metrics(tmp_path, res)
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert set(data["sequential"]) == set(data["baseline"]) == {"cd_cm", "emd_m", "trans_cm",
                                                                "rot_deg"}
    assert isinstance(data["cd_floor_cm"], float)
    seq = res.of("sequential")
    assert data["sequential"]["cd_cm"] == pytest.approx(100 * np.mean(seq["cd_m"]))
    assert data["sequential"]["emd_m"] == pytest.approx(np.nanmean(seq["emd_m"]))
    assert data["baseline"]["rot_deg"] == pytest.approx(
        np.degrees(np.mean(res.of("baseline")["rot_rad"])))
    assert data["cd_floor_cm"] == pytest.approx(data["sequential"]["cd_cm"], rel=0.05)
    assert isinstance(data["emd_floor_m"], float)
    floors = data["floor"]["per_method"]
    gains = data["above_floor"]

    def by_hand(key, floor_key):
        s, b = data["sequential"][key], data["baseline"][key]
        fs, fb = floors["sequential"][floor_key], floors["baseline"][floor_key]
        return 100 * ((s - fs) - (b - fb)) / (b - fb)

    assert gains["cd_pct"] == pytest.approx(by_hand("cd_cm", "cd_floor_cm"))
    assert gains["emd_pct"] == pytest.approx(by_hand("emd_m", "emd_floor_m"))
    assert gains["trans_pct"] == pytest.approx(
        100 * (data["sequential"]["trans_cm"] / data["baseline"]["trans_cm"] - 1))
    assert gains["cd_pct"] < 0 and gains["trans_pct"] < 0  # less pose noise: better
    noflip = [data["details"][m]["rot_deg_without_flips"] for m in ("sequential", "baseline")]
    assert gains["rot_noflip_pct"] == pytest.approx(100 * (noflip[0] / noflip[1] - 1))
    assert summary["paper"] == PAPER_TABLE
    md = (tmp_path / "metrics.md").read_text()
    assert "| sequential (paper) | 2.30 | 0.250 | 9.40 | 12.00 |" in md
    assert "CD floor" in md and "EMD floor" in md and "EMD above its floor" in md
    lines = (tmp_path / "per_frame.csv").read_text().splitlines()
    assert lines[0].split(",") == list(FIELDS) and len(lines) == len(res.records["frame"]) + 1
    for png in write_plots(tmp_path, res):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    html = write_track_html(tmp_path / "track.html", tracks[0],
                            {k: OracleEstimator(tracks) for k in ests}, max_points=100)
    text = html.read_text()
    assert "plotly" in text and "cdn.plot.ly" not in text.split("<body>")[0][-2000:]
    assert text.count('"name":"') > 0 and len(text) > 1_000_000  # plotly.js is inlined


def test_write_metrics_requires_both_methods(dataset, tmp_path):
    from seqshape.errors import SeqshapeError
    from seqshape.evaluation.report import write_metrics

    tr = dataset.split("val")[0]
    res = evaluate_tracks({"sequential": OracleEstimator([tr])}, [tr], emd_every=0, workers=0)
    with pytest.raises(SeqshapeError, match="baseline"):
        write_metrics(tmp_path, res)


def _untrained_checkpoint(path, kind):
    torch = pytest.importorskip("torch")
    from seqshape.model.config import ModelConfig
    from seqshape.model.network import ShapePoseNet

    torch.manual_seed(0)
    cfg = ModelConfig(num_points=64, encoder1=(16, 32), encoder2=(32, 32), hidden=32,
                      shape_decoder=(32,), pose_decoder=(32,), num_complete=128)
    net = ShapePoseNet(cfg, recurrent=kind == "sequential")
    torch.save({"format": "seqshape-checkpoint", "version": 1, "kind": kind,
                "model_config": cfg.to_dict(), "train_config": {},
                "state_dict": net.state_dict(), "metrics": {}}, path)
    return path


def test_evaluate_cli_end_to_end(dataset, tmp_path):
    pytest.importorskip("seqshape.model.estimator")
    from seqshape.cli import main

    seq = _untrained_checkpoint(tmp_path / "seq.pt", "sequential")
    base = _untrained_checkpoint(tmp_path / "base.pt", "baseline")
    out = tmp_path / "eval"
    rc = main(["evaluate", "--data", str(dataset.path), "--checkpoint", str(seq),
               "--baseline", str(base), "--out", str(out), "--max-tracks", "2",
               "--emd-every", "3", "--emd-points", "64", "--workers", "0"])
    assert rc == 0
    data = json.loads((out / "metrics.json").read_text())
    for m in ("sequential", "baseline"):
        assert set(data[m]) == {"cd_cm", "emd_m", "trans_cm", "rot_deg"}
        assert all(np.isfinite(v) for v in data[m].values())
    assert data["settings"]["n_pred_points"] == {"sequential": 128, "baseline": 128}
    for f in ("metrics.md", "per_frame.csv", "errors_vs_detections.png",
              "errors_vs_distance.png", "track_view.html"):
        assert (out / f).stat().st_size > 0
    # the models swapped are a clear error naming the flag
    rc = main(["evaluate", "--data", str(dataset.path), "--checkpoint", str(base),
               "--out", str(out), "--workers", "0"])
    assert rc == 1


def test_demo_end_to_end_with_untrained_models(tmp_path, monkeypatch):
    """Generation (tiny preset) + evaluation + report, about 5 s."""
    pytest.importorskip("seqshape.model.estimator")
    pytest.importorskip("seqshape.sim.generate")
    from seqshape.cli import main
    from seqshape.demo import DemoStep, Section, pipeline

    seq = _untrained_checkpoint(tmp_path / "seq.pt", "sequential")
    base = _untrained_checkpoint(tmp_path / "base.pt", "baseline")
    out = tmp_path / "demo"
    extra = []
    mine = [s for s in pipeline.STEPS if s.name in ("generate", "models", "evaluate")]
    assert [s.name for s in mine] == ["generate", "models", "evaluate"]
    # only this module's steps, plus one appended the way later features extend the demo
    monkeypatch.setattr(pipeline, "STEPS", mine + [DemoStep(
        "extra", "an appended step", lambda ctx: extra.append(ctx.data) or ctx.sections.append(
            Section("Extra", "appended `step`\n")))])
    rc = main(["demo", "--out", str(out), "--checkpoint", str(seq), "--baseline", str(base),
               "--preset", "tiny", "--vehicles", "0", "--tracks-per-vehicle", "0", "--max-tracks", "2", "--emd-every", "4", "--workers", "1"])
    assert rc == 0 and extra == [out / "data"]
    report = (out / "report.md").read_text()
    assert "| sequential (ours) |" in report and "## Extra" in report
    index = (out / "index.html").read_text()
    assert "<table>" in index and "<code>step</code>" in index
    for rel in ("eval/errors_vs_detections.png", "eval/track_view.html", "eval/metrics.json"):
        assert rel in index and (out / rel).is_file()


def test_flip_diagnostic_counts_frames_tracks_and_the_rest():
    from seqshape.evaluation.report import method_summary, metrics_markdown

    # track a: 0.1 rad and a full flip (pi); track b: 3.0 rad (171.9 deg, a flip), 2.5 rad
    # (143.2 deg, not one) and an unknown pose; track c: 0.3 rad
    rot = np.array([0.1, np.pi, 3.0, 2.5, np.nan, 0.3])
    n = len(rot)
    rec = {"frame": np.arange(n), "track_id": np.array(list("aabbbc")), "rot_rad": rot,
           **{c: np.full(n, 0.2) for c in ("cd_m", "emd_m", "trans_m", "cd_true_pose_m")}}
    table, details = method_summary(rec)
    assert details["rot_flip_frames"] == 2 and details["rot_flip_tracks"] == 2
    assert details["rot_deg_without_flips"] == pytest.approx(np.degrees((0.1 + 2.5 + 0.3) / 3))
    assert table["rot_deg"] == pytest.approx(np.degrees(np.nanmean(rot)))
    md = metrics_markdown({"sequential": table, "details": {"sequential": details}})
    assert "sequential 2 of 5 frames in 2 tracks, rotation without them 55.39 deg" in md


# --------------------------------------------------------------------------------------------
# real tracks: radial/tangential, extents, flips, breakdowns, the box fit row


def test_radial_tangential_hand_computed():
    from seqshape.evaluation.runner import radial_tangential

    gt = np.array([3.0, 4.0, -1.0, 0.2])  # unit line of sight (0.6, 0.8), normal (-0.8, 0.6)
    est = gt + [0.5 * 0.6 - 0.2 * 0.8, 0.5 * 0.8 + 0.2 * 0.6, 0.3, 0.0]
    radial, tangential = radial_tangential(est, gt)
    assert radial == pytest.approx(0.5) and tangential == pytest.approx(0.2)
    radial, tangential = radial_tangential([2.4, 3.2, 0, 0], gt)  # 1 m too close
    assert radial == pytest.approx(-1.0) and tangential == pytest.approx(0.0, abs=1e-12)


def test_extents_of_a_box_cloud_and_of_a_fitted_box():
    from seqshape.evaluation.runner import estimate_extents
    from seqshape.model.boxfit import BoxEstimate

    size = (4.0, 1.7, 1.5)
    pose = np.array([10.0, -2.0, -1.0, 0.7])
    cloud = canonical_to_sensor(box_surface(1024, 3, size), pose)
    stray = np.r_[cloud, [[30.0, 30.0, 0.0]] * 5]  # under 1 %: ignored by the percentiles
    np.testing.assert_allclose(estimate_extents(Estimate("a", stray, pose, 10)), size[:2],
                               atol=0.01)
    # seen with a yaw 90 degrees off, the same cloud has length and width swapped
    turned = pose + [0, 0, 0, np.pi / 2]
    np.testing.assert_allclose(estimate_extents(Estimate("a", cloud, turned, 10)),
                               size[1::-1], atol=0.01)
    boxed = BoxEstimate("a", cloud, pose, 10, np.array([3.0, 1.0, 1.2]))
    np.testing.assert_allclose(estimate_extents(boxed), [3.0, 1.0])
    assert np.isnan(estimate_extents(Estimate("a", np.zeros((0, 3)), pose, 0))).all()


TRUCK = (8.0, 2.5, 3.0)


def make_real_track(i: int, cls: str, size, reference: bool, n_frames: int = 6) -> Track:
    """A real-like track: meta as ``seqshape tracks`` writes it, no split, points of the side
    facing the sensor, ``complete`` an accumulated-style reference or None."""
    rng = np.random.default_rng(100 + i)
    surface = box_surface(4096, 200 + i, size)
    half = np.asarray(size) / 2
    t = np.arange(n_frames)
    poses = np.c_[6.0 + 4 * i + 0.6 * t, (-1) ** i * (2.5 + i) + 0.1 * t, np.full(n_frames, -1.0),
                  np.full(n_frames, 0.05 * i)]
    points = []
    for f in range(n_frames):
        # the faces whose outward side looks at the sensor (canonical frame)
        sensor = sensor_to_canonical(np.zeros((1, 3)), poses[f])[0]
        on = np.isclose(np.abs(surface), half, atol=1e-5)
        seen = on & (np.sign(surface) * sensor > half)
        visible = canonical_to_sensor(surface[seen.any(axis=1)], poses[f])
        k = 0 if f == 2 else min(len(visible), [5, 40, 0, 150, 400, 1200][f % 6])
        points.append(visible[rng.choice(len(visible), k, replace=False)])
    meta = {"source": "real", "dataset": "av2", "log": "log0", "class": cls,
            "category": cls.upper(), "frames": t.tolist()}
    complete = None
    if reference:
        meta["reference"] = {"kind": "accumulated"}
        complete = box_surface(2048, 300 + i, size)
    return Track(f"log0_{cls}{i}", points, poses, complete, size, 0.1 * t, meta)


@dataclass
class Flipper:
    """The true pose, its yaw turned by 180 degrees on odd frames of each track."""

    tracks: dict
    recurrent: bool = False

    def __post_init__(self):
        self.t: dict[str, int] = {}

    def reset(self, track_id=None):
        self.t.clear() if track_id is None else self.t.pop(track_id, None)

    def step(self, track_ids, point_lists):
        out = []
        for tid in track_ids:
            tr = self.tracks[tid]
            t = self.t.get(tid, detection_span(tr)[0])
            self.t[tid] = t + 1
            pose, shape = self.estimate(tr, t)
            out.append(Estimate(tid, shape, pose, len(tr.points[t])))
        return out

    def estimate(self, tr, t):
        pose = tr.poses[t] + [0, 0, 0, np.pi * (t % 2)]
        return pose, canonical_to_sensor(box_surface(512, t, tr.size), pose)


def test_flip_rate_axis_error_and_breakdown_on_a_flipped_track():
    from seqshape.evaluation.report import summarize

    tr = make_real_track(0, "car", SIZE, reference=True)
    res = evaluate_tracks({"sequential": Flipper({tr.track_id: tr}),
                           "baseline": Flipper({tr.track_id: tr})}, [tr], emd_every=0,
                          workers=0)
    rec = res.of("sequential")
    odd = rec["frame"] % 2 == 1
    np.testing.assert_allclose(rec["rot_rad"][odd], np.pi, atol=1e-9)
    np.testing.assert_allclose(rec["rot_axis_rad"], 0.0, atol=1e-9)
    np.testing.assert_allclose(rec["trans_m"], 0.0, atol=1e-12)
    # the extents of a box cloud seen in its own (flipped or not) frame are the box's
    np.testing.assert_allclose(rec["length_err_m"], 0.0, atol=0.02)
    np.testing.assert_allclose(rec["width_err_m"], 0.0, atol=0.02)
    assert set(rec["class"]) == {"car"}
    summary = summarize(res)
    assert res.settings["real"] is True
    d = summary["details"]["sequential"]
    assert d["rot_flip_rate"] == pytest.approx(odd.mean())
    assert d["rot_axis_deg"] == pytest.approx(0.0, abs=1e-6)
    allf = summary["breakdown"]["all"]["all"]["sequential"]
    assert allf["flip_pct"] == pytest.approx(100 * odd.mean())
    assert allf["n_frames"] == len(rec["frame"]) and allf["rot_deg_without_flips_median"] == 0
    points = summary["breakdown"]["points"]
    assert set(points) == {"0", "1-9", "30-99", "100-299", "300-999", "1000+"}
    assert points["0"]["sequential"]["n_frames"] == 1


@dataclass
class Stretcher(Flipper):
    """The true pose (never flipped) with a box cloud ``factor`` times the true length."""

    factor: float = 1.1

    def estimate(self, tr, t):
        size = np.asarray(tr.size, dtype=np.float64) * [self.factor, 1.0, 1.0]
        return tr.poses[t], canonical_to_sensor(box_surface(2048, t, size), tr.poses[t])


def test_relative_length_error_of_a_truck_and_a_car():
    """A truck and a car both estimated 10 % too long: the same relative error, an absolute
    one in proportion to their lengths; the breakdown reports |length| % by class group."""
    from seqshape.evaluation.report import summarize

    tracks = [make_real_track(0, "car", SIZE, False), make_real_track(1, "truck", TRUCK, False)]
    est = Stretcher({tr.track_id: tr for tr in tracks}, factor=1.1)
    res = evaluate_tracks({"sequential": est}, tracks, emd_every=0, workers=0)
    rec = res.of("sequential")
    truck = rec["class"] == "truck"
    # extents are the 1st-99th percentile spread of the cloud: a little under the box
    np.testing.assert_allclose(rec["length_rel_err"], 0.1, atol=0.015)
    np.testing.assert_allclose(rec["length_err_m"][truck], 0.1 * TRUCK[0], atol=0.015 * TRUCK[0])
    np.testing.assert_allclose(rec["length_rel_err"],
                               rec["length_err_m"] / np.where(truck, TRUCK[0], SIZE[0]))
    groups = summarize(res)["breakdown"]["class_group"]
    for group in ("car", "larger (van/truck/bus/trailer)"):
        assert groups[group]["sequential"]["length_rel_abs_pct_median"] == pytest.approx(
            10.0, abs=1.5)


def test_evaluate_cli_on_a_real_like_dataset(tmp_path):
    pytest.importorskip("seqshape.model.estimator")
    from seqshape.cli import main

    tracks = [make_real_track(0, "car", SIZE, True), make_real_track(1, "truck", TRUCK, True),
              make_real_track(2, "car", SIZE, False)]
    data = write_dataset(tmp_path / "real", tracks)
    out = tmp_path / "eval"
    rc = main(["evaluate", "--data", str(data.path), "--checkpoint", "pretrained",
               "--out", str(out), "--emd-points", "64", "--emd-every", "2", "--workers", "0",
               "--view", "none"])
    assert rc == 0
    summary = json.loads((out / "metrics.json").read_text())
    assert summary["settings"]["methods"] == ["sequential", "baseline", "boxfit"]
    assert summary["settings"]["n_tracks"] == 3 and summary["settings"]["real"]
    assert summary["settings"]["n_reference_tracks"] == 2
    groups = summary["breakdown"]["class_group"]
    assert set(groups) == {"car", "larger (van/truck/bus/trailer)"}
    assert set(summary["breakdown"]["class"]) == {"car", "truck"}
    assert groups["car"]["boxfit"]["n_frames"] == 2 * 6  # two car tracks, all frames scored
    md = (out / "metrics.md").read_text()
    assert "CD vs accumulated reference (cm)" in md and "(paper)" not in md
    assert "### Cars vs larger vehicles (medians)" in md and "### By class (means)" in md and "| 1000+ | boxfit |" in md
    import csv

    with open(out / "per_frame.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(FIELDS)
    no_ref = [r for r in rows if r["track_id"] == tracks[2].track_id]
    assert no_ref and all(r["cd_m"] == "" and r["emd_m"] == "" for r in no_ref)
    assert all(r["trans_m"] and r["length_err_m"] and r["radial_m"] for r in no_ref
               if r["n_points"] != "0" or r["method"] != "boxfit")
    with_ref = [r for r in rows if r["track_id"] == tracks[1].track_id]
    assert all(r["cd_m"] for r in with_ref) and any(r["emd_m"] for r in with_ref)
    assert {r["class"] for r in with_ref} == {"truck"}
    # the box fit sees an L of the truck in its last, densest frame: its centre and extents
    # are the truck's within a few cm; its row is off with --no-boxfit
    best = [r for r in with_ref if r["method"] == "boxfit" and r["frame"] == "5"]
    assert int(best[0]["n_points"]) > 300
    for col in ("trans_m", "length_err_m", "width_err_m"):
        assert abs(float(best[0][col])) < 0.05
    rc = main(["evaluate", "--data", str(data.path), "--checkpoint", "pretrained",
               "--out", str(out), "--emd-every", "0", "--workers", "0", "--view", "none",
               "--no-boxfit", "--split", "all"])
    assert rc == 0
    assert json.loads((out / "metrics.json").read_text())["settings"]["methods"] == [
        "sequential", "baseline"]


def test_one_way_reference_to_estimate_distance_by_brute_force(dataset):
    """ref_to_est_m is the reference->estimate half of the CD, checked against cdist."""
    from scipy.spatial.distance import cdist

    tr = TrackDataset(dataset.path).split("val")[0]
    est = OracleEstimator([tr], pose_noise=0.05, seed=3)
    res = evaluate_tracks({"sequential": est}, [tr], emd_every=0, workers=0)
    rec = res.records
    again = OracleEstimator([tr], pose_noise=0.05, seed=3)
    frames, estimates = predict_track(again, tr)
    for i, t in enumerate(frames):
        d = cdist(tr.complete_in_frame(t), estimates[i].complete)
        assert rec["ref_to_est_m"][i] == pytest.approx(d.min(1).mean(), rel=1e-9)
        assert rec["cd_m"][i] == pytest.approx(d.min(1).mean() + d.min(0).mean(), rel=1e-9)


def test_track_hints_give_class_and_ego_poses_never_the_size():
    from seqshape.evaluation.runner import track_hints
    from seqshape.model import Estimator

    est = Estimator.from_pretrained("baseline")
    pts = [np.zeros((3, 3), np.float32)] * 2
    synthetic = Track("s", pts, np.zeros((2, 4)), None, SIZE, np.arange(2.0), {})
    ego = [np.eye(4).tolist(), (np.eye(4) * 2).tolist()]
    real = Track("r", pts, np.zeros((2, 4)), None, SIZE, np.arange(2.0),
                 {"source": "real", "class": "truck", "ego_poses": ego})
    bare = Track("b", pts, np.zeros((2, 4)), None, SIZE, np.arange(2.0),
                 {"source": "real", "class": "car"})
    h = track_hints(est, [synthetic, real], [0, 1])
    assert h["classes"] == [None, "truck"] and "sizes" not in h
    np.testing.assert_array_equal(h["ego_poses"][0], np.eye(4))  # the generator's static sensor
    np.testing.assert_array_equal(h["ego_poses"][1], np.eye(4) * 2)  # the track's own frame 1
    assert track_hints(est, [bare], [0]) == {"classes": ["car"], "ego_poses": None}
    assert track_hints(OracleEstimator([]), [real], [0]) == {}  # other estimators: nothing


def test_outside_shares_by_hand():
    from seqshape.evaluation.runner import footprint, outside_shares

    # a 4 x 2 m box at (10, 0) facing +x, the sensor at the origin: its near face is x = 8
    pose = np.array([10.0, 0.0, 0.0, 0.0])
    box = (np.array([-2.0, -1.0]), np.array([2.0, 1.0]))
    pts = np.array([[7.5, 0.0, 0.0],     # in front of the near face: out, near
                    [9.0, 0.5, 0.0],     # inside
                    [12.5, 0.0, 0.0],    # behind the far face: out, far
                    [11.0, 1.5, 0.0],    # beside it, beyond the centre: out, far
                    [9.5, -1.2, 0.3]])   # beside it, on the sensor's side: out, near
    assert outside_shares(pts, pose, box) == pytest.approx((0.4, 0.4))
    # the same scene turned by 90 degrees about the sensor (box yaw too): same shares
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    turned = np.array([0.0, 10.0, 0.0, np.pi / 2])
    assert outside_shares(pts @ rot.T, turned, box) == pytest.approx((0.4, 0.4))
    # a box moved 1.5 m away from the sensor leaves the near points out, nothing behind
    far = np.array([11.5, 0.0, 0.0, 0.0])
    assert outside_shares(pts[:3], far, box) == pytest.approx((2 / 3, 0.0))
    assert np.isnan(outside_shares(np.zeros((0, 3)), pose, box)).all()
    assert np.isnan(outside_shares(pts, pose, None)).all()

    # footprint: the box fit's size, or the 1-99 % extents of the estimated cloud
    cloud = np.array([[x, y, 0.0] for x in np.linspace(8, 12, 41) for y in np.linspace(-1, 1, 21)])
    est = type("Est", (), {"pose": pose, "complete": cloud})()
    lo, hi = footprint(est)
    np.testing.assert_allclose(np.concatenate([lo, hi]), [-2, -1, 2, 1], atol=1e-9)  # end rows > 1 %

    fit = type("Fit", (), {"pose": pose, "size": np.array([4.0, 2.0, 1.5])})()
    np.testing.assert_allclose(np.concatenate(footprint(fit)), [-2, -1, 2, 1])


def test_face_gaps_by_hand():
    from seqshape.evaluation.runner import face_gaps

    # a 4 x 2 m box at (10, 0) facing +x, the sensor at the origin: it sees the tail (x = 8)
    # head-on and no side; 100 points on a plane 0.3 m behind that face, then on the face
    size = np.array([4.0, 2.0, 1.5])
    pose = np.array([10.0, 0.0, -1.0, 0.0])
    y = np.linspace(-0.9, 0.9, 100)
    behind = np.c_[np.full(100, 8.3), y, np.full(100, -1.0)]
    g = face_gaps(behind, pose, size)
    assert g[0] == pytest.approx(0.3) and np.isnan(g[1])
    assert face_gaps(behind - [0.3, 0, 0], pose, size)[0] == pytest.approx(0.0, abs=1e-12)
    # points beyond the face (a box too small or displaced away): a negative gap
    assert face_gaps(behind - [0.5, 0, 0], pose, size)[0] == pytest.approx(-0.2)
    # heading toward the sensor: the nose is the face seen, the same numbers
    assert face_gaps(behind, pose + [0, 0, 0, np.pi], size)[0] == pytest.approx(0.3)
    # at 45 degrees two faces are seen, each gap measured along its own axis: the box at
    # (10, 10) heading -y sees the sensor at (0.71, -0.71) in its frame (nose and right side)
    diag = np.array([10.0, 10.0, -1.0, -np.pi / 2])
    c, s = np.cos(diag[3]), np.sin(diag[3])
    local = np.array([[x, yy] for x in np.linspace(-2.0, 1.8, 39)
                      for yy in np.linspace(-0.7, 0.9, 17)])  # 0.2 m short of the nose,
    pts = np.c_[local @ np.array([[c, s], [-s, c]]) + diag[:2], np.full(len(local), -1.0)]
    g = face_gaps(pts, diag, size)  # ... 0.3 m short of the right side
    want = [2.0 - np.quantile(local[:, 0], 0.98), 1.0 - np.quantile(-local[:, 1], 0.98)]
    np.testing.assert_allclose(g, want, atol=1e-9)
    assert 0.19 < g[0] < 0.21 and 0.29 < g[1] < 0.31


def test_annotation_breakdown_splits_boxes_off_their_points():
    from seqshape.evaluation.report import summarize

    good = make_real_track(0, "car", SIZE, reference=False)
    # the same points under a box moved 0.5 m toward the sensor: it no longer holds them
    poses = good.poses.copy()
    poses[:, :2] -= 0.5 * poses[:, :2] / np.linalg.norm(poses[:, :2], axis=1, keepdims=True)
    bad = Track("log0_car9", good.points, poses, None, good.size, good.timestamps,
                dict(good.meta))
    tracks = {t.track_id: t for t in (good, bad)}
    res = evaluate_tracks({"sequential": Flipper(tracks)}, [good, bad], emd_every=0, workers=0)
    rec = res.of("sequential")
    gap, n = rec["ref_face_gap_m"], rec["n_points"]
    assert np.isnan(gap[n < 10]).all() and np.isfinite(gap[n >= 10]).all()
    is_bad = rec["track_id"] == "log0_car9"
    assert np.all(gap[~is_bad & (n >= 10)] < 0.05)  # points on the faces the sensor sees
    assert np.all(gap[is_bad & (n >= 10)] > 0.3)  # about 0.5 m along the line of sight
    groups = summarize(res)["breakdown"]["annotation"]
    fits, off = "box fits its points (<= 0.15 m)", "box off its points (> 0.15 m)"
    assert groups[fits]["sequential"]["n_frames"] == int(np.sum(~is_bad & (n >= 10)))
    assert groups[off]["sequential"]["n_frames"] == int(np.sum(is_bad & (n >= 10)))
    assert groups[fits]["sequential"]["centre_cm_median"] == pytest.approx(0.0, abs=1e-6)
    gaps = summarize(res)["breakdown"]["face_gap"]  # the same frames in the finer bins
    assert set(gaps) == {"gap <= 5 cm", "gap > 30 cm"}
    assert gaps["gap <= 5 cm"]["sequential"]["n_frames"] == int(np.sum(~is_bad & (n >= 10)))
    assert gaps["gap > 30 cm"]["sequential"]["n_frames"] == int(np.sum(is_bad & (n >= 10)))
    assert gaps["gap > 30 cm"]["sequential"]["centre_cm_median"] == pytest.approx(0.0, abs=1e-6)


def test_no_emd_no_emd_floor(dataset):
    """Without EMD (``emd_every=0``) no EMD floor is computed and the above-floor EMD change is
    null, while the CD's is still there."""
    from seqshape.evaluation.report import summarize

    tracks = list(dataset.split("val"))[:2]
    ests = {"sequential": OracleEstimator(tracks, pose_noise=0.01, seed=1),
            "baseline": OracleEstimator(tracks, pose_noise=0.1, seed=2)}
    res = evaluate_tracks(ests, tracks, emd_every=0, workers=0)
    assert np.isnan(res.floors["emd_floor_m"]).all()
    out = summarize(res)
    assert out["emd_floor_m"] is None
    assert out["above_floor"]["emd_pct"] is None and out["above_floor"]["cd_pct"] is not None
