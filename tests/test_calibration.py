"""Size calibration (seqshape.model.calibration): the scaled world, and the scale of a log."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("torch")

from seqshape.errors import ConfigError  # noqa: E402
from seqshape.model import Estimator  # noqa: E402
from seqshape.model.calibration import (  # noqa: E402
    SCALE_LIMITS,
    calibrate_size,
    frame_lengths,
    shipped_prior,
    size_prior,
)
from seqshape.model.offline import estimate_tracks  # noqa: E402
from seqshape.testing import box_surface  # noqa: E402


def seen_half(size, pose, n, rng):
    """The half of a box surface nearer the sensor (a partial view), float32."""
    pts = box_surface(2 * n, rng, size, pose=pose, dtype=np.float32)
    near = np.linalg.norm(pts[:, :2], axis=1) <= np.hypot(pose[0], pose[1])
    return pts[near]


def side_track(length, seed, frames=5, y=7.0):
    """A parked car of ``length`` seen broadside while the ego drives past (the whole
    length in view): points, ego poses (sensor -> fixed frame) and timestamps."""
    rng = np.random.default_rng(seed)
    pts, egos = [], []
    for t in range(frames):
        ego_x = -1.0 + 0.5 * t  # the sensor moves along x, the car stays at (0, y)
        ego = np.eye(4)
        ego[0, 3] = ego_x
        egos.append(ego)
        pts.append(seen_half((length, 1.8, 1.5), (-ego_x, y, -0.9, 0.0), 400, rng))
    return {"points": pts, "ego_poses": egos, "timestamps": [0.1 * t for t in range(frames)],
            "cls": "car", "track_id": f"side{seed}"}


def end_track(length, seed, frames=4):
    """A car of ``length`` seen from straight behind at 15 m (its length never in view)."""
    rng = np.random.default_rng(seed)
    pts = [seen_half((length, 1.8, 1.5), (15.0, 0.0, -0.9, 0.0), 300, rng)
           for _ in range(frames)]
    return {"points": pts, "ego_poses": [np.eye(4)] * frames,
            "timestamps": [0.1 * t for t in range(frames)], "cls": "car",
            "track_id": f"end{seed}"}


@pytest.fixture(scope="module")
def shipped():
    return Estimator.from_pretrained("sequential", backend="torch")


def scaled(track, k):
    out = dict(track, points=[p * np.float32(k) for p in track["points"]])
    egos = []
    for e in track["ego_poses"]:
        e = np.array(e)
        e[:3, 3] *= k
        egos.append(e)
    out["ego_poses"] = egos
    return out


@pytest.mark.parametrize("backend", ["torch", "onnx"])
def test_a_scaled_estimator_is_the_unscaled_one_on_the_scaled_world(backend, tmp_path):
    """``size_scale = k`` on a world equals scale 1 on the world times k, divided by k:
    step by step (points, ego poses, size hints) and whole tracks online and offline."""
    pytest.importorskip("onnxruntime") if backend == "onnx" else None
    k = 1.23
    track = side_track(4.0, 0)
    plain = Estimator.from_pretrained("sequential", backend=backend)
    scaled_est = Estimator.from_pretrained("sequential", backend=backend, size_scale=k)
    big = scaled(track, k)
    for t in range(len(track["points"])):
        a = plain.step(["a"], [big["points"][t]], sizes=[4.0 * k], classes=["car"],
                       ego_poses=[big["ego_poses"][t]], timestamps=[track["timestamps"][t]])[0]
        b = scaled_est.step(["a"], [track["points"][t]], sizes=[4.0], classes=["car"],
                            ego_poses=[track["ego_poses"][t]],
                            timestamps=[track["timestamps"][t]])[0]
        np.testing.assert_allclose(b.pose[:3], a.pose[:3] / k, rtol=0, atol=1e-6)
        assert b.pose[3] == pytest.approx(a.pose[3], abs=1e-9)
        np.testing.assert_allclose(b.complete, a.complete / k, rtol=0, atol=1e-5)
        assert (b.valid, b.flipped, b.num_points) == (a.valid, a.flipped, a.num_points)
    for mode in ("online", "offline"):
        a_all = estimate_tracks(plain, [big], mode)[0]
        b_all = estimate_tracks(scaled_est, [track], mode)[0]
        for a, b in zip(a_all, b_all, strict=True):
            np.testing.assert_allclose(b.pose[:3], a.pose[:3] / k, rtol=0, atol=1e-6)
            np.testing.assert_allclose(b.complete, a.complete / k, rtol=0, atol=1e-5)


def test_the_scale_changes_far_end_on_estimates_and_not_the_inputs(shipped):
    """A car seen end-on is estimated shorter, its centre nearer the sensor, at k > 1
    (what the calibration is for); the caller's arrays are left as they were."""
    track = end_track(4.0, 1)
    before = [p.copy() for p in track["points"]]
    est = Estimator.from_pretrained("sequential", backend="torch")
    plain = est.step(["e"], [track["points"][0]], classes=["car"])[0]
    est.reset()
    est.size_scale = 1.2
    short = est.step(["e"], [track["points"][0]], classes=["car"])[0]
    for p, q in zip(track["points"], before, strict=True):
        np.testing.assert_array_equal(p, q)
    assert short.pose[0] < plain.pose[0] - 0.05  # nearer the sensor at the origin
    assert frame_lengths(short, track["points"][0])[0] < frame_lengths(plain,
                                                                      track["points"][0])[0]


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), 3.0, "x", True, None])
def test_a_bad_size_scale_is_refused(bad, shipped):
    with pytest.raises(ConfigError, match="size_scale"):
        shipped.size_scale = bad
    with pytest.raises(ConfigError, match="size_scale"):
        Estimator.from_pretrained("sequential", backend="torch", size_scale=bad)
    assert shipped.size_scale == 1.0


