"""Network hyper-parameters: :class:`ModelConfig` and the named presets.

``small`` is sized to train usefully on 2 CPU cores in about half an hour; ``paper`` follows
the PCN encoder widths (128-256 / 512-1024) and K = 2048 output points, for a GPU. Both use
the paper's input (``view_input`` off).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch

from seqshape.errors import ConfigError

SCALE_NORMS = ("none", "length")
#: Size of the motion vector m_t (``ModelConfig.motion_input``): displacement (3), time since
#: the last detection (1), point count (1), viewing direction (2).
MOTION_SIZE = 7
#: Frozen-weights-compatible fields: they add no parameters, so ``--init`` accepts weights
#: whose configuration differs from the run's only in these (see ``load_init``): the input
#: scale, and the points a frame is cut to (the encoder is per point, then max-pooled).
PARAMETER_FREE_FIELDS = ("scale_norm", "scale_ref", "scale_max", "num_points")


@dataclass(frozen=True)
class ModelConfig:
    """Widths and point counts of :class:`seqshape.model.network.ShapePoseNet`."""

    num_points: int = 256
    """N: every input frame is resampled to at most N points (random subset without
    replacement when it has more; padded with a lengths mask when it has fewer)."""
    encoder1: tuple[int, ...] = (64, 128)
    """Widths of the first shared point MLP (input 3); its max-pool is the first global
    feature, concatenated back to every point (PCN)."""
    encoder2: tuple[int, ...] = (256, 256)
    """Widths of the second shared point MLP (input 2 * encoder1[-1]); its max-pool is the
    frame feature f_t (size encoder2[-1])."""
    hidden: int = 256
    """H: size of the GRU hidden state h_t (also the decoder input size of the baseline)."""
    shape_decoder: tuple[int, ...] = (512, 512)
    """Hidden widths of the shape MLP; its output layer has 3 * num_complete units."""
    pose_decoder: tuple[int, ...] = (256, 256)
    """Hidden widths of the pose MLP; its output is (x, y, z, cos yaw, sin yaw)."""
    num_complete: int = 1024
    """K: number of points of the estimated complete shape."""
    view_input: bool = False
    """Extension (not in the paper): append the unit direction from the sensor to the frame
    mean to every demeaned point (encoder input 6 instead of 3), restoring the viewpoint
    that demeaning removes (which side of the vehicle faces the sensor)."""
    shape_frame: str = "sensor"
    """Frame of the shape decoder's output. ``"sensor"`` (the paper): the MLP outputs X'_t
    directly in the demeaned sensor frame. ``"canonical"`` (extension): the MLP outputs the
    shape in the canonical vehicle frame and it is placed with the predicted pose,
    X_t = R(yaw_t) C_t + (x_t, y_t, z_t); the Chamfer loss then also trains the pose decoder."""
    frame_skip: bool = False
    """Extension (not in the paper; sequential model only): the decoders read the GRU state
    plus a linear projection of the latest frame feature, d_t = h_t + W f_t, so the
    recurrent model contains the per-frame baseline (h_t = Linear(f_t)) as a special case and
    need not squeeze the current frame's detail through the GRU gates. W starts at zero, so a
    model without it loads unchanged (``--init``) and begins as the plain GRU model. The
    recurrent state is then (h_t, W f_t): an empty frame carries both. Ignored by the
    baseline."""
    scale_norm: str = "none"
    """Extension (issue 15, vehicles 2-4x a car): ``"none"`` (the paper; bit-identical to
    models without the field) or ``"length"``: per track and frame an input scale
    ``s = clip(L / scale_ref, 1, scale_max)`` from a vehicle length L (a tracker's or
    annotator's box, a class, or the points' own extent), the demeaned points are divided by
    s before the encoder and the decoded shape and pose offsets multiplied by s after (exactly
    scale-equivariant; s = 1, the unchanged network, for anything up to ``scale_ref`` long).
    Adds no parameters: weights trained without it load unchanged (``--init``)."""
    scale_ref: float = 6.0
    """L_ref (m): lengths up to this give s = 1 (the shipped weights saw cars 3.6-5.8 m)."""
    scale_max: float = 4.0
    """Upper clip of s (a 24 m vehicle)."""
    motion_input: bool = False
    """Extension (issue 19; sequential model only): the GRU input is ``[f_t, m_t]`` with the
    7-vector m_t of :func:`seqshape.model.network.motion_features` per frame: the change of
    the frame mean since the track's last frame with points (3, divided by the input scale s,
    clipped to +-``MOTION_CLIP`` m; zero at the track's first detection), the time since that
    detection (s, clipped to [0, 2]; zero at the first detection), the frame's point count
    before resampling as log1p(n) / log1p(1000), and the bird's-eye unit direction from the
    sensor to the frame mean (x, y). Demeaning removes all of these. The GRU's extra input
    columns start at zero, so a model without the option loads unchanged (``--init``, the
    columns padded with zeros) and begins computing exactly what it did. The carried state
    gains the time since the last detection. Ignored by the baseline."""

    def __post_init__(self):
        for name in ("encoder1", "encoder2", "shape_decoder", "pose_decoder"):
            value = tuple(int(v) for v in getattr(self, name))
            if not value or min(value) < 1:
                raise ConfigError(f"ModelConfig.{name} must be a non-empty tuple of positive "
                                  f"widths, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        if self.shape_frame not in ("sensor", "canonical"):
            raise ConfigError(f"ModelConfig.shape_frame must be 'sensor' or 'canonical', got "
                              f"{self.shape_frame!r}")
        if self.scale_norm not in SCALE_NORMS:
            raise ConfigError(f"ModelConfig.scale_norm must be one of {SCALE_NORMS}, got "
                              f"{self.scale_norm!r}")
        if not (float(self.scale_ref) > 0 and float(self.scale_max) >= 1):
            raise ConfigError(f"ModelConfig needs scale_ref > 0 and scale_max >= 1, got "
                              f"{self.scale_ref!r}, {self.scale_max!r}")
        if not isinstance(self.motion_input, bool):
            raise ConfigError(f"ModelConfig.motion_input must be true or false, got "
                              f"{self.motion_input!r}")
        object.__setattr__(self, "scale_ref", float(self.scale_ref))
        object.__setattr__(self, "scale_max", float(self.scale_max))
        for name in ("num_points", "hidden", "num_complete"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"ModelConfig.{name} must be >= 1, got {getattr(self, name)}")

    @property
    def feature_size(self) -> int:
        """Size of the frame feature f_t."""
        return self.encoder2[-1]

    @property
    def motion_size(self) -> int:
        """Size of the motion vector m_t the GRU reads besides f_t (0 without
        ``motion_input``)."""
        return MOTION_SIZE if self.motion_input else 0

    def scale_for(self, length):
        """Input scale ``s = clip(length / scale_ref, 1, scale_max)`` for vehicle lengths (m):
        a float, a numpy array or a tensor (same type out). Non-finite or non-positive
        lengths (unknown) give 1."""
        if isinstance(length, torch.Tensor):
            ok = torch.isfinite(length) & (length > 0)
            s = torch.where(ok, length, torch.zeros_like(length)) / self.scale_ref
            return s.clamp(1.0, self.scale_max)
        arr = np.asarray(length, dtype=np.float64)
        s = np.clip(np.where(np.isfinite(arr) & (arr > 0), arr, 0.0) / self.scale_ref,
                    1.0, self.scale_max)
        return float(s) if s.ndim == 0 else s

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        """Inverse of :meth:`to_dict`; unknown keys are a :class:`ConfigError`."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"unknown ModelConfig fields {unknown}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


MODEL_PRESETS: dict[str, ModelConfig] = {
    "small": ModelConfig(shape_frame="canonical"),
    "paper": ModelConfig(num_points=1024, encoder1=(128, 256), encoder2=(512, 1024),
                         hidden=1024, shape_decoder=(1024, 1024), pose_decoder=(512, 256),
                         num_complete=2048),
}


def get_model_config(name: str) -> ModelConfig:
    """The preset ``name`` (see :data:`MODEL_PRESETS`)."""
    try:
        return MODEL_PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown model preset {name!r}; choose from "
                          f"{sorted(MODEL_PRESETS)}") from None
