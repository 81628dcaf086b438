"""Training: losses (Chamfer, pose, joint), configs and presets, the three-stage trainer,
checkpoints. Importing this package imports torch."""

from seqshape.train.config import TRAIN_PRESETS, StageConfig, TrainConfig, get_train_config
from seqshape.train.losses import JointLoss, chamfer_distance, pose_loss
from seqshape.train.trainer import Trainer, train

__all__ = ["TRAIN_PRESETS", "JointLoss", "StageConfig", "TrainConfig", "Trainer",
           "chamfer_distance", "get_train_config", "pose_loss", "train"]
