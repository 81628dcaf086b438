"""Planar poses applied to torch point sets: the one torch version of the pose transform.

A pose ``(x, y, z, yaw)`` maps canonical vehicle points to the sensor frame as
``p = R_z(yaw) c + t`` (the convention of :mod:`seqshape.geometry`, which does the same in
numpy). Used by the network's canonical shape decoder, the trainer's ground-truth placement
and the pose loss.

>>> import math
>>> import torch
>>> pose = torch.tensor([[1.0, 2.0, 0.5, math.pi / 2]])
>>> pts = torch.tensor([[[1.0, 0.0, 0.0]]])
>>> place_points(pts, pose).round(decimals=6)
tensor([[[1.0000, 3.0000, 0.5000]]])
>>> unplace_points(place_points(pts, pose), pose).round(decimals=6)
tensor([[[1., 0., 0.]]])
"""

from __future__ import annotations

import torch


def place_points(points: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Canonical points (..., K, 3) to the sensor frame with poses (..., 4): ``R c + t``."""
    c = torch.cos(pose[..., 3])[..., None]  # (..., 1)
    s = torch.sin(pose[..., 3])[..., None]
    x, y = points[..., 0], points[..., 1]  # (..., K)
    placed = torch.stack([c * x - s * y, s * x + c * y, points[..., 2]], dim=-1)
    return placed + pose[..., :3].unsqueeze(-2)


def unplace_points(points: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Sensor points (..., K, 3) to the canonical frame of poses (..., 4): ``R^T (p - t)``."""
    d = points - pose[..., :3].unsqueeze(-2)  # (..., K, 3)
    c = torch.cos(pose[..., 3])[..., None]  # (..., 1)
    s = torch.sin(pose[..., 3])[..., None]
    return torch.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1],
                        d[..., 2]], dim=-1)
