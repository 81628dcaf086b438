"""The `Vehicle` record shared by procedural and user-supplied vehicles."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import trimesh

KINDS = ("sedan", "hatchback", "suv", "van", "pickup")


@dataclass
class Vehicle:
    """A vehicle mesh in the canonical frame.

    Attributes:
        vehicle_id: unique, filesystem-safe identifier (e.g. ``proc-0007-sedan``).
        mesh: triangle mesh in the canonical vehicle frame: the centre of its axis-aligned
            bounding box (wheels included) at the origin, x forward, y left, z up, metres.
        kind: ``"sedan" | "hatchback" | "suv" | "van" | "pickup" | "user"``.
        source: ``"procedural:<kind>:<seed>"`` or the path of the file it was loaded from.
    """

    vehicle_id: str
    mesh: trimesh.Trimesh
    kind: str
    source: str

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
    """Translate ``mesh`` in place so that its bounding-box centre is the origin; return it."""
    lo, hi = mesh.bounds
    mesh.apply_translation(-(lo + hi) / 2.0)
    return mesh
