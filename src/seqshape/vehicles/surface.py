"""Complete ground truth: points sampled uniformly on the OUTSIDE surface of a mesh.

Interior geometry (seats, engine, the inner skin of a double-walled body, a closed mesh inside
another one) must not appear in the ground truth, since no sensor can ever see it. Method:

1. draw candidate points uniformly (area-weighted) on all faces;
2. a candidate is *outside* if it is visible from far away: a ray leaving it in some direction
   escapes to infinity without hitting the mesh. Each candidate is tested against a fixed set of
   directions (a Fibonacci sphere), those closest to its face normal (either side) first, and
   stops at the first escaping ray; rays go through Embree (trimesh + embreex) when available;
3. the first ``n`` outside candidates in sampling order are returned; since the candidates are
   i.i.d. uniform on the whole surface, the kept ones are i.i.d. uniform on the visible part.

Deterministic for a seed. Thin open sheets (non-watertight meshes) are visible from both sides.
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh

from seqshape.errors import ConfigError

log = logging.getLogger(__name__)

_N_DIRS = 96          # escape directions per candidate (worst case, for hidden points)
_MAX_ROUNDS = 8       # candidate batches before giving up


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) float64 unit vectors spread evenly over the sphere (deterministic)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = np.pi * (1.0 + 5.0**0.5) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def ray_intersector(mesh: trimesh.Trimesh):
    """Embree intersector for ``mesh`` if embreex is installed, else trimesh's pure-Python one."""
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    except Exception:  # pragma: no cover - depends on the environment
        log.warning("embreex not available: outer-surface sampling uses the slow ray engine")
        return trimesh.ray.ray_triangle.RayMeshIntersector(mesh)


def sample_surface_uniform(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator):
    """``count`` points uniform on the surface by area: ((count, 3) float64, (count,) face ids)."""
    area = mesh.area_faces
    cum = np.cumsum(area)
    face = np.searchsorted(cum, rng.random(count) * cum[-1], side="right")
    face = np.minimum(face, len(area) - 1)
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    tri = mesh.triangles[face]
    pts = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    return pts, face


def visible_from_outside(mesh, points, normals, intersector=None, n_dirs=_N_DIRS) -> np.ndarray:
    """(N,) bool: True where a ray from the point escapes the mesh in some direction.

    Args:
        mesh: the mesh the points lie on.
        points: (N, 3) points on the surface.
        normals: (N, 3) unit normals of the faces they lie on (sign irrelevant).
        intersector: optional prebuilt `ray_intersector(mesh)`.
        n_dirs: number of test directions (more catches points in deeper concavities).
    """
    isect = intersector or ray_intersector(mesh)
    dirs = fibonacci_sphere(n_dirs)
    eps = 1e-5 * max(float(mesh.scale), 1e-9)
    # order the directions per point by |cos| to the normal: likely escapes are tried first
    order = np.argsort(-np.abs(normals @ dirs.T), axis=1)
    visible = np.zeros(len(points), dtype=bool)
    todo = np.arange(len(points))
    for k in range(n_dirs):
        if len(todo) == 0:
            break
        d = dirs[order[todo, k]]
        # leave the surface on the side the ray goes to, so the ray does not hit its own face
        side = np.sign(np.einsum("ij,ij->i", d, normals[todo]))
        side[side == 0] = 1.0
        origins = points[todo] + eps * (side[:, None] * normals[todo]) + eps * d
        hit = isect.intersects_any(origins, d)
        visible[todo[~hit]] = True
        todo = todo[hit]
    return visible


def sample_outer_surface(mesh: trimesh.Trimesh, n: int = 2048, seed: int = 0) -> np.ndarray:
    """``n`` points uniform (area-weighted) on the outside surface of ``mesh``.

    Args:
        mesh: triangle mesh, any frame (points come back in the same frame).
        n: number of points.
        seed: random seed; the same mesh and seed give the same points.

    Returns:
        (n, 3) float32 points on the faces of ``mesh`` that are visible from outside.
    """
    if n < 1:
        raise ConfigError(f"n must be >= 1, got {n}")
    if len(mesh.faces) == 0 or mesh.area <= 0:
        raise ConfigError("cannot sample the surface of an empty mesh")
    rng = np.random.default_rng([int(seed), 0x0A7E])
    isect = ray_intersector(mesh)
    normals = mesh.face_normals
    kept: list[np.ndarray] = []
    have, batch = 0, max(2 * n, 1024)
    for _ in range(_MAX_ROUNDS):
        pts, face = sample_surface_uniform(mesh, batch, rng)
        vis = visible_from_outside(mesh, pts, normals[face], isect)
        kept.append(pts[vis])
        have += int(vis.sum())
        if have >= n:
            break
        frac = max(vis.mean(), 0.02)
        batch = int(min(max(1.3 * (n - have) / frac, 1024), 50 * n))
    else:
        if have == 0:
            raise ConfigError("no part of the mesh surface is visible from outside")
        log.warning("outer surface: only %d of %d points found; repeating points", have, n)
    out = np.concatenate(kept)
    if len(out) < n:
        out = out[rng.integers(0, len(out), n)]
    return out[:n].astype(np.float32)
