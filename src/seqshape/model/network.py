"""The paper's network: demean, PCN-style PointNet encoder, GRU fusion, shape and pose MLPs.

Shapes used throughout: B tracks (batch), W frames per track (window), N points per frame
(padded; ``lengths`` (B, W) says how many are real), H hidden size, K output points.
All coordinates are in metres in each frame's sensor frame. With ``scale_norm="length"`` the
caller passes a per-frame input scale s (B, W) (see :meth:`ModelConfig.scale_for`): the
demeaned points are divided by s before the encoder, the decoded shape and pose offsets are
multiplied by s after, so the network is exactly scale-equivariant; without it (``scale``
None) nothing is rescaled.

Per frame t (paper Eqs. 3-7)::

    mean_t = masked mean of Z_t                     (last known mean if Z_t is empty)
    f_t    = encoder((Z_t - mean_t) / s_t)          PointNet -> max-pool -> concat -> PointNet -> max
    h_t    = GRU(h_{t-1}, f_t)                      (baseline: h_t = Linear(f_t); empty frame: h_t = h_{t-1})
             (extension ``motion_input``: GRU(h_{t-1}, [f_t, m_t]), see motion_features)
    d_t    = h_t  (extension ``frame_skip``: h_t + W f_t, W zero-initialised)
    X_t    = s_t g_shape(d_t) + mean_t              (K, 3)      (s_t = 1 without scale_norm)
    T_t    = g_pose(d_t) = (x, y, z, cos, sin) -> (s x + mean, s y + mean, s z + mean, atan2(sin, cos))
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from seqshape.model.config import ModelConfig
from seqshape.model.transforms import place_points

#: Time step (s) assumed between consecutive frames of a track when no timestamps are given
#: (10 Hz, the usual rotating-LiDAR rate).
DEFAULT_FRAME_PERIOD = 0.1
#: Clip (m, after dividing by the input scale) of each displacement component of m_t.
MOTION_CLIP = 5.0
#: Clip (s) of the time since the last detection in m_t.
MOTION_MAX_GAP = 2.0
#: Point count at which the count feature of m_t reaches 1 (log1p(n) / log1p(this)).
MOTION_COUNT_REF = 1000.0


def mlp(sizes: Sequence[int], point_wise: bool = False) -> nn.Sequential:
    """Linear layers with ReLU between them (none after the last one).

    ``point_wise`` only documents intent: ``nn.Linear`` acts on the last axis, so the same MLP
    is shared by all points of a ``(..., N, C)`` tensor.
    """
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def motion_features(mean: torch.Tensor, last_mean: torch.Tensor, seen: torch.Tensor,
                    gap: torch.Tensor, count: torch.Tensor,
                    scale: torch.Tensor | None = None) -> torch.Tensor:
    """The motion vector m_t (B, 7) of ``ModelConfig.motion_input`` for one frame.

    Args:
        mean: (B, 3) this frame's point mean (sensor frame, m).
        last_mean: (B, 3) the mean of the track's last earlier frame with points.
        seen: (B,) bool, whether the track had points before this frame (False at its first
            detection, and at the first detection of a training window: the same fresh start).
        gap: (B,) time (s) since that earlier frame.
        count: (B,) the frame's number of points before resampling to N.
        scale: (B,) input scale s (None: 1).

    Returns ``[dx, dy, dz, dt, c, vx, vy]``: the displacement ``(mean - last_mean) / s``
    clipped to +-:data:`MOTION_CLIP` per component, ``dt = clip(gap, 0,`` :data:`MOTION_MAX_GAP`
    ``)`` (both zero where not ``seen``), ``c = log1p(count) / log1p(``:data:`MOTION_COUNT_REF`
    ``)``, and the bird's-eye unit direction (vx, vy) from the sensor to ``mean`` (zero at the
    origin).
    """
    seen = seen.bool().unsqueeze(-1)
    disp = mean - last_mean
    if scale is not None:
        disp = disp / scale.unsqueeze(-1)
    disp = torch.where(seen, disp.clamp(-MOTION_CLIP, MOTION_CLIP), torch.zeros_like(disp))
    dt = gap.unsqueeze(-1).clamp(0.0, MOTION_MAX_GAP)
    dt = torch.where(seen, dt, torch.zeros_like(dt))
    c = torch.log1p(count.to(mean.dtype).clamp(min=0)).unsqueeze(-1)
    c = c / math.log1p(MOTION_COUNT_REF)
    xy = mean[:, :2]
    view = xy / xy.norm(dim=-1, keepdim=True).clamp(min=1e-6)
    return torch.cat([disp, dt, c, view], dim=-1)


def add_motion_columns(state_dict: dict[str, torch.Tensor],
                       cfg: ModelConfig) -> dict[str, torch.Tensor]:
    """A sequential model's weights trained without ``motion_input``, fitted to a model with
    it (``cfg``): ``fusion.weight_ih`` gains :data:`~seqshape.model.config.MOTION_SIZE` zero
    columns, so the new model computes exactly what the old one did. Weights that already
    have them (or a ``cfg`` without the option) are returned unchanged."""
    w = state_dict.get("fusion.weight_ih")
    if not cfg.motion_input or w is None or w.shape[1] != cfg.feature_size:
        return state_dict
    out = dict(state_dict)
    out["fusion.weight_ih"] = torch.cat([w, w.new_zeros(w.shape[0], cfg.motion_size)], dim=1)
    return out


class PointEncoder(nn.Module):
    """PCN encoder: shared MLP -> max-pool g -> [per-point, g] -> shared MLP -> max-pool.

    ``forward(points (F, N, C), mask (F, N) bool) -> (F, encoder2[-1])``, C = 3 (demeaned
    xyz) or 6 (plus the viewing direction, ``ModelConfig.view_input``).
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.mlp1 = mlp([6 if cfg.view_input else 3, *cfg.encoder1], point_wise=True)
        self.mlp2 = mlp([2 * cfg.encoder1[-1], *cfg.encoder2], point_wise=True)

    def forward(self, points: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        # Padded rows become copies of the frame's real rows (cyclically): the per-point MLPs
        # give a copy the same features as its original and a max over a set with repeats is
        # the max over the set, so both max-pools are plain maxima, as exact as masking them
        # and without the masked copies of (F, N, C) features.
        n, c_in = points.shape[1:]
        count = mask.sum(dim=1, keepdim=True)
        real_first = torch.argsort((~mask).to(torch.uint8), dim=1, stable=True)
        rows = real_first.gather(1, torch.arange(n, device=points.device) % count.clamp(min=1))
        x = self.mlp1(points.gather(1, rows.unsqueeze(-1).expand(-1, -1, c_in)))
        # max with indices: its backward scatters into the argmax rows (amax's compares every
        # element with the max); ties are copies of one row, so the weight gradients agree
        g = x.max(dim=1).values
        # mlp2's first layer on [x, g] is x W_x^T + (g W_g^T + b): the global half is computed
        # once per frame instead of once per point
        first, c = self.mlp2[0], x.shape[-1]
        y = F.linear(x, first.weight[:, :c])
        y += F.linear(g, first.weight[:, c:], first.bias).unsqueeze(1)
        if len(self.mlp2) > 1:  # mlp2[1] is its first ReLU
            y = self.mlp2[2:](torch.relu_(y))
        out = y.max(dim=1).values
        return torch.where(count > 0, out, torch.zeros_like(out))


class ShapePoseNet(nn.Module):
    """Sequential (``recurrent=True``) or per-frame baseline (``recurrent=False``) estimator.

    The baseline (Goforth et al. 2020) has the same encoder and decoders; its decoder input is
    ``Linear(f_t)`` instead of the GRU state. For both, a frame with no points leaves the state
    unchanged (the baseline then repeats its last estimate, placed at the last known mean).
    """

    def __init__(self, cfg: ModelConfig, recurrent: bool = True):
        super().__init__()
        self.cfg = cfg
        self.recurrent = bool(recurrent)
        self.encoder = PointEncoder(cfg)
        self.motion = self.recurrent and cfg.motion_input
        if self.recurrent:
            self.fusion: nn.Module = nn.GRUCell(cfg.feature_size + self.motion_size, cfg.hidden)
            with torch.no_grad():  # the motion columns start at zero: f_t alone, as without
                self.fusion.weight_ih[:, cfg.feature_size:] = 0.0
        else:
            self.fusion = nn.Linear(cfg.feature_size, cfg.hidden)
        self.skip: nn.Linear | None = None
        if self.recurrent and cfg.frame_skip:
            self.skip = nn.Linear(cfg.feature_size, cfg.hidden)
            nn.init.zeros_(self.skip.weight)
            nn.init.zeros_(self.skip.bias)
        self.shape_decoder = mlp([cfg.hidden, *cfg.shape_decoder, 3 * cfg.num_complete])
        self.pose_decoder = mlp([cfg.hidden, *cfg.pose_decoder, 5])

    @property
    def kind(self) -> str:
        return "sequential" if self.recurrent else "baseline"

    @property
    def motion_size(self) -> int:
        """Size of the motion vector m_t the GRU reads (0: none, the paper's network)."""
        return self.cfg.motion_size if self.motion else 0

    @property
    def state_size(self) -> int:
        """Size of the state a track carries between frames: H, or 2H with ``frame_skip``
        (the GRU state and the projected last frame feature)."""
        return self.cfg.hidden * (1 if self.skip is None else 2)

    def backbone_parameters(self) -> list[nn.Parameter]:
        """Encoder + fusion (GRU or linear, and the frame skip): what stage 1 trains besides
        the shape decoder."""
        params = list(self.encoder.parameters()) + list(self.fusion.parameters())
        if self.skip is not None:
            params += list(self.skip.parameters())
        return params

    def shape_parameters(self) -> list[nn.Parameter]:
        """Everything the shape (Chamfer) loss reaches: stage 1's parameters.

        With ``shape_frame="canonical"`` the shape is placed by the predicted pose, so the pose
        decoder is part of it.
        """
        params = self.backbone_parameters() + list(self.shape_decoder.parameters())
        if self.cfg.shape_frame == "canonical":
            params += list(self.pose_decoder.parameters())
        return params

    def encode(self, points: torch.Tensor, lengths: torch.Tensor,
               hidden: torch.Tensor | None = None, last_mean: torch.Tensor | None = None,
               seen: torch.Tensor | None = None,
               scale: torch.Tensor | None = None, dts: torch.Tensor | None = None,
               counts: torch.Tensor | None = None, gap: torch.Tensor | None = None,
               times: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Run the encoder and the fusion over a window.

        Args:
            points: (B, W, N, 3) sensor-frame points, padded per frame.
            lengths: (B, W) number of real points per frame (0 = empty frame).
            hidden: (B, S) state before the first frame (zeros if None), S =
                :attr:`state_size`.
            last_mean: (B, 3) last known frame mean of each track (zeros if None).
            seen: (B,) bool, whether each track had points before (False if None).
            scale: (B, W) input scale s per frame (None: no rescaling, the paper's network).
                The caller chooses s for empty frames too (the decoders use it there).
            dts: (B, W) time (s) from each track's previous frame (step) to this one; only
                ``motion_input`` reads it (None, or NaN entries: :data:`DEFAULT_FRAME_PERIOD`;
                negative entries count as 0).
            counts: (B, W) points per frame before resampling to N (None: ``lengths``); only
                ``motion_input`` reads it.
            gap: (B,) time (s) from each track's last frame with points to the frame before
                the window (zeros if None); only ``motion_input`` reads it.
            times: (B, W) per-frame times (s, small numbers: subtract an origin first), an
                alternative to ``dts`` (used only when ``dts`` is None): dts are their
                differences, the first frame's unknown (:data:`DEFAULT_FRAME_PERIOD`).

        Returns ``h`` (B, W, H) decoder input after each frame, ``means`` (B, W, 3) the offset added
        back to each frame's outputs, ``seen`` (B, W) whether any points were seen up to that
        frame, ``scales`` (B, W) (None without ``scale``), ``motion`` (B, W, 7) the GRU's
        motion inputs (only with ``motion_input``), and ``hidden`` (B, S), ``mean`` (B, 3),
        ``seen_last`` (B,), ``gap`` (B,) to continue from.
        """
        b, w, n, _ = points.shape
        lengths = lengths.to(points.device).long()
        mask = torch.arange(n, device=points.device) < lengths.unsqueeze(-1)  # (B, W, N)
        m = mask.unsqueeze(-1).to(points.dtype)
        frame_mean = (points * m).sum(2) / lengths.clamp(min=1).unsqueeze(-1).to(points.dtype)
        x = points - frame_mean.unsqueeze(2)
        if scale is not None:
            scale = scale.to(points.device, points.dtype).reshape(b, w)
            x = x / scale[:, :, None, None]
        if self.cfg.view_input:
            view = frame_mean / frame_mean.norm(dim=-1, keepdim=True).clamp(min=1e-6)
            x = torch.cat([x, view.unsqueeze(2).expand(-1, -1, n, -1)], dim=-1)
        feats = self._frame_features(x.reshape(b * w, n, x.shape[-1]),
                                     mask.reshape(b * w, n)).reshape(b, w, -1)
        h = points.new_zeros(b, self.state_size) if hidden is None else hidden
        hd = self.cfg.hidden
        mean = points.new_zeros(b, 3) if last_mean is None else last_mean
        seen_t = (torch.zeros(b, dtype=torch.bool, device=points.device) if seen is None
                  else seen.to(points.device).bool())
        since = points.new_zeros(b) if gap is None else gap.to(points.device, points.dtype)
        if self.motion:
            if dts is None and times is not None:
                times = times.to(points.device, points.dtype).reshape(b, w)
                dts = torch.cat([torch.full_like(times[:, :1], float("nan")),
                                 times[:, 1:] - times[:, :-1]], dim=1)
            dts = (points.new_full((b, w), DEFAULT_FRAME_PERIOD) if dts is None
                   else dts.to(points.device, points.dtype).reshape(b, w))
            dts = torch.where(torch.isfinite(dts), dts.clamp(min=0.0),
                              torch.full_like(dts, DEFAULT_FRAME_PERIOD))
            counts = lengths if counts is None else counts.to(points.device).reshape(b, w)
        hs, means, seens, motions = [], [], [], []
        for t in range(w):
            has = (lengths[:, t] > 0).unsqueeze(-1)
            m_t = None
            if self.motion:
                since = since + dts[:, t]
                m_t = motion_features(frame_mean[:, t], mean, seen_t, since, counts[:, t],
                                      None if scale is None else scale[:, t])
                motions.append(m_t)
                since = torch.where(has.squeeze(-1), torch.zeros_like(since), since)
            if not self.recurrent:
                h_new = self.fusion(feats[:, t])
            elif self.skip is None:
                h_new = self._gru(feats[:, t], m_t, h)
            else:
                h_new = torch.cat([self._gru(feats[:, t], m_t, h[:, :hd]),
                                   self.skip(feats[:, t])], dim=-1)
            h = torch.where(has, h_new, h)
            mean = torch.where(has, frame_mean[:, t], mean)
            seen_t = seen_t | has.squeeze(-1)
            hs.append(h if self.skip is None else h[:, :hd] + h[:, hd:])
            means.append(mean)
            seens.append(seen_t)
        out = {"h": torch.stack(hs, 1), "means": torch.stack(means, 1),
               "seen": torch.stack(seens, 1), "scales": scale, "hidden": h, "mean": mean,
               "seen_last": seen_t, "gap": since}
        if self.motion:
            out["motion"] = torch.stack(motions, 1)
        return out

    def _frame_features(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Encoder features (F, C) of frames (F, N, c) with point masks (F, N): the encoder
        runs on the frames with points only (an empty frame's feature is 0 and unused: its
        state is held), which skips 20-30 % of a training window's frames."""
        has = mask.any(dim=1)  # (F,)
        if bool(has.all()):
            return self.encoder(x, mask)
        idx = has.nonzero().squeeze(1)
        out = x.new_zeros(x.shape[0], self.cfg.feature_size)
        if len(idx) == 0:
            return out
        return out.index_copy(0, idx, self.encoder(x.index_select(0, idx),
                                                   mask.index_select(0, idx)))

    def _gru(self, f: torch.Tensor, m: torch.Tensor | None, h: torch.Tensor) -> torch.Tensor:
        """One GRU step on ``[f, m]`` (``m`` None: on ``f``, the paper's GRU).

        The motion columns enter as a per-track input-gate bias ``m W_m^T + b_ih`` and ``f``
        goes through the GRU's own kernel with the feature columns W_f: with W_m = 0 this is
        bitwise the GRU without motion inputs (a GEMM over the concatenated input sums in a
        different order)."""
        if m is None:
            return self.fusion(f, h)
        g, nf = self.fusion, self.cfg.feature_size
        bias = F.linear(m, g.weight_ih[:, nf:], g.bias_ih)
        return torch.gru_cell(f, h, g.weight_ih[:, :nf], g.weight_hh, bias, g.bias_hh)

    def decode_shape(self, h: torch.Tensor, mean: torch.Tensor,
                     pose: torch.Tensor | None = None,
                     scale: torch.Tensor | None = None) -> torch.Tensor:
        """Complete shape (..., K, 3) in the sensor frame from states (..., H), means (..., 3).

        With ``shape_frame="canonical"`` the decoded canonical shape is placed with ``pose``
        (..., 4) (decoded here when not given). ``scale`` (...) multiplies the decoded shape.
        """
        out = self.shape_decoder(h).reshape(*h.shape[:-1], self.cfg.num_complete, 3)
        if scale is not None:
            out = out * scale[..., None, None]
        if self.cfg.shape_frame == "sensor":
            return out + mean.unsqueeze(-2)
        if pose is None:
            pose = self.decode_pose(h, mean, scale)
        return place_points(out, pose)  # (..., K, 3)

    def decode_pose(self, h: torch.Tensor, mean: torch.Tensor,
                    scale: torch.Tensor | None = None) -> torch.Tensor:
        """Pose (..., 4) = (x, y, z, yaw) in the sensor frame; yaw = atan2(sin, cos).
        ``scale`` (...) multiplies the decoded offset from the mean."""
        p = self.pose_decoder(h)
        yaw = torch.atan2(p[..., 4], p[..., 3])
        offset = p[..., :3] if scale is None else p[..., :3] * scale.unsqueeze(-1)
        return torch.cat([offset + mean, yaw.unsqueeze(-1)], dim=-1)

    def forward(self, points: torch.Tensor, lengths: torch.Tensor,
                hidden: torch.Tensor | None = None, last_mean: torch.Tensor | None = None,
                seen: torch.Tensor | None = None, shape: bool = True,
                pose: bool = True, scale: torch.Tensor | None = None,
                dts: torch.Tensor | None = None, counts: torch.Tensor | None = None,
                gap: torch.Tensor | None = None,
                times: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Estimate shape and pose for every frame of a window (see :meth:`encode`; ``scale``
        (B, W) is the per-frame input scale, None for none; ``dts`` (or ``times``), ``counts``,
        ``gap`` feed the motion inputs of a ``motion_input`` model).

        Returns ``complete`` (B, W, K, 3) and ``pose`` (B, W, 4) in each frame's sensor frame
        (left out when ``shape`` / ``pose`` is False), ``hidden`` (B, H), ``mean`` (B, 3),
        ``gap`` (B,), ``seen`` (B, W): frames before a track's first points have meaningless
        estimates.
        """
        enc = self.encode(points, lengths, hidden, last_mean, seen, scale, dts, counts, gap,
                          times)
        out = {"hidden": enc["hidden"], "mean": enc["mean"], "seen": enc["seen"],
               "gap": enc["gap"]}
        sc = enc["scales"]
        if pose or (shape and self.cfg.shape_frame == "canonical"):
            pose_t = self.decode_pose(enc["h"], enc["means"], sc)
            if pose:
                out["pose"] = pose_t
        if shape:
            out["complete"] = self.decode_shape(
                enc["h"], enc["means"], pose_t if self.cfg.shape_frame == "canonical" else None,
                sc)
        return out

