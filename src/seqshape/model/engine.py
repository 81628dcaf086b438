"""Inference backends of :meth:`seqshape.model.estimator.Estimator.step`.

One streaming step of a :class:`~seqshape.model.network.ShapePoseNet` (one frame per track,
W = 1) is a pure function of the frame and the state the track carries::

    (points (B, N, 3), lengths (B,), hidden (B, S), mean (B, 3), seen (B,), scale (B,),
     dts (B,), counts (B,), gap (B,))  ->  (complete (B, K, 3), pose (B, 4), hidden, mean,
                                            seen, gap)

:class:`StepGraph` is that function as a small torch module written for inference: the rows of
a frame beyond its ``lengths`` must be cyclic copies of its real rows (what
:meth:`Estimator.step` builds), so both max-pools are plain maxima (no gather), the weights are
split and made contiguous once (the split layer's per-point half folded before the first point
MLP's last layer, :func:`fold_split_layer`), and the GRU cell is spelled out (exportable). The recurrent
state stays outside, so streaming, resets and many tracks work the same on every backend.
:class:`OneTrackGraph` is the same step for a pass of one track whose frame has points (no
padding, no masks, both max-pools over a contiguous axis), the ONNX engines' graph for it.

Backends (:data:`BACKENDS`), each tested against the PyTorch reference (the model's own
``forward``, backend ``"torch"``):

* ``"onnx"``: :class:`StepGraph` exported to ONNX (dynamic batch and point axes) and run by
  ONNX Runtime (optional extra ``seqshape[fast]``); float32, within 1e-4 m of the reference.
* ``"torch-lean"``: :class:`StepGraph` run by PyTorch in float32 (the reference's arithmetic
  without its module and masking overhead).
* ``"onnx-int8"``: ``"onnx"`` with int8 matrix products (:func:`quantize_onnx`, inputs
  quantised per track, so a track's estimate does not depend on the other tracks of its pass):
  in passes of many tracks the shape decoder's and the encoder's last per-point layers
  (:data:`INT8_STEP_LAYERS`; 1.4-1.5x the throughput), estimates held to the reference by
  distribution (:data:`INT8_NOISE`: no further off than 1 cm of noise on the points would
  move them); a track alone the shape decoder's only (:data:`INT8_LAYERS`: the pose float32,
  shape points within 6 cm, :data:`INT8_TOLERANCE`); paper-val metrics within 0.5 % of the
  reference.

The placement refiner (:mod:`seqshape.model.placement`) runs inside the same graphs on every
fast backend (issue 47): :class:`RefinedStepGraph` and :class:`RefinedOneTrackGraph` are the
step followed by the refiner's first pass (the frame's points in the estimated box frame, the
refiner's PointNet, the clipped correction applied to the pose and the shape; inputs
:data:`REFINED_INPUTS`, outputs :data:`REFINED_OUTPUTS`), one pass over all the tracks of a
point-count group, no per-track Python; ``"onnx-int8"`` also quantises the refiner's last
per-point layer in the batch graph (:data:`INT8_REFINER_LAYERS`). The further passes of long
vehicles run on the refiner's own graph (:meth:`OnnxEngine.refiner`). A pass holds at most
:data:`MAX_PASS_ROWS` encoder rows; one that fails to allocate raises :class:`PassTooLarge`
(the estimator splits it, or refuses the step with a ``ConfigError``), never the runtime's
raw error.

``"auto"`` (:func:`select_backend`) takes the first of :data:`AUTO_ORDER` whose runtime is
installed and whose outputs match the reference on this machine
(:func:`seqshape.model.estimator.check_backend`), warning about any it passes over, and the
reference when none qualifies; the decision is cached per process and model.
``"auto-float"`` does the same over the float32 backends only (:data:`FLOAT_ORDER`).
"""

from __future__ import annotations

import io
import json
import logging
import os
import time
import warnings
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from seqshape.errors import ConfigError, MissingDependencyError, require
from seqshape.geometry import box_surface
from seqshape.model.graph_cache import cached_graph, cached_verdict
from seqshape.model.int8 import quantize_onnx
from seqshape.model.network import DEFAULT_FRAME_PERIOD, ShapePoseNet, motion_features
from seqshape.model.transforms import place_points, unplace_points

log = logging.getLogger(__name__)

