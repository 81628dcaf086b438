"""ShapePoseNet: shapes, masking, demeaning, empty frames, presets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seqshape.data.windows import resample_frame
from seqshape.errors import ConfigError
from seqshape.model import MODEL_PRESETS, ModelConfig, ShapePoseNet

TINY = ModelConfig(num_points=32, encoder1=(8, 16), encoder2=(16, 24), hidden=20,
                   shape_decoder=(32,), pose_decoder=(16,), num_complete=40)


@pytest.fixture(params=[True, False], ids=["sequential", "baseline"])
def net(request):
    torch.manual_seed(0)
    return ShapePoseNet(TINY, recurrent=request.param).eval()


def test_output_shapes_and_yaw_range(net):
    pts, lengths = torch.randn(3, 5, 32, 3), torch.randint(1, 33, (3, 5))
    out = net(pts, lengths)
    assert out["complete"].shape == (3, 5, 40, 3)
    assert out["pose"].shape == (3, 5, 4)
    assert out["hidden"].shape == (3, 20)
    assert torch.all(out["pose"][..., 3].abs() <= np.pi)


def test_padding_is_ignored(net):
    """Padded rows (whatever their values) change nothing: masked mean and masked max."""
    pts = torch.randn(2, 3, 32, 3)
    lengths = torch.tensor([[5, 12, 1], [32, 7, 3]])
    out1 = net(pts, lengths)
    mask = torch.arange(32) < lengths[..., None]
    out2 = net(torch.where(mask[..., None], pts, torch.full_like(pts, 1e4)), lengths)
    torch.testing.assert_close(out1["complete"], out2["complete"])
    torch.testing.assert_close(out1["pose"], out2["pose"])


def test_encoder_matches_the_plain_pcn_encoder_per_frame():
    """The fast encoder (padded rows as copies, split first layer) against the textbook PCN
    encoder run on each frame's real points alone: same features and same gradients, for
    prefix and scattered masks and an empty frame."""
    torch.manual_seed(3)
    enc = ShapePoseNet(TINY).encoder
    pts = torch.randn(4, 32, 3, requires_grad=True)
    mask = torch.arange(32) < torch.tensor([[32], [9], [1], [0]])
    mask[1] = torch.rand(32) < 0.4  # not a prefix
    fast = enc(pts, mask)
    ref = []
    for p, m in zip(pts, mask, strict=True):
        if not m.any():
            ref.append(torch.zeros(TINY.encoder2[-1]))
            continue
        x = enc.mlp1(p[m])
        x = torch.cat([x, x.amax(0, keepdim=True).expand_as(x)], dim=-1)
        ref.append(enc.mlp2(x).amax(0))
    ref = torch.stack(ref)
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-6)
    w = torch.randn_like(ref)
    g_fast = torch.autograd.grad((fast * w).sum(), [pts, *enc.parameters()])
    g_ref = torch.autograd.grad((ref * w).sum(), [pts, *enc.parameters()])
    for a, b in zip(g_fast, g_ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_translation_equivariance(net):
    """Demeaning: shifting a frame's points shifts its outputs by the same vector."""
    pts, lengths = torch.randn(1, 4, 32, 3), torch.full((1, 4), 20)
    shift = torch.tensor([10.0, -5.0, 1.0])
    a, b = net(pts, lengths), net(pts + shift, lengths)
    torch.testing.assert_close(b["complete"], a["complete"] + shift, atol=1e-4, rtol=0)
    torch.testing.assert_close(b["pose"][..., :3], a["pose"][..., :3] + shift, atol=1e-4,
                               rtol=0)
    torch.testing.assert_close(b["pose"][..., 3], a["pose"][..., 3], atol=1e-5, rtol=0)


def test_empty_frame_keeps_state_and_mean(net):
    pts = torch.randn(1, 3, 32, 3) + 7.0
    lengths = torch.tensor([[10, 0, 0]])
    out = net(pts, lengths)
    torch.testing.assert_close(out["complete"][0, 1], out["complete"][0, 0])
    torch.testing.assert_close(out["complete"][0, 2], out["complete"][0, 0])
    torch.testing.assert_close(out["pose"][0, 2], out["pose"][0, 0])
    one = net(pts[:, :1], lengths[:, :1])
    torch.testing.assert_close(out["hidden"], one["hidden"])
    torch.testing.assert_close(out["mean"], pts[0, 0, :10].mean(0)[None])
    assert out["seen"].tolist() == [[True, True, True]]


