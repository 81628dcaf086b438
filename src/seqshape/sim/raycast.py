"""First-hit LiDAR raycasting of vehicle meshes through Embree (embreex).

Speed comes from these choices:

* one Embree scene per mesh, built once and cached (:func:`mesh_raycaster`), queried directly
  (``EmbreeScene.run``: one call returns the hit face of every ray; no trimesh wrapper, no
  second pass);
* the mesh is never moved: the rays of each frame are mapped into the vehicle's canonical
  frame with the inverse of its pose;
* only the rays that can hit the vehicle are cast: the channels and azimuth steps inside the
  angular window of the vehicle's posed bounding box (plus a small margin);
* the rays are built in float32, straight from per-sensor tables: ``cos``/``sin`` of the
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
from functools import lru_cache

import numpy as np

from seqshape.sim.sensors import LidarConfig, directions

# spatial margin (m) around the mesh bounds and angular margin (in azimuth steps) of the window
_BOX_MARGIN = 0.05
_AZ_MARGIN_STEPS = 1.5
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
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

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


@dataclass(frozen=True)
class _SensorTables:
    """Per-sensor trig tables; channels in ascending elevation (``order`` maps to presets)."""

    elev: np.ndarray  # (C,) rad, ascending
    cos_e: np.ndarray  # (C,) float64
    sin_e: np.ndarray
    cos_e32: np.ndarray  # (C,) float32
    sin_e32: np.ndarray
    az: np.ndarray  # (A,) rad, k * step
    cos_a: np.ndarray  # (A,) float64
    sin_a: np.ndarray


@lru_cache(maxsize=8)
def _tables(cfg: LidarConfig) -> _SensorTables:
    elev = np.sort(cfg.elevations_rad)
    az = np.arange(cfg.n_azimuths) * np.deg2rad(cfg.azimuth_step_deg)
    ce, se = np.cos(elev), np.sin(elev)
    return _SensorTables(elev, ce, se, ce.astype(np.float32), se.astype(np.float32), az,
                         np.cos(az), np.sin(az))


@lru_cache(maxsize=8)
def _direction_table(cfg: LidarConfig) -> np.ndarray:
    """All ray directions of a sweep, ``(C, A, 3)`` float64 (channel in preset order, azimuth)."""
    az = np.arange(cfg.n_azimuths) * np.deg2rad(cfg.azimuth_step_deg)
    return directions(cfg.elevations_rad, az).reshape(len(cfg.elevations_deg), -1, 3)


def _windows(bounds: np.ndarray, poses: np.ndarray, cfg: LidarConfig):
    """Per frame: channel range ``c0:c1`` in ascending-elevation order and azimuth indices
    ``k0..k1`` (all ``(T,)`` int64).

    The window covers the posed, margin-grown bounding box exactly in elevation (a
    conservative bound from the nearest and farthest footprint distances) and in azimuth (the
    footprint corners). A frame whose footprint contains the sensor gets the full sweep.
    """
    lo, hi = bounds[0] - _BOX_MARGIN, bounds[1] + _BOX_MARGIN
    c, s = np.cos(poses[:, 3]), np.sin(poses[:, 3])
    # sensor origin in the canonical frame of each pose (planar part)
    qx = -(c * poses[:, 0] + s * poses[:, 1])
    qy = -(-s * poses[:, 0] + c * poses[:, 1])
    dx = np.maximum(np.maximum(lo[0] - qx, qx - hi[0]), 0.0)
    dy = np.maximum(np.maximum(lo[1] - qy, qy - hi[1]), 0.0)
    rmin = np.hypot(dx, dy)
    cx = np.array([lo[0], hi[0], hi[0], lo[0]])
    cy = np.array([lo[1], lo[1], hi[1], hi[1]])
    px = poses[:, :1] + c[:, None] * cx - s[:, None] * cy  # (T, 4) footprint corners
    py = poses[:, 1:2] + s[:, None] * cx + c[:, None] * cy
    rmax = np.hypot(px, py).max(1)
    zlo, zhi = poses[:, 2] + lo[2], poses[:, 2] + hi[2]
    inside = rmin <= 1e-9
    rmin_s = np.maximum(rmin, 1e-9)
    e_hi = np.where(zhi > 0, np.arctan2(zhi, rmin_s), np.arctan2(zhi, rmax))
    e_lo = np.where(zlo < 0, np.arctan2(zlo, rmin_s), np.arctan2(zlo, rmax))
    e_hi[inside & (zhi > 0)] = np.pi / 2
    e_lo[inside & (zlo < 0)] = -np.pi / 2
    elev = np.sort(cfg.elevations_rad)
    c0 = np.searchsorted(elev, e_lo - 1e-6, side="left")
    c1 = np.searchsorted(elev, e_hi + 1e-6, side="right")
    centre = np.arctan2(poses[:, 1], poses[:, 0])
    rel = (np.arctan2(py, px) - centre[:, None] + np.pi) % (2 * np.pi) - np.pi
    step = np.deg2rad(cfg.azimuth_step_deg)
    a_lo = centre + rel.min(1) - _AZ_MARGIN_STEPS * step
    a_hi = centre + rel.max(1) + _AZ_MARGIN_STEPS * step
    k0 = np.ceil(a_lo / step).astype(np.int64)
    k1 = np.floor(a_hi / step).astype(np.int64)
    k1 = np.minimum(k1, k0 + cfg.n_azimuths - 1)
    k0[inside] = 0
    k1[inside] = cfg.n_azimuths - 1
    return c0, c1, k0, k1




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
        tab = _tables(cfg)
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
    tab = _tables(cfg)
    c0, c1, k0, k1 = _windows(bounds, poses, cfg)
    n_ch = np.maximum(c1 - c0, 0)
    n_az = np.where(n_ch > 0, np.maximum(k1 - k0 + 1, 0), 0)
    n_ch = np.where(n_az > 0, n_ch, 0)
    frames = np.arange(len(poses))
    # columns: one per (frame, azimuth); trig of (azimuth - yaw) once per column
    col_start = np.cumsum(n_az) - n_az
    col_frame = np.repeat(frames, n_az)
    col_k = (np.arange(len(col_frame)) + np.repeat(k0 - col_start, n_az)) % cfg.n_azimuths
    cy, sy = np.cos(poses[:, 3])[col_frame], np.sin(poses[:, 3])[col_frame]
    ca, sa = tab.cos_a[col_k], tab.sin_a[col_k]
    col_cos, col_sin = ca * cy + sa * sy, sa * cy - ca * sy  # cos / sin of (azimuth - yaw)
    # rows: one per (frame, channel), each a run of n_az[frame] consecutive columns
    row_frame = np.repeat(frames, n_ch)
    row_ch = np.arange(len(row_frame)) + np.repeat(c0 - (np.cumsum(n_ch) - n_ch), n_ch)
    width = n_az[row_frame]
    ray_row = np.repeat(np.arange(len(row_frame)), width)
    row_first = np.cumsum(width) - width
    ray_col = np.arange(len(ray_row)) + (col_start[row_frame] - row_first)[ray_row]
    dirs = np.empty((len(ray_row), 3), np.float32)
    ce = tab.cos_e32[row_ch][ray_row]
    np.multiply(ce, col_cos.astype(np.float32)[ray_col], out=dirs[:, 0])
    np.multiply(ce, col_sin.astype(np.float32)[ray_col], out=dirs[:, 1])
    dirs[:, 2] = tab.sin_e32[row_ch][ray_row]
    frame_origin = _canonical_origins(poses)
    origins = np.repeat(frame_origin.astype(np.float32), n_ch * n_az, axis=0)
    return TrackRays(origins, dirs, frame_origin, ray_row, ray_col, row_frame, row_ch, col_k,
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
    if cfg.range_noise_std > 0:
        ret[4] = ret[4] + rng.normal(0.0, cfg.range_noise_std, len(ret[4]))
    if cfg.dropout > 0:
        ret = _subset(ret, rng.random(len(ret[4])) >= cfg.dropout)
    frame, dx, dy, dz, r = ret
    pts = np.empty((len(r), 3), np.float32)
    pts[:, 0], pts[:, 1], pts[:, 2] = dx * r, dy * r, dz * r
    ends = np.searchsorted(frame, np.arange(1, len(poses) + 1)).tolist()
    return [pts[a:b] for a, b in zip([0, *ends[:-1]], ends, strict=True)]


def _hit_returns(rt: MeshRaycaster, rays: TrackRays, tri: np.ndarray, cfg: LidarConfig):
    """The exact returns of the rays that hit face ``tri`` (R,) (-1: none), within the
    sensor's range limits, in ray order: ``[frame, dx, dy, dz, r]``, each ``(H,)``: frame index,
    sensor-frame unit direction (float64) and float64 range from the hit face's plane."""
    tab = _tables(cfg)
    idx = np.flatnonzero(tri >= 0)
    row, col = rays.ray_row[idx], rays.ray_col[idx]
    frame, ch = rays.row_frame[row], rays.row_ch[row]
    ce, se = tab.cos_e[ch], tab.sin_e[ch]
    r = rt.plane_ranges(tri[idx], tuple(a[frame] for a in rays.frame_origin.T.copy()),
                        (ce * rays.col_cos[col], ce * rays.col_sin[col], se))
    k = rays.col_k[col]
    ret = [frame, ce * tab.cos_a[k], ce * tab.sin_a[k], se, r]
    return _subset(ret, (r >= cfg.min_range) & (r <= cfg.max_range))


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
    dirs = _direction_table(cfg).reshape(-1, 3)
    return intersector.intersects_first(np.zeros_like(dirs), dirs)


def full_sweep_points(mesh, pose, cfg: LidarConfig) -> np.ndarray:
    """Slow exact reference: move the mesh to ``pose``, cast every ray of a sweep, no noise.

    Uses ``intersects_location(multiple_hits=False)``; returns float64 ``(N, 3)`` hit points in
    the sensor frame (within the sensor's range limits).
    """
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    from seqshape.geometry import pose_to_matrix

    posed = mesh.copy()
    posed.apply_transform(pose_to_matrix(pose))
    dirs = _direction_table(cfg).reshape(-1, 3)
    loc, _, _ = RayMeshIntersector(posed).intersects_location(
        np.zeros_like(dirs), dirs, multiple_hits=False)
    r = np.linalg.norm(loc, axis=1)
    return loc[(r >= cfg.min_range) & (r <= cfg.max_range)]
