"""Training hyper-parameters: :class:`TrainConfig`, :class:`StageConfig` and named presets.

Stages (paper, "Training"): 1 Chamfer loss on encoder + fusion + shape decoder; 2 pose loss on
the pose decoder alone (the rest frozen); 3 the joint loss with learned sigmas on everything.
Each stage runs ``steps`` optimiser steps or until its wall-clock ``time_budget_min`` is used
up, whichever comes first. Runs stopped by a time budget are not bit-reproducible (the step
at which a stage ends and the learning-rate schedule depend on the clock); step-limited runs
are.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from seqshape.errors import ConfigError
from seqshape.model.config import ModelConfig, get_model_config

STAGE_NAMES = ("shape", "pose", "joint")


@dataclass(frozen=True)
class StageConfig:
    """One training stage."""

    steps: int
    """Optimiser steps of this stage (upper bound when a time budget is set)."""
    lr: float = 1e-3
    """Adam learning rate at the start of the stage."""
    time_budget_min: float | None = None
    """Wall-clock minutes for this stage (None: unlimited); the stage ends when used up."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (saved with every checkpoint)."""

    model_preset: str = "small"
    """Name of the :data:`seqshape.model.MODEL_PRESETS` entry the network starts from."""
    model_overrides: dict = field(default_factory=dict)
    """ModelConfig fields replacing the preset's (e.g. ``{"num_complete": 512}``)."""
    stages: tuple[StageConfig, ...] = (StageConfig(3000), StageConfig(1000),
                                       StageConfig(3000, lr=5e-4))
    """The three stages, in order (shape, pose, joint)."""
    window: int = 12
    """W: consecutive frames per training window (the GRU starts from zero at its first)."""
    batch_size: int = 6
    """Windows per optimiser step and process (frames per step = batch_size * window)."""
    num_complete_gt: int = 1024
    """Ground-truth complete points per window used by both losses."""
    p_first: float = 0.25
    """Probability that a training window starts at the track's first frame."""
    early_weight: float = 0.0
    """Extra weight, in the training objective, of each window's first ``early_frames``
    detections: the GRU starts from zero there, as at a track's first detection, and with
    long windows those frames are a small share of the loss (docs/model.md, "Early
    detections in the loss"). 0: every frame alike (the paper). Validation is unweighted."""
    early_frames: int = 4
    """The detections of a window that ``early_weight`` applies to."""
    windows_per_track: int = 4
    """Windows drawn per track and epoch."""
    lr_min_ratio: float = 0.05
    """Each stage's learning rate decays (cosine) from lr to lr * lr_min_ratio."""
    sigma_lr: float = 1e-2
    """Adam learning rate of the stage-3 log-sigmas."""
    grad_clip: float | None = 10.0
    """Clip the global gradient norm (None: off)."""
    val_every: int = 250
    """Validate every this many steps (and at every stage end); 0 disables."""
    val_windows: int = 64
    """Fixed validation windows drawn from the val split."""
    ckpt_every: int = 250
    """Write RUN/last.pt every this many steps (and at every stage end)."""
    log_every: int = 25
    """Write a training row to RUN/log.csv every this many steps."""
    seed: int = 0
    """Seeds the weights, the windows and their order."""
    threads: int = 1
    """torch intra-op threads per process."""
    cache_size: int = 128
    """Tracks kept in memory per process."""
    tensorboard: bool = True
    """Also log to TensorBoard (RUN/tb) when the package is installed."""
    length_hint_noise: float = 0.08
    """Only with ``ModelConfig.scale_norm="length"``: the input scale's length is a tracker's
    box length, the true length times exp(N(0, this) per window + N(0, this/3) per frame)
    (:class:`seqshape.data.windows.WindowDataset`)."""
    length_points_prob: float = 0.3
    """Only with ``scale_norm="length"``: probability that a window's length comes from its
    points instead (what ``Estimator`` uses without hints: running maximum for the sequential
    model, per frame for the baseline)."""

    def __post_init__(self):
        if len(self.stages) != 3:
            raise ConfigError(f"TrainConfig.stages needs 3 stages, got {len(self.stages)}")
        stages = tuple(s if isinstance(s, StageConfig) else StageConfig(**s) for s in self.stages)
        object.__setattr__(self, "stages", stages)
        for i, s in enumerate(stages):
            if s.steps < 0 or s.lr <= 0:
                raise ConfigError(f"stage {i + 1}: steps must be >= 0 and lr > 0, got {s}")
        if self.early_weight < 0:
            raise ConfigError(f"TrainConfig.early_weight must be >= 0, got {self.early_weight}")
        for name in ("window", "batch_size", "num_complete_gt", "threads", "log_every",
                     "early_frames"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("p_first", "length_points_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"TrainConfig.{name} must be in [0, 1], got "
                                  f"{getattr(self, name)}")
        if self.length_hint_noise < 0:
            raise ConfigError(f"TrainConfig.length_hint_noise must be >= 0, got "
                              f"{self.length_hint_noise}")

    def model_config(self) -> ModelConfig:
        """The resolved network configuration."""
        base = get_model_config(self.model_preset).to_dict()
        unknown = sorted(set(self.model_overrides) - set(base))
        if unknown:
            raise ConfigError(f"unknown model_overrides {unknown}")
        return ModelConfig.from_dict({**base, **self.model_overrides})

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"unknown TrainConfig fields {unknown}")
        d = dict(d)
        if "stages" in d:
            d["stages"] = tuple(StageConfig(**s) if isinstance(s, dict) else s
                                for s in d["stages"])
        return cls(**d)

    def with_stage_steps(self, steps: tuple[int, int, int]) -> TrainConfig:
        return replace(self, stages=tuple(replace(s, steps=int(n))
                                          for s, n in zip(self.stages, steps, strict=True)))

    def with_time_budget(self, minutes: float,
                         fractions: tuple[float, float, float] = (0.45, 0.15, 0.40)
                         ) -> TrainConfig:
        """Split a total wall-clock budget over the stages (default 45/15/40 %)."""
        return replace(self, stages=tuple(replace(s, time_budget_min=minutes * f)
                                          for s, f in zip(self.stages, fractions, strict=True)))


TRAIN_PRESETS: dict[str, TrainConfig] = {
    # the step counts are upper bounds (seconds per step: docs/history/model.md, "Measurements"), pair
    # with --time-budget-min to fit a wall-clock slot.
    "small": TrainConfig(),
    "paper": TrainConfig(model_preset="paper", batch_size=16, window=12,
                         num_complete_gt=2048,
                         stages=(StageConfig(60000), StageConfig(10000),
                                 StageConfig(60000, lr=5e-4)),
                         val_every=2000, ckpt_every=2000, log_every=100, threads=4,
                         cache_size=512),
    # seconds, for tests: a shrunken network and a handful of steps
    "smoke": TrainConfig(model_overrides={"num_points": 64, "encoder1": [16, 32],
                                          "encoder2": [64, 64], "hidden": 64,
                                          "shape_decoder": [128], "pose_decoder": [64],
                                          "num_complete": 128},
                         stages=(StageConfig(12, lr=3e-3), StageConfig(4, lr=3e-3),
                                 StageConfig(6, lr=1e-3)),
                         window=4, batch_size=2, num_complete_gt=128, windows_per_track=2,
                         val_every=6, val_windows=4, ckpt_every=5, log_every=2,
                         cache_size=16, tensorboard=False),
}


def get_train_config(name: str) -> TrainConfig:
    try:
        return TRAIN_PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown training preset {name!r}; choose from "
                          f"{sorted(TRAIN_PRESETS)}") from None