def test_all_empty_window_from_a_state(net):
    h0 = torch.randn(2, 20)
    m0 = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    out = net(torch.zeros(2, 4, 32, 3), torch.zeros(2, 4, dtype=torch.long), h0, m0,
              torch.tensor([True, False]))
    assert torch.equal(out["hidden"], h0) and torch.equal(out["mean"], m0)
    assert out["seen"].tolist() == [[True] * 4, [False] * 4]
    assert torch.isfinite(out["complete"]).all()


def test_recurrence_uses_the_past():
    torch.manual_seed(1)
    seq = ShapePoseNet(TINY, recurrent=True).eval()
    base = ShapePoseNet(TINY, recurrent=False).eval()
    pts = torch.randn(1, 2, 32, 3)
    lengths = torch.full((1, 2), 32)
    other_first = torch.cat([torch.randn(1, 1, 32, 3), pts[:, 1:]], 1)
    for m, differs in ((seq, True), (base, False)):
        a, b = m(pts, lengths)["complete"][0, 1], m(other_first, lengths)["complete"][0, 1]
        assert (not torch.allclose(a, b)) == differs


def test_any_number_of_points_resampled():
    rng = np.random.default_rng(0)
    for n in (0, 1, 10, 10_000):
        src = rng.normal(size=(n, 3)).astype(np.float32)
        out, length = resample_frame(src, 32, rng)
        assert out.shape == (32, 3) and out.dtype == np.float32 and length == min(n, 32)
        if 0 < n <= 32:
            np.testing.assert_array_equal(out[:n], src)
        if n > 32:  # a subset without replacement
            assert len({tuple(p) for p in out}) == 32
            assert {tuple(p) for p in out} <= {tuple(p) for p in src}


def test_presets_and_config_round_trip():
    small, paper = MODEL_PRESETS["small"], MODEL_PRESETS["paper"]
    assert small.num_complete == 1024 and small.encoder2 == (256, 256)
    assert paper.encoder1 == (128, 256) and paper.encoder2 == (512, 1024)
    assert paper.num_complete == 2048
    assert ModelConfig.from_dict(small.to_dict()) == small
    with pytest.raises(ConfigError):
        ModelConfig(encoder1=())
    with pytest.raises(ConfigError):
        ModelConfig.from_dict({"bogus": 1})


def test_view_input_option():
    """view_input appends the sensor-to-mean direction: a pure shift along the viewing
    direction changes nothing but the offset; a shift across it changes the estimate."""
    import dataclasses

    torch.manual_seed(0)
    net = ShapePoseNet(dataclasses.replace(TINY, view_input=True)).eval()
    assert net.encoder.mlp1[0].in_features == 6
    pts = torch.randn(1, 2, 32, 3) * 0.5
    pts = pts - pts.mean(2, keepdim=True) + torch.tensor([10.0, 0.0, 0.0])  # mean on +x
    lengths = torch.full((1, 2), 32)
    a = net(pts, lengths)
    along = net(pts + torch.tensor([5.0, 0.0, 0.0]), lengths)
    torch.testing.assert_close(along["complete"], a["complete"] + torch.tensor([5.0, 0, 0]),
                               atol=1e-4, rtol=0)
    across = net(pts + torch.tensor([0.0, 10.0, 0.0]), lengths)
    assert not torch.allclose(across["complete"] - torch.tensor([0.0, 10.0, 0.0]),
                              a["complete"], atol=1e-4)


def test_canonical_shape_frame_is_placed_by_the_predicted_pose():
    torch.manual_seed(0)
    cfg = ModelConfig(encoder1=(8, 16), encoder2=(16, 16), hidden=16, shape_decoder=(32,),
                      pose_decoder=(16,), num_complete=20, shape_frame="canonical")
    net = ShapePoseNet(cfg, recurrent=True).eval()
    pts = torch.randn(2, 3, 30, 3) + torch.tensor([10.0, -4.0, 0.0])
    out = net(pts, torch.full((2, 3), 30))
    enc = net.encode(pts, torch.full((2, 3), 30))
    canonical = net.shape_decoder(enc["h"]).reshape(2, 3, 20, 3)
    pose = out["pose"].detach().numpy()
    for b in range(2):
        for t in range(3):
            yaw = pose[b, t, 3]
            r = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0],
                          [0, 0, 1]])
            expected = canonical[b, t].detach().numpy() @ r.T + pose[b, t, :3]
            np.testing.assert_allclose(out["complete"][b, t].detach().numpy(), expected,
                                       atol=1e-4)
    # the pose decoder is trained by the shape loss in this mode
    ids = {id(p) for p in net.shape_parameters()}
    assert all(id(p) in ids for p in net.pose_decoder.parameters())
    with pytest.raises(ConfigError, match="shape_frame"):
        ModelConfig(shape_frame="world")


