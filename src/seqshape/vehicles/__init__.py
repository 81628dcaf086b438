"""seqshape.vehicles: vehicle meshes in the canonical frame and their complete ground truth.

* `vehicle_library` / `procedural_vehicle`: procedural sedans, hatchbacks, SUVs, vans, pickups;
* `sample_outer_surface`: points uniform on the outside surface only (interior removed).

Canonical frame: centre of the mesh's bounding box at the origin, x forward, y left, z up, metres.
"""

from seqshape.vehicles.base import KINDS, Vehicle
from seqshape.vehicles.procedural import (
    VehicleParams,
    build_vehicle_mesh,
    procedural_vehicle,
    sample_params,
    vehicle_library,
)
from seqshape.vehicles.surface import sample_outer_surface

__all__ = [
    "KINDS",
    "Vehicle",
    "VehicleParams",
    "build_vehicle_mesh",
    "procedural_vehicle",
    "sample_outer_surface",
    "sample_params",
    "vehicle_library",
]