def test_calibration_follows_the_logs_car_length(shipped):
    """Two logs of broadside cars, 3.8 m and 4.6 m: the seen lengths follow the cars (the
    network measures a whole car seen from the side; on these plain boxes about 0.75 m a
    metre of length, 4.18 and 4.86 m, where a car's real width or the labels would give 1.8
    m or the exact lengths), and the shorter log gets the larger scale, in the ratio of the
    lengths."""
    short = calibrate_size(shipped, [side_track(3.8, s) for s in range(4)])
    long = calibrate_size(shipped, [side_track(4.6, s) for s in range(4)])
    assert short.reason == "" and short.tracks == long.tracks == 4
    assert short.frames >= 12 and long.frames >= 12
    assert short.length == pytest.approx(3.8, abs=0.45)
    assert long.length == pytest.approx(4.6, abs=0.45)
    assert 0.5 <= long.length - short.length <= 1.0
    assert short.prior == long.prior == pytest.approx(shipped_prior("sequential"))
    assert short.scale == pytest.approx(short.prior / short.length) and short.scale > 1.0
    # cars longer than the training data's are not scaled down (SCALE_LIMITS), with the reason
    assert long.length > long.prior and long.scale == 1.0 and "not scaled down" in long.reason
    assert shipped.size_scale == 1.0  # measured at scale 1 and left as it was


def test_calibration_needs_cars_seen_whole(shipped):
    """End-on views show no length, vans are not cars, and too few tracks give scale 1
    with the reason; the scale is clipped to SCALE_LIMITS."""
    ends = calibrate_size(shipped, [end_track(4.0, s) for s in range(4)])
    assert (ends.scale, ends.tracks, ends.length) == (1.0, 0, None)
    assert "0 car tracks" in ends.reason
    vans = [dict(side_track(4.0, s), cls="van") for s in range(4)]
    assert calibrate_size(shipped, vans).tracks == 0
    unknown = [dict(side_track(4.0, s), cls=None) for s in range(4)]
    assert calibrate_size(shipped, unknown).tracks == 4  # a car's length, no class hint
    two = calibrate_size(shipped, [side_track(4.0, s) for s in range(2)])
    assert two.scale == 1.0 and two.tracks == 2 and "3 needed" in two.reason
    assert calibrate_size(shipped, [side_track(4.0, s) for s in range(2)],
                          min_tracks=2).reason == ""
    tiny = calibrate_size(shipped, [side_track(4.0, s) for s in range(3)], prior=2.0)
    huge = calibrate_size(shipped, [side_track(4.0, s) for s in range(3)], prior=9.0)
    assert (tiny.scale, huge.scale) == SCALE_LIMITS
    assert calibrate_size(shipped, []).tracks == 0


