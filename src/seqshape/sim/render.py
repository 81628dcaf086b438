"""Camera and LiDAR rendering of a frame of vehicle meshes over a ground plane, with exact masks.

Everything is in the frame's sensor (velodyne) frame. Both sensors go through the one raycast
core (:func:`seqshape.sim.raycast.scene_hits`, Embree, one cached intersector per canonical
mesh): rays are mapped into each vehicle's canonical frame, only the rays inside the vehicle's
bounding cone (sphere around its box seen from the ray origin) are cast, and the first hit of
the scene is the nearest of the per-vehicle hits. The LiDAR's sweep directions, range limits,
noise and dropout are the sensor's own (:class:`seqshape.sim.sensors.LidarConfig`); the ground plane ``z = ground_z`` is
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

import warnings
from dataclasses import dataclass

import numpy as np

from seqshape.geometry import yaw_to_rotmat
from seqshape.sim.raycast import VehicleHits, cast_posed, cone_rays, scene_hits
from seqshape.sim.sensors import LidarConfig

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
        idx = cone_rays(rays.outer_dirs, rays.origin, pose, float(np.linalg.norm(mesh.extents)) / 2)
        if len(idx):
            tri, _, _ = cast_posed(mesh, pose, rays.origin, rays.outer_dirs[idx])
            outer[k] = float(np.count_nonzero(tri >= 0)) * OUTER_STRIDE ** 2
    nearest = np.array([hk.rng.min() if len(hk.rng) else np.inf for hk in hits])
    image = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8).reshape(h, w, 3)
    return CameraFrame(image, code.reshape(h, w), depth.reshape(h, w), amodal, visible, outer,
                       nearest)


def render_lidar(meshes, poses, colours, cfg: LidarConfig, rng: np.random.Generator,
                 ground_z: float | None = None, ground_material=None):
    """One LiDAR sweep of the scene (vehicles + ground), with noise and dropout of ``cfg``.

    Returns ``points`` (N, 4) float32 (x, y, z, reflectance in [0, 1]) in the sensor frame and
    ``owner`` (N,) int64: the vehicle index of each return, or GROUND.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    ground_z = -cfg.height if ground_z is None else ground_z
    dirs = cfg.sweep_directions()
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
    keep = np.flatnonzero(np.isfinite(dist) & cfg.in_range(dist))
    r = cfg.noisy_ranges(dist[keep], rng)
    refl = np.clip(albedo[keep] * np.sqrt(cos_inc[keep]) + rng.normal(0, 0.02, len(r)), 0, 1)
    sel = cfg.kept_returns(len(r), rng)
    pts = np.c_[dirs[keep[sel]] * r[sel, None], refl[sel]].astype(np.float32)
    return pts, owner[keep[sel]]


def __getattr__(name: str):
    """``cast_vehicle`` moved to :func:`seqshape.sim.raycast.cast_posed` (the one raycast core);
    the old name works for one release with a :class:`DeprecationWarning`."""
    if name != "cast_vehicle":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(f"{__name__}.cast_vehicle moved to seqshape.sim.raycast.cast_posed; the old "
                  f"path will be removed in the next release", DeprecationWarning, stacklevel=2)
    return cast_posed
