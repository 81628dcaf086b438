"""The one raycast core: first-hit raycasting of vehicle meshes through Embree (embreex).

Every simulator casts through it: the track scan (:func:`scan_track`, used by
``seqshape generate``), the ``real`` path (:class:`MeshRaycaster` of each scene object) and
the camera + LiDAR scenes (:func:`scene_hits` / :func:`cast_posed`, used by
:mod:`seqshape.sim.render`). The sensor side (sweep directions, window, range limits, noise,
dropout) is the sensor's own (:class:`seqshape.sim.sensors.LidarConfig`).

Speed comes from these choices:

* one Embree scene per mesh, built once and cached (:func:`mesh_raycaster`), queried directly
  (``EmbreeScene.run``: one call returns the hit face of every ray; no trimesh wrapper, no
  second pass);
* the mesh is never moved: the rays of each frame are mapped into the vehicle's canonical
  frame with the inverse of its pose;
* only the rays that can hit the vehicle are cast: the channels and azimuth steps inside the
  angular window of the vehicle's posed bounding box (plus a small margin,
  :func:`seqshape.sim.sensors.ray_window`);
* the rays are built in float32, straight from the sensor's tables
  (:meth:`~seqshape.sim.sensors.LidarConfig.tables`): ``cos``/``sin`` of the
  channel elevations times ``cos``/``sin`` of (azimuth - yaw), evaluated once per (frame,
  azimuth) column and shared by the channels;
* all frames of a track go through Embree in one call (:func:`scan_track`); the float64 work
  (exact range from the hit face's plane, sensor-frame direction) is done for hits only.

Returned points are ``range * direction`` in the sensor frame, float32 ``(N, 3)``; ``(0, 3)``
when nothing is hit. The range is exact in float64 (hit face's plane), so points lie on the
mesh to float32 precision. Each ray is computed by the same operations whatever the other
frames of the call are, so results do not depend on batching, workers or shards.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from seqshape.geometry import pose_to_matrix, yaw_to_rotmat
from seqshape.sim.sensors import (
    LidarConfig,
    direction_table,
    ray_window,
    sensor_tables,
    window_grid,
)

_MIN_COS = 1e-6  # hits whose ray is this close to parallel to the triangle are dropped


class MeshRaycaster:
    """Cached ray-casting state of one mesh (in its own canonical frame).

    Attributes:
        scene: ``embreex.rtcore_scene.EmbreeScene`` of the mesh (float32 vertices, as given).
        planes: ``(F, 4)`` float64 ``(nx, ny, nz, n . v0)``: unit normal and offset of the
            plane of every face, to turn a hit face into an exact range.
        plane_points / plane_normals: ``(F, 3)`` float64, a vertex and the unit normal per face.
        bounds: ``(2, 3)`` float64 min / max corner.

    The object holds no reference to the mesh (its cache entry dies with the mesh).
    """

    def __init__(self, mesh):
        from embreex import rtcore_scene  # optional: installed on x86_64 only (pyproject)
        from embreex.mesh_construction import TriangleMesh  # same

        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=self.scene,
                     vertices=np.ascontiguousarray(mesh.vertices, dtype=np.float32),
                     indices=np.ascontiguousarray(mesh.faces, dtype=np.int32))
        tris = np.asarray(mesh.triangles, dtype=np.float64)
        self.plane_points = tris[:, 0].copy()
        self.plane_normals = np.asarray(mesh.face_normals, dtype=np.float64).copy()
        self.planes = np.concatenate(
            [self.plane_normals,
             np.einsum("ij,ij->i", self.plane_normals, self.plane_points)[:, None]], 1)
        self.bounds = np.asarray(mesh.bounds, dtype=np.float64).copy()

    def first_faces(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """One Embree call: the first face hit by each ray ``(R, 3)`` (mesh frame), ``(R,)``
        int32, -1 where nothing is hit.

        ``origins`` and ``dirs`` are C-contiguous float32 (converted otherwise); ``dirs`` need
        not be unit length.
        """
        o, d = _f32(origins), _f32(dirs)
        if len(o) == 0:
            return np.zeros(0, np.int32)
        return self.scene.run(o, d)

    def first_hits(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`first_faces`, plus Embree's float32 hit parameter ``t`` (R,): the hit is
        at ``origin + t * dir`` (a distance for unit ``dirs``; 1e37 where nothing is hit).
        Embree computes ``t`` in float32; :meth:`plane_ranges` gives float64-exact ranges."""
        o, d = _f32(origins), _f32(dirs)
        if len(o) == 0:
            return np.zeros(0, np.int32), np.zeros(0, np.float32)
        out = self.scene.run(o, d, output=1)
        return out["primID"], out["tfar"]

    def plane_ranges(self, tri: np.ndarray, origins, dirs) -> np.ndarray:
        """Exact float64 distances ``(H,)`` from ``origins`` along unit ``dirs`` to the planes
        of faces ``tri`` ``(H,)``; inf where the ray is (nearly) parallel to the face or the
        plane lies behind the origin.

        ``origins`` and ``dirs`` are ``(H, 3)`` arrays or triples of ``(H,)`` arrays (x, y, z).
        """
        (ox, oy, oz), (dx, dy, dz) = _columns(origins), _columns(dirs)
        p = self.planes.take(np.asarray(tri, dtype=np.intp), axis=0)  # (H, 4)
        nx, ny, nz = p[:, 0], p[:, 1], p[:, 2]
        denom = nx * dx + ny * dy + nz * dz
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (p[:, 3] - (nx * ox + ny * oy + nz * oz)) / denom
        r[~(r >= 0) | (np.abs(denom) <= _MIN_COS)] = np.inf
        return r

    def offset_ranges(self, tri: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """:meth:`plane_ranges` in the point-offset form ``((v0 - o) . n) / (d . n)`` (inf
        where ``|d . n| <= 1e-9`` or behind the origin), ``origins`` / ``dirs`` ``(H, 3)``.

        The camera and scene LiDAR rendering (:func:`cast_posed`) have always used this form;
        it differs from :meth:`plane_ranges` by float64 rounding only, and is kept so that the
        written scenes stay byte-identical.
        """
        n = self.plane_normals[tri]
        denom = np.einsum("ij,ij->i", dirs, n)
        num = np.einsum("ij,ij->i", self.plane_points[tri] - origins, n)
        ok = np.abs(denom) > 1e-9
        r = np.where(ok, num / np.where(ok, denom, 1.0), np.inf)
        return np.where(r >= 0, r, np.inf)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hits of rays ``(R, 3)`` (mesh frame; ``dirs`` unit length).

        Returns ``hit`` (R,) bool and ``rng`` (R,) float64 exact distances (inf where no hit).
        """
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        tri = self.first_faces(origins, dirs)
        idx = np.flatnonzero(tri >= 0)
        rng = np.full(len(tri), np.inf)
        rng[idx] = self.plane_ranges(tri[idx], origins[idx], dirs[idx])
        return np.isfinite(rng), rng


def _f32(a) -> np.ndarray:
    """``(R, 3)`` C-contiguous float32 (no copy when it already is)."""
    return np.ascontiguousarray(a, dtype=np.float32).reshape(-1, 3)


def _columns(a):
    """x, y, z of ``(H, 3)`` array or a triple of ``(H,)`` arrays."""
    return (a[:, 0], a[:, 1], a[:, 2]) if isinstance(a, np.ndarray) else tuple(a)


_CACHE: dict[int, tuple[weakref.ref, MeshRaycaster]] = {}


def mesh_raycaster(mesh) -> MeshRaycaster:
    """The cached :class:`MeshRaycaster` of ``mesh`` (built on first use, freed with the mesh)."""
    key = id(mesh)
    entry = _CACHE.get(key)
    if entry is not None and entry[0]() is mesh:
        return entry[1]
    rt = MeshRaycaster(mesh)
    _CACHE[key] = (weakref.ref(mesh, lambda _r, k=key: _CACHE.pop(k, None)), rt)
    return rt


# ------------------------------------------------------------------- rays from one origin


def cast_posed(mesh, pose, origin, dirs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast sensor-frame rays (``origin`` (3,), unit ``dirs`` (R, 3)) at a mesh placed at ``pose``.

    Returns ``tri`` (R,) hit face (-1 for none), ``rng`` (R,) distance (inf for none) and
    ``local`` (R, 3) hit points in the vehicle's canonical frame (NaN for none).
    """
    rt = mesh_raycaster(mesh)
    rot = yaw_to_rotmat(pose[3])
    o = np.broadcast_to((np.asarray(origin, dtype=np.float64) - pose[:3]) @ rot, dirs.shape)
    d = dirs @ rot
    tri = rt.first_faces(o, d).astype(np.int64)
    rng = np.full(len(d), np.inf)
    hit = np.flatnonzero(tri >= 0)
    if len(hit):
        rng[hit] = rt.offset_ranges(tri[hit], o[hit], d[hit])
    tri = np.where(np.isfinite(rng), tri, -1)
    local = o + d * np.where(np.isfinite(rng), rng, np.nan)[:, None]
    return tri, rng, local


def cone_rays(dirs: np.ndarray, origin: np.ndarray, pose: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the rays (from ``origin``) that can meet a sphere of ``radius`` at ``pose``."""
    c = np.asarray(pose[:3], dtype=np.float64) - origin
    dist = float(np.linalg.norm(c))
    if dist <= radius:
        return np.arange(len(dirs))
    cos_a = np.sqrt(1.0 - (radius / dist) ** 2)
    return np.flatnonzero(dirs @ (c / dist) >= cos_a - 1e-9)


@dataclass
class VehicleHits:
    """Rays of one vehicle: ``index`` into the ray array, ``rng``, ``tri``, ``local`` points."""

    index: np.ndarray
    rng: np.ndarray
    tri: np.ndarray
    local: np.ndarray


def scene_hits(meshes, poses, origin, dirs) -> tuple[list[VehicleHits], np.ndarray, np.ndarray]:
    """Per-vehicle hits of every ray from ``origin`` and the scene's first hit (vehicles only).

    Only the rays inside a vehicle's bounding cone (sphere around its box) are cast at it.
    Returns ``hits`` (one :class:`VehicleHits` per vehicle), ``owner`` (R,) int (vehicle
    index or -1) and ``dist`` (R,) float64 (inf where no vehicle is hit).
    """
    owner = np.full(len(dirs), -1, dtype=np.int64)
    dist = np.full(len(dirs), np.inf)
    hits = []
    for k, (mesh, pose) in enumerate(zip(meshes, poses, strict=True)):
        radius = float(np.linalg.norm(mesh.extents)) / 2 + 0.05
        idx = cone_rays(dirs, origin, pose, radius)
        tri, rng, local = cast_posed(mesh, pose, origin, dirs[idx])
        ok = tri >= 0
        h = VehicleHits(idx[ok], rng[ok], tri[ok], local[ok])
        hits.append(h)
        better = h.rng < dist[h.index]
        dist[h.index[better]] = h.rng[better]
        owner[h.index[better]] = k
    return hits, owner, dist


@dataclass
class TrackRays:
    """The rays of a track that can hit a vehicle, ready for :meth:`MeshRaycaster.first_hits`.

    Rays are frame-major, then by ascending channel elevation, then by azimuth
    (counter-clockwise). A *row* is one (frame, channel) pair; a *column* one (frame, azimuth).

    Attributes:
        origins: ``(R, 3)`` float32 the sensor in each ray's frame's vehicle canonical frame.
        dirs: ``(R, 3)`` float32 unit directions, canonical frame.
        frame_origin: ``(T, 3)`` float64 the sensor in each frame's canonical frame.
        ray_row / ray_col: ``(R,)`` int64 row and column of each ray.
        row_frame / row_ch: ``(n_rows,)`` int64 frame and channel (ascending-elevation index).
        col_k: ``(n_cols,)`` int64 azimuth index (``0 .. n_azimuths - 1``) of each column.
        col_cos / col_sin: ``(n_cols,)`` float64 ``cos`` / ``sin`` of (azimuth - yaw).
    """

    origins: np.ndarray
    dirs: np.ndarray
    frame_origin: np.ndarray
    ray_row: np.ndarray
    ray_col: np.ndarray
    row_frame: np.ndarray
    row_ch: np.ndarray
    col_k: np.ndarray
    col_cos: np.ndarray
    col_sin: np.ndarray

    def __len__(self) -> int:
        return len(self.dirs)

    def frames(self, idx: np.ndarray) -> np.ndarray:
        """Frame index ``(H,)`` of the rays ``idx`` ``(H,)``."""
        return self.row_frame[self.ray_row[idx]]

    def exact_dirs(self, idx: np.ndarray, cfg: LidarConfig):
        """Float64 unit directions of the rays ``idx``: ``(canonical (H, 3), sensor (H, 3))``."""
        tab = sensor_tables(cfg)
        ch, col = self.row_ch[self.ray_row[idx]], self.ray_col[idx]
        ce, se = tab.cos_e[ch], tab.sin_e[ch]
        k = self.col_k[col]
        canon = np.stack([ce * self.col_cos[col], ce * self.col_sin[col], se], 1)
        sensor = np.stack([ce * tab.cos_a[k], ce * tab.sin_a[k], se], 1)
        return canon, sensor


def _canonical_origins(poses: np.ndarray) -> np.ndarray:
    """The sensor (origin) in the canonical frame of each pose: ``(T, 3)`` float64."""
    c, s = np.cos(poses[:, 3]), np.sin(poses[:, 3])
    x, y = -poses[:, 0], -poses[:, 1]
    return np.stack([c * x + s * y, -s * x + c * y, -poses[:, 2]], 1)


def track_rays(bounds: np.ndarray, poses, cfg: LidarConfig) -> TrackRays:
    """The rays of every frame that can hit a box ``bounds`` (canonical) placed at ``poses``
    ``(T, 4)``, mapped into the canonical frame (see :class:`TrackRays`)."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    tab = sensor_tables(cfg)
    g = window_grid(cfg, *ray_window(cfg, bounds, poses))
    row_ch, ray_row, ray_col, col_k = g.row_ch, g.ray_row, g.ray_col, g.col_k
    # trig of (azimuth - yaw) once per column (frame, azimuth)
    cy, sy = np.cos(poses[:, 3])[g.col_frame], np.sin(poses[:, 3])[g.col_frame]
    ca, sa = tab.cos_a[col_k], tab.sin_a[col_k]
    col_cos, col_sin = ca * cy + sa * sy, sa * cy - ca * sy  # cos / sin of (azimuth - yaw)
    dirs = np.empty((len(ray_row), 3), np.float32)
    ce = tab.cos_e32[row_ch][ray_row]
    np.multiply(ce, col_cos.astype(np.float32)[ray_col], out=dirs[:, 0])
    np.multiply(ce, col_sin.astype(np.float32)[ray_col], out=dirs[:, 1])
    dirs[:, 2] = tab.sin_e32[row_ch][ray_row]
    frame_origin = _canonical_origins(poses)
    origins = np.repeat(frame_origin.astype(np.float32), g.frame_rays, axis=0)
    return TrackRays(origins, dirs, frame_origin, ray_row, ray_col, g.row_frame, row_ch, col_k,
                     col_cos, col_sin)


def _to_canonical(dirs: np.ndarray, frame: np.ndarray, poses: np.ndarray):
    """Ray origins ``(R, 3)`` (the sensor) and directions ``(R, 3)`` (sensor-frame ``dirs`` of
    frames ``frame``) mapped into a vehicle's canonical frames at ``poses`` ``(T, 4)``."""
    c, s = np.cos(poses[frame, 3]), np.sin(poses[frame, 3])
    d = np.empty_like(dirs)
    d[:, 0] = c * dirs[:, 0] + s * dirs[:, 1]
    d[:, 1] = -s * dirs[:, 0] + c * dirs[:, 1]
    d[:, 2] = dirs[:, 2]
    return _canonical_origins(poses)[frame], d


def _occluded(dirs, frame, rng, cfg: LidarConfig, occluders, ground: bool) -> np.ndarray:
    """Mask of the target returns blocked by the ground plane or another vehicle."""
    blocked = np.zeros(len(rng), dtype=bool)
    if ground:
        down = dirs[:, 2] < -1e-9
        t_ground = np.where(down, -cfg.height / np.where(down, dirs[:, 2], -1.0), np.inf)
        blocked |= t_ground < rng - 1e-3
    for mesh, occ_poses in occluders:
        keep = ~blocked
        if not keep.any():
            break
        occ_poses = np.asarray(occ_poses, dtype=np.float64).reshape(-1, 4)
        idx = np.flatnonzero(keep)
        o, d = _to_canonical(dirs[idx], frame[idx], occ_poses)
        hit, r = mesh_raycaster(mesh).cast(o, d)
        blocked[idx[hit & (r < rng[idx])]] = True
    return blocked


def scan_track(mesh, poses, cfg: LidarConfig, rng: np.random.Generator,
               occluders: Sequence = (), ground: bool = False) -> list[np.ndarray]:
    """Scan a vehicle at every pose of a track; the returns of the target only.

    Args:
        mesh: the target's ``trimesh.Trimesh`` in its canonical frame.
        poses: ``(T, 4)`` poses (x, y, z, yaw) of the target in the sensor frame.
        cfg: the sensor; its ``range_noise_std`` and ``dropout`` are applied.
        rng: source of the noise and dropout draws.
        occluders: ``(mesh, poses (T, 4))`` pairs of other vehicles; they only block rays.
        ground: if True the ground plane ``z = -cfg.height`` blocks rays too.

    Returns:
        T float32 arrays ``(N_t, 3)`` in each frame's sensor frame (``(0, 3)`` when empty).
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    rt = mesh_raycaster(mesh)
    rays = track_rays(rt.bounds, poses, cfg)
    ret = _hit_returns(rt, rays, rt.first_faces(rays.origins, rays.dirs), cfg)
    if occluders or ground:
        frame, dx, dy, dz, r = ret
        blocked = _occluded(np.stack([dx, dy, dz], 1), frame, r, cfg, occluders, ground)
        ret = _subset(ret, ~blocked)
    ret[4] = cfg.noisy_ranges(ret[4], rng)
    ret = _subset(ret, cfg.kept_returns(len(ret[4]), rng))
    frame, dx, dy, dz, r = ret
    pts = np.empty((len(r), 3), np.float32)
    pts[:, 0], pts[:, 1], pts[:, 2] = dx * r, dy * r, dz * r
    ends = np.searchsorted(frame, np.arange(1, len(poses) + 1)).tolist()
    return [pts[a:b] for a, b in zip([0, *ends[:-1]], ends, strict=True)]


def _hit_returns(rt: MeshRaycaster, rays: TrackRays, tri: np.ndarray, cfg: LidarConfig):
    """The exact returns of the rays that hit face ``tri`` (R,) (-1: none), within the
    sensor's range limits, in ray order: ``[frame, dx, dy, dz, r]``, each ``(H,)``: frame index,
    sensor-frame unit direction (float64) and float64 range from the hit face's plane."""
    tab = sensor_tables(cfg)
    idx = np.flatnonzero(tri >= 0)
    row, col = rays.ray_row[idx], rays.ray_col[idx]
    frame, ch = rays.row_frame[row], rays.row_ch[row]
    ce, se = tab.cos_e[ch], tab.sin_e[ch]
    r = rt.plane_ranges(tri[idx], tuple(a[frame] for a in rays.frame_origin.T.copy()),
                        (ce * rays.col_cos[col], ce * rays.col_sin[col], se))
    k = rays.col_k[col]
    ret = [frame, ce * tab.cos_a[k], ce * tab.sin_a[k], se, r]
    return _subset(ret, cfg.in_range(r))


def _subset(arrays: list, keep: np.ndarray) -> list:
    """``[a[keep] for a in arrays]`` (the same list when every element is kept)."""
    return arrays if keep.all() else [a[keep] for a in arrays]


def scan_vehicle(mesh, pose, cfg: LidarConfig, rng: np.random.Generator,
                 occluders: Sequence = (), ground: bool = False) -> np.ndarray:
    """One sweep of a vehicle at ``pose`` (4,): float32 ``(N, 3)`` target returns, sensor frame.

    ``occluders`` are ``(mesh, pose (4,))`` pairs of other vehicles (they only block rays);
    ``ground=True`` adds the ground plane at ``z = -cfg.height`` as an occluder.
    """
    occ = [(m, np.asarray(p, dtype=np.float64).reshape(1, 4)) for m, p in occluders]
    return scan_track(mesh, np.asarray(pose, dtype=np.float64).reshape(1, 4), cfg, rng,
                      occ, ground)[0]


def full_sweep(intersector, cfg: LidarConfig) -> np.ndarray:
    """Bare reference: one ``intersects_first`` call with every ray of a sweep.

    ``intersector`` is a ``RayMeshIntersector`` of a mesh already placed in the sensor
    frame. Returns the hit face per ray, ``(cfg.rays_per_sweep,)`` int (-1: no hit).
    """
    dirs = direction_table(cfg).reshape(-1, 3)
    return intersector.intersects_first(np.zeros_like(dirs), dirs)


def full_sweep_points(mesh, pose, cfg: LidarConfig) -> np.ndarray:
    """Slow exact reference: move the mesh to ``pose``, cast every ray of a sweep, no noise.

    Uses ``intersects_location(multiple_hits=False)``; returns float64 ``(N, 3)`` hit points in
    the sensor frame (within the sensor's range limits).
    """
    # embreex is installed on x86_64 only (pyproject): imported where a reference needs it
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    posed = mesh.copy()
    posed.apply_transform(pose_to_matrix(pose))
    dirs = direction_table(cfg).reshape(-1, 3)
    loc, _, _ = RayMeshIntersector(posed).intersects_location(
        np.zeros_like(dirs), dirs, multiple_hits=False)
    return loc[cfg.in_range(np.linalg.norm(loc, axis=1))]