def test_the_prior_comes_from_the_weights(shipped, tmp_path):
    assert size_prior(shipped) == shipped_prior("sequential") == pytest.approx(4.5, abs=0.2)
    base = Estimator.from_pretrained("baseline", backend="torch")
    assert size_prior(base) == shipped_prior("baseline")
    table = json.loads((shipped.weights_file.parent / "size_prior.json").read_text())
    assert table["sequential"]["length"] == size_prior(shipped)
    own = Estimator(shipped.model, backend="torch")  # built from a model: no weights file
    with pytest.raises(ConfigError, match="size prior"):
        size_prior(own)
    with pytest.raises(ConfigError, match="size prior"):
        calibrate_size(own, [side_track(4.0, 0)])
    own.metrics["size_prior"] = 4.2
    assert size_prior(own) == 4.2
    own.metrics["size_prior"] = -1
    with pytest.raises(ConfigError, match="between 1 and 20"):
        size_prior(own)
    with pytest.raises(ConfigError, match="prior"):
        calibrate_size(shipped, [side_track(4.0, 0)], prior="long")


def test_evaluate_records_the_calibrated_scale(tmp_path):
    """``seqshape evaluate --size-scale auto`` calibrates each network on the evaluated
    tracks and records it; a number is used as it is; a bad one is a clear error."""
    from seqshape.cli import main
    from seqshape.data import Track, write_dataset

    tracks, inputs = [], []
    for s in range(3):
        tr = side_track(3.8, s)
        inputs.append(dict(tr, track_id=f"car{s}"))
        n = len(tr["points"])
        poses = np.array([[1.0 - 0.5 * t, 7.0, -0.9, 0.0] for t in range(n)])
        meta = {"class": "car", "source": "real", "dataset": "kitti", "log": "0",
                "ego_poses": [e.tolist() for e in tr["ego_poses"]]}
        tracks.append(Track(f"car{s}", tr["points"], poses, None, np.array([3.8, 1.8, 1.5]),
                            np.array(tr["timestamps"]), meta))
    data = write_dataset(tmp_path / "log", tracks)
    out = tmp_path / "eval"
    base = ["evaluate", "--data", str(data.path), "--checkpoint", "pretrained", "--out",
            str(out), "--emd-every", "0", "--workers", "0", "--view", "none", "--no-boxfit"]
    assert main(base + ["--size-scale", "auto"]) == 0
    settings = json.loads((out / "metrics.json").read_text())["settings"]
    for kind in ("sequential", "baseline"):  # as the library finds it on the same tracks
        direct = calibrate_size(Estimator.from_pretrained(kind, backend="auto-float"), inputs)
        cal = settings["size_scale"][kind]
        assert cal == direct.to_dict() and cal["tracks"] == 3 and cal["reason"] == ""
        assert cal["prior"] == pytest.approx(shipped_prior(kind), abs=1e-3)
        assert cal["scale"] > 1.0  # 3.8 m cars: shorter than the fleet's
    assert main(base + ["--size-scale", "1.1", "--offline"]) == 0
    settings = json.loads((out / "metrics.json").read_text())["settings"]
    assert settings["size_scale"] == {"sequential": 1.1, "baseline": 1.1}
    assert main(base) == 0
    assert "size_scale" not in json.loads((out / "metrics.json").read_text())["settings"]
    assert main(base + ["--size-scale", "big"]) == 1


def test_the_scale_applies_to_cars_and_unknown_classes_only():
    """A van, truck or bus keeps its learned sizes (the calibration measures cars): its
    estimates at any size_scale are those at scale 1, step by step and whole tracks; a track
    without a class hint is scaled as a car."""
    track = side_track(5.0, 3)
    plain = Estimator.from_pretrained("sequential", backend="torch")
    big = Estimator.from_pretrained("sequential", backend="torch", size_scale=1.2)
    for t in range(3):
        kw = dict(ego_poses=[track["ego_poses"][t]], timestamps=[track["timestamps"][t]])
        a = plain.step(["v", "u"], [track["points"][t]] * 2, classes=["van", None],
                       **{k: v * 2 for k, v in kw.items()})
        b = big.step(["v", "u"], [track["points"][t]] * 2, classes=["van", None],
                     **{k: v * 2 for k, v in kw.items()})
        np.testing.assert_array_equal(a[0].pose, b[0].pose)
        np.testing.assert_array_equal(a[0].complete, b[0].complete)
        assert np.abs(a[1].pose[:2] - b[1].pose[:2]).max() > 1e-3  # scaled: another estimate
    for cls in ("van", "truck", "bus", "trailer"):
        a = estimate_tracks(plain, [dict(track, cls=cls)], "offline")[0]
        b = estimate_tracks(big, [dict(track, cls=cls)], "offline")[0]
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x.pose, y.pose)
