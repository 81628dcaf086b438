"""Camera and LiDAR rendering of a frame of vehicle meshes over a ground plane, with exact masks.

Everything is in the frame's sensor (velodyne) frame. Both sensors are raycast through Embree
with one cached intersector per canonical mesh (:func:`seqshape.sim.raycast.mesh_raycaster`):
rays are mapped into each vehicle's canonical frame, only the rays inside the vehicle's
bounding cone (sphere around its box seen from the ray origin) are cast, and the first hit of
the scene is the nearest of the per-vehicle hits; the ground plane ``z = ground_z`` is
intersected analytically and only where no vehicle is hit (vehicles stand on it).

Camera: one ray per pixel centre (integer pixel coordinates, as in KITTI and
:func:`seqshape.camera.project_points`), from camera 2's optical centre. Per vehicle k:

* amodal mask = pixels whose ray hits vehicle k's mesh (cast against that mesh alone);
* visible mask = pixels whose first scene hit is vehicle k.

The two come from the same rays and the same intersector, so ``visible <= amodal`` holds
exactly, a vehicle nobody hides has ``visible == amodal`` exactly, and visible masks are
disjoint. Truncation needs the amodal area outside the image: rays on the image plane extended
by one image size on every side (stride :data:`OUTER_STRIDE` px, each hit counting
``OUTER_STRIDE**2`` pixels); beyond that extension the truncation is a lower bound.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from seqshape.geometry import yaw_to_rotmat
from seqshape.sim.raycast import mesh_raycaster
from seqshape.sim.sensors import LidarConfig, ray_directions

OUTER_STRIDE = 4
SKY, GROUND = -2, -1  #: owner codes of pixels / returns that hit no vehicle
_SUN = np.array([0.35, 0.45, 0.82]) / np.linalg.norm([0.35, 0.45, 0.82])  # sensor frame
_AMBIENT, _DIFFUSE = 0.35, 0.65


@dataclass
class CameraRays:
    """Pixel rays of one camera in the velodyne frame.

    ``origin`` (3,) optical centre; ``dirs`` (H*W, 3) unit directions, row-major over (v, u);
    ``outer_dirs`` (M, 3) the rays of the extended image plane outside the image.
    """

    origin: np.ndarray
    dirs: np.ndarray
    outer_dirs: np.ndarray
    width: int
    height: int


def camera_rays(calib, cam: int = 2) -> CameraRays:
    """Rays through every pixel centre of camera ``cam`` of a ``seqshape.camera.KittiCalib``.

    A point ``origin + t * dirs[v * W + u]`` projects exactly to pixel ``(u, v)``.
    """
    key = (cam, calib.image_size, calib.P(cam).tobytes(), calib.velo_to_rect.tobytes())
    if key not in _RAY_CACHE:
        if len(_RAY_CACHE) >= 4:
            _RAY_CACHE.pop(next(iter(_RAY_CACHE)))
        _RAY_CACHE[key] = _build_camera_rays(calib.P(cam), calib.rect_to_velo,
                                             *calib.image_size)
    return _RAY_CACHE[key]


_RAY_CACHE: dict[tuple, CameraRays] = {}


def _build_camera_rays(p, rect_to_velo, w, h) -> CameraRays:
    m_inv = np.linalg.inv(p[:, :3])
    centre_rect = -m_inv @ p[:, 3]
    lin = rect_to_velo[:3, :3]
    origin = lin @ centre_rect + rect_to_velo[:3, 3]

    def dirs_of(u, v):
        d = np.stack([u, v, np.ones_like(u)], -1) @ (lin @ m_inv).T
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    vv, uu = np.mgrid[0:h, 0:w]
    inner = dirs_of(uu.ravel().astype(np.float64), vv.ravel().astype(np.float64))
    s = OUTER_STRIDE
    ov, ou = np.mgrid[-h + s // 2:2 * h:s, -w + s // 2:2 * w:s]
    out = ~((ou >= 0) & (ou < w) & (ov >= 0) & (ov < h))
    outer = dirs_of(ou[out].astype(np.float64), ov[out].astype(np.float64))
    return CameraRays(origin, inner, outer, int(w), int(h))


def _cone(dirs: np.ndarray, origin: np.ndarray, pose: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the rays (from ``origin``) that can meet a sphere of ``radius`` at ``pose``."""
    c = np.asarray(pose[:3], dtype=np.float64) - origin
    dist = float(np.linalg.norm(c))
    if dist <= radius:
        return np.arange(len(dirs))
    cos_a = np.sqrt(1.0 - (radius / dist) ** 2)
    return np.flatnonzero(dirs @ (c / dist) >= cos_a - 1e-9)