#: Every backend name :meth:`Estimator.load` accepts.
BACKENDS = ("auto", "auto-float", "torch", "onnx", "torch-lean", "onnx-int8")
#: Candidates of ``backend="auto"``, fastest first (measured in docs/model.md,
#: "Inference backends (issue 17)" and "Sixth round: int8 per track"); the reference
#: ``"torch"`` is the fallback.
AUTO_ORDER = ("onnx-int8", "onnx", "torch-lean")
#: Candidates of ``backend="auto-float"``: the float32 ones of :data:`AUTO_ORDER` (the
#: reference's arithmetic in another order; ``seqshape evaluate`` and ``label`` default to it:
#: metrics of the model itself, and labelling's passes of 10-20 tracks gain nothing from int8).
FLOAT_ORDER = ("onnx", "torch-lean")
#: The candidates of each automatic backend name.
AUTO_ORDERS = {"auto": AUTO_ORDER, "auto-float": FLOAT_ORDER}
#: Inputs and outputs of :class:`StepGraph` (and of the exported ONNX graph), in order.
GRAPH_INPUTS = ("points", "lengths", "hidden", "mean", "seen", "scale", "dts", "counts", "gap")
GRAPH_OUTPUTS = ("complete", "pose", "hidden_out", "mean_out", "seen_out", "gap_out")
#: Inputs and outputs of :class:`OneTrackGraph` (one track with points, no padding).
ONE_INPUTS = tuple(name for name in GRAPH_INPUTS if name != "lengths")
ONE_OUTPUTS = GRAPH_OUTPUTS[:4]
#: Grouping of the tracks of one step by point count (:func:`length_buckets`). At least 32
#: rows a pass since the refiner joined the graphs (a pass's fixed cost grew; measured in
#: docs/history/model.md, "Eighth round").
BUCKET_FILL, BUCKET_MIN_ROWS = 0.75, 32
#: Encoder rows (tracks x padded points) from which a pass of the ONNX engines runs on
#: :data:`LARGE_PASS_THREADS` threads when ``threads`` is left at None and a core is free
#: (:func:`spare_cores`; one-track passes too, see :class:`OnnxEngine`); the other passes of
#: a few tracks run on one thread, the fastest for them. Two threads on cores that other
#: processes keep busy lose throughput (docs/history/model.md, "Threads"). 1,024 rather than 4,096:
#: 100 live tracks 2,595-2,684 against 2,347-2,461 updates/s, interleaved runs on a quiet
#: machine (18:23 UTC, 2026-12-02).
LARGE_PASS_ROWS = 1024
LARGE_PASS_THREADS = 2
#: Most encoder rows (tracks x padded points) of one pass of the fast backends
#: (:meth:`seqshape.model.estimator.Estimator.step` cuts a larger group of tracks into
#: passes of this size): 256 tracks of 256 points, a few hundred MB of activations with the
#: ``paper`` preset at most. A step of 10,000 live tracks then runs as about 40 passes instead
#: of one that asks ONNX Runtime's arena for gigabytes; a pass that still finds too little
#: memory is split again (:class:`PassTooLarge`). 100 tracks of 300 points are one pass.
MAX_PASS_ROWS = 1 << 16
#: Seconds for which :meth:`OnnxEngine.spare` trusts its last count of free cores.
SPARE_CHECK_PERIOD = 0.1
#: The layers whose weights ``"onnx-int8"`` quantises (:func:`quantize_onnx`): the shape
#: decoder, 70 % of the weights and of the bytes a single-track step reads. Quantising the
#: encoder, the GRU or the pose decoder as well turns some tracks' yaws by tens of degrees
#: (docs/history/model.md, "Inference backends (issue 17)").
INT8_LAYERS = ("shape_decoder",)
#: The same for the batched step graph (:class:`StepGraph`), the one of many-track passes:
#: also the encoder's per-point layers after the split one (``mlp2_rest``; 61 % of the
#: encoder's multiply-adds with the ``small`` preset), 1.4-1.6x the float32 throughput of 100
#: live tracks. Every per-point product of the encoder would add 3 % more and move yaws twice
#: as far (docs/history/model.md, "Fifth round: the encoder in int8"). Measured and not kept
#: (issue 47, 2026-12-07): the per-point half of the split layer too (``mlp2_split``, the
#: graph's largest float32 product, 28 % of a 57-track pass's kernel time; inputs on one scale
#: per point): a pass of 64 tracks x 256 points with the refiner 35-40 -> 28-29 ms on one
#: thread, 100 live tracks without the refiner 1.4x, and within :data:`INT8_NOISE`'s bound on
#: :func:`car_stream` seeds 0-2, but the shipped baseline with the refiner failed it on seed 5
#: (24 tracks, 3 steps): too near the bound for ``"auto"`` to keep choosing int8 everywhere.
#: Measured and not kept either (issue 47, later the same day): the folded split layer
#: (:func:`fold_split_layer`, 64 -> 256 on a ReLU's output, one scale per point) within the
#: bound on seeds 0, 1, 2, 5 for both shipped networks with and without the refiner (worst 0.84
#: of the bound), but a 64-track refined pass only 48.0 -> 47.3 ms: rescaling its per-point
#: output costs what the int8 product saves.
INT8_STEP_LAYERS = ("shape_decoder", "mlp2_rest")
#: The refiner's layers ``"onnx-int8"`` quantises in the refined batch graph
#: (:class:`RefinedStepGraph`): its last per-point layer (57 % of its multiply-adds), in the
#: encoder's form (one scale per track over all its points). Measured with the shipped
#: weights and refiner on :func:`car_stream` (seed 0; p50 / p90 of the worst shape point,
#: centre, yaw), within :data:`INT8_NOISE`'s bound: sequential 1.39 / 4.49 cm, 0.41 / 1.47
#: cm, 0.07 / 0.67 deg (bound 3.0 / 8.7, 1.1 / 3.3, 0.21 / 1.5); baseline 2.1 / 6.4, 0.59 /
#: 1.8, 0.12 / 0.99 (bound 3.9 / 21, 1.5 / 5.8, 0.23 / 2.7); paper val within 0.15 % of the
#: former int8 engine (issue 47, 2026-12-07). Measured and not kept: the per-point half of its
#: split layer too (``refiner_split``, 28 % of its multiply-adds; one scale per point): within
#: the bound on seeds 0, 1, 2, 5, but the baseline's paper-val translation moved 0.5 %.
INT8_REFINER_LAYERS = ("refiner_rest",)
#: Layers of the batched graph quantised on one scale per track over a frame's rows
#: (:func:`~seqshape.model.int8.quantize_onnx`'s ``rows``), where the graph has the encoder's
#: form: the folded split layer (:func:`fold_split_layer`), its integer sums never rescaled
#: point by point (its scales divide the global term and fold into ``mlp2_rest``), its input
#: ReLU's channels equalised on :func:`equalisation_sample` first. Measured (issue 47, session
#: 34; docs/history/model.md, "Ninth round"): a 100-track step's passes 0.89x the time on one
#: thread, 0.94x on two (side by side in one process), within
#: :data:`INT8_NOISE`'s bound on :func:`car_stream` seeds 0, 1, 2, 5 for both shipped
#: networks with and without the refiner, the odd test stream and the 24-track one (worst 0.64
#: of it). Not kept: the first MLP's last layer as well (the baseline with the refiner then
#: leaves the bound on the 24-track stream, 1.06 of it), or equalising on the unit cube's
#: bound instead of car views (the split layer then leaves it there too, 1.18).
INT8_ROW_LAYERS = ("mlp2_split",)
#: ONNX opset of the export.
ONNX_OPSET = 17
#: Agreement of a fast backend with the reference: shape points (m), pose centre (m), yaw
#: (rad); used by ``check_backend`` and the tests. The fast backends compute the reference's
#: float32 arithmetic in another order; measured on the shipped and round-8 weights, 40
#: tracks over 8 steps: up to 0.8 mm, 0.02 mm, 2e-4 rad (ONNX Runtime), where the reference
#: itself, batched against track by track, differs by up to 0.2 mm, 0.01 mm, 7e-5 rad (the
#: yaw of a nearly degenerate (cos, sin) output moves most; the shape follows it).
TOLERANCE = (2e-3, 2e-4, 1e-3)
#: The same for ``"onnx-int8"``'s one-track graph (:class:`OneTrackGraph`, the shape decoder
#: alone in int8): its pose is float32 (the tolerance above), its shape points move by the
#: int8 rounding of the shape decoder's weights and inputs: measured on the shipped (round 9)
#: weights, :func:`car_stream`'s 40 tracks over 4 steps each stepped alone, the worst point of
#: an estimate up to 16 mm (both models), median 8 mm (per-row quantisation; ONNX Runtime's
#: dynamic one gave 32 and 46 mm); a wrong scale or zero point of the quantisation moves them
#: by decimetres. Its batched graph is held to :data:`INT8_NOISE`.
INT8_TOLERANCE = (6e-2, TOLERANCE[1], TOLERANCE[2])
#: ``"onnx-int8"``'s batched graph also runs the encoder's last per-point layers in int8
#: (:data:`INT8_STEP_LAYERS`), with the inputs quantised per track over all its points: that
#: moves an estimate about as far as 5 mm of Gaussian noise on its points would (less than a
#: LiDAR's range noise, 2-3 cm), and sometimes a yaw the network is unsure of by degrees, so it
#: is held to the reference by distribution, not estimate by estimate: over
#: :func:`car_stream`, the median and 90th percentile of its estimates' deviations from the
#: reference's (worst shape point, centre, yaw) must not exceed those of the reference's own
#: estimates with this much Gaussian noise (m) on the points
#: (:func:`seqshape.model.estimator.noise_quantiles`). Measured with the shipped weights on
#: :func:`car_stream`, three seeds (90th percentiles, int8 against 1 cm of noise, mean of the
#: seeds): sequential worst shape point 3.5 against 18.9 cm, centre 0.37 against 2.1 cm, yaw
#: 0.8 against 4.4 degrees; baseline 5.4, 0.85 and 1.2 against 19.9, 3.4 and 4.2; paper-val
#: metrics within 0.5 % (docs/history/model.md, "Sixth round: int8 per track").
#: A wrong scale or zero point moves every estimate by decimetres.
INT8_NOISE = 0.01


def split_first_layer(first: nn.Linear, c: int) -> tuple[torch.Tensor, ...]:
    """``(W_x, W_g, b)`` of the first layer of a PointNet's second MLP on ``[x, g]`` (``c`` the
    per-point width), contiguous copies: :func:`split_pointnet` applies the global half once a
    frame instead of once a point."""
    w = first.weight.detach()
    return w[:, :c].contiguous(), w[:, c:].contiguous(), first.bias.detach().clone()


def fold_split_layer(mlp1: nn.Sequential, wx: torch.Tensor, b: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``(W_f, b_f)``: the per-point half ``wx`` of a split first layer
    (:func:`split_first_layer`) moved before ``mlp1``'s last (linear, no activation after it)
    layer ``x = W_l h + b_l``: ``wx x = (wx W_l) h + wx b_l``, the constant added to the
    global half's bias ``b``. Products in float64, rounded once. None when that layer widens
    its input no further (no multiply-adds saved): the network's encoder (64 -> 128, then 128
    -> 256 a point: 40 % fewer of the split layer's and the first MLP's last layer's
    multiply-adds together), not the refiner's (64 -> 64)."""
    last = mlp1[-1] if isinstance(mlp1, nn.Sequential) and len(mlp1) else None
    if not isinstance(last, nn.Linear) or last.in_features >= last.out_features:
        return None
    w64, lw, lb = wx.double(), last.weight.detach().double(), last.bias.detach().double()
    return (w64 @ lw).float().contiguous(), (b.double() + w64 @ lb).float()


def split_pointnet(x: torch.Tensor, mlp1: nn.Module, wx: torch.Tensor | nn.Module,
                   wg: torch.Tensor,
                   b: torch.Tensor, rest: nn.Module | None, folded: bool = False
                   ) -> torch.Tensor:
    """Features (B, F) of a two-stage PointNet (``mlp1`` -> max-pool g -> [x, g] -> second MLP
    -> max-pool) on points (B, N, C) whose padded rows are copies; the second MLP's first layer
    given split (:func:`split_first_layer`; ``wx`` the per-point half, a tensor or a bias-free
    ``nn.Linear``, which names its product in the export for int8, :func:`_split_layer`),
    ``rest`` its layers after the ReLU (None: none).

    The per-point layers run on (B * N, C) matrices, so that ONNX Runtime fuses their biases
    and ReLUs into the matrix products (Gemm / FusedGemm nodes). The network's encoder
    (:class:`StepGraph`) and the placement refiner's (:class:`RefinerGraph`) are both this.
    ``folded``: ``wx`` and ``b`` are :func:`fold_split_layer`'s, applied to the input of
    ``mlp1``'s last layer."""
    n_b, n, c = x.shape
    h = x.reshape(n_b * n, c)
    if folded:
        h = mlp1[:-1](h)  # (B * N, C0): the input of mlp1's last layer
    x = (mlp1[-1] if folded else mlp1)(h)  # (B * N, C1)
    g = x.reshape(n_b, n, -1).amax(dim=1)  # (B, C1)
    h = h if folded else x
    xw = wx(h) if isinstance(wx, nn.Module) else F.linear(h, wx)  # a module: named layer
    y = xw.reshape(n_b, n, -1) + F.linear(g, wg, b).unsqueeze(1)
    if rest is not None:
        y = rest(torch.relu(y).reshape(n_b * n, -1))
    return y.reshape(n_b, n, -1).amax(dim=1)  # (B, F)


