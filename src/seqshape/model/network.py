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
    d_t    = h_t  (extension ``frame_skip``: h_t + W f_t, W zero-initialised)
    X_t    = s_t g_shape(d_t) + mean_t              (K, 3)      (s_t = 1 without scale_norm)
    T_t    = g_pose(d_t) = (x, y, z, cos, sin) -> (s x + mean, s y + mean, s z + mean, atan2(sin, cos))
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from seqshape.model.config import ModelConfig


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
        g = x.amax(dim=1)
        # mlp2's first layer on [x, g] is x W_x^T + (g W_g^T + b): the global half is computed
        # once per frame instead of once per point
        first, c = self.mlp2[0], x.shape[-1]
        y = F.linear(x, first.weight[:, :c])
        y += F.linear(g, first.weight[:, c:], first.bias).unsqueeze(1)
        if len(self.mlp2) > 1:  # mlp2[1] is its first ReLU
            y = self.mlp2[2:](torch.relu_(y))
        out = y.amax(dim=1)
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
        if self.recurrent:
            self.fusion: nn.Module = nn.GRUCell(cfg.feature_size, cfg.hidden)
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
               scale: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
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

        Returns ``h`` (B, W, H) decoder input after each frame, ``means`` (B, W, 3) the offset added
        back to each frame's outputs, ``seen`` (B, W) whether any points were seen up to that
        frame, ``scales`` (B, W) (None without ``scale``), and ``hidden`` (B, S), ``mean``
        (B, 3), ``seen_last`` (B,) to continue from.
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
        feats = self.encoder(x.reshape(b * w, n, x.shape[-1]),
                             mask.reshape(b * w, n)).reshape(b, w, -1)
        h = points.new_zeros(b, self.state_size) if hidden is None else hidden
        hd = self.cfg.hidden
        mean = points.new_zeros(b, 3) if last_mean is None else last_mean
        seen_t = (torch.zeros(b, dtype=torch.bool, device=points.device) if seen is None
                  else seen.to(points.device).bool())
        hs, means, seens = [], [], []
        for t in range(w):
            has = (lengths[:, t] > 0).unsqueeze(-1)
            if not self.recurrent:
                h_new = self.fusion(feats[:, t])
            elif self.skip is None:
                h_new = self.fusion(feats[:, t], h)
            else:
                h_new = torch.cat([self.fusion(feats[:, t], h[:, :hd]),
                                   self.skip(feats[:, t])], dim=-1)
            h = torch.where(has, h_new, h)
            mean = torch.where(has, frame_mean[:, t], mean)
            seen_t = seen_t | has.squeeze(-1)
            hs.append(h if self.skip is None else h[:, :hd] + h[:, hd:])
            means.append(mean)
            seens.append(seen_t)
        return {"h": torch.stack(hs, 1), "means": torch.stack(means, 1),
                "seen": torch.stack(seens, 1), "scales": scale, "hidden": h, "mean": mean,
                "seen_last": seen_t}

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
        c, s = torch.cos(pose[..., 3:4]), torch.sin(pose[..., 3:4])  # (..., 1)
        x = c * out[..., 0] - s * out[..., 1]
        y = s * out[..., 0] + c * out[..., 1]
        placed = torch.stack([x, y, out[..., 2]], dim=-1)  # (..., K, 3)
        return placed + pose[..., :3].unsqueeze(-2)

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
                pose: bool = True, scale: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Estimate shape and pose for every frame of a window (see :meth:`encode`; ``scale``
        (B, W) is the per-frame input scale, None for none).

        Returns ``complete`` (B, W, K, 3) and ``pose`` (B, W, 4) in each frame's sensor frame
        (left out when ``shape`` / ``pose`` is False), ``hidden`` (B, H), ``mean`` (B, 3),
        ``seen`` (B, W): frames before a track's first points have meaningless estimates.
        """
        enc = self.encode(points, lengths, hidden, last_mean, seen, scale)
        out = {"hidden": enc["hidden"], "mean": enc["mean"], "seen": enc["seen"]}
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

