"""Estimator: batched == per-track, empty frames, any point count, weight files."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from seqshape.errors import DataError
from seqshape.model import Estimator, ModelConfig, ShapePoseNet
from seqshape.model import estimator as estimator_module
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
    # a track with no points yet is decoded around the origin (no known mean)
    assert np.linalg.norm(out[0].complete.mean(0)) < np.linalg.norm(out[2].complete.mean(0))


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
    nan[:5] = np.nan  # non-finite rows are dropped, not propagated
    assert np.all(np.isfinite(b.step(["y"], [nan])[0].complete))


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
    np.testing.assert_array_equal(est.step(["a"], [pts])[0].complete, ref.complete)


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
    monkeypatch.setattr(estimator_module, "PRETRAINED_DIR", tmp_path)
    with pytest.raises(DataError, match="seqshape train --model baseline"):
        Estimator.from_pretrained("baseline")
    save_payload(tmp_path / "sequential.pt", model_payload(_model(), {}, {}))
    assert Estimator.from_pretrained("sequential").recurrent
