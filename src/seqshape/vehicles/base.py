"""The `Vehicle` record shared by procedural and user-supplied vehicles, and its label codes."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np
import trimesh

KINDS = ("sedan", "hatchback", "suv", "van", "pickup")

#: seqshape's vehicle classes, smallest first. Kept equal to
#: ``seqshape.data.sequence.VEHICLE_CLASSES`` (a test checks it); it is repeated here so that
#: the vehicles package does not import the data package.
VEHICLE_CLASSES = ("car", "van", "truck", "bus", "trailer")

# Per-face material labels (`Vehicle.face_labels`, uint8). A raycaster uses them to treat the
# surfaces differently: glass lets rays through, tyres and trim are dark (low reflectivity),
# lamps and number plates are retro-reflective, interior parts are only seen through glass.
BODY = 0       #: painted body panels (metal or painted plastic)
GLASS = 1      #: windows (windshield, side and rear glass, glass roofs)
TYRE = 2       #: tyre rubber
RIM = 3        #: wheel rims / hub caps (metal)
TRIM = 4       #: unpainted dark plastic: lower bumpers, cladding, mirrors' arms, roof rails,
#: chassis, frame rails, fuel tanks
LAMP = 5       #: tail lamps and reflex reflectors (retro-reflective)
INTERIOR = 6   #: seats and dashboard inside the cabin, the radiator behind a car's grille
#: (closed, only visible through glass or the grille's openings)
CARGO = 7      #: load platforms and trailer decks
GRILLE = 8     #: a car's open front grille and air intakes (dark bars over openings)
HEADLAMP = 9   #: headlamps: a clear lens over a mirror-like reflector (most rays are lost)

#: code -> name of every face label.
FACE_LABELS = {BODY: "body", GLASS: "glass", TYRE: "tyre", RIM: "rim", TRIM: "trim",
               LAMP: "lamp", INTERIOR: "interior", CARGO: "cargo", GRILLE: "grille",
               HEADLAMP: "headlamp"}


@dataclass
class Vehicle:
    """A vehicle mesh in the canonical frame.

    Attributes:
        vehicle_id: unique, filesystem-safe identifier (e.g. ``proc-0007-sedan``).
        mesh: triangle mesh in the canonical vehicle frame: the centre of its axis-aligned
            bounding box (wheels included) at the origin, x forward, y left, z up, metres.
        kind: fine kind. Original procedural kinds ``"sedan" | "hatchback" | "suv" | "van" |
            "pickup"``, fleet kinds (`seqshape.vehicles.FLEET_KINDS`, e.g. ``"estate"``,
            ``"box_truck"``) or ``"user"``.
        source: ``"procedural:<kind>:<seed>"``, ``"fleet:<kind>:<seed>"`` or the path of the
            file it was loaded from; `seqshape.vehicles.vehicle_from_source` rebuilds the
            first two.
        cls: vehicle class, one of `VEHICLE_CLASSES` (None: unknown, e.g. a user mesh).
        face_labels: (F,) uint8 material label of every face of ``mesh`` (codes in
            `FACE_LABELS`), or None when unknown. Faces keep their order through
            `centre_on_bbox`, so the labels stay valid.
        box_size: (3,) length, width, height (m) of the box an annotator draws: the mesh's
            extents without the side mirrors (None: same as `size`).
    """

    vehicle_id: str
    mesh: trimesh.Trimesh
    kind: str
    source: str
    cls: str | None = None
    face_labels: np.ndarray | None = field(default=None, repr=False, compare=False)
    box_size: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def size(self) -> np.ndarray:
        """(3,) float64: length, width, height of the bounding box (m)."""
        return np.asarray(self.mesh.extents, dtype=np.float64)


def safe_id(text: str) -> str:
    """Make ``text`` filesystem-safe: runs of characters outside ``[A-Za-z0-9._-]`` -> ``-``.

    >>> safe_id("cars/1a2b c/models/model.obj")
    'cars-1a2b-c-models-model.obj'
    """
    out = re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-.")
    return out or "mesh"


def centre_on_bbox(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Translate ``mesh`` in place so that its bounding-box centre is the origin; return it.

    Vertices and faces keep their order, so per-face labels stay valid.
    """
    lo, hi = mesh.bounds
    mesh.apply_translation(-(lo + hi) / 2.0)
    return mesh
