"""Motion inputs of the sequential model (``ModelConfig.motion_input``, issue 19): the vector
the GRU receives on a hand-made track, zero initialisation (the shipped weights reproduce),
streaming == batch, training windows and the ``--init`` / ``--model-set`` paths."""

from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np
import pytest
import torch
from _model_data import make_dataset

from seqshape.data import Track
from seqshape.data.windows import WindowDataset, window_motion
from seqshape.errors import ConfigError
from seqshape.model import Estimator, ModelConfig, ShapePoseNet
from seqshape.model.estimator import PRETRAINED_DIR, build_model, read_model_file
from seqshape.model.network import add_motion_columns, motion_features
from seqshape.scripts import train as train_script
from seqshape.train import Trainer, get_train_config
from seqshape.train.checkpoint import load_init

TINY = ModelConfig(num_points=64, encoder1=(8, 16), encoder2=(16, 24), hidden=20,
                   shape_decoder=(32,), pose_decoder=(16,), num_complete=40)
MOTION = dataclasses.replace(TINY, motion_input=True)
SMOKE = get_train_config("smoke")


def _motion_net(randomise: bool = True) -> ShapePoseNet:
    torch.manual_seed(0)
    net = ShapePoseNet(MOTION).eval()
    if randomise:  # non-zero motion columns, so that the motion changes the outputs
        with torch.no_grad():
            net.fusion.weight_ih[:, TINY.feature_size:].normal_(0.0, 0.5)
    return net


def _cloud(centre, n, rng):
    """``n`` points whose mean is exactly ``centre`` (float32)."""
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    pts -= pts.mean(0)
    return (pts + np.asarray(centre, np.float32)).astype(np.float32)


def test_motion_vector_reaching_the_gru_is_the_hand_computed_one():
    """Frames: points at (10, 0, 0) (4 of them), an empty frame, points at (11, 0.5, 0.2)
    (500 before resampling): the third frame's m_t is the displacement (1, 0.5, 0.2) / s,
    the 0.25 s since the first frame, log1p(500)/log1p(1000), and the direction of (11, 0.5)."""
    net = _motion_net()
    n = TINY.num_points
    points = torch.zeros(1, 3, n, 3)
    points[0, 0, :4] = torch.tensor([[10, 0, 0], [10, 1, 0], [10, -1, 0], [10, 0, 0]],
                                    dtype=torch.float32)
    points[0, 2, :2] = torch.tensor([[11, 0.5, 1.2], [11, 0.5, -0.8]])
    lengths = torch.tensor([[4, 0, 2]])
    counts = torch.tensor([[4, 0, 500]])
    dts = torch.tensor([[0.0, 0.1, 0.15]])
    calls, gru = [], net._gru

    def spy(f, m, h):
        calls.append((f, m, h))
        return gru(f, m, h)

    net._gru = spy
    with torch.no_grad():
        enc = net.encode(points, lengths, scale=torch.tensor([[2.0, 2.0, 2.0]]), dts=dts,
                         counts=counts)
        # the GRU step equals a GRU cell on the concatenated input [f_t, m_t]
        f, m, h = calls[2]
        np.testing.assert_allclose(gru(f, m, h).numpy(),
                                   net.fusion(torch.cat([f, m], -1), h).numpy(), atol=1e-6)
    c = 1.0 / math.log1p(1000)
    first = [0, 0, 0, 0, math.log1p(4) * c, 1, 0]
    third = [0.5, 0.25, 0.1, 0.25, math.log1p(500) * c, 11 / math.hypot(11, 0.5),
             0.5 / math.hypot(11, 0.5)]
    gru_motion = torch.stack([m[0] for _, m, _ in calls])
    np.testing.assert_allclose(gru_motion[0].numpy(), first, atol=1e-6)
    np.testing.assert_allclose(gru_motion[2].numpy(), third, atol=1e-6)
    np.testing.assert_allclose(enc["motion"][0, 2].numpy(), third, atol=1e-6)
    assert enc["seen"].tolist() == [[True, True, True]]
    assert float(enc["gap"][0]) == 0.0  # the last frame had points


