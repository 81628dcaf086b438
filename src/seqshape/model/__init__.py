"""The sequential shape-and-pose network, its per-frame baseline, and streaming inference."""

from seqshape.model.config import MODEL_PRESETS, ModelConfig, get_model_config
from seqshape.model.estimator import Estimate, Estimator, build_model, read_model_file
from seqshape.model.heading import HeadingConfig
from seqshape.model.network import PointEncoder, ShapePoseNet
from seqshape.model.offline import OfflineConfig, OfflineEstimator, estimate_track

__all__ = ["MODEL_PRESETS", "Estimate", "Estimator", "HeadingConfig", "ModelConfig",
           "OfflineConfig", "OfflineEstimator", "PointEncoder", "ShapePoseNet", "build_model",
           "estimate_track", "get_model_config", "read_model_file"]
