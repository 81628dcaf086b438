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


def test_collected_sizes_are_the_true_shapes_extents(data, frames):
    first = list(data.split("train"))[0]
    np.testing.assert_allclose(frames["size"][0], P.extents_of(first.complete, np.zeros(4)))
    assert np.all(np.isfinite(frames["size"])) and frames["size"].shape == (len(frames["n"]), 3)


def test_size_targets_and_loss(frames):
    idx = np.arange(min(6, len(frames["n"])))
    _, _, tgt = R.make_batch(frames, idx, np.random.default_rng(0), 0.0)
    want = np.log(frames["size"][idx, :2] / frames["ext"][idx, :2])  # no jitter: the estimate's
    np.testing.assert_allclose(tgt[:, 4:6].numpy(), want, rtol=1e-5, atol=1e-6)
    out = torch.zeros(len(idx), 6)
    total, centre, axis, size = R.loss_terms(out, tgt)
    assert float(size) > 0 and math.isclose(float(total), float(centre + 0.5 * axis + 0.5 * size),
                                            rel_tol=1e-6)
    tgt[:, 4:6] = float("nan")  # sizes unknown: no size term, a finite loss
    total, *_, size = R.loss_terms(out, tgt)
    assert float(size) == 0 and math.isfinite(float(total))
    assert float(R.loss_terms(out[:, :4], tgt)[3]) == 0  # a network without the size head


def test_size_head_warm_start_keeps_the_placement_and_learns_sizes(frames, tmp_path):
    torch.manual_seed(0)
    init = P.PlacementRefiner(P.build_net())
    with torch.no_grad():
        for p in init.net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    cfg = R.RefinerTrainConfig(steps=1, batch=4, lr=1e-12, size=True)
    ref = R.train_refiner(frames, {}, tmp_path / "warm", cfg, init=init)
    assert ref.net.outputs == 6
    idx = list(range(min(5, len(frames["n"]))))
    pts = [R.frame_points(frames, i) for i in idx]
    a = init.corrections(pts, frames["est"][idx], frames["ext"][idx], seeds=idx)
    b = ref.corrections(pts, frames["est"][idx], frames["ext"][idx], seeds=idx)
    np.testing.assert_allclose(b[:, :4], a, atol=1e-6)  # lr ~0: the placement is init's
    assert np.abs(b[:, 4:]).max() < 1e-6  # the new rows start at 0
    loaded = P.PlacementRefiner.load(tmp_path / "warm" / "refiner.pt")
    assert loaded.net.outputs == 6
    # trained for real, the size head moves the extents toward the true ones
    cfg = R.RefinerTrainConfig(steps=150, batch=16, lr=3e-3, size=True, jitter=1.0)
    ref = R.train_refiner(frames, {"train": frames}, tmp_path / "trained", cfg, init=init)
    before, after = ref.meta["val"]["train"]["estimated"], ref.meta["val"]["train"]["refined"]
    assert after["length_median"] < before["length_median"]


def test_size_needs_true_shapes(frames, tmp_path):
    blind = {**frames, "size": np.full_like(frames["size"], np.nan)}
    with pytest.raises(ConfigError, match="no training frame has a true shape"):
        R.train_refiner(blind, {}, tmp_path, R.RefinerTrainConfig(steps=1, size=True))
