"""Small synthetic track datasets for the model/train/estimator tests: box-shaped vehicles
moving along straight lines, partial frames = the sensor-facing half of the surface."""

from __future__ import annotations

import numpy as np

from seqshape.data import Track, write_dataset
from seqshape.geometry import canonical_to_sensor
from seqshape.testing import box_shell


def box_track(track_id: str, split: str, rng: np.random.Generator, frames: int = 12,
              empty_frame: int | None = None) -> Track:
    """One box track moving along a line; frame ``empty_frame`` has no points."""
    size = np.array([rng.uniform(3.5, 5.0), rng.uniform(1.6, 2.0), rng.uniform(1.3, 1.8)])
    complete = box_shell(1024, rng, size, dtype=np.float32)
    x0, y0, yaw = rng.uniform(5, 20), rng.uniform(-8, 8), rng.uniform(-np.pi, np.pi)
    v = rng.uniform(0.0, 1.0)
    t = np.arange(frames)
    poses = np.stack([x0 + v * t * np.cos(yaw), y0 + v * t * np.sin(yaw),
                      np.full(frames, -1.0), np.full(frames, yaw)], 1)
    points = []
    for k in range(frames):
        s = canonical_to_sensor(complete, poses[k])
        near = s[np.linalg.norm(s[:, :2], axis=1) < np.linalg.norm(poses[k, :2])]
        near = near[rng.random(len(near)) < rng.uniform(0.1, 0.6)]
        points.append(near[:0] if k == empty_frame else near)
    return Track(track_id, points, poses, complete, size, t * 0.1, {"split": split})


def make_dataset(path, n_train: int = 8, n_val: int = 3, frames: int = 12, seed: int = 0):
    """Write a dataset folder with ``n_train`` / ``n_val`` box tracks; returns it opened."""
    rng = np.random.default_rng(seed)
    tracks = [box_track(f"train{i:03d}", "train", rng, frames, 3 if i % 3 == 0 else None)
              for i in range(n_train)]
    tracks += [box_track(f"val{i:03d}", "val", rng, frames) for i in range(n_val)]
    return write_dataset(path, tracks)


def write_checkpoint(path, kind: str, cfg, seed: int = 0) -> str:
    """A randomly initialised ``kind`` network of ``cfg`` saved as a weights file; its path."""
    import torch

    from seqshape.model import ShapePoseNet

    torch.manual_seed(seed)
    net = ShapePoseNet(cfg, recurrent=kind == "sequential")
    torch.save({"format": "seqshape-checkpoint", "version": 1, "kind": kind,
                "model_config": cfg.to_dict(), "train_config": {},
                "state_dict": net.state_dict(), "metrics": {}}, path)
    return str(path)