def cast_vehicle(mesh, pose, origin, dirs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        n = rt.plane_normals[tri[hit]]
        denom = np.einsum("ij,ij->i", d[hit], n)
        num = np.einsum("ij,ij->i", rt.plane_points[tri[hit]] - o[hit], n)
        ok = np.abs(denom) > 1e-9
        r = np.where(ok, num / np.where(ok, denom, 1.0), np.inf)
        rng[hit] = np.where(r >= 0, r, np.inf)
    tri = np.where(np.isfinite(rng), tri, -1)
    local = o + d * np.where(np.isfinite(rng), rng, np.nan)[:, None]
    return tri, rng, local


@dataclass
class VehicleHits:
    """Rays of one vehicle: ``index`` into the ray array, ``rng``, ``tri``, ``local`` points."""

    index: np.ndarray
    rng: np.ndarray
    tri: np.ndarray
    local: np.ndarray


def scene_hits(meshes, poses, origin, dirs) -> tuple[list[VehicleHits], np.ndarray, np.ndarray]:
    """Per-vehicle hits of every ray and the scene's first hit (vehicles only).

    Returns ``hits`` (one :class:`VehicleHits` per vehicle), ``owner`` (R,) int (vehicle
    index or -1) and ``dist`` (R,) float64 (inf where no vehicle is hit).
    """
    owner = np.full(len(dirs), -1, dtype=np.int64)
    dist = np.full(len(dirs), np.inf)
    hits = []
    for k, (mesh, pose) in enumerate(zip(meshes, poses, strict=True)):
        radius = float(np.linalg.norm(mesh.extents)) / 2 + 0.05
        idx = _cone(dirs, origin, pose, radius)
        tri, rng, local = cast_vehicle(mesh, pose, origin, dirs[idx])
        ok = tri >= 0
        h = VehicleHits(idx[ok], rng[ok], tri[ok], local[ok])
        hits.append(h)
        better = h.rng < dist[h.index]
        dist[h.index[better]] = h.rng[better]
        owner[h.index[better]] = k
    return hits, owner, dist


def _ground_t(origin, dirs, ground_z: float) -> np.ndarray:
    """Distance along each ray to the plane ``z = ground_z`` (inf when not hit)."""
    down = dirs[:, 2] < -1e-12
    t = np.full(len(dirs), np.inf)
    t[down] = (ground_z - origin[2]) / dirs[down, 2]
    t[t < 0] = np.inf
    return t


def _vehicle_material(mesh, hits: VehicleHits, pose, colour):
    """Shaded RGB ``(n, 3)`` and LiDAR albedo ``(n,)`` of a vehicle's hits.

    Paint with darker glass above the belt line (side faces only) and a dark band of
    tyres and sills near the ground; Lambertian shading under a fixed sun.
    """
    h = float(mesh.extents[2])
    n_local = np.asarray(mesh.face_normals)[hits.tri]
    z = hits.local[:, 2]
    glass = (z > 0.12 * h) & (np.abs(n_local[:, 2]) < 0.85)
    low = z < -h / 2 + 0.28
    base = np.tile(np.asarray(colour, dtype=np.float64), (len(z), 1))
    base[glass] = [0.10, 0.13, 0.17]
    base[low & ~glass] = [0.08, 0.08, 0.08]
    albedo = np.full(len(z), 0.25 + 0.45 * float(np.mean(colour)))
    albedo[glass] = 0.05
    albedo[low] = 0.12
    n = n_local @ yaw_to_rotmat(pose[3]).T
    lam = np.abs(n @ _SUN)
    return base * (_AMBIENT + _DIFFUSE * lam)[:, None], albedo, n


@dataclass
class CameraFrame:
    """A rendered camera frame.

    ``image`` (H, W, 3) uint8 RGB; ``owner`` (H, W) int (vehicle index, or GROUND / SKY);
    ``depth`` (H, W) float distance along the pixel ray (inf for sky); per vehicle k:
    ``amodal[k]`` / ``visible[k]`` (H, W) bool, ``outer_area[k]`` amodal pixels outside the
    image (estimated, see the module doc) and ``nearest[k]`` the smallest ray distance of its
    amodal pixels (inf when not seen).
    """

    image: np.ndarray
    owner: np.ndarray
    depth: np.ndarray
    amodal: list[np.ndarray]
    visible: list[np.ndarray]
    outer_area: np.ndarray
    nearest: np.ndarray


def render_camera(meshes, poses, colours, rays: CameraRays, ground_z: float,
                  ground_material=None) -> CameraFrame:
    """Render vehicles ``meshes`` at sensor-frame ``poses`` (K, 4) with ``colours`` (K, 3).

    ``ground_material(points (N, 3) sensor frame) -> (rgb (N, 3), albedo (N,))`` colours the
    ground (uniform asphalt when None).
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    w, h = rays.width, rays.height
    hits, owner, dist = scene_hits(meshes, poses, rays.origin, rays.dirs)
    rgb = np.empty((h * w, 3))
    elev = rays.dirs[:, 2]
    rgb[:] = np.c_[0.55 - 0.3 * elev, 0.70 - 0.2 * elev, 0.92 + 0.0 * elev]  # sky
    tg = _ground_t(rays.origin, rays.dirs, ground_z)
    gsel = np.flatnonzero((owner < 0) & np.isfinite(tg))
    pts = rays.origin + rays.dirs[gsel] * tg[gsel, None]
    if ground_material is None:
        g_rgb = np.full((len(gsel), 3), 0.32)
    else:
        g_rgb = np.asarray(ground_material(pts)[0], dtype=np.float64)
    fog = np.exp(-tg[gsel] / 250.0)[:, None]
    rgb[gsel] = g_rgb * (_AMBIENT + _DIFFUSE * _SUN[2]) * fog + rgb[gsel] * (1 - fog)
    code = np.full(h * w, SKY, dtype=np.int64)
    code[gsel] = GROUND
    depth = np.where(owner >= 0, dist, tg)
    amodal, visible = [], []
    for k, hk in enumerate(hits):
        vis = owner[hk.index] == k
        shade, _, _ = _vehicle_material(meshes[k], hk, poses[k], colours[k])
        rgb[hk.index[vis]] = shade[vis]
        a = np.zeros(h * w, dtype=bool)
        a[hk.index] = True
        amodal.append(a.reshape(h, w))
        visible.append((owner == k).reshape(h, w))
    code[owner >= 0] = owner[owner >= 0]
    outer = np.zeros(len(meshes))
    for k, (mesh, pose) in enumerate(zip(meshes, poses, strict=True)):
        idx = _cone(rays.outer_dirs, rays.origin, pose, float(np.linalg.norm(mesh.extents)) / 2)
        if len(idx):
            tri, _, _ = cast_vehicle(mesh, pose, rays.origin, rays.outer_dirs[idx])
            outer[k] = float(np.count_nonzero(tri >= 0)) * OUTER_STRIDE ** 2
    nearest = np.array([hk.rng.min() if len(hk.rng) else np.inf for hk in hits])
    image = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8).reshape(h, w, 3)
    return CameraFrame(image, code.reshape(h, w), depth.reshape(h, w), amodal, visible, outer,
                       nearest)


@lru_cache(maxsize=4)
def _sweep_dirs(cfg: LidarConfig) -> np.ndarray:
    return ray_directions(cfg)


def render_lidar(meshes, poses, colours, cfg: LidarConfig, rng: np.random.Generator,
                 ground_z: float | None = None, ground_material=None):
    """One LiDAR sweep of the scene (vehicles + ground), with noise and dropout of ``cfg``.

    Returns ``points`` (N, 4) float32 (x, y, z, reflectance in [0, 1]) in the sensor frame and
    ``owner`` (N,) int64: the vehicle index of each return, or GROUND.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    ground_z = -cfg.height if ground_z is None else ground_z
    dirs = _sweep_dirs(cfg)
    origin = np.zeros(3)
    hits, owner, dist = scene_hits(meshes, poses, origin, dirs)
    albedo = np.zeros(len(dirs))
    cos_inc = np.ones(len(dirs))
    for k, hk in enumerate(hits):
        vis = owner[hk.index] == k
        _, alb, n = _vehicle_material(meshes[k], hk, poses[k], colours[k])
        albedo[hk.index[vis]] = alb[vis]
        cos_inc[hk.index[vis]] = np.abs(np.einsum("ij,ij->i", n[vis], dirs[hk.index[vis]]))
    tg = _ground_t(origin, dirs, ground_z)
    g = np.flatnonzero((owner < 0) & np.isfinite(tg))
    dist[g] = tg[g]
    owner[g] = GROUND
    cos_inc[g] = np.abs(dirs[g, 2])
    if ground_material is None:
        albedo[g] = 0.15
    else:
        albedo[g] = ground_material(dirs[g] * tg[g, None])[1]
    keep = np.flatnonzero(np.isfinite(dist) & (dist >= cfg.min_range) & (dist <= cfg.max_range))
    r = dist[keep]
    if cfg.range_noise_std > 0:
        r = r + rng.normal(0.0, cfg.range_noise_std, len(r))
    refl = np.clip(albedo[keep] * np.sqrt(cos_inc[keep]) + rng.normal(0, 0.02, len(r)), 0, 1)
    drop = rng.random(len(r)) < cfg.dropout if cfg.dropout > 0 else np.zeros(len(r), bool)
    sel = ~drop
    pts = np.c_[dirs[keep[sel]] * r[sel, None], refl[sel]].astype(np.float32)
    return pts, owner[keep[sel]]
