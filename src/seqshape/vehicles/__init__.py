"""seqshape.vehicles: vehicle meshes in the canonical frame and their complete ground truth.

* `vehicle_library` / `procedural_vehicle`: procedural sedans, hatchbacks, SUVs, vans, pickups;
* `load_vehicle` / `load_vehicle_folder`: user meshes (OBJ/PLY/STL/OFF/GLB/GLTF), normalised;
* `sample_outer_surface`: points uniform on the outside surface only (interior removed).

Canonical frame: centre of the mesh's bounding box at the origin, x forward, y left, z up, metres.
"""

from seqshape.vehicles.base import KINDS, Vehicle
from seqshape.vehicles.io import MESH_SUFFIXES, load_vehicle, load_vehicle_folder
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
    "MESH_SUFFIXES",
    "Vehicle",
    "VehicleParams",
    "build_vehicle_mesh",
    "load_vehicle",
    "load_vehicle_folder",
    "procedural_vehicle",
    "sample_outer_surface",
    "sample_params",
    "vehicle_library",
]