def test_frame_skip_starts_as_the_plain_gru_and_carries_its_state():
    """frame_skip: zero-initialised, so the same GRU weights give the same outputs; the state
    doubles (GRU state, projected feature) and an empty frame carries both."""
    torch.manual_seed(3)
    plain = ShapePoseNet(TINY, recurrent=True).eval()
    skip = ShapePoseNet(ModelConfig(**{**TINY.to_dict(), "frame_skip": True}), True).eval()
    missing = skip.load_state_dict(plain.state_dict(), strict=False)
    assert sorted(missing.missing_keys) == ["skip.bias", "skip.weight"]
    assert skip.state_size == 40 and plain.state_size == 20
    pts, lengths = torch.randn(2, 4, 32, 3), torch.tensor([[5, 0, 9, 32], [1, 2, 3, 0]])
    a, b = plain(pts, lengths), skip(pts, lengths)
    torch.testing.assert_close(b["complete"], a["complete"])
    torch.testing.assert_close(b["hidden"][:, :20], a["hidden"])
    assert torch.equal(b["hidden"][:, 20:], torch.zeros(2, 20))
    # with a non-zero projection: the decoder reads h + W f of the last frame with points
    with torch.no_grad():
        skip.skip.weight.normal_()
        skip.skip.bias.normal_()
    out = skip(pts, lengths)
    assert not torch.allclose(out["complete"], a["complete"])
    torch.testing.assert_close(out["complete"][1, 3], out["complete"][1, 2])  # empty frame
    torch.testing.assert_close(out["complete"][0, 1], out["complete"][0, 0])
    # the state returned continues the window exactly: frames 0-1, then 2-3 from the state
    first = skip(pts[:, :2], lengths[:, :2])
    second = skip(pts[:, 2:], lengths[:, 2:], first["hidden"], first["mean"],
                  first["seen"][:, -1])
    torch.testing.assert_close(second["complete"], out["complete"][:, 2:])
    # the baseline ignores the option
    base = ShapePoseNet(ModelConfig(**{**TINY.to_dict(), "frame_skip": True}), False)
    assert base.skip is None and base.state_size == 20


# ---------------------------------------------------------------------- input scale (issue 15)
SCALED = ModelConfig(**{**TINY.to_dict(), "encoder1": (8, 16), "encoder2": (16, 24),
                        "shape_decoder": (32,), "pose_decoder": (16,), "scale_norm": "length",
                        "shape_frame": "canonical"})


@pytest.mark.parametrize("shape_frame", ["canonical", "sensor"])
@pytest.mark.parametrize("recurrent", [True, False])
def test_scale_is_exactly_equivariant(shape_frame, recurrent):
    """Input scaled by 2 with s = 2 gives exactly 2x the output at s = 1 (powers of two are
    exact in float), pose yaw unchanged; the recurrent state is the same."""
    torch.manual_seed(0)
    cfg = ModelConfig(**{**SCALED.to_dict(), "shape_frame": shape_frame})
    net = ShapePoseNet(cfg, recurrent=recurrent).eval()
    pts = torch.randn(2, 4, 32, 3) * torch.tensor([2.0, 0.8, 0.6]) + torch.tensor([9.0, -3, -1])
    lengths = torch.tensor([[32, 0, 7, 20], [3, 32, 32, 1]])
    one = net(pts, lengths, scale=torch.ones(2, 4))
    two = net(2 * pts, lengths, scale=torch.full((2, 4), 2.0))
    assert torch.equal(two["complete"], 2 * one["complete"])
    assert torch.equal(two["pose"][..., :3], 2 * one["pose"][..., :3])
    assert torch.equal(two["pose"][..., 3], one["pose"][..., 3])
    assert torch.equal(two["hidden"], one["hidden"])


