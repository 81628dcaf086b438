"""seqshape: sequential joint shape and pose estimation of vehicles from partial LiDAR scans.

Conventions (fixed everywhere, see docs/design.md):

* metres and radians inside; centimetres and degrees only in reports;
* sensor frame: x forward, y left, z up, origin at the LiDAR;
* canonical vehicle frame: origin at the centre of the vehicle's 3D bounding box, x to the
  front, y left, z up; a pose (x, y, z, yaw) maps ``p_sensor = R_z(yaw) @ p_canonical + t``;
* point arrays are float32 (N, 3); poses float64 (T, 4); an empty frame is a (0, 3) array.
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["Estimator", "Track", "TrackDataset", "__version__"]


def __getattr__(name: str):  # lazy: importing seqshape must not import torch
    if name == "Estimator":
        from seqshape.model.estimator import Estimator

        return Estimator
    if name in ("Track", "TrackDataset"):
        from seqshape import data

        return getattr(data, name)
    raise AttributeError(f"module 'seqshape' has no attribute {name!r}")
