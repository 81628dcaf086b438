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
import re
from pathlib import Path

import numpy as np
import trimesh

from seqshape._io import check_regular
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
    """Read ``path`` into one geometry-only mesh; DataError naming the file on any problem.

    Refused: an empty or unreadable file, a file holding no triangles, face indices out of
    range (OBJ's 1-based index 0, which trimesh would read as vertex 1, included), NaN or
    infinite vertices, coordinates so large that areas overflow, and degenerate meshes: no
    face of non-zero area, or no extent along one of the axes (a flat mesh: zero height...).
    """
    if not path.exists():
        raise DataError(path, "no such file")
    check_regular(path, "mesh file", "mesh")  # a FIFO, a folder: refused, never opened
    if path.stat().st_size == 0:
        raise DataError(path, "file is empty")
    if path.suffix.lower() == ".obj":
        _check_obj_indices(path)
    try:
        loaded = trimesh.load(str(path), force=None, process=False)
        if isinstance(loaded, trimesh.Scene):
            geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
            loaded = trimesh.util.concatenate(geoms) if geoms else None
    except ImportError as exc:  # trimesh falls back on charset detection for non-UTF-8 text
        raise DataError(path, "cannot decode the file as text: not a valid "
                        f"{path.suffix.lower()[1:].upper()} file ({exc})") from exc
    except IndexError as exc:
        if path.suffix.lower() == ".obj":
            _check_obj_indices(path, out_of_range=True)  # names the index and its line
        raise DataError(path, f"face indices out of range ({exc})") from exc
    except Exception as exc:  # trimesh raises many types on malformed input
        raise DataError(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        what = type(loaded).__name__ if loaded is not None else "nothing"
        raise DataError(path, f"no triangle faces found (read {what}); is this a mesh file?")
    verts, faces = _checked_arrays(path, loaded)
    with np.errstate(all="ignore"):  # overflowing areas are refused below, not warned about
        mesh = trimesh.Trimesh(verts, faces, process=True)
        mesh.update_faces(mesh.nondegenerate_faces())
        mesh.remove_unreferenced_vertices()
        area = float(mesh.area) if len(mesh.faces) else 0.0
    if not np.isfinite(area):
        raise DataError(path, "coordinates too large: the mesh's area overflows")
    if len(mesh.faces) == 0 or area <= 0:
        raise DataError(path, "mesh has no faces with non-zero area")
    _check_extent(path, mesh.vertices)
    return mesh


def _checked_arrays(path: Path, loaded: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, faces (F, 3) int64)`` of a loaded mesh: finite vertices,
    triangle faces indexing existing vertices; DataError naming the file otherwise."""
    verts = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces)
    if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) == 0:
        raise DataError(path, f"vertices of shape {verts.shape}, expected (V, 3)")
    if not np.all(np.isfinite(verts)):
        raise DataError(path, "vertices contain NaN or infinite values")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise DataError(path, f"faces of shape {faces.shape} ({faces.dtype}), expected (F, 3) "
                              "vertex indices")
    bad = (faces < 0) | (faces >= len(verts))
    if bad.any():
        f = int(np.flatnonzero(bad.any(axis=1))[0])
        raise DataError(path, f"face {f} refers to vertex {int(faces[bad][0])}, out of range "
                              f"for {len(verts)} vertices")
    return verts, faces.astype(np.int64)


def _check_extent(path: Path, vertices: np.ndarray) -> None:
    """Refuse a flat mesh: no extent (relative to its largest) along one of the file's axes."""
    extent = np.ptp(vertices, axis=0)
    flat = extent <= 1e-9 * extent.max()
    if flat.any():
        axes = ", ".join("xyz"[int(a)] for a in np.flatnonzero(flat))
        raise DataError(path, f"mesh is flat: no extent along the file's {axes} axis "
                              f"(extents {np.round(extent, 6).tolist()}); a vehicle needs "
                              "length, width and height")


_OBJ_VERTEX = re.compile(rb"^[ \t]*v[ \t]", re.MULTILINE)
_OBJ_FACE = re.compile(rb"^[ \t]*f[ \t]+([^\r\n#]*)", re.MULTILINE)
_OBJ_INDEX = re.compile(rb"(?<!\S)([+-]?\d+)(?=/|\s|$)")  # the vertex index of v, v/vt, v//vn
_BEFORE_ZERO = np.zeros(256, dtype=bool)  # bytes that may come before an index 0 token
_BEFORE_ZERO[list(b" \t+-")] = True
_AFTER_ZERO = np.zeros(256, dtype=bool)  # and after it
_AFTER_ZERO[list(b" \t\r\n/")] = True


def _may_hold_zero_index(data: bytes) -> bool:
    """Whether the OBJ text ``data`` holds a token ``0``, ``-0`` or ``+0`` (possibly followed by
    ``/``) anywhere: a fast test (numpy over the bytes) before the exact scan of face lines."""
    b = np.frombuffer(b" " + data + b"\n", dtype=np.uint8)  # a space before, a newline after
    zeros = np.flatnonzero(b[1:-1] == ord("0")) + 1
    return bool(np.any(_BEFORE_ZERO[b[zeros - 1]] & _AFTER_ZERO[b[zeros + 1]]))


def _check_obj_indices(path: Path, out_of_range: bool = False) -> None:
    """Refuse OBJ faces whose vertex index is 0 (OBJ indices are 1-based; trimesh would
    silently read vertex 1) or, with ``out_of_range`` (after trimesh failed on them), beyond
    the vertex count; DataError naming the file and the line. Texture and normal indices
    (``v/vt/vn``) are not checked; tokens that are not integers are left to trimesh."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(path, f"unreadable file ({exc.strerror or exc})") from None
    if not out_of_range and not _may_hold_zero_index(data):
        return  # the common case
    n = len(_OBJ_VERTEX.findall(data))
    for m in _OBJ_FACE.finditer(data):  # the first bad index, with its line
        for head in _OBJ_INDEX.findall(m.group(1)):
            index = int(head)
            if index == 0 or not -n <= index <= n:
                line = data.count(b"\n", 0, m.start()) + 1
                raise DataError(path, f"face vertex index {index} is out of range for {n} "
                                      "vertices (OBJ indices are 1-based)", line=line)


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
