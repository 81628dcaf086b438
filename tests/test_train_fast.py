"""The fast training path (issue 17) against the reference step it replaced.

k-d-tree Chamfer search against the dense one and a brute-force double loop; trimmed padding and
selected-frame decoding against :func:`seqshape.train.reference.reference_losses`; the batch
prefetcher against building batches in place; fused Adam against plain Adam.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from _model_data import make_dataset
from test_losses import brute_chamfer

from seqshape.data.windows import FRAME_KEYS, WindowDataset, batch_for_step, trim_padding
from seqshape.errors import DataError
from seqshape.geometry import canonical_to_sensor
from seqshape.testing import box_shell
from seqshape.train import Trainer, get_train_config
from seqshape.train.losses import (
    _nearest_indices_dense,
    _nearest_indices_kdtree,
    chamfer_distance,
)
from seqshape.train.prefetch import BatchPrefetcher
from seqshape.train.reference import reference_losses
from seqshape.train.trainer import early_weights, make_adam


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("tracks") / "ds", frames=12)


def _padded_pairs(rng, sizes, offset=20.0):
    """Random clouds far from the origin, padded with far-away rows that must be ignored."""
    n = max(max(s) for s in sizes)
    x, y = torch.zeros(len(sizes), n, 3), torch.full((len(sizes), n, 3), 1e3)
    xs, ys = [], []
    for i, (p, q) in enumerate(sizes):
        xs.append(rng.normal(size=(p, 3)) + offset)
        ys.append(rng.normal(size=(q, 3)) + offset)
        x[i, :p] = torch.from_numpy(xs[i]).float()
        y[i, :q] = torch.from_numpy(ys[i]).float()
    lengths = (torch.tensor([p for p, _ in sizes]), torch.tensor([q for _, q in sizes]))
    return x, y, lengths, xs, ys


def test_kdtree_chamfer_matches_dense_and_brute_force_with_padding():
    rng = np.random.default_rng(0)
    sizes = [(30, 45), (50, 25), (40, 40), (0, 20), (20, 0)]
    x, y, (xl, yl), xs, ys = _padded_pairs(rng, sizes)
    x.requires_grad_()
    out = {}
    for method in ("kdtree", "dense"):
        x.grad = None
        cd = chamfer_distance(x, y, xl, yl, method=method)
        cd.sum().backward()
        out[method] = cd.detach(), x.grad.clone()
    ref = [brute_chamfer(a, b) if len(a) and len(b) else 0.0 for a, b in zip(xs, ys, strict=True)]
    np.testing.assert_allclose(out["kdtree"][0].numpy(), ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["kdtree"][0], out["dense"][0], rtol=1e-6, atol=0)
    torch.testing.assert_close(out["kdtree"][1], out["dense"][1], rtol=1e-6, atol=1e-9)
    assert torch.all(out["kdtree"][1][0, 30:] == 0)  # padded rows get no gradient
    assert out["kdtree"][0][3] == 0 and out["kdtree"][0][4] == 0  # empty cloud: 0


def test_kdtree_chamfer_on_vehicle_clouds_finds_the_true_nearest_neighbours():
    """Real-looking pairs: a 1024-point box surface placed at a pose in the sensor frame and a
    noisy, shifted estimate of it. The dense float32 search can pick a neighbour that is a
    hair farther (a near tie); the k-d tree's never is: equal losses, same neighbours
    almost everywhere, never a farther one."""
    rng = np.random.default_rng(1)
    size = np.array([4.4, 1.8, 1.5])
    gt, est = [], []
    for _ in range(6):
        c = box_shell(1024, rng, size)
        pose = np.array([rng.uniform(5, 40), rng.uniform(-10, 10), -1.0, rng.uniform(-3, 3)])
        gt.append(canonical_to_sensor(c, pose))
        noisy = c[rng.permutation(1024)] + rng.normal(0, 0.08, (1024, 3))
        est.append(canonical_to_sensor(noisy, pose + [0.2, -0.1, 0.0, 0.05]))
    x = torch.from_numpy(np.stack(est)).float()
    y = torch.from_numpy(np.stack(gt)).float()
    full = torch.ones(6, 1024, dtype=torch.bool)
    kd = _nearest_indices_kdtree(x, y, np.full(6, 1024), np.full(6, 1024))
    dense = _nearest_indices_dense(x, y, full, full)
    for (a, b), (src, dst) in zip(zip(kd, dense, strict=True), ((x, y), (y, x)), strict=True):
        assert (a == b).float().mean() > 0.999
        d_kd = (src - torch.gather(dst, 1, a[..., None].expand(-1, -1, 3))).double().norm(dim=-1)
        d_dense = (src - torch.gather(dst, 1, b[..., None].expand(-1, -1, 3))).double().norm(
            dim=-1)
        assert torch.all(d_kd <= d_dense + 1e-9)
        assert float((d_dense - d_kd).max()) < 1e-5
    cd_kd = chamfer_distance(x, y, method="kdtree")
    cd_dense = chamfer_distance(x, y, method="dense")
    torch.testing.assert_close(cd_kd, cd_dense, rtol=1e-6, atol=0)
    assert torch.equal(chamfer_distance(x, y), cd_kd)  # "auto" = k-d trees on CPU


def test_chamfer_non_finite_points_fall_back_to_dense_and_unknown_method_fails():
    x, y = torch.randn(2, 80, 3), torch.randn(2, 80, 3)
    x[1, 5, 0] = float("nan")
    cd = chamfer_distance(x, y, method="kdtree")
    assert torch.isfinite(cd[0]) and torch.isnan(cd[1])
    torch.testing.assert_close(cd[0], chamfer_distance(x[:1], y[:1], method="dense")[0])
    with pytest.raises(ValueError, match="method"):
        chamfer_distance(x, y, method="octree")


def test_trim_padding_drops_only_trailing_frames_nobody_has(dataset):
    every_option = WindowDataset(dataset.split("train"), window=5, num_points=8, num_complete=8,
                                 length_hint_noise=0.1, motion=True)
    assert set(every_option.window_at(0, 0)) - {"complete", "start"} <= set(FRAME_KEYS)
    batch = {"points": torch.zeros(2, 6, 4, 3), "lengths": torch.tensor([[3, 0, 2, 0, 0, 0],
                                                                        [1, 1, 0, 0, 0, 0]]),
             "valid": torch.tensor([[1, 1, 1, 1, 0, 0], [1, 1, 0, 0, 0, 0]]).bool(),
             "poses": torch.zeros(2, 6, 4), "complete": torch.zeros(2, 5, 3),
             "start": torch.zeros(2, dtype=torch.int64), "dts": torch.zeros(2, 6)}
    out = trim_padding(batch)
    assert out["points"].shape == (2, 4, 4, 3) and out["dts"].shape == (2, 4)
    assert out["complete"] is batch["complete"] and out["start"] is batch["start"]
    assert trim_padding(out) is out  # nothing left to trim
    none = dict(batch, lengths=torch.zeros(2, 6, dtype=torch.int64), valid=torch.zeros(2, 6).bool())
    assert trim_padding(none)["lengths"].shape == (2, 1)


def _recipe_trainer(dataset, tmp_path, kind):
    """The smoke network with the shipped recipe's options, windows longer than the tracks
    (12 frames in 16: every window ends in padding)."""
    cfg = get_train_config("smoke")
    overrides = {**cfg.model_overrides, "scale_norm": "length", "scale_ref": 2.0}
    if kind == "sequential":
        overrides.update(motion_input=True, frame_skip=True)
    cfg = dataclasses.replace(cfg, model_overrides=overrides, window=16, length_points_prob=0.5)
    return Trainer(dataset.path, tmp_path / kind, kind, cfg)


def _losses_and_grads(tr, fn):
    tr.model.zero_grad(set_to_none=True)
    for p in tr.model.parameters():
        p.requires_grad_(True)
    res = fn()
    sum(v for k, v in res.items() if k != "frames").backward()
    grads = {k: p.grad.clone() for k, p in tr.model.named_parameters() if p.grad is not None}
    return {k: v.detach() for k, v in res.items()}, grads


@pytest.mark.parametrize("kind", ["sequential", "baseline"])
def test_fast_losses_equal_the_reference_step(dataset, tmp_path, kind):
    tr = _recipe_trainer(dataset, tmp_path, kind)
    tr.runlog.close()
    windows = tr._windows(2)
    for stage in (0, 1, 2):
        batch = batch_for_step(windows, stage, 2)
        assert trim_padding(batch)["points"].shape[1] < batch["points"].shape[1]
        got, g_got = _losses_and_grads(tr, lambda b=batch, s=stage: tr._losses(b, s))
        ref, g_ref = _losses_and_grads(
            tr, lambda b=batch, s=stage: reference_losses(tr.model, b, s, tr._scale(b)))
        assert got.keys() == ref.keys() and g_got.keys() == g_ref.keys()
        for k in ref:
            torch.testing.assert_close(got[k], ref[k], rtol=1e-6, atol=0)
        for k in g_ref:
            torch.testing.assert_close(g_got[k], g_ref[k], rtol=1e-4, atol=1e-7)


def test_early_weights_by_hand():
    lengths = torch.tensor([[0, 5, 0, 3, 4, 2, 0], [7, 7, 7, 0, 0, 0, 0]])
    w = early_weights(lengths, 3.0, 2)
    # row 0: nothing before the first detection; detections 1 and 2 (and the empty frame
    # between them) weigh 4; row 1: frames 0-1 are its first two detections
    torch.testing.assert_close(w, torch.tensor([[1, 4, 4, 4, 1, 1, 1], [4, 4, 1, 1, 1, 1, 1.]]))
    assert torch.all(early_weights(lengths, 0.0, 4) == 1)


def test_early_weight_weighs_each_windows_first_detections(dataset, tmp_path):
    """The weighted objective equals the per-frame losses of the reference averaged with the
    weights (computed here from the frames' detection counts); validation stays unweighted."""
    tr = _recipe_trainer(dataset, tmp_path, "sequential")
    tr.runlog.close()
    windows = tr._windows(2)
    batch = batch_for_step(windows, 0, 2)
    with torch.no_grad():
        plain = tr._losses(batch, 2)
        tr.cfg = dataclasses.replace(tr.cfg, early_weight=4.0, early_frames=3)
        assert tr._losses(batch, 2)["cd"] == plain["cd"]  # unweighted unless asked
        got = tr._losses(batch, 2, weighted=True)
    # the reference's per-frame losses: its batch mean over one selected frame at a time
    sel = (batch["valid"] & (torch.cumsum((batch["lengths"] > 0).long(), 1) > 0)).numpy()
    cds, poses, ws = [], [], []
    for b, t in zip(*np.nonzero(sel), strict=True):
        one = dict(batch, valid=torch.zeros_like(batch["valid"]))
        one["valid"][b, t] = True
        with torch.no_grad():
            ref = reference_losses(tr.model, one, 2, tr._scale(one))
        cds.append(float(ref["cd"]))
        poses.append(float(ref["pose"]))
        ws.append(5.0 if int((batch["lengths"][b, :t + 1] > 0).sum()) <= 3 else 1.0)
    ws = np.array(ws)
    assert 0 < np.sum(ws > 1) < len(ws)
    np.testing.assert_allclose(float(got["cd"]), np.dot(ws, cds) / ws.sum(), rtol=1e-5)
    np.testing.assert_allclose(float(got["pose"]), np.dot(ws, poses) / ws.sum(), rtol=1e-5)
    np.testing.assert_allclose(float(plain["cd"]), np.mean(cds), rtol=1e-5)


def test_prefetched_batches_equal_batches_built_in_place(dataset):
    windows = WindowDataset(dataset.split("train"), window=5, num_points=32, num_complete=64,
                            seed=3, key=1, motion=True)
    with BatchPrefetcher(windows, 3) as batches:
        for step in (0, 1, 2, 7, 3, 4):  # in order, then a jump and back
            got, ref = batches.get(step), batch_for_step(windows, step, 3)
            assert got.keys() == ref.keys()
            assert all(torch.equal(got[k], ref[k]) for k in ref)
    assert batches._pool is None
    in_place = BatchPrefetcher(windows, 3, enabled=False)
    assert torch.equal(in_place.get(5)["points"], batch_for_step(windows, 5, 3)["points"])


class _BrokenEpoch(WindowDataset):
    """Windows whose epoch 2 cannot be read (one batch = one epoch below: step 2 fails)."""

    def window_at(self, i, epoch):
        if epoch == 2:
            raise DataError(self.cache.tracks.path, "unreadable on purpose")
        return super().window_at(i, epoch)


def test_prefetch_errors_surface_at_the_step_that_needs_the_batch(dataset):
    windows = _BrokenEpoch(dataset.split("train"), window=5, num_points=32, num_complete=64,
                           seed=3, key=1)
    with BatchPrefetcher(windows, len(windows)) as batches:
        batches.get(0)
        batches.get(1)  # step 2 now fails in the background ...
        with pytest.raises(DataError, match="on purpose"):
            batches.get(2)  # ... and raises here, where its batch is needed
        batches.get(1)  # step 2 is being built again: its failure is dropped, not raised
        assert batches.get(3)["points"].shape[0] == len(windows)


def test_fused_adam_follows_plain_adam():
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(8, 16), torch.nn.ReLU(), torch.nn.Linear(16, 3))
    twin = [p.detach().clone().requires_grad_() for p in net.parameters()]
    fast = make_adam([{"params": list(net.parameters()), "lr": 1e-2}])
    plain = torch.optim.Adam([{"params": twin, "lr": 1e-2}])
    x = torch.randn(32, 8)
    for _ in range(10):
        for opt, params in ((fast, list(net.parameters())), (plain, twin)):
            opt.zero_grad()
            h = torch.relu(x @ params[0].T + params[1]) @ params[2].T + params[3]
            (h ** 2).mean().backward()
            opt.step()
    for a, b in zip(net.parameters(), twin, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_encoder_max_pool_and_empty_frame_skip_match_the_plain_forms():
    # the encoder pools with max(dim).values (its backward scatters to the argmax rows) and
    # encode() runs it on the frames with points only; both must equal the plain forms: amax
    # pooling over every frame, empty frames giving zero features
    from seqshape.model import MODEL_PRESETS, ShapePoseNet
    torch.manual_seed(0)
    net = ShapePoseNet(dataclasses.replace(MODEL_PRESETS["small"], num_complete=64))
    enc = net.encoder
    f, n = 6, 40
    x = torch.randn(f, n, 3)
    mask = torch.rand(f, n) < 0.7
    mask[[1, 4]] = False  # two empty frames
    mask[2, 1:] = False  # one point: ties everywhere in its max pool

    def plain(x, mask):  # the same forward with amax pools, every frame encoded
        orig = torch.Tensor.max
        try:
            torch.Tensor.max = lambda t, dim=None, **k: (  # noqa: E731
                orig(t) if dim is None else type("V", (), {"values": t.amax(dim=dim)})())
            return enc(x, mask)
        finally:
            torch.Tensor.max = orig

    a = net._frame_features(x, mask)
    b = plain(x, mask)
    assert torch.equal(a[[1, 4]], torch.zeros_like(a[[1, 4]]))
    assert torch.allclose(a, b, rtol=0, atol=1e-6)
    ga = torch.autograd.grad(a.square().sum(), list(enc.parameters()))
    gb = torch.autograd.grad(b.square().sum(), list(enc.parameters()))
    for u, v in zip(ga, gb, strict=True):
        assert torch.allclose(u, v, rtol=1e-4, atol=1e-6)
