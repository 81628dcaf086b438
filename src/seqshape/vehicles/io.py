"""Load user vehicle meshes (OBJ, PLY, STL, OFF, GLB, GLTF) into the canonical frame.

Every file goes through trimesh; scenes (GLB/GLTF, multi-object OBJ) are flattened to one
mesh with their node transforms applied; materials, UVs and normals are dropped and duplicate
vertices merged (geometry only). Then the mesh is

1. rotated so that the file's ``up`` axis becomes +z and its ``forward`` axis becomes +x
   (each one of ``"x", "-x", "y", "-y", "z", "-z"``; left = up x forward becomes +y);
2. scaled by ``scale`` (e.g. 0.01 for centimetres), or, when ``target_length`` is given,
   rescaled so that its length along x equals ``target_length`` metres;
3. translated so that the centre of its axis-aligned bounding box is the origin.

ShapeNet cars (``model_normalized.obj``) are typically y-up and face -z, and are normalised to
unit diagonal: ``load_vehicle_folder(root, up="y", forward="-z", target_length=4.5)``. Check one
render when using a new source: a car facing backwards needs the opposite ``forward``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh

from seqshape.errors import ConfigError, DataError
from seqshape.vehicles.base import Vehicle, centre_on_bbox, safe_id

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
_AXES = {"x": 0, "y": 1, "z": 2}


def axis_vector(name: str) -> np.ndarray:
    """Unit vector (3,) for ``"x" | "-x" | "y" | "-y" | "z" | "-z"`` (also ``"+x"`` etc.)."""
    key = str(name).strip().lower()
    sign = -1.0 if key.startswith("-") else 1.0
    key = key.lstrip("+-")
    if key not in _AXES:
        raise ConfigError(f"axis must be one of x, -x, y, -y, z, -z; got {name!r}")
    v = np.zeros(3)
    v[_AXES[key]] = sign
    return v


def canonical_rotation(up: str = "z", forward: str = "x") -> np.ndarray:
    """(3, 3) rotation taking the file's ``forward``/``up`` axes to +x/+z (rows: x, y, z)."""
    u, f = axis_vector(up), axis_vector(forward)
    if abs(float(u @ f)) > 0.5:
        raise ConfigError(f"up={up!r} and forward={forward!r} must be different axes")
    return np.stack([f, np.cross(u, f), u])


def _read_mesh(path: Path) -> trimesh.Trimesh:
    """Read ``path`` into one geometry-only mesh; DataError naming the file on any problem."""
    if not path.is_file():
        raise DataError(path, "no such file")
    if path.stat().st_size == 0:
        raise DataError(path, "file is empty")
    try:
        loaded = trimesh.load(str(path), force=None, process=False)
    except ImportError as exc:  # trimesh falls back on charset detection for non-UTF-8 text
        raise DataError(path, "cannot decode the file as text: not a valid "
                        f"{path.suffix.lower()[1:].upper()} file ({exc})") from exc
    except Exception as exc:  # trimesh raises many types on malformed input
        raise DataError(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geoms) if geoms else None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        what = type(loaded).__name__ if loaded is not None else "nothing"
        raise DataError(path, f"no triangle faces found (read {what}); is this a mesh file?")
    verts = np.asarray(loaded.vertices, dtype=np.float64)
    if not np.all(np.isfinite(verts)):
        raise DataError(path, "vertices contain NaN or infinite values")
    mesh = trimesh.Trimesh(verts, np.asarray(loaded.faces), process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0 or mesh.area <= 0:
        raise DataError(path, "mesh has no faces with non-zero area")
    return mesh


def load_vehicle(path, up: str = "z", forward: str = "x", scale: float = 1.0,
                 target_length: float | None = None, vehicle_id: str | None = None) -> Vehicle:
    """Load one mesh file as a `Vehicle` in the canonical frame.

    Args:
        path: OBJ/PLY/STL/OFF/GLB/GLTF file.
        up, forward: the file's axes pointing up and towards the vehicle's front.
        scale: multiplies coordinates (file units -> metres); ignored if ``target_length``.
        target_length: if given, rescale so that the length along x is this many metres.
        vehicle_id: id to use (default ``user-<file stem>``, filesystem-safe).

    Raises:
        DataError: the file cannot be read or holds no usable triangles (names the file).
        ConfigError: bad axis names or scale.

    A mesh that is not watertight is loaded anyway, with a logged warning (its outer surface
    and raycasting still work; only inside/outside queries are unreliable).
    """
    path = Path(path)
    rot = canonical_rotation(up, forward)
    if target_length is None and not (np.isfinite(scale) and scale > 0):
        raise ConfigError(f"scale must be a positive number, got {scale}")
    if target_length is not None and not (np.isfinite(target_length) and target_length > 0):
        raise ConfigError(f"target_length must be a positive number, got {target_length}")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DataError(path, f"unsupported mesh format; expected one of {MESH_SUFFIXES}")
    mesh = _read_mesh(path)
    mesh.vertices = mesh.vertices @ rot.T
    if target_length is not None:
        length = float(np.ptp(mesh.vertices[:, 0]))
        if length <= 0:
            raise DataError(path, "mesh has zero length along its forward axis")
        scale = target_length / length
    mesh.vertices = mesh.vertices * scale
    centre_on_bbox(mesh)
    if not mesh.is_watertight:
        log.warning("%s: mesh is not watertight (open or non-manifold edges); using it anyway",
                    path)
    return Vehicle(vehicle_id=vehicle_id or f"user-{safe_id(path.stem)}", mesh=mesh,
                   kind="user", source=str(path))


def find_mesh_files(folder) -> list[Path]:
    """Mesh files under ``folder`` (recursive, sorted, hidden files and folders skipped)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(folder, "not a folder")
    files = [p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in MESH_SUFFIXES
             and not any(part.startswith(".") for part in p.relative_to(folder).parts)]
    return sorted(files)


def load_vehicle_folder(folder, up: str = "z", forward: str = "x", scale: float = 1.0,
                        target_length: float | None = None) -> list[Vehicle]:
    """Load every mesh file under ``folder`` (recursively, sorted by path) as `Vehicle`\\ s.

    Ids are ``user-<relative path without suffix>`` made filesystem-safe, so nested layouts
    such as ShapeNet's ``<model id>/models/model_normalized.obj`` get distinct ids. The axis
    and scale arguments are as in `load_vehicle` and apply to every file.

    Raises:
        DataError: ``folder`` is not a folder, holds no mesh file, or a file is unreadable.
    """
    folder = Path(folder)
    files = find_mesh_files(folder)
    if not files:
        raise DataError(folder, f"no mesh files found (looked for {', '.join(MESH_SUFFIXES)})")
    out, seen = [], set()
    for f in files:
        base = "user-" + safe_id(str(f.relative_to(folder).with_suffix("")))
        vid, k = base, 2
        while vid in seen:
            vid, k = f"{base}-{k}", k + 1
        seen.add(vid)
        out.append(load_vehicle(f, up=up, forward=forward, scale=scale,
                                target_length=target_length, vehicle_id=vid))
    log.info("loaded %d vehicle meshes from %s", len(out), folder)
    return out
