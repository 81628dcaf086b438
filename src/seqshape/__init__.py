"""seqshape: sequential joint shape and pose estimation of vehicles from partial LiDAR scans.

Conventions (fixed everywhere, see docs/architecture.md):

* metres and radians inside; centimetres and degrees only in reports;
* sensor frame: x forward, y left, z up, origin at the LiDAR;
* canonical vehicle frame: origin at the centre of the vehicle's 3D bounding box, x to the
  front, y left, z up; a pose (x, y, z, yaw) maps ``p_sensor = R_z(yaw) @ p_canonical + t``;
* point arrays are float32 (N, 3); poses float64 (T, 4); an empty frame is a (0, 3) array.
"""

from __future__ import annotations

from seqshape._version import __version__

__all__ = ["Estimator", "Track", "TrackDataset", "__version__"]


def __getattr__(name: str):  # lazy: `seqshape --help` imports this package; keep it light
    if name == "Estimator":
        from seqshape.model.estimator import Estimator  # lazy: torch

        return Estimator
    if name in ("Track", "TrackDataset"):
        import seqshape.data as data  # lazy: numpy and the data readers

        return getattr(data, name)
    raise AttributeError(f"module 'seqshape' has no attribute {name!r}")
