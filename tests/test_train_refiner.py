"""Training the placement refiner (seqshape.train.refiner, ``seqshape train-refiner``): the
frames it collects, the mirror augmentation against a hand computation, determinism, and an
interrupted run resumed bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _model_data import make_dataset

torch = pytest.importorskip("torch")

from seqshape.cli import main  # noqa: E402
from seqshape.errors import ConfigError  # noqa: E402
from seqshape.model import Estimator, ModelConfig, ShapePoseNet  # noqa: E402
from seqshape.model import placement as P  # noqa: E402
from seqshape.train import refiner as R  # noqa: E402

CFG = ModelConfig(num_points=32, encoder1=(16, 32), encoder2=(32, 32), hidden=24,
                  shape_decoder=(32,), pose_decoder=(32,), num_complete=64,
                  shape_frame="canonical")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("refdata"), n_train=4, n_val=2, frames=6)


@pytest.fixture(scope="module")
def frames(data):
    torch.manual_seed(0)
    est = Estimator(ShapePoseNet(CFG), threads=1)
    return R.collect_frames(est, data.split("train"))


def test_collected_frames_are_the_frames_with_points(data, frames):
    tracks = list(data.split("train"))
    n = sum(int((tr.num_points > 0).sum()) for tr in tracks)
    assert len(frames["n"]) == n and frames["pts"].shape == (n, R.STORED_POINTS, 3)
    first = tracks[0]
    t0 = int(np.flatnonzero(first.num_points > 0)[0])
    np.testing.assert_array_equal(frames["true"][0], first.poses[t0])
    assert frames["n"][0] == len(first.points[t0])
    got = R.frame_points(frames, 0)
    assert len(got) == min(len(first.points[t0]), R.STORED_POINTS)
    assert np.isin(got, first.points[t0]).all()
    assert np.all(np.isfinite(frames["est"])) and np.all(frames["ext"] > 0)


def test_mirror_negates_the_lateral_offset_and_the_turn():
    rng = np.random.default_rng(0)
    est = np.array([12.0, -4.0, -1.0, 0.7])
    true = est + [0.3, -0.2, 0.05, 0.04]
    pts = rng.normal(size=(50, 3)) + est[:3]
    before_t = P.targets(est, true)[0]
    before_q = P.box_frame(pts, est)
    before_s = P.box_frame(np.zeros((1, 3)), est)[0]
    e2, t2, p2 = est.copy(), true.copy(), pts.copy()
    R._mirror(p2, e2, t2)
    assert e2[3] == est[3]
    np.testing.assert_allclose(P.targets(e2, t2)[0], before_t * [1, -1, 1, -1], atol=1e-9)
    np.testing.assert_allclose(P.box_frame(p2, e2), before_q * [1, -1, 1], atol=1e-9)
    # the sensor is still at the origin, now on the mirrored side of the box
    np.testing.assert_allclose(P.box_frame(np.zeros((1, 3)), e2)[0], before_s * [1, -1, 1],
                               atol=1e-9)
    assert math.isclose(np.hypot(*e2[:2]), np.hypot(*est[:2]), rel_tol=1e-12)


def test_batches_are_seeded(frames):
    idx = np.arange(min(8, len(frames["n"])))
    a = R.make_batch(frames, idx, np.random.default_rng(3), 0.5)
    b = R.make_batch(frames, idx, np.random.default_rng(3), 0.5)
    for x, y in zip(a, b, strict=True):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    c = R.make_batch(frames, idx, np.random.default_rng(4), 0.5)
    assert not torch.equal(a[0], c[0])


def test_interrupted_training_resumes_bit_for_bit(frames, tmp_path):
    cfg = R.RefinerTrainConfig(steps=6, batch=8, checkpoint_every=3)
    whole = R.train_refiner(frames, {"v": frames}, tmp_path / "whole", cfg)
    # the same run stopped after its first checkpoint, then resumed
    part = tmp_path / "part"
    R.train_refiner(frames, {}, part, R.RefinerTrainConfig(steps=6, batch=8,
                                                          checkpoint_every=3, minutes=1e-9))
    assert torch.load(part / "refiner.ckpt", weights_only=False)["step"] == 1
    with pytest.raises(ConfigError, match="other settings"):
        R.train_refiner(frames, {}, part, cfg, resume=True)
    stop3 = tmp_path / "stop3"
    R.train_refiner(frames, {}, stop3, R.RefinerTrainConfig(steps=3, batch=8,
                                                           checkpoint_every=3))
    # a 3-step run's checkpoint is not a 6-step run's (the schedule differs): refused
    with pytest.raises(ConfigError, match="other settings"):
        R.train_refiner(frames, {}, stop3, cfg, resume=True)
    # interrupt a 6-step run after its checkpoint at step 3 by raising in the 4th step
    calls = {"n": 0}
    real = R.make_batch

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real(*a, **k)

    cut = tmp_path / "cut"
    R.make_batch = failing
    try:
        with pytest.raises(KeyboardInterrupt):
            R.train_refiner(frames, {}, cut, cfg)
    finally:
        R.make_batch = real
    assert torch.load(cut / "refiner.ckpt", weights_only=False)["step"] == 3
    resumed = R.train_refiner(frames, {"v": frames}, cut, cfg, resume=True)
    for k, v in whole.net.state_dict().items():
        torch.testing.assert_close(resumed.net.state_dict()[k], v, rtol=0, atol=0)
    back = P.PlacementRefiner.load(tmp_path / "whole" / "refiner.pt")
    assert back.meta["steps"] == 6 and "v" in back.meta["val"]


def test_cli_trains_from_dataset_folders(data, tmp_path, monkeypatch, capsys):
    weights = tmp_path / "model.pt"
    torch.manual_seed(0)
    from seqshape.model.estimator import Estimator as E

    monkeypatch.setattr(E, "load", classmethod(
        lambda cls, spec, **kw: Estimator(ShapePoseNet(CFG, recurrent=kw.get("kind") !=
                                                       "baseline"), threads=1)))
    out = tmp_path / "out"
    argv = ["train-refiner", "--data", str(data.path),
            "--out", str(out), "--steps", "4", "--batch", "4", "--checkpoint", str(weights)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "val, sequential" in text and "val, baseline" in text
    assert (out / "refiner.pt").exists() and len(list((out / "frames").glob("*.npz"))) == 4
    assert main(argv[:-2] + ["--every", "1", "2", "3"]) == 1  # one --every per folder
