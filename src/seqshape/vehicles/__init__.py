"""seqshape.vehicles: vehicle meshes in the canonical frame and their complete ground truth.

* `vehicle_library` / `procedural_vehicle`: the original procedural sedans, hatchbacks, SUVs,
  vans and pickups (unchanged meshes);
* `fleet_library` / `fleet_vehicle`: every class a driving dataset annotates (car, van, truck,
  bus, trailer) in 18 fine kinds sized from real-fleet statistics, with per-face material
  labels (`FACE_LABELS`: glass, body, tyre, ...);
* `vehicle_from_source`: rebuild a procedural or fleet vehicle from its ``source`` string;
* `load_vehicle` / `load_vehicle_folder`: user meshes (OBJ/PLY/STL/OFF/GLB/GLTF), normalised;
* `sample_outer_surface`: points uniform on the outside surface only (interior removed).

Canonical frame: centre of the mesh's bounding box at the origin, x forward, y left, z up, metres.
"""

from seqshape.vehicles.base import (
    BODY,
    CARGO,
    FACE_LABELS,
    GLASS,
    GRILLE,
    HEADLAMP,
    INTERIOR,
    KINDS,
    LAMP,
    RIM,
    TRIM,
    TYRE,
    VEHICLE_CLASSES,
    Vehicle,
)
from seqshape.vehicles.fleet import (
    CAR_MIX_BY_REGION,
    CLASS_MIX,
    DEFAULT_MIX,
    FLEET_KINDS,
    KIND_MIX,
    MIXES,
    fleet_library,
    fleet_vehicle,
    kind_quotas,
    vehicle_from_source,
)
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
    "BODY",
    "CARGO",
    "CAR_MIX_BY_REGION",
    "CLASS_MIX",
    "DEFAULT_MIX",
    "FACE_LABELS",
    "FLEET_KINDS",
    "GLASS",
    "INTERIOR",
    "KINDS",
    "KIND_MIX",
    "LAMP",
    "GRILLE",
    "HEADLAMP",
    "MESH_SUFFIXES",
    "MIXES",
    "RIM",
    "TRIM",
    "TYRE",
    "VEHICLE_CLASSES",
    "Vehicle",
    "VehicleParams",
    "build_vehicle_mesh",
    "fleet_library",
    "fleet_vehicle",
    "kind_quotas",
    "load_vehicle",
    "load_vehicle_folder",
    "procedural_vehicle",
    "sample_outer_surface",
    "sample_params",
    "vehicle_from_source",
    "vehicle_library",
]