@pytest.mark.parametrize("recurrent", [True, False])
def test_scale_one_is_the_unscaled_network(recurrent):
    """s = 1 (every vehicle up to scale_ref) is bit-identical to the network without
    scale_norm, with the same weights: old weights behave the same on cars."""
    torch.manual_seed(0)
    plain = ShapePoseNet(ModelConfig(**{**SCALED.to_dict(), "scale_norm": "none"}), recurrent)
    scaled = ShapePoseNet(SCALED, recurrent)
    scaled.load_state_dict(plain.state_dict())
    pts, lengths = torch.randn(2, 3, 32, 3), torch.tensor([[32, 5, 0], [1, 32, 9]])
    a = plain.eval()(pts, lengths)
    b = scaled.eval()(pts, lengths, scale=torch.ones(2, 3))
    assert torch.equal(a["complete"], b["complete"]) and torch.equal(a["pose"], b["pose"])
    enc = scaled.encode(pts, lengths, scale=torch.ones(2, 3))
    assert torch.equal(scaled.decode_pose(enc["h"], enc["means"], enc["scales"]), a["pose"])


def test_scale_for_and_config_fields():
    cfg = SCALED
    assert cfg.scale_for(4.5) == 1.0 and cfg.scale_for(6.0) == 1.0
    assert cfg.scale_for(12.0) == 2.0 and cfg.scale_for(100.0) == cfg.scale_max == 4.0
    assert cfg.scale_for(float("nan")) == 1.0 and cfg.scale_for(0.0) == 1.0
    np.testing.assert_array_equal(cfg.scale_for(np.array([3.0, 9.0])), [1.0, 1.5])
    torch.testing.assert_close(cfg.scale_for(torch.tensor([[18.0, -1.0]])),
                               torch.tensor([[3.0, 1.0]]))
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    assert ModelConfig().scale_norm == "none"
    # a config written before the fields existed reads with the defaults
    old = {k: v for k, v in cfg.to_dict().items() if not k.startswith("scale_")}
    assert ModelConfig.from_dict(old).scale_norm == "none"
    for bad in ({"scale_norm": "points"}, {"scale_ref": 0.0}, {"scale_max": 0.5}):
        with pytest.raises(ConfigError):
            ModelConfig(**bad)


# ------------------------------------------------------------- the one torch pose transform


def test_place_points_matches_numpy_geometry_and_round_trips():
    from seqshape.geometry import canonical_to_sensor
    from seqshape.model.transforms import place_points, unplace_points

    rng = np.random.default_rng(4)
    poses = np.column_stack([rng.normal(size=(2, 3, 3)).reshape(6, 3),
                             rng.uniform(-np.pi, np.pi, 6)]).reshape(2, 3, 4)  # (B, T, 4)
    pts = rng.normal(size=(2, 3, 7, 3))  # (B, T, K, 3)
    placed = place_points(torch.from_numpy(pts), torch.from_numpy(poses)).numpy()
    for b in range(2):
        for t in range(3):
            np.testing.assert_allclose(placed[b, t], canonical_to_sensor(pts[b, t], poses[b, t]),
                                       atol=1e-12)
    back = unplace_points(torch.from_numpy(placed), torch.from_numpy(poses)).numpy()
    np.testing.assert_allclose(back, pts, atol=1e-12)
    # a quarter turn by hand: canonical +x becomes sensor +y, then the translation
    quarter = torch.tensor([[1.0, 2.0, 3.0, np.pi / 2]])
    got = place_points(torch.tensor([[[2.0, 0.0, 0.5]]]), quarter)
    np.testing.assert_allclose(got.numpy(), [[[1.0, 4.0, 3.5]]], atol=1e-6)


def test_place_points_is_bitwise_the_three_former_copies():
    """The network, trainer and pose-loss formulas it replaced, written out: same bits."""
    from seqshape.model.transforms import place_points, unplace_points

    torch.manual_seed(1)
    out, pose = torch.randn(5, 40, 3), torch.randn(5, 4)
    c, s = torch.cos(pose[..., 3:4]), torch.sin(pose[..., 3:4])  # network
    net = torch.stack([c * out[..., 0] - s * out[..., 1], s * out[..., 0] + c * out[..., 1],
                       out[..., 2]], dim=-1) + pose[..., :3].unsqueeze(-2)
    c, s = torch.cos(pose[:, 3])[:, None], torch.sin(pose[:, 3])[:, None]  # trainer
    trainer = torch.stack([c * out[..., 0] - s * out[..., 1], s * out[..., 0] + c * out[..., 1],
                           out[..., 2]], -1) + pose[:, None, :3]
    d = out - pose[:, None, :3]  # pose loss
    loss = torch.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1],
                        d[..., 2]], dim=-1)
    assert torch.equal(place_points(out, pose), net)
    assert torch.equal(place_points(out, pose), trainer)
    assert torch.equal(unplace_points(out, pose), loss)