def _split_layer(w: torch.Tensor) -> nn.Linear:
    """A bias-free ``nn.Linear`` holding ``w`` (the per-point half of a split first layer,
    :func:`split_first_layer`), so that its product carries the layer's name in the exported
    graph and :func:`~seqshape.model.int8.quantize_onnx` can pick it."""
    layer = nn.Linear(w.shape[1], w.shape[0], bias=False)
    with torch.no_grad():
        layer.weight.copy_(w)
    return layer.requires_grad_(False)


class StepGraph(nn.Module):
    """One streaming step of ``model`` (see the module docstring for the signature).

    ``model``'s weights are shared, not copied (the split first layer of the second point
    MLP excepted).
    """

    def __init__(self, model: ShapePoseNet):
        super().__init__()
        cfg = model.cfg
        self.cfg, self.recurrent, self.motion = cfg, model.recurrent, model.motion
        enc = model.encoder
        self.mlp1 = enc.mlp1
        # mlp2's first layer on [x, g]: x W_x^T + (g W_g^T + b), the global half once a frame
        w2x, w2g, b2 = split_first_layer(enc.mlp2[0], cfg.encoder1[-1])
        fold = fold_split_layer(enc.mlp1, w2x, b2)
        self.folded = fold is not None  # w2x acts on the input of mlp1's last layer
        if self.folded:
            w2x, b2 = fold
        self.register_buffer("w2x", w2x)
        self.register_buffer("w2g", w2g)
        self.register_buffer("b2", b2)
        self.mlp2_split = _split_layer(w2x)  # the same weights as a layer (int8 by name)
        self.mlp2_rest = enc.mlp2[2:] if len(enc.mlp2) > 1 else None
        self.fusion, self.skip = model.fusion, model.skip
        if self.recurrent:
            nf, w_ih = cfg.feature_size, model.fusion.weight_ih.detach()
            self.register_buffer("w_if", w_ih[:, :nf].contiguous())
            self.register_buffer("w_im", w_ih[:, nf:].contiguous())
        self.shape_decoder, self.pose_decoder = model.shape_decoder, model.pose_decoder

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Frame features (B, F) of demeaned points (B, N, C) whose padded rows are copies
        (:func:`split_pointnet`)."""
        return split_pointnet(x, self.mlp1, self.mlp2_split, self.w2g, self.b2,
                              self.mlp2_rest, self.folded)

    def gru(self, f: torch.Tensor, m: torch.Tensor | None, h: torch.Tensor) -> torch.Tensor:
        """``nn.GRUCell`` on ``[f, m]`` spelled out (PyTorch's gate order r, z, n)."""
        g = self.fusion
        gi = F.linear(f, self.w_if, g.bias_ih)  # (B, 3H)
        if m is not None:
            gi = gi + F.linear(m, self.w_im)
        gh = F.linear(h, g.weight_hh, g.bias_hh)
        i_r, i_z, i_n = gi.chunk(3, dim=1)
        h_r, h_z, h_n = gh.chunk(3, dim=1)
        r, z = torch.sigmoid(i_r + h_r), torch.sigmoid(i_z + h_z)
        n = torch.tanh(i_n + r * h_n)
        return (1.0 - z) * n + z * h

    def forward(self, points, lengths, hidden, mean, seen, scale, dts, counts, gap):
        _, complete, pose, h, mean_out, seen_out, since = self.step(
            points, lengths, hidden, mean, seen, scale, dts, counts, gap)
        return complete, pose, h, mean_out, seen_out, since

    def step(self, points, lengths, hidden, mean, seen, scale, dts, counts, gap):
        """:meth:`forward`'s outputs after the shape in the box frame (:meth:`decode_box`)."""
        n = points.shape[1]
        mask = (torch.arange(n) < lengths.unsqueeze(1)).unsqueeze(-1)  # (B, N, 1)
        count = lengths.clamp(min=1).unsqueeze(-1).to(points.dtype)
        frame_mean = (points * mask.to(points.dtype)).sum(1) / count  # (B, 3)
        f = self.encode(self.normalise(points, frame_mean, scale))
        has = lengths > 0  # (B,)
        since = gap
        m = None
        if self.motion:
            since = gap + dts
            m = motion_features(frame_mean, mean, seen, since, counts, scale)
            since = torch.where(has, torch.zeros_like(since), since)
        h = torch.where(has.unsqueeze(1), self.fuse(f, m, hidden), hidden)
        mean_out = torch.where(has.unsqueeze(1), frame_mean, mean)
        box, complete, pose = self.decode_box(h, mean_out, scale)
        return box, complete, pose, h, mean_out, seen | has, since

    def normalise(self, points: torch.Tensor, frame_mean: torch.Tensor,
                  scale: torch.Tensor) -> torch.Tensor:
        """The encoder's input (B, N, C): demeaned points over the input scale (and the
        viewing direction with ``view_input``)."""
        x = (points - frame_mean.unsqueeze(1)) / scale[:, None, None]
        if self.cfg.view_input:
            view = frame_mean / frame_mean.norm(dim=-1, keepdim=True).clamp(min=1e-6)
            x = torch.cat([x, view.unsqueeze(1).expand(-1, points.shape[1], -1)], dim=-1)
        return x

    def fuse(self, f: torch.Tensor, m: torch.Tensor | None, hidden: torch.Tensor) -> torch.Tensor:
        """The new state (B, S) of a frame with points: GRU (and frame skip) or the baseline's
        linear layer."""
        if not self.recurrent:
            return self.fusion(f)
        if self.skip is None:
            return self.gru(f, m, hidden)
        hd = self.cfg.hidden
        return torch.cat([self.gru(f, m, hidden[:, :hd]), self.skip(f)], dim=-1)

    def decode(self, h: torch.Tensor, mean: torch.Tensor,
               scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(complete (B, K, 3), pose (B, 4)) decoded from the state around ``mean``."""
        _, complete, pose = self.decode_box(h, mean, scale)
        return complete, pose

    def decode_box(self, h: torch.Tensor, mean: torch.Tensor, scale: torch.Tensor
                   ) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
        """:meth:`decode` after the shape in the pose's box frame before it is placed
        (``shape_frame="canonical"``; None for a model that decodes in the sensor frame)."""
        hd = self.cfg.hidden
        d = h if self.skip is None else h[:, :hd] + h[:, hd:]
        p = self.pose_decoder(d)  # (B, 5)
        yaw = torch.atan2(p[:, 4], p[:, 3])
        pose = torch.cat([p[:, :3] * scale.unsqueeze(1) + mean, yaw.unsqueeze(1)], dim=1)
        shape = self.shape_decoder(d).reshape(-1, self.cfg.num_complete, 3)
        shape = shape * scale[:, None, None]
        if self.cfg.shape_frame == "sensor":
            return None, shape + mean.unsqueeze(1), pose
        return shape, place_points(shape, pose), pose


class OneTrackGraph(StepGraph):
    """:class:`StepGraph` for the most common pass of a stream, one track whose frame has
    points (batch 1, no padded rows): ``(points (1, n, 3), hidden, mean, seen, scale, dts,
    counts, gap) -> (complete, pose, hidden, mean)`` (:data:`ONE_INPUTS`,
    :data:`ONE_OUTPUTS`; the track is seen and its time since a detection is 0 after it).

    Without padding the frame mean is a plain mean and no output needs a ``where``; the
    encoder runs channels first from the last layer of the first point MLP on, so that both
    max-pools reduce the contiguous axis (ONNX Runtime's ``ReduceMax`` over the points axis
    of a (1, n, C) tensor costs as much as a matrix product of the encoder)."""

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Frame features (1, F) of the demeaned points (1, n, C)."""
        return one_track_pointnet(x, self.mlp1, self.w2x, self.w2g, self.b2, self.mlp2_rest,
                                  self.folded)

    def forward(self, points, hidden, mean, seen, scale, dts, counts, gap):
        return self.step(points, hidden, mean, seen, scale, dts, counts, gap)[1:]

    def step(self, points, hidden, mean, seen, scale, dts, counts, gap):
        """:meth:`forward`'s outputs after the shape in the box frame (:meth:`decode_box`)."""
        frame_mean = points.mean(dim=1)  # (1, 3)
        f = self.encode(self.normalise(points, frame_mean, scale))
        m = None
        if self.motion:
            m = motion_features(frame_mean, mean, seen, gap + dts, counts, scale)
        h = self.fuse(f, m, hidden)
        box, complete, pose = self.decode_box(h, frame_mean, scale)
        return box, complete, pose, h, frame_mean


def one_track_pointnet(x: torch.Tensor, mlp1: nn.Module, wx: torch.Tensor, wg: torch.Tensor,
                       b: torch.Tensor, rest: nn.Module | None, folded: bool = False
                       ) -> torch.Tensor:
    """:func:`split_pointnet` of one frame without padding, ``x (1, n, C)`` -> ``(1, F)``,
    channels first from the last layer of the first MLP on, so that both max-pools reduce
    the contiguous axis (:class:`OneTrackGraph`); ``folded`` as there."""
    *first, last = mlp1
    h = x[0]  # (n, C)
    for layer in first:
        h = layer(h)
    ht = h.t()  # (C0, n)
    xt = torch.addmm(last.bias.unsqueeze(1), last.weight, ht)  # (C1, n)
    g = xt.amax(dim=1, keepdim=True)  # (C1, 1)
    y = wx @ (ht if folded else xt) + torch.addmm(b.unsqueeze(1), wg, g)  # (C2, n)
    if rest is not None:
        y = torch.relu(y)
        for layer in rest:
            y = (torch.addmm(layer.bias.unsqueeze(1), layer.weight, y)
                 if isinstance(layer, nn.Linear) else layer(y))
    return y.amax(dim=1).unsqueeze(0)


class RefinerGraph(nn.Module):
    """The placement refiner's network (:class:`~seqshape.model.placement.PlacementRefiner`)
    for export: ``(xyz (B, n, 3), cond (B, C)) -> (B, 4)`` or ``(B, 6)`` with the size head,
    the arithmetic of :meth:`~seqshape.model.placement.PlacementRefiner.forward`
    (:func:`split_pointnet`; rows beyond a frame's points are copies)."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.mlp1, self.head = net.mlp1, net.head
        wx, wg, b = split_first_layer(net.mlp2[0], net.mlp1[-1].out_features)
        self.register_buffer("wx", wx)
        self.register_buffer("wg", wg)
        self.register_buffer("b", b)
        self.rest = net.mlp2[2:] if len(net.mlp2) > 1 else None

    def forward(self, xyz: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        y = split_pointnet(xyz, self.mlp1, self.wx, self.wg, self.b, self.rest)
        return self.head(torch.cat([y, cond], dim=1))


def export_refiner_onnx(net: nn.Module) -> bytes:
    """The ONNX model (bytes) of :class:`RefinerGraph` of a refiner's network, dynamic batch
    and point axes (inputs ``xyz``, ``cond``; output ``correction``)."""
    require("onnx", "exporting the placement refiner to ONNX", "seqshape[fast]")
    graph = RefinerGraph(net).eval()
    cond = graph.head[0].in_features - graph.wx.shape[0]
    example = (torch.zeros(2, 5, 3), torch.zeros(2, cond))
    buf = io.BytesIO()
    with warnings.catch_warnings(), torch.inference_mode():
        warnings.simplefilter("ignore")
        torch.onnx.export(graph, example, buf, input_names=["xyz", "cond"],
                          output_names=["correction"],
                          dynamic_axes={"xyz": {0: "batch", 1: "points"}, "cond": {0: "batch"},
                                        "correction": {0: "batch"}},
                          opset_version=ONNX_OPSET, dynamo=False)
    return buf.getvalue()


#: The refiner's clips and threshold, the ``limits`` input (float32 (5,)) of the refined
#: graphs (:class:`RefinedStepGraph`), from its :class:`~seqshape.model.placement.
#: RefinerConfig` (:func:`refine_limits`): inputs rather than constants, so that a change of
#: the configuration needs no new graph.
LIMIT_FIELDS = ("max_shift", "max_turn", "max_resize_length", "max_resize_width", "min_points")
#: Inputs and outputs of the refined graphs: the step's, then (outputs) the network's own pose
#: (B, 4), the first pass's correction (B, 6) (the refiner's ``CORRECTION_FIELDS``: the pose's
#: move in the network pose's box frame, clipped, then the clipped log size ratios; zeros for
#: a row left alone) and the network shape's extents (B, 3) the refiner read.
REFINED_INPUTS = (*GRAPH_INPUTS, "limits")
REFINED_OUTPUTS = (*GRAPH_OUTPUTS, "pose_net", "correction", "extents")
REFINED_ONE_INPUTS = (*ONE_INPUTS, "limits")
REFINED_ONE_OUTPUTS = (*ONE_OUTPUTS, "pose_net", "correction", "extents")


def refine_limits(config) -> np.ndarray:
    """The ``limits`` input (:data:`LIMIT_FIELDS`) of a
    :class:`~seqshape.model.placement.RefinerConfig`: a size limit of 0 turns that size
    correction off (``size`` off, or ``size_width`` off for the width)."""
    resize = float(config.max_resize) if config.size else 0.0
    return np.array([config.max_shift, config.max_turn, resize,
                     resize if config.size_width else 0.0, max(int(config.min_points), 1)],
                    np.float32)


class _Refined:
    """The first pass of the placement refiner appended to a step graph (the mixin of
    :class:`RefinedStepGraph` and :class:`RefinedOneTrackGraph`): the arithmetic of
    :meth:`~seqshape.model.placement.PlacementRefiner.refine`'s first pass and of
    :func:`~seqshape.model.placement.apply_corrections`, in float32 on the graph's tensors
    (the reference runs them in numpy float64 on the network's float32 outputs; the results
    differ by float32 rounding, a few micrometres).

    * extents: numpy's linear 1st and 99th percentiles of the shape in the box frame
      (:func:`~seqshape.model.placement.percentiles_1_99`) from two ``TopK`` of a dozen
      values; the shape in the box frame is the decoder's before it is placed (no
      transform back);
    * the frame's points in the estimate's box frame over the scale s, and the conditioning
      vector (``COND_FIELDS``), then the refiner's PointNet (:func:`split_pointnet`, so the
      padded rows, copies of the frame's, change nothing: a group pads to its longest frame,
      not to the refiner's 256 points) and head;
    * the correction clipped by ``limits`` (:data:`LIMIT_FIELDS`), the pose moved, the shape
      stretched along its box axes and placed with the new pose; a row with fewer than
      ``min_points`` points keeps the network's estimate bit for bit (correction 0).

    The submodules are named ``refiner_*``: :func:`~seqshape.model.int8.quantize_onnx` picks
    ``refiner_rest`` (the last per-point layer, 57 % of the refiner's multiply-adds) by that
    name."""

    def attach_refiner(self, net: nn.Module) -> None:
        from seqshape.model.placement import SCALE_MAX, SCALE_REF

        self.refiner_mlp1, self.refiner_head = net.mlp1, net.head
        wx, wg, b = split_first_layer(net.mlp2[0], net.mlp1[-1].out_features)
        self.register_buffer("refiner_wx", wx)
        self.register_buffer("refiner_wg", wg)
        self.register_buffer("refiner_b", b)
        self.refiner_split = _split_layer(wx)
        self.refiner_rest = net.mlp2[2:] if len(net.mlp2) > 1 else None
        self.size_head = net.head[-1].out_features >= 6
        self.scale_ref, self.scale_max = SCALE_REF, SCALE_MAX
        k = self.cfg.num_complete
        virtual = (k - 1) * (np.array([1.0, 99.0]) / 100)  # as percentiles_1_99
        below = np.floor(virtual).astype(int)
        self.pct = (k, [int(v) for v in below], [float(g) for g in virtual - below])

    def extents(self, box: torch.Tensor) -> torch.Tensor:
        """(B, 3): 99th minus 1st percentile of ``box`` (B, K, 3) along K (numpy's linear
        interpolation, :func:`~seqshape.model.placement.percentiles_1_99`)."""
        k, (lo_b, hi_b), (lo_g, hi_g) = self.pct
        q = box.transpose(1, 2)  # (B, 3, K)
        if k < 2:
            return torch.zeros(box.shape[0], 3, dtype=box.dtype)
        asc = torch.topk(q, min(k, lo_b + 2), dim=2, largest=False, sorted=True).values
        desc = torch.topk(q, min(k, k - hi_b), dim=2, largest=True, sorted=True).values

        def interp(a, b, t):
            d = b - a
            return b - d * (1 - t) if t >= 0.5 else a + d * t

        lo = interp(asc[..., lo_b], asc[..., lo_b + 1], lo_g)
        hi = interp(desc[..., k - 1 - hi_b], desc[..., k - 2 - hi_b], hi_g)
        return hi - lo

    def refine(self, points: torch.Tensor, count: torch.Tensor, box: torch.Tensor | None,
               complete: torch.Tensor, pose: torch.Tensor, limits: torch.Tensor,
               one_track: bool = False) -> tuple[torch.Tensor, ...]:
        """``(complete, pose, correction, extents)`` of the refined estimate (class doc);
        ``count`` (B,) float: the frame's points."""
        if box is None:  # a model that decodes in the sensor frame
            box = unplace_points(complete, pose)
        ext = self.extents(box)  # (B, 3)
        s = torch.clamp(ext[:, 0] / self.scale_ref, 1.0, self.scale_max)  # (B,)
        xyz = unplace_points(points, pose) / s[:, None, None]  # (B, N, 3)
        c, sn = torch.cos(pose[:, 3]), torch.sin(pose[:, 3])
        ox, oy = -pose[:, 0], -pose[:, 1]
        sx, sy = c * ox + sn * oy, -sn * ox + c * oy  # the sensor in the box frame
        rng = torch.sqrt(sx * sx + sy * sy)
        d = torch.clamp(rng, min=1e-6)
        cond = torch.stack([ext[:, 0] / s, ext[:, 1] / s, ext[:, 2] / s, sx / d, sy / d,
                            torch.log1p(rng) / 4.0, torch.log1p(count) / 7.0, s / 4.0], dim=1)
        if one_track:
            y = one_track_pointnet(xyz, self.refiner_mlp1, self.refiner_wx, self.refiner_wg,
                                   self.refiner_b, self.refiner_rest)
        else:
            y = split_pointnet(xyz, self.refiner_mlp1, self.refiner_split, self.refiner_wg,
                               self.refiner_b, self.refiner_rest)
        out = self.refiner_head(torch.cat([y, cond], dim=1))
        lim = limits
        shift = out[:, :3] * s.unsqueeze(1)
        shift = torch.minimum(torch.maximum(shift, -lim[0]), lim[0])
        turn = torch.minimum(torch.maximum(out[:, 3:4], -lim[1]), lim[1])
        if self.size_head:
            size_lim = lim[2:4].unsqueeze(0)
            size = torch.minimum(torch.maximum(out[:, 4:6], -size_lim), size_lim)
        else:
            size = torch.zeros_like(out[:, :2])
        has = count >= lim[4]  # (B,)
        corr = torch.cat([shift, turn, size], dim=1)
        corr = torch.where(has.unsqueeze(1), corr, torch.zeros_like(corr))
        new = torch.stack([pose[:, 0] + c * corr[:, 0] - sn * corr[:, 1],
                           pose[:, 1] + sn * corr[:, 0] + c * corr[:, 1],
                           pose[:, 2] + corr[:, 2], pose[:, 3] + corr[:, 3]], dim=1)
        stretch = torch.cat([torch.exp(corr[:, 4:6]), torch.ones_like(corr[:, :1])], dim=1)
        changed = has & (corr != 0).any(dim=1)
        # one placement: a row left alone is its box times 1 placed with its own pose, the
        # network's placed shape to the bit (the network's ``complete`` is not computed)
        stretch = torch.where(changed.unsqueeze(1), stretch, torch.ones_like(stretch))
        pose_out = torch.where(changed.unsqueeze(1), new, pose)
        complete = place_points(box * stretch.unsqueeze(1), pose_out)
        return complete, pose_out, corr, ext


class RefinedStepGraph(_Refined, StepGraph):
    """:class:`StepGraph` followed by the first pass of the placement refiner (:class:`_Refined`),
    one graph: ``(REFINED_INPUTS) -> (REFINED_OUTPUTS)``, the refined estimate in place of the
    network's."""

    def __init__(self, model: ShapePoseNet, net: nn.Module):
        super().__init__(model)
        self.attach_refiner(net)

    def forward(self, points, lengths, hidden, mean, seen, scale, dts, counts, gap, limits):
        box, complete, pose, h, mean_out, seen_out, since = self.step(
            points, lengths, hidden, mean, seen, scale, dts, counts, gap)
        complete_r, pose_r, corr, ext = self.refine(points, lengths.to(points.dtype), box,
                                                    complete, pose, limits)
        return complete_r, pose_r, h, mean_out, seen_out, since, pose, corr, ext


class RefinedOneTrackGraph(_Refined, OneTrackGraph):
    """:class:`OneTrackGraph` followed by the refiner's first pass: ``(REFINED_ONE_INPUTS) ->
    (REFINED_ONE_OUTPUTS)``."""

    def __init__(self, model: ShapePoseNet, net: nn.Module):
        super().__init__(model)
        self.attach_refiner(net)

    def forward(self, points, hidden, mean, seen, scale, dts, counts, gap, limits):
        box, complete, pose, h, frame_mean = self.step(points, hidden, mean, seen, scale, dts,
                                                       counts, gap)
        count = torch.ones_like(points[:, :, 0]).sum(dim=1)  # (1,): n, traced
        complete_r, pose_r, corr, ext = self.refine(points, count, box, complete, pose, limits,
                                                    one_track=True)
        return complete_r, pose_r, h, frame_mean, pose, corr, ext


@dataclass
class StepInputs:
    """Numpy inputs of one step of the rows a backend computes (see :data:`GRAPH_INPUTS`)."""

    points: np.ndarray  # (B, N, 3) float32, rows past lengths are cyclic copies
    lengths: np.ndarray  # (B,) int64
    hidden: np.ndarray  # (B, S) float32
    mean: np.ndarray  # (B, 3) float32
    seen: np.ndarray  # (B,) bool
    scale: np.ndarray  # (B,) float32 (ones without scale_norm)
    dts: np.ndarray  # (B,) float32, finite and >= 0
    counts: np.ndarray  # (B,) int64
    gap: np.ndarray  # (B,) float32
    limits: np.ndarray | None = None  # (5,) float32: the refined graphs' (LIMIT_FIELDS)

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in GRAPH_INPUTS}


class PassTooLarge(MemoryError):
    """A pass of an engine found too little memory (ONNX Runtime's failed allocation, or
    PyTorch's): :meth:`seqshape.model.estimator.Estimator.step` splits the pass, and refuses
    the step with a :class:`~seqshape.errors.ConfigError` naming its size when one track
    alone does not fit. ``rows``, ``points``: the pass's tracks and padded points."""

    def __init__(self, rows: int, points: int, detail: str):
        super().__init__(f"a pass of {rows} tracks x {points} points ran out of memory "
                         f"({detail})")
        self.rows, self.points, self.detail = rows, points, detail


#: Words of the runtimes' messages for a failed allocation (ONNX Runtime's arena:
#: "BFCArena::AllocateRawInternal ... Failed to allocate memory"; PyTorch's CPU allocator:
#: "DefaultCPUAllocator: can't allocate memory").
_ALLOCATION_WORDS = ("bfcarena", "failed to allocate", "allocate memory", "bad_alloc",
                     "out of memory")


def allocation_failure(exc: BaseException) -> bool:
    """Whether ``exc`` (raised by a pass) is a runtime's failure to allocate memory."""
    if isinstance(exc, MemoryError):
        return True
    text = str(exc).lower()
    return any(w in text for w in _ALLOCATION_WORDS)


def _guarded(inputs: StepInputs, run: Callable[[], tuple]) -> tuple:
    """``run()``, an allocation failure turned into :class:`PassTooLarge` (other errors pass
    through as they are)."""
    try:
        return run()
    except PassTooLarge:
        raise
    except Exception as exc:  # ONNX Runtime's Fail / RuntimeException, torch's RuntimeError
        if not allocation_failure(exc):
            raise
        b, n = inputs.points.shape[:2]
        raise PassTooLarge(b, n, str(exc).strip().splitlines()[0][:300]) from None


class TorchGraphEngine:
    """:class:`StepGraph` run by PyTorch in float32 (``"torch-lean"``).

    ``threads``: torch's intra-op threads during this engine's steps only (restored after;
    None: 1). With a refiner attached (:meth:`set_refiner`), a pass whose inputs carry
    ``limits`` runs :class:`RefinedStepGraph` instead."""

    name = "torch-lean"
    tolerance = TOLERANCE
    noise: float | None = None  # a statistical check instead (:data:`INT8_NOISE`)

    def __init__(self, model: ShapePoseNet, threads: int | None = None):
        self.threads = threads or 1
        self.model = model
        self.graph = StepGraph(model).eval()
        self._refiner: tuple | None = None  # (net, RefinerGraph)
        self._refined: tuple | None = None  # (net, RefinedStepGraph)

    def set_refiner(self, net: nn.Module) -> None:
        """The refiner network of the passes with ``limits`` (:class:`RefinedStepGraph`)."""
        if self._refined is None or self._refined[0] is not net:
            self._refined = (net, RefinedStepGraph(self.model, net).eval())

    def run(self, inputs: StepInputs) -> tuple[np.ndarray, ...]:
        """The outputs of :data:`GRAPH_OUTPUTS` as numpy arrays (:data:`REFINED_OUTPUTS`
        when ``inputs.limits`` is set)."""
        args = [torch.from_numpy(a) for a in inputs.arrays().values()]
        graph = self.graph
        if inputs.limits is not None:
            graph = self._refined[1]
            args.append(torch.from_numpy(inputs.limits))

        def run():
            with torch.inference_mode(), _torch_threads(self.threads):
                return graph(*args)

        return tuple(o.numpy() for o in _guarded(inputs, run))

    def refiner(self, net: nn.Module) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """The forward pass of a placement refiner's network on this engine's torch threads
        (:class:`RefinerGraph`), so that it shares the network's thread pool."""
        if self._refiner is None or self._refiner[0] is not net:
            self._refiner = (net, RefinerGraph(net).eval())
        graph = self._refiner[1]

        def run(xyz: np.ndarray, cond: np.ndarray) -> np.ndarray:
            with torch.inference_mode(), _torch_threads(self.threads):
                return graph(torch.from_numpy(xyz), torch.from_numpy(cond)).numpy()

        return run


class _Sessions:
    """The sessions of one pair of graphs (batch, one-track): one thread each, and the
    two-thread ones (:meth:`wide`) created at their first use."""

    def __init__(self, ort, graphs: tuple[bytes, bytes], threads: int | None, more: int):
        self.ort, self.graphs, self.more = ort, graphs, more
        self.session = _Session(ort, graphs[0], threads or 1)
        self.one = _Session(ort, graphs[1], threads or 1)
        self._wide: list[_Session | None] = [None, None]

    def wide(self, one_track: bool) -> _Session | None:
        if self.more < 2:
            return None
        if self._wide[one_track] is None:
            self._wide[one_track] = _Session(self.ort, self.graphs[one_track], self.more,
                                             spin=one_track)
        return self._wide[one_track]


class OnnxEngine:
    """:class:`StepGraph` exported to ONNX and run by ONNX Runtime (``"onnx"``).

    Two graphs: :class:`OneTrackGraph` for a pass of one track whose frame has points (a
    single-track stream's every step), :class:`StepGraph` for the others. ``threads``: ONNX
    Runtime's intra-op threads of every pass, whose workers do not spin while waiting (other
    processes on the same cores keep their time). None: one thread, and while a core is free
    (:func:`spare_cores`, read at most every :data:`SPARE_CHECK_PERIOD` s), two
    (:data:`LARGE_PASS_THREADS`, at most the cores this process may use) for passes of at
    least :data:`LARGE_PASS_ROWS` encoder rows and for one-track passes; the latter's second
    thread spins during the pass (each of its matrix products is too short to wake a sleeping
    thread for) and stops when the pass ends.

    With a placement refiner attached (:meth:`set_refiner`), the passes whose inputs carry
    ``limits`` run the refined pair instead (:class:`RefinedStepGraph`,
    :class:`RefinedOneTrackGraph`: the network and the refiner's first pass in one graph),
    exported and cached like the plain pair (the cache key holds both networks' weights).
    """

    name = "onnx"
    #: (shape, centre, yaw) agreement with the reference (:data:`TOLERANCE`).
    tolerance = TOLERANCE
    #: Not None: held to the reference by distribution as well (:data:`INT8_NOISE`).
    noise: float | None = None

    def __init__(self, model: ShapePoseNet, threads: int | None = None):
        ort = require("onnxruntime", "the ONNX inference backend", "seqshape[fast]")
        self.threads, self.motion, self.model = threads, model.motion, model
        self.cores = _usable_cores()
        self.more = min(LARGE_PASS_THREADS, self.cores) if threads is None else 1
        self._ort = ort
        self._plain = _Sessions(ort, (self.graph_bytes(model), self.one_graph_bytes(model)),
                                threads, self.more)
        self.session, self.one = self._plain.session, self._plain.one
        self._spare_at, self._spare = -np.inf, False
        self._refiner: tuple | None = None  # (net, one-thread session, wide session)
        self._refined: tuple | None = None  # (net, _Sessions of the refined graphs)

    def wide(self, one_track: bool) -> _Session | None:
        """The two-thread session of the batch or the one-track graph (None when ``threads``
        is given or the process has one core), created at its first use."""
        return self._plain.wide(one_track)

    def spare(self) -> bool:
        """Whether a core is free (:func:`spare_cores`, cached :data:`SPARE_CHECK_PERIOD` s)."""
        now = time.monotonic()
        if now - self._spare_at > SPARE_CHECK_PERIOD:
            self._spare_at, self._spare = now, spare_cores(self.cores) > 0
        return self._spare

    def graph_bytes(self, model: ShapePoseNet, net: nn.Module | None = None) -> bytes:
        """The ONNX model of :class:`StepGraph` this engine runs (exported, or read from the
        disk cache of :mod:`seqshape.model.graph_cache`); with a refiner's ``net``,
        :class:`RefinedStepGraph`'s."""
        if net is not None:
            return cached_graph(_Pair(model, net), "step+refiner",
                                lambda: export_onnx(model, refiner=net))
        return cached_graph(model, "step", lambda: export_onnx(model))

    def one_graph_bytes(self, model: ShapePoseNet, net: nn.Module | None = None) -> bytes:
        """The ONNX model of :class:`OneTrackGraph` this engine runs (likewise cached; with
        ``net``, :class:`RefinedOneTrackGraph`'s)."""
        if net is not None:
            return cached_graph(_Pair(model, net), "one+refiner",
                                lambda: export_onnx(model, one_track=True, refiner=net))
        return cached_graph(model, "one", lambda: export_onnx(model, one_track=True))

    def set_refiner(self, net: nn.Module) -> None:
        """Attach a placement refiner's network: the refined graphs are built (or read from
        the cache) now, once per network."""
        if self._refined is None or self._refined[0] is not net:
            graphs = (self.graph_bytes(self.model, net), self.one_graph_bytes(self.model, net))
            self._refined = (net, _Sessions(self._ort, graphs, self.threads, self.more))

    def refiner(self, net: nn.Module) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """The forward pass of a placement refiner's network (``xyz``, ``cond`` -> ``(B, 4)``,
        ``(B, 6)`` with the size head) on ONNX Runtime, with the thread rule of :meth:`run` (two threads for passes of at
        least :data:`LARGE_PASS_ROWS` points while a core is free): the refiner's further
        passes (long vehicles), and the whole refinement where the refined graphs do not
        apply. Numpy's own forward would
        run on OpenBLAS's threads, which keep spinning after each product and take the core
        the next network pass counts on (measured: 100 live tracks 650 against 930 updates/s
        with OpenBLAS held to one thread; docs/model.md)."""
        if self._refiner is None or self._refiner[0] is not net:
            graph = cached_graph(net, "refiner", lambda: export_refiner_onnx(net))
            one = _Session(self._ort, graph, self.threads or 1)
            wide = _Session(self._ort, graph, self.more) if self.more > 1 else None
            self._refiner = (net, one, wide)
        _, one, wide = self._refiner

        def run(xyz: np.ndarray, cond: np.ndarray) -> np.ndarray:
            big = xyz.shape[0] * xyz.shape[1] >= LARGE_PASS_ROWS
            session = wide if wide is not None and big and self.spare() else one
            return session.session.run(None, {"xyz": xyz, "cond": cond})[0]

        return run

    def run(self, inputs: StepInputs) -> tuple[np.ndarray, ...]:
        """The outputs of :data:`GRAPH_OUTPUTS` as numpy arrays (:data:`REFINED_OUTPUTS` when
        ``inputs.limits`` is set: the refined graphs of :meth:`set_refiner`). A failed
        allocation raises :class:`PassTooLarge`."""
        return _guarded(inputs, lambda: self._run(inputs))

    def _run(self, inputs: StepInputs) -> tuple[np.ndarray, ...]:
        sessions = self._plain if inputs.limits is None else self._refined[1]
        b, n = inputs.points.shape[:2]
        if b == 1 and inputs.lengths[0] == n:  # one track with points, no padding
            one = sessions.wide(True) if self.more > 1 and self.spare() else sessions.one
            complete, pose, hidden, mean, *rest = one.run(inputs)
            gap = np.zeros(1, np.float32) if self.motion else inputs.gap
            return complete, pose, hidden, mean, np.ones(1, bool), gap, *rest
        if self.more > 1 and b * n >= LARGE_PASS_ROWS and self.spare():
            return tuple(sessions.wide(False).run(inputs))
        return tuple(sessions.session.run(inputs))


class _Pair:
    """A network and its refiner's network as one key of the graph cache
    (:func:`~seqshape.model.graph_cache.graph_key` reads ``kind``, ``cfg`` and
    ``state_dict``)."""

    def __init__(self, model: ShapePoseNet, net: nn.Module):
        self.kind, self.cfg, self._model, self._net = model.kind, model.cfg, model, net

    def state_dict(self) -> dict:
        out = dict(self._model.state_dict())
        out.update({f"refiner.{k}": v for k, v in self._net.state_dict().items()})
        return out


class OnnxInt8Engine(OnnxEngine):
    """``"onnx"`` with the weights of the layers :data:`INT8_LAYERS` quantised to int8
    (``"onnx-int8"``, :func:`quantize_onnx`), built in memory at load time (about 1.5 s: two
    graphs). With a refiner, the batch graph's refiner layers :data:`INT8_REFINER_LAYERS` too
    (the one-track graph's refiner stays float32)."""

    name = "onnx-int8"
    tolerance = INT8_TOLERANCE
    noise = INT8_NOISE

    def graph_bytes(self, model: ShapePoseNet, net: nn.Module | None = None) -> bytes:
        rows = INT8_ROW_LAYERS
        tag = f"{','.join(INT8_STEP_LAYERS)};rows:{','.join(rows)};eq:cars8x2000"
        if net is not None:
            layers = INT8_STEP_LAYERS + INT8_REFINER_LAYERS
            key = f"step+refiner-int8:{tag};{','.join(INT8_REFINER_LAYERS)}"
            return cached_graph(_Pair(model, net), key, lambda: quantize_onnx(
                export_onnx(model, refiner=net), layers, rows, equalisation_sample(model)))
        return cached_graph(model, f"step-int8:{tag}", lambda: quantize_onnx(
            export_onnx(model), INT8_STEP_LAYERS, rows, equalisation_sample(model)))

    def one_graph_bytes(self, model: ShapePoseNet, net: nn.Module | None = None) -> bytes:
        if net is not None:
            return cached_graph(_Pair(model, net), f"one+refiner-int8:{','.join(INT8_LAYERS)}",
                                lambda: quantize_onnx(export_onnx(model, one_track=True,
                                                                  refiner=net), INT8_LAYERS))
        return cached_graph(model, f"one-int8:{','.join(INT8_LAYERS)}",
                            lambda: quantize_onnx(export_onnx(model, one_track=True),
                                                  INT8_LAYERS))


def equalisation_sample(model: ShapePoseNet, seed: int = 0) -> np.ndarray:
    """Typical encoder inputs ``(M, C)`` for :func:`~seqshape.model.int8.quantize_onnx`'s
    channel equalisation: a 4.6 x 1.85 x 1.5 m car's surface demeaned, at 8 headings, 2,000
    points each (the scale of a car is 1), with the viewing direction of a car 10 m away at
    that heading for a ``view_input`` model; seeded, so the graph is the same each time."""
    rng = np.random.default_rng(seed)
    rows = []
    for yaw in np.linspace(0.0, np.pi, 8, endpoint=False):
        p = box_surface(2000, rng, (4.6, 1.85, 1.5), pose=(0.0, 0.0, 0.0, yaw))
        p = p - p.mean(axis=0)
        if model.cfg.view_input:
            view = np.array([np.cos(yaw), np.sin(yaw), -0.09])
            p = np.hstack([p, np.broadcast_to(view / np.linalg.norm(view), p.shape)])
        rows.append(p)
    return np.concatenate(rows).astype(np.float32)


class _Session:
    """An ONNX Runtime session of one graph and thread count, fed from :class:`StepInputs`
    (the inputs the exporter kept: a model without motion inputs has no ``dts``...)."""

    def __init__(self, ort, graph: bytes, threads: int, spin: bool = False):
        self.session = ort.InferenceSession(graph, _session_options(ort, threads, spin),
                                            providers=["CPUExecutionProvider"])
        self.inputs = [i.name for i in self.session.get_inputs()]

    def run(self, inputs: StepInputs) -> list[np.ndarray]:
        return self.session.run(None, {k: getattr(inputs, k) for k in self.inputs})


def _usable_cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def spare_cores(cores: int) -> int:
    """Of ``cores`` (this process's), how many no other task wants right now: ``cores``
    minus the kernel's count of runnable tasks (``/proc/loadavg``, which counts the calling
    thread); 0 where the count is not available (not Linux)."""
    try:
        with open("/proc/loadavg", "rb") as f:
            running = int(f.read().split()[3].split(b"/")[0])
    except (OSError, ValueError, IndexError):
        return 0
    return max(0, cores - running)


def _session_options(ort, threads: int | None, spin: bool = False):
    """ONNX Runtime session options of the ONNX engines (see :class:`OnnxEngine`): with
    ``spin`` the workers spin for work during a run and stop when it returns."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads or 1)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
    if spin:
        opts.add_session_config_entry("session.force_spinning_stop", "1")
    opts.log_severity_level = 3
    return opts


def export_onnx(model: ShapePoseNet, one_track: bool = False,
                refiner: nn.Module | None = None) -> bytes:
    """The ONNX model (bytes) of one streaming step of ``model`` (:class:`StepGraph`), with
    dynamic batch and point axes; with ``one_track`` :class:`OneTrackGraph` (batch 1, dynamic
    point axis); with a placement ``refiner``'s network, the refined graphs
    (:class:`RefinedStepGraph`, :class:`RefinedOneTrackGraph`). PyTorch's exporter needs the
    ``onnx`` package."""
    require("onnx", "exporting the network to ONNX", "seqshape[fast]")
    if refiner is None:
        inputs, outputs = (ONE_INPUTS, ONE_OUTPUTS) if one_track else (GRAPH_INPUTS,
                                                                      GRAPH_OUTPUTS)
        graph = (OneTrackGraph if one_track else StepGraph)(model).eval()
    else:
        inputs, outputs = ((REFINED_ONE_INPUTS, REFINED_ONE_OUTPUTS) if one_track
                           else (REFINED_INPUTS, REFINED_OUTPUTS))
        graph = (RefinedOneTrackGraph if one_track else RefinedStepGraph)(model, refiner).eval()
    example = example_inputs(model, batch=1 if one_track else 2, points=5).arrays()
    example["limits"] = np.array([1.5, 0.35, 0.3, 0.0, 1.0], np.float32)
    if one_track:
        axes = {"points": {1: "points"}}
    else:
        axes = {name: {0: "batch"} for name in (*inputs, *outputs) if name != "limits"}
        axes["points"] = {0: "batch", 1: "points"}
    buf = io.BytesIO()
    with warnings.catch_warnings(), torch.inference_mode():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notices
        torch.onnx.export(graph, tuple(torch.from_numpy(example[k]) for k in inputs), buf,
                          input_names=list(inputs), output_names=list(outputs),
                          dynamic_axes=axes, opset_version=ONNX_OPSET, dynamo=False)
    return buf.getvalue()


def example_inputs(model: ShapePoseNet, batch: int, points: int,
                   seed: int = 0) -> StepInputs:
    """Random valid :class:`StepInputs` (the export's example and a smoke input)."""
    rng = np.random.default_rng(seed)
    lengths = rng.integers(1, points + 1, size=batch)
    pts = np.zeros((batch, points, 3), np.float32)
    for i, n in enumerate(lengths):
        pts[i] = np.resize(rng.normal(size=(n, 3)) + [10.0, 0.0, 0.0], (points, 3))
    return StepInputs(pts, lengths.astype(np.int64),
                      np.zeros((batch, model.state_size), np.float32),
                      np.zeros((batch, 3), np.float32), np.zeros(batch, bool),
                      np.ones(batch, np.float32), np.full(batch, DEFAULT_FRAME_PERIOD, np.float32),
                      lengths.astype(np.int64), np.zeros(batch, np.float32))


def length_buckets(lengths: np.ndarray, fill: float = BUCKET_FILL,
                   min_rows: int = BUCKET_MIN_ROWS) -> list[np.ndarray]:
    """Rows grouped for separate passes so that little of the padded batch is padding.

    Longest first: a group takes the rows at least ``fill`` times its longest (at least
    ``min_rows`` rows; a remainder under ``min_rows`` joins the last group), so at most
    ``1 / fill - 1`` of a group's encoder work is padding instead of up to ``N / min(n_i)``.

    >>> [g.tolist() for g in length_buckets(np.array([10, 256, 40, 250, 200]), min_rows=1)]
    [[1, 3, 4], [2], [0]]
    """
    if len(lengths) < 2:
        return [np.arange(len(lengths))]
    order = np.argsort(-np.asarray(lengths), kind="stable")
    if len(order) < 2 * min_rows:  # one group whatever the lengths (the loop's outcome)
        return [order]
    desc = np.asarray(lengths)[order]
    groups, start = [], 0
    while start < len(order):
        end = start + int(np.searchsorted(-desc[start:], -fill * desc[start], side="right"))
        end = max(end, start + min_rows)
        if len(order) - end < min_rows:
            end = len(order)
        groups.append(order[start:end])
        start = end
    return groups


def pack_frames(frames: list[np.ndarray], buffer: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Frames (n_i, 3) as one contiguous (B, N, 3) float32 batch, N = max(1, max n_i), rows
    past n_i cyclic copies of the frame's points (zeros for an empty frame), as
    :class:`StepGraph` needs. ``buffer`` (flat float32) is reused when large enough; returns
    (batch, buffer) with the buffer to pass next time."""
    b, n = len(frames), max(1, max(len(f) for f in frames))
    if buffer.size < b * n * 3:
        buffer = np.empty(max(b * n * 3, 2 * buffer.size), np.float32)
    batch = buffer[:b * n * 3].reshape(b, n, 3)
    for i, f in enumerate(frames):
        k = len(f)
        if k == n:
            batch[i] = f
        elif k == 0:
            batch[i] = 0.0
        else:
            np.take(f, np.arange(n) % k, axis=0, out=batch[i])
    return batch, buffer


def check_stream(num_points: int, seed: int = 0) -> list[dict]:
    """The steps of :func:`seqshape.model.estimator.check_backend`: three tracks over six
    steps (box-like clouds of 0, 1, about N/2 and 3N points, empty frames, a track that starts
    late, timestamps known and unknown, a length hint, a step in which one track alone has
    points: the ONNX engines' one-track graph)."""
    rng = np.random.default_rng(seed)

    def cloud(n: int, x: float) -> np.ndarray:
        return (rng.normal(size=(n, 3)) * [2.0, 0.9, 0.6] + [x, 3.0, -0.8]).astype(np.float32)

    half = max(2, num_points // 2)
    counts = [(half, 1, 0), (3 * num_points, 0, half), (0, half, 1),
              (half, 3 * num_points, half), (1, half, 0), (0, half, 0)]
    steps = []
    for t, row in enumerate(counts):
        ids = ["a", "b", "c"] if t != 3 else ["a", "b", "fresh"]
        steps.append({"track_ids": ids,
                      "point_lists": [cloud(n, 8.0 + 4 * i + 0.3 * t) for i, n in enumerate(row)],
                      "timestamps": [0.1 * t, None, 0.1 * t + 0.05],
                      "sizes": [None, None, (12.0, 2.5, 3.2)]})
    return steps


def car_stream(num_points: int, seed: int = 0, n_tracks: int = 40,
               n_steps: int = 4) -> list[dict]:
    """Steps of ``n_tracks`` moving tracks of partial car views (the half of a car-sized box
    surface nearer the sensor, N/4 to 2N points, 0.8 m a step, timestamps 0.1 s apart), so
    that a pass splits into point-count groups: the stream of the statistical check of
    ``"onnx-int8"`` (:data:`INT8_NOISE`)."""
    rng = np.random.default_rng(seed)
    starts = rng.uniform(6, 30, size=(n_tracks, 2)) * rng.choice([-1, 1], size=(n_tracks, 2))
    yaws = rng.uniform(-np.pi, np.pi, size=n_tracks)
    ids = [f"car{i}" for i in range(n_tracks)]
    steps = []
    for t in range(n_steps):
        clouds = []
        for i in range(n_tracks):
            n = int(rng.integers(max(2, num_points // 4), 2 * num_points + 1))
            xy = starts[i] + 0.8 * t * np.array([np.cos(yaws[i]), np.sin(yaws[i])])
            pts = box_surface(2 * n + 2, rng, pose=(*xy, -0.9, yaws[i]), dtype=np.float32)
            near = np.linalg.norm(pts[:, :2], axis=1) <= np.linalg.norm(xy)
            clouds.append(pts[near][:n])
        steps.append({"track_ids": ids, "point_lists": clouds,
                      "timestamps": [0.1 * t] * n_tracks})
    return steps


def make_engine(model: ShapePoseNet, name: str, threads: int | None = None):
    """The engine of backend ``name`` (not ``"auto"`` nor ``"torch"``) for ``model``."""
    if name == "onnx":
        return OnnxEngine(model, threads)
    if name == "onnx-int8":
        return OnnxInt8Engine(model, threads)
    if name == "torch-lean":
        return TorchGraphEngine(model, threads)
    raise ConfigError(f"unknown inference backend {name!r}; choose from {BACKENDS}")


class _torch_threads:
    """Context: torch's intra-op threads set to ``n`` inside, restored after (None: as is)."""

    def __init__(self, n: int | None):
        self.n, self.old = n, None

    def __enter__(self):
        if self.n is not None and torch.get_num_threads() != self.n:
            self.old = torch.get_num_threads()
            torch.set_num_threads(self.n)

    def __exit__(self, *exc):
        if self.old is not None:
            torch.set_num_threads(self.old)


_AUTO_CACHE: dict[tuple, str] = {}


def _weights_crc(module: nn.Module) -> int:
    """A checksum of a module's weights (names and bytes)."""
    crc = 0
    for name, t in module.state_dict().items():
        crc = zlib.crc32(name.encode(), crc)
        crc = zlib.crc32(t.detach().contiguous().numpy().tobytes(), crc)
    return crc


def model_fingerprint(model: ShapePoseNet) -> tuple:
    """A key of ``model``'s function: kind, configuration and a checksum of its weights."""
    return model.kind, json.dumps(model.cfg.to_dict(), sort_keys=True), _weights_crc(model)


def select_backend(model: ShapePoseNet, check: Callable[[str], bool],
                   order: tuple[str, ...] = AUTO_ORDER, refiner: nn.Module | None = None) -> str:
    """The backend ``"auto"`` picks for ``model``: the first of ``order`` whose runtime is
    installed and for which ``check(name)`` is True, else the reference ``"torch"``. Warns
    (``RuntimeWarning``) when a backend is passed over, saying why; an int8 one whose check
    fails only logs it (float32 is then the exact choice: some weights round worse than
    others). Cached per process, model (:func:`model_fingerprint`), placement ``refiner``'s
    network (the check runs the estimator with it: the refined graphs are checked too) and
    ``order``, so the check runs once; and each backend's verdict on disk, per model,
    refiner and machine (:func:`seqshape.model.graph_cache.cached_verdict`), so later
    processes skip it."""
    extra = "" if refiner is None else f"+refiner:{_weights_crc(refiner)}"
    key = (model_fingerprint(model), order, extra)
    if key in _AUTO_CACHE:
        return _AUTO_CACHE[key]
    reasons, quiet, chosen = [], [], "torch"
    for name in order:
        try:
            ok = cached_verdict(model, name + extra, lambda name=name: check(name))
        except MissingDependencyError:
            reasons.append(f"{name}: runtime not installed (pip install 'seqshape[fast]')")
            continue
        if ok:
            chosen = name
            break
        why = f"{name}: outputs differ from the reference on this machine"
        (quiet if name == "onnx-int8" else reasons).append(why)
    if quiet:
        log.info("inference backend %r chosen (%s)", chosen, "; ".join(quiet))
    if reasons:
        warnings.warn(f"inference backend {chosen!r} chosen ({'; '.join(reasons + quiet)})",
                      RuntimeWarning, stacklevel=3)
    _AUTO_CACHE[key] = chosen
    return chosen
