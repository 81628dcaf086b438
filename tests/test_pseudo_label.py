"""Pseudo-labels for self-supervised fine-tuning (``seqshape pseudo-label``,
:mod:`seqshape.train.pseudo`)."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest
from _model_data import box_track, make_dataset, write_checkpoint

from seqshape.cli import main
from seqshape.data import Track, TrackDataset
from seqshape.data.reference import BOX_MARGIN
from seqshape.geometry import canonical_to_sensor, sensor_to_canonical
from seqshape.model import Estimator, ModelConfig
from seqshape.model.offline import estimate_tracks
from seqshape.train.pseudo import pseudo_label, pseudo_track

CFG = ModelConfig(num_points=32, encoder1=(16, 32), encoder2=(32, 32), hidden=24,
                  shape_decoder=(32,), pose_decoder=(32,), num_complete=64,
                  shape_frame="canonical")


@dataclass
class _Est:
    pose: np.ndarray
    complete: np.ndarray
    valid: bool = True


def test_true_estimates_give_the_true_poses_and_an_accumulation_inside_the_box():
    """Fed the true poses (a perfect estimator), the pseudo-labels are the truth: the same
    poses, the extents of the true shape, and a mirrored accumulation of the track's own
    points that lies within the true box (plus the reference's margin)."""
    tr = box_track("t", "train", np.random.default_rng(4), frames=12, empty_frame=5)
    frames = range(0, 12)
    ests = [_Est(tr.poses[t], canonical_to_sensor(tr.complete, tr.poses[t])) for t in frames]
    out = pseudo_track(tr, ests, frames, "truth")
    np.testing.assert_array_equal(out.poses, tr.poses)
    np.testing.assert_allclose(out.size[:2], tr.size[:2], rtol=0.03)  # 1st-99th percentiles
    assert out.complete is not None and len(out.complete) == 2048
    half = out.size / 2 + BOX_MARGIN + 1e-6
    assert np.all(np.abs(out.complete[:, :2]) <= half[:2])
    # mirrored: the cloud's y -> -y image is the cloud (as sets, up to resampling)
    assert abs(float(np.mean(out.complete[:, 1]))) < 0.05
    assert out.meta["pseudo"]["frames"] == 12 and out.meta["split"] == "train"
    assert out.meta["reference"]["kind"] == "accumulated"


def test_poses_are_the_offline_estimates_and_nan_outside_the_detections(tmp_path):
    est = Estimator.load(write_checkpoint(tmp_path / "s.pt", "sequential", CFG),
                         backend="torch", refiner="none")
    rng = np.random.default_rng(1)
    tr = box_track("a", "val", rng, frames=10)
    pts = list(tr.points)
    pts[0] = pts[0][:0]
    pts[9] = pts[9][:0]  # no detection in the first and last frames
    tr = Track(tr.track_id, pts, tr.poses, tr.complete, tr.size, tr.timestamps,
               {**tr.meta, "class": "car"})
    empty = Track("e", [p[:0] for p in pts], tr.poses, None, tr.size, tr.timestamps,
                  {"split": "train"})
    out = pseudo_label([tr, empty], est, source="test")
    want = estimate_tracks(est, [{"points": pts[1:9], "timestamps": tr.timestamps[1:9],
                                  "cls": "car", "ego_poses": [np.eye(4)] * 8,
                                  "track_id": "a"}], "offline")[0]
    np.testing.assert_allclose(out[0].poses[1:9], [w.pose for w in want], atol=1e-9)
    assert np.isnan(out[0].poses[[0, 9]]).all()
    assert not np.allclose(out[0].poses[1:9], tr.poses[1:9])  # not the annotations
    # an untrained network's boxes hold none of the points: no shape, and the reason is kept
    local = np.concatenate([sensor_to_canonical(pts[t], out[0].poses[t]) for t in range(1, 9)])
    inside = np.all(np.abs(local[:, :2]) <= out[0].size[:2] / 2 + BOX_MARGIN, axis=1)
    if inside.sum() < 50:
        assert out[0].complete is None
        assert "usable points" in out[0].meta["reference"]["error"]
    assert np.all(np.isnan(out[1].poses)) and out[1].complete is None
    assert out[1].meta["reference"]["kind"] is None


def _perfect(monkeypatch, data):
    """The offline estimates replaced by the truth (an untrained network's boxes hold none of
    the points, so no track would get a shape)."""
    truth = {data[i].track_id: data[i] for i in range(len(data))}

    def estimate(est, tracks, mode):
        out = []
        for a in tracks:
            tr = truth[a["track_id"]]
            first = int(np.flatnonzero(tr.num_points > 0)[0])
            out.append([_Est(tr.poses[first + k], canonical_to_sensor(tr.complete,
                                                                        tr.poses[first + k]))
                        for k in range(len(a["points"]))])
        return out
    monkeypatch.setattr("seqshape.train.pseudo.estimate_tracks", estimate)


def test_cli_with_an_untrained_network_says_there_is_nothing_to_tune_on(tmp_path):
    data = make_dataset(tmp_path / "ds", n_train=2, n_val=1, frames=6)
    ckpt = write_checkpoint(tmp_path / "s.pt", "sequential", CFG)
    assert main(["pseudo-label", "--data", str(data.path), "--out", str(tmp_path / "p"),
                 "--checkpoint", ckpt, "--refiner", "none"]) == 1
    assert not (tmp_path / "p" / "manifest.json").exists()


def test_cli_writes_a_dataset_that_trains(tmp_path, monkeypatch):
    data = make_dataset(tmp_path / "ds", n_train=2, n_val=1, frames=6)
    ckpt = write_checkpoint(tmp_path / "s.pt", "sequential", CFG)
    _perfect(monkeypatch, data)
    out = tmp_path / "pseudo"
    assert main(["pseudo-label", "--data", str(data.path), "--out", str(out), "--checkpoint",
                 ckpt, "--refiner", "none"]) == 0
    ds = TrackDataset(out)
    assert sorted(ds[i].track_id for i in range(len(ds))) == sorted(
        data[i].track_id for i in range(len(data)))
    assert {e["split"] for e in ds.entries} == {"train", "val"}
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["pseudo_label"]["checkpoint"] == ckpt
    for i in range(len(ds)):
        assert ds[i].meta["pseudo"]["labels"] == "offline estimates"
        assert ds[i].complete is not None and ds[i].meta["reference"]["kind"] == "accumulated"
    assert not (tmp_path / "pseudo.partial").exists()  # written aside, then renamed
    # refuses to write into a folder that holds something
    assert main(["pseudo-label", "--data", str(data.path), "--out", str(out), "--checkpoint",
                 ckpt, "--refiner", "none"]) == 1
    # only one split
    assert main(["pseudo-label", "--data", str(data.path), "--out", str(tmp_path / "v"),
                 "--checkpoint", ckpt, "--refiner", "none", "--split", "val"]) == 0
    assert len(TrackDataset(tmp_path / "v")) == 1
    # fine-tuning on them runs (two stage-3 steps from the same weights)
    run = tmp_path / "run"
    assert main(["train", "--data", str(out), "--model", "sequential", "--init", ckpt,
                 "--stage-steps", "0,0,2", "--no-tensorboard", "--threads", "1",
                 "--preset", "smoke", "--out", str(run)]) == 0
    assert (run / "model.pt").exists()


@pytest.mark.parametrize("split", ["nope"])
def test_cli_rejects_an_unknown_split(tmp_path, split):
    with pytest.raises(SystemExit):
        main(["pseudo-label", "--data", str(tmp_path), "--out", str(tmp_path / "o"),
              "--split", split])