def test_motion_features_clips_and_a_fresh_track_has_no_motion():
    mean = torch.tensor([[30.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    last = torch.tensor([[10.0, 0.0, 0.0], [5.0, 5.0, 0.0]])
    m = motion_features(mean, last, torch.tensor([True, False]), torch.tensor([3.0, 1.0]),
                        torch.tensor([0, 1000]))
    np.testing.assert_allclose(m[0].numpy(), [5, 0, 0, 2, 0, 1, 0], atol=1e-6)
    np.testing.assert_allclose(m[1].numpy(), [0, 0, 0, 0, 1, 0, 0], atol=1e-6)


def test_motion_changes_the_estimate_and_zero_columns_do_not():
    rng = np.random.default_rng(1)
    frames = [_cloud([10, 0, -1], 40, rng), _cloud([10.8, 0.3, -1], 40, rng)]
    est = Estimator(_motion_net())
    a = [est.step(["t"], [f], timestamps=[k * 0.1])[0] for k, f in enumerate(frames)]
    est.reset()
    b = [est.step(["t"], [f], timestamps=[k * 1.0])[0] for k, f in enumerate(frames)]
    np.testing.assert_array_equal(a[0].complete, b[0].complete)  # first detection: no motion
    assert np.abs(a[1].complete - b[1].complete).max() > 1e-4  # a different time step reaches
    zero = _motion_net(randomise=False)
    assert not zero.fusion.weight_ih[:, TINY.feature_size:].any()
    torch.manual_seed(0)
    plain = ShapePoseNet(TINY).eval()
    plain.load_state_dict({k: v[:, :TINY.feature_size] if k == "fusion.weight_ih" else v
                           for k, v in zero.state_dict().items()})
    # the same function up to float rounding: the GRU's input product has 7 more (zero) columns,
    # and a BLAS may block a product of another shape differently (bit for bit on some CPUs,
    # last-digit differences on AVX-512 ones), on the reference and the fast backends alike
    for backend in ("torch", "auto"):
        e1, e2 = Estimator(zero, backend=backend), Estimator(plain, backend=backend)
        for k, f in enumerate(frames):
            x, y = e1.step(["t"], [f], timestamps=[k * 0.3])[0], e2.step(["t"], [f])[0]
            np.testing.assert_allclose(x.complete, y.complete, rtol=0, atol=1e-5)
            np.testing.assert_allclose(x.pose, y.pose, rtol=0, atol=1e-6)


def test_shipped_weights_padded_with_zero_columns_reproduce_the_shipped_model():
    """The ``--init pretrained`` path into a motion_input run: bitwise the same outputs."""
    payload = read_model_file(PRETRAINED_DIR / "sequential.pt")
    old = build_model(payload)
    cfg = dataclasses.replace(old.cfg, motion_input=True)
    state_dict, record = load_init("pretrained", "sequential", cfg)
    assert state_dict["fusion.weight_ih"].shape == (3 * cfg.hidden, cfg.feature_size + 7)
    assert record["source"] == "pretrained"
    new = ShapePoseNet(cfg)
    new.load_state_dict(state_dict)
    rng = np.random.default_rng(2)
    centres = [[9, 3, -1], [9.4, 3.1, -1], None, [10.1, 3.3, -1], [10.5, 3.2, -1]]
    e_old, e_new = Estimator(old), Estimator(new)
    for k, centre in enumerate(centres):
        pts = (_cloud(centre, 120, rng) * [1, 1, 0.3] if centre is not None
               else np.zeros((0, 3), np.float32))
        ts = [1.7e9 + 0.1 * k]  # the same inputs: the weights alone may differ
        a = e_old.step(["car"], [pts], timestamps=ts)[0]
        b = e_new.step(["car"], [pts], timestamps=ts)[0]
        assert np.array_equal(b.complete, a.complete) and np.array_equal(b.pose, a.pose)
    # already padded weights and the paper configuration pass through unchanged
    assert add_motion_columns(state_dict, cfg) is state_dict
    assert add_motion_columns(payload["state_dict"], old.cfg) is payload["state_dict"]


def _track(rng, timestamps):
    centres = [[8 + 0.7 * k, 2 + 0.2 * k, -1] for k in range(len(timestamps))]
    points = [_cloud(c, int(rng.integers(5, 60)), rng) for c in centres]
    points[3] = points[3][:0]  # an empty frame
    poses = np.array([[*c, 0.1] for c in centres])
    return Track("t", points, poses, rng.normal(size=(50, 3)), np.array([4.5, 1.8, 1.5]),
                 np.asarray(timestamps, np.float64), {"split": "train"})


@pytest.mark.parametrize("start", [0, 2])
def test_streaming_equals_one_forward_pass_over_the_window(start):
    """Estimator step by step (absolute timestamps ~1.7e9 s) == the network over the window
    the trainer builds (window_motion), also for a window that starts mid-track."""
    rng = np.random.default_rng(3)
    ts = 1.7e9 + np.array([0.0, 0.1, 0.25, 0.35, 0.45, 1.0, 1.1])
    track = _track(rng, ts)
    net = _motion_net()
    w = len(track) - start
    dts, counts = window_motion(track, start, w, w)
    points = np.zeros((1, w, TINY.num_points, 3), np.float32)
    for k in range(w):
        f = track.points[start + k]
        if len(f):
            points[0, k] = np.resize(f, (TINY.num_points, 3))
    with torch.no_grad():
        batch = net(torch.from_numpy(points), torch.from_numpy(counts[None]),
                    dts=torch.from_numpy(dts[None]), counts=torch.from_numpy(counts[None]))
    with torch.no_grad():  # per-frame times instead of dts: the same
        by_times = net(torch.from_numpy(points), torch.from_numpy(counts[None]),
                       times=torch.from_numpy((ts[start:] - ts[start])[None]),
                       counts=torch.from_numpy(counts[None]))
    np.testing.assert_allclose(by_times["pose"].numpy(), batch["pose"].numpy(), atol=1e-5)
    est = Estimator(net)
    for k in range(w):
        out = est.step(["t"], [track.points[start + k]], timestamps=[ts[start + k]])[0]
        np.testing.assert_allclose(out.complete, batch["complete"][0, k].numpy(), atol=1e-5)
        np.testing.assert_allclose(out.pose, batch["pose"][0, k].numpy(), atol=1e-5)
    # without timestamps the Estimator assumes one frame period per step
    est2 = Estimator(net, frame_period=0.25)
    regular = [est2.step(["u"], [track.points[k]])[0] for k in range(3)]
    with torch.no_grad():
        ref = net(torch.from_numpy(_pad(track.points[:3])), torch.tensor([[len(p) for p in
                                                                            track.points[:3]]]),
                  dts=torch.full((1, 3), 0.25))
    np.testing.assert_allclose(regular[2].pose, ref["pose"][0, 2].numpy(), atol=1e-5)
    est2.reset()
    nan = [est2.step(["u"], [track.points[k]], timestamps=[[0.0, np.nan, 0.5][k]])[0]
           for k in range(3)]  # NaN: unknown, one frame period
    np.testing.assert_allclose(nan[2].pose, ref["pose"][0, 2].numpy(), atol=1e-5)
    with pytest.raises(ConfigError, match="timestamps"):
        est2.step(["u"], [track.points[0]], timestamps=["noon"])


def _pad(frames):
    out = np.zeros((1, len(frames), TINY.num_points, 3), np.float32)
    for k, f in enumerate(frames):
        out[0, k] = np.resize(f, (TINY.num_points, 3))
    return out


def test_window_motion_entries(tmp_path):
    rng = np.random.default_rng(4)
    track = _track(rng, 1.7e9 + np.array([0.0, 0.1, 0.3, np.nan, 0.5, 0.6, 0.7]))
    dts, counts = window_motion(track, 1, 4, 6)
    np.testing.assert_allclose(dts[:3], [0.0, 0.2, np.nan], atol=1e-6)
    assert np.isnan(dts[3]) and (dts[4:] == 0).all()
    assert counts.tolist() == [len(track.points[k]) for k in range(1, 5)] + [0, 0]
    ds = make_dataset(tmp_path / "ds", n_train=2, n_val=1)
    plain = WindowDataset(ds.split("train"), window=4, num_points=32, num_complete=16)
    motion = WindowDataset(ds.split("train"), window=4, num_points=32, num_complete=16,
                           motion=True)
    a, b = plain.window_at(1, 0), motion.window_at(1, 0)
    assert set(b) - set(a) == {"dts", "counts"}
    assert all(np.array_equal(a[k], b[k]) for k in a)  # the rest is unchanged


def test_config_and_baseline():
    assert ModelConfig.from_dict(MOTION.to_dict()) == MOTION
    assert MOTION.motion_size == 7 and TINY.motion_size == 0
    with pytest.raises(ConfigError, match="motion_input"):
        ModelConfig(motion_input="yes")
    torch.manual_seed(0)
    base = ShapePoseNet(MOTION, recurrent=False)
    torch.manual_seed(0)
    ref = ShapePoseNet(TINY, recurrent=False)
    assert base.motion_size == 0
    pts = torch.randn(2, 3, TINY.num_points, 3) + 8
    lengths = torch.tensor([[5, 0, 9], [64, 3, 1]])
    with torch.no_grad():
        assert torch.equal(base(pts, lengths)["complete"], ref(pts, lengths)["complete"])


def test_model_set_parses_and_training_reaches_the_motion_columns(tmp_path):
    parser = argparse.ArgumentParser()
    train_script.add_arguments(parser)
    args = parser.parse_args(["--data", "x", "--out", "y", "--preset", "smoke",
                              "--model-set", "motion_input=true", "--stage-steps", "3,0,2"])
    cfg = train_script.build_config(args)
    assert cfg.model_config().motion_input is True
    ds = make_dataset(tmp_path / "ds", n_train=3, n_val=1)
    tr = Trainer(ds.path, tmp_path / "run", "sequential", cfg)
    f = tr.model.cfg.feature_size
    assert not tr.model.fusion.weight_ih[:, f:].any()
    out = tr.run()
    weights = torch.load(out, weights_only=True)
    assert weights["model_config"]["motion_input"] is True
    assert weights["state_dict"]["fusion.weight_ih"][:, f:].abs().sum() > 0
    # weights with motion inputs do not load into a run without them
    with pytest.raises(ConfigError, match="motion_input"):
        load_init(out, "sequential", tr.model.cfg.__class__.from_dict(
            {**weights["model_config"], "motion_input": False}))
