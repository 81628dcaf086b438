"""The ``real`` generation path: a scene scanned the way a real LiDAR sees it, then cropped the
way a real user crops it (docs/generation.md, "The real preset").

Per track (everything drawn from ``SeedSequence([seed, track, tag])`` streams):

* a sensor model drawn from :attr:`RealConfig.sensors`, mounted ``height`` m above the ground
  with a small ``pitch`` and ``roll`` of the LiDAR head. The sensor frame stays level (the ego
  axes, origin at the LiDAR): the *rays* are tilted (:func:`seqshape.sim.sensors.
  mount_rotation`) and the points are reported in the level frame, as a calibrated driving log
  reports them;
* a ground plane ``z = -height + sx x + sy y`` (small longitudinal slope and cross fall) that
  returns points, and static clutter near the path (curbs, poles, bushes, walls);
* the target and the occluding vehicles, which return points too, with their per-face material
  labels (`seqshape.vehicles.base`): glass lets a ray through with ``glass_pass`` (it goes on to
  the interior, the far side of the car or beyond; less at grazing incidence, by the pane's
  Fresnel transmission), returns from the pane with ``glass_return``, else the ray is lost;
  every surface is detected with a probability that falls with range and rises with
  reflectivity (dark paint, tyres and trim drop out first), a vehicle's or clutter face's
  reflectivity times ``cos(incidence) ** incidence_exponent`` (grazing faces drop out);
* Gaussian range noise, and mixed returns at silhouette edges: a ray whose azimuth neighbour
  returns from more than ``edge_gap`` m away also casts four sub-rays at the edge of its
  divergence cone; if they disagree the return is, with ``mixed_prob``, their mean range (a
  point floating between foreground and background), else the nearest.

Each frame's points are then cut out by :func:`seqshape.data.crop.crop_vehicle` (the function
``seqshape tracks`` and ``seqshape label`` use) with a tracker-like box: the true box jittered
and enlarged (:class:`TrackerJitter`), seeded per (seed, track, frame). The poses stay exact.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import trimesh

from seqshape.data.crop import CropConfig, crop_vehicle
from seqshape.errors import ConfigError
from seqshape.geometry import pose_to_matrix
from seqshape.sim.raycast import MeshRaycaster, mesh_raycaster
from seqshape.sim.sensors import LidarConfig, get_sensor, ray_window, window_grid
from seqshape.sim.trajectories import footprint_distance, footprints_overlap
from seqshape.vehicles.base import BODY as _BODY
from seqshape.vehicles.base import FACE_LABELS, GRILLE, HEADLAMP
from seqshape.vehicles.base import GLASS as _GLASS

#: point source codes recorded per frame in the track meta (``sources``)
SOURCES = ("target", "target_through_glass", "other_vehicle", "ground", "clutter")
_TAG_SCENE, _TAG_JITTER, _TAG_RAYS = 0x5CE4E, 0x717E2, 0x2A75
_EPS = 1e-3  # m a ray moves past a glass pane before it goes on
_MAX_PANES = 4  # glass panes one ray may cross
_N_GLASS = 1.52  # refractive index of soda-lime glass (and of laminated glass's PVB) at 905 nm
_LEGACY_LABELS = 8  # face labels before GRILLE and HEADLAMP
_DEFAULT_REFLECTIVITY = (0.5, 0.1, 0.03, 0.3, 0.05, 0.9, 0.25, 0.2, 0.05, 0.3)


@dataclass(frozen=True)
class TrackerJitter:
    """A tracker's box: the true box moved, turned, rescaled and enlarged, per frame.

    centre_std: std (m) of the box centre's x and y error; centre_z_std: of z.
    yaw_std_deg: std of the heading error (deg).
    size_std: std of the log of the per-axis size scale.
    enlarge: metres added to length and width (and half of it to height) before the crop.
    """

    centre_std: float = 0.2
    centre_z_std: float = 0.05
    yaw_std_deg: float = 3.0
    size_std: float = 0.05
    enlarge: float = 0.2

    def __post_init__(self):
        if min(self.centre_std, self.centre_z_std, self.yaw_std_deg, self.size_std,
               self.enlarge) < 0:
            raise ConfigError("tracker jitter parameters must be >= 0")


@dataclass(frozen=True)
class RealConfig:
    """Parameters of the real scan (module doc); values and sources in docs/generation.md."""

    sensors: tuple[str, ...] = ("vlp16", "vlp32c", "vlp32c_pair", "hdl64", "os128")
    """Sensor models, one drawn per track with ``sensor_weights`` (docs/generation.md: the
    Argoverse 2 pair's dense near-horizon beams put real points where they lie on cars)."""
    sensor_weights: tuple[float, ...] = (0.15, 0.2, 0.25, 0.2, 0.2)
    height_range: tuple[float, float] = (1.5, 2.2)
    """Mounting height of the LiDAR above the ground (m), uniform."""
    tilt_deg: float = 1.5
    """Pitch and roll of the LiDAR head, each uniform in +-tilt_deg."""
    glass_pass: float = 0.85
    """Probability that a ray hitting glass goes through it (at normal incidence, see
    ``glass_fresnel``)."""
    glass_fresnel: bool = True
    """Scale ``glass_pass`` by the pane's Fresnel transmission relative to normal incidence
    (:func:`pane_transmission`): a raked windshield or a side window seen end-on reflects more
    of the beam away (lost) and passes less."""
    glass_return: float = 0.05
    """Probability that a ray hitting glass returns from the pane (else it is lost)."""
    reflectivity: tuple[float, ...] = _DEFAULT_REFLECTIVITY
    """Reflectivity per face label (body, glass, tyre, rim, trim, lamp, interior, cargo, grille,
    headlamp); the body's is replaced by the vehicle's paint. Eight values (a configuration
    saved before the grille and headlamp labels) get this default's last two."""
    grille_pass: tuple[float, float] = (0.2, 0.8)
    """Share of the rays hitting a car's front grille that go through its openings (on to the
    radiator behind it, or deeper), per vehicle uniform in this range: from near-closed
    fronts (many electric cars) to open grilles; the others return from the bars."""
    headlamp_loss: float = 0.7
    """Probability that a ray hitting a headlamp is lost: the mirror-like reflector behind the
    clear lens sends the beam away, unlike a tail lamp's retro-reflector; else it returns from
    the lens."""
    dark_paint_share: float = 0.35
    """Share of vehicles with dark paint (reflectivity 0.03-0.08; others 0.2-0.8)."""
    detection_sharpness: float = 4.0
    """k of the detection probability ``1 / (1 + (r / R50) ** k)``."""
    base_dropout: float = 0.01
    """Probability that any return is lost."""
    incidence_exponent: float = 1.0
    """n of the incidence factor: a vehicle or clutter face hit at angle theta from its normal
    returns like one of reflectivity ``rho cos(theta) ** n`` (Lambertian: 1; 0: no incidence
    effect). Not the ground (:func:`incidence_cosine`)."""
    edge_gap: float = 0.3
    """Range jump (m) between azimuth neighbours that marks a silhouette edge."""
    mixed_prob: float = 0.5
    """Probability that an edge ray with disagreeing sub-rays returns their mean range."""
    max_slope: float = 0.03
    """Ground longitudinal slope and cross fall, each uniform in +-max_slope (rise / run)."""
    ground_reflectivity: tuple[float, float] = (0.08, 0.2)
    max_clutter: int = 6
    """Up to this many clutter objects (curbs, poles, bushes, walls) near the path."""
    context: float = 2.5
    """Metres around the target's box within which the scene is scanned."""
    jitter: TrackerJitter = field(default_factory=TrackerJitter)
    crop: CropConfig = field(default_factory=CropConfig)

    def __post_init__(self):
        if isinstance(self.jitter, dict):
            object.__setattr__(self, "jitter", TrackerJitter(**self.jitter))
        if isinstance(self.crop, dict):
            object.__setattr__(self, "crop", CropConfig(**self.crop))
        for name in ("sensors", "sensor_weights", "height_range", "reflectivity",
                     "ground_reflectivity", "grille_pass"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if len(self.reflectivity) == _LEGACY_LABELS:
            object.__setattr__(self, "reflectivity",
                               self.reflectivity + _DEFAULT_REFLECTIVITY[_LEGACY_LABELS:])
        if not self.sensors or len(self.sensors) != len(self.sensor_weights):
            raise ConfigError("real: sensors and sensor_weights need the same non-zero length")
        if min(self.sensor_weights) < 0 or sum(self.sensor_weights) <= 0:
            raise ConfigError("real: sensor_weights must be >= 0 with a positive sum")
        for s in self.sensors:
            cfg = get_sensor(s)
            if cfg.divergence_mrad <= 0 or cfg.range_10pct <= 0:
                raise ConfigError(f"real: sensor {s!r} has no divergence_mrad/range_10pct")
        lo, hi = self.height_range
        if not 0 < lo <= hi:
            raise ConfigError("real: need 0 < height_range[0] <= height_range[1]")
        probs = (self.glass_pass, self.glass_return, self.dark_paint_share, self.base_dropout,
                 self.mixed_prob, self.headlamp_loss, *self.grille_pass)
        if min(probs) < 0 or max(probs) > 1 or self.glass_pass + self.glass_return > 1:
            raise ConfigError("real: probabilities must lie in [0, 1] and "
                              "glass_pass + glass_return <= 1")
        if len(self.reflectivity) != len(FACE_LABELS) or min(self.reflectivity) <= 0:
            raise ConfigError(f"real: reflectivity needs {len(FACE_LABELS)} positive values "
                              f"(one per face label: {', '.join(FACE_LABELS.values())})")
        if len(self.grille_pass) != 2 or self.grille_pass[0] > self.grille_pass[1]:
            raise ConfigError("real: grille_pass needs two values, low <= high")
        if min(self.tilt_deg, self.edge_gap, self.max_slope, self.context,
               self.detection_sharpness, self.incidence_exponent) < 0 or self.max_clutter < 0:
            raise ConfigError("real: tilt, edge_gap, slopes, context, sharpness, "
                              "incidence_exponent and max_clutter must be >= 0")

    def to_dict(self) -> dict:
        return asdict(self)


# ------------------------------------------------------------------------------ the scene


@dataclass
class SceneObject:
    """A mesh in the scene: its raycaster, per-frame poses ``(T, 4)`` (None: static, already
    in the sensor frame), per-face reflectivity ``(F,)``, glass mask ``(F,)`` and source code;
    for the faces that are not glass, the probability ``(F,)`` that a ray goes through
    (``opening``: a grille) or is lost (``loss``: a headlamp); None: 0 everywhere."""

    rt: MeshRaycaster
    poses: np.ndarray | None
    rho: np.ndarray
    glass: np.ndarray
    source: int
    opening: np.ndarray | None = None
    loss: np.ndarray | None = None


@dataclass
class Scene:
    """Objects plus the ground plane ``n . p + d = 0`` (n up, unit) of one track."""

    objects: list[SceneObject]
    ground_n: np.ndarray
    ground_d: float
    ground_rho: float


def ground_plane(height: float, slope_x: float, slope_y: float) -> tuple[np.ndarray, float]:
    """Unit up normal and offset of the ground ``z = -height + slope_x x + slope_y y``."""
    n = np.array([-slope_x, -slope_y, 1.0])
    norm = float(np.linalg.norm(n))
    return n / norm, height / norm


def ground_height(n: np.ndarray, d: float, x, y):
    """``z`` of the ground plane at ``(x, y)``."""
    return -(n[0] * np.asarray(x) + n[1] * np.asarray(y) + d) / n[2]


def vehicle_object(mesh, poses, labels, paint: float, cfg: RealConfig, source: int,
                   grille: float | None = None):
    """A vehicle as a :class:`SceneObject` (``labels`` None: every face is body); ``grille``
    is the share of grille hits that go through (:func:`sample_grille`; None: the middle of
    ``cfg.grille_pass``)."""
    n_faces = len(mesh.faces)
    lab = (np.zeros(n_faces, np.int64) if labels is None
           else np.asarray(labels, dtype=np.int64).reshape(-1))
    if len(lab) != n_faces:
        raise ConfigError(f"face_labels has {len(lab)} entries for {n_faces} faces")
    table = np.asarray(cfg.reflectivity, dtype=np.float64).copy()
    table[_BODY] = paint
    lab = np.clip(lab, 0, len(table) - 1)
    if grille is None:
        grille = float(np.mean(cfg.grille_pass))
    return SceneObject(mesh_raycaster(mesh), np.asarray(poses, dtype=np.float64).reshape(-1, 4),
                       table[lab], lab == _GLASS, source,
                       opening=np.where(lab == GRILLE, grille, 0.0),
                       loss=np.where(lab == HEADLAMP, cfg.headlamp_loss, 0.0))


def sample_grille(rng: np.random.Generator, cfg: RealConfig) -> float:
    """A vehicle's grille openness: uniform in ``cfg.grille_pass``."""
    return float(rng.uniform(*cfg.grille_pass))


def sample_paint(rng: np.random.Generator, cfg: RealConfig) -> float:
    """A body reflectivity: dark paint with ``dark_paint_share``, else a light or mid colour."""
    if rng.random() < cfg.dark_paint_share:
        return float(rng.uniform(0.03, 0.08))
    return float(rng.uniform(0.2, 0.8))


# ----------------------------------------------------------------------------- clutter


def _box(centre, size, yaw):
    m = trimesh.creation.box(extents=size)
    m.apply_transform(pose_to_matrix([*centre, yaw]))
    return m


def _cylinder(centre, radius, height):
    m = trimesh.creation.cylinder(radius=radius, height=height, sections=12)
    m.apply_translation(centre)
    return m


def sample_clutter(rng: np.random.Generator, poses: np.ndarray, size, blockers, n, d,
                   cfg: RealConfig):
    """Static clutter near the track: list of ``(mesh in the sensor frame, reflectivity, kind)``.

    Objects stand beside the path (1.0 to 3.5 m from the target's side at a random frame) and
    never overlap any footprint of ``blockers`` (``(poses (T, 4), size)`` pairs) in any frame.
    """
    out = []
    n_obj = int(rng.integers(0, cfg.max_clutter + 1))
    for _ in range(n_obj):
        t = int(rng.integers(len(poses)))
        x, y, _, yaw = poses[t]
        side = rng.choice([-1.0, 1.0])
        lat = side * (size[1] / 2 + rng.uniform(1.0, 3.5))
        lon = rng.uniform(-size[0], size[0])
        cx = x + np.cos(yaw) * lon - np.sin(yaw) * lat
        cy = y + np.sin(yaw) * lon + np.cos(yaw) * lat
        kind = str(rng.choice(["curb", "pole", "bush", "wall"], p=[0.35, 0.3, 0.2, 0.15]))
        if kind == "curb":
            dims, rho = np.array([rng.uniform(8, 25), 0.3, rng.uniform(0.1, 0.16)]), 0.25
            oyaw = yaw
        elif kind == "pole":
            r = rng.uniform(0.05, 0.15)
            dims, rho, oyaw = np.array([2 * r, 2 * r, rng.uniform(2.5, 4.5)]), 0.3, 0.0
        elif kind == "bush":
            dims = np.array([rng.uniform(0.8, 3.0), rng.uniform(0.6, 1.5), rng.uniform(0.5, 1.4)])
            rho, oyaw = 0.2, yaw + rng.normal(0, 0.2)
        else:
            dims = np.array([rng.uniform(3, 10), 0.25, rng.uniform(0.8, 2.0)])
            rho, oyaw = 0.3, yaw
        pose = np.array([[cx, cy, 0.0, oyaw]])
        if footprint_distance(pose[:, 0], pose[:, 1], pose[:, 3], dims[0], dims[1]).min() < 1.5:
            continue
        rep = np.repeat(pose, len(poses), 0)
        if any(footprints_overlap(p, s, rep, dims, margin=0.4).any() for p, s in blockers):
            continue
        z = float(ground_height(n, d, cx, cy)) + dims[2] / 2 - 0.05  # sunk 5 cm into the ground
        if kind == "pole":
            mesh = _cylinder([cx, cy, z], dims[0] / 2, dims[2])
        else:
            mesh = _box([cx, cy, z], dims, oyaw)
        out.append((mesh, rho, kind))
    return out


def clutter_object(clutter) -> SceneObject | None:
    """All clutter meshes as one static :class:`SceneObject` (None when there is none)."""
    if not clutter:
        return None
    mesh = trimesh.util.concatenate([m for m, _, _ in clutter])
    rho = np.concatenate([np.full(len(m.faces), r) for m, r, _ in clutter])
    return SceneObject(MeshRaycaster(mesh), None, rho, np.zeros(len(rho), bool), 4)


# ------------------------------------------------------------------------------ rays


@dataclass
class Rays:
    """The rays of a track's scan, frame-major then channel then azimuth.

    elev / az: ``(R,)`` head-frame elevation and azimuth (rad); frame / row: ``(R,)`` frame
    index and row id (one row per (frame, channel)); dirs: ``(R, 3)`` tilted unit directions in
    the level sensor frame.
    """

    elev: np.ndarray
    az: np.ndarray
    frame: np.ndarray
    row: np.ndarray
    dirs: np.ndarray


def head_directions(elev, az, rot: np.ndarray) -> np.ndarray:
    """Directions ``(R, 3)`` in the level sensor frame of head-frame beams ``(elev, az)``."""
    ce = np.cos(elev)
    d = np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(elev)], 1)
    return d @ rot.T


def scan_rays(sensor: LidarConfig, mesh_bounds: np.ndarray, poses: np.ndarray,
              rot: np.ndarray, tilt_rad: float, context: float, ground_drop: float) -> Rays:
    """The rays of every frame that can reach the vehicle's box ``mesh_bounds`` (canonical)
    grown by ``context`` m and down to ``ground_drop`` m below it (:func:`scan_bounds`), at
    ``poses``, for a head tilted by ``rot`` (at most ``tilt_rad`` off level).

    Per frame the context shrinks so that the sensor stays 0.5 m outside the grown box (else
    the window would be the whole sweep).
    """
    size = mesh_bounds[1] - mesh_bounds[0]
    gap = footprint_distance(poses[:, 0], poses[:, 1], poses[:, 3], size[0], size[1])
    ctx = np.clip(np.minimum(context, gap - 0.5), 0.0, None)
    win = [ray_window(sensor, scan_bounds(mesh_bounds, float(c), ground_drop), poses[t:t + 1])
           for t, c in enumerate(ctx)]
    c0, c1, k0, k1 = (np.concatenate(w) for w in zip(*win, strict=True))
    tab = sensor.tables()
    elev = tab.elev
    spacing = np.diff(elev).min() if len(elev) > 1 else 1.0
    m = int(np.ceil(tilt_rad / spacing)) + 1
    c0, c1 = np.maximum(c0 - m, 0), np.minimum(c1 + m, len(elev))
    k_extra = int(np.ceil(np.tan(tilt_rad) * 2 / np.deg2rad(sensor.azimuth_step_deg))) + 1
    full = (k1 - k0 + 1) >= sensor.n_azimuths
    k0 = np.where(full, k0, k0 - k_extra)
    k1 = np.where(full, k1, np.minimum(k1 + k_extra, k0 + sensor.n_azimuths - 1))
    g = window_grid(sensor, c0, c1, k0, k1)
    row = g.ray_row
    ch, k = g.row_ch[row], g.col_k[g.ray_col]
    d = np.empty((len(row), 3))
    d[:, 0] = tab.cos_e[ch] * tab.cos_a[k]
    d[:, 1] = tab.cos_e[ch] * tab.sin_a[k]
    d[:, 2] = tab.sin_e[ch]
    return Rays(elev[ch], tab.az[k], g.row_frame[row], row, d @ rot.T)


# --------------------------------------------------------------------------- casting


def cast_scene(scene: Scene, origins: np.ndarray, dirs: np.ndarray, frame: np.ndarray,
               offset: np.ndarray | None = None):
    """Nearest hit of each ray among the scene's objects and the ground.

    The rays run along lines from the sensor; ``offset`` (R,) is how far each ray's origin
    already is along its line (0 when None). A moving object is cast only with the rays that
    can reach its bounding circle: within its azimuth span and not on the ground before it.

    Returns ``t`` (R,) float64 from ``origins`` (inf: none), ``obj`` (R,) int (index into
    ``scene.objects``, ``len(objects)`` for the ground, -1 none) and ``face`` (R,) int (-1 for
    the ground / none).
    """
    n = len(dirs)
    t = np.full(n, np.inf)
    obj = np.full(n, -1, np.int64)
    face = np.full(n, -1, np.int64)
    denom = dirs @ scene.ground_n
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = -(origins @ scene.ground_n + scene.ground_d) / denom
    tg[~(tg > 0) | (denom > -1e-9)] = np.inf
    reach = tg if offset is None else tg + offset
    horiz = np.hypot(dirs[:, 0], dirs[:, 1])
    for j, ob in enumerate(scene.objects):
        sel = np.arange(n) if ob.poses is None else _reachable(ob, dirs, horiz, reach, frame)
        if len(sel) == 0:
            continue
        o, d = origins[sel], dirs[sel]
        if ob.poses is not None:
            p = ob.poses[frame[sel]]
            c, s = np.cos(p[:, 3]), np.sin(p[:, 3])
            rel = o - p[:, :3]
            o = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                          rel[:, 2]], 1)
            d = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], 1)
        tri = ob.rt.first_faces(o, d)
        hit = np.flatnonzero(tri >= 0)
        if len(hit) == 0:
            continue
        r = ob.rt.plane_ranges(tri[hit], o[hit], d[hit])
        idx = sel[hit]
        better = r < t[idx]
        idx, r, f = idx[better], r[better], tri[hit][better]
        t[idx], obj[idx], face[idx] = r, j, f
    g = tg < t
    t[g], obj[g], face[g] = tg[g], len(scene.objects), -1
    return t, obj, face


def _reachable(ob: SceneObject, dirs, horiz, reach: np.ndarray, frame: np.ndarray):
    """Indices of the rays (``dirs``, horizontal norm ``horiz``, ground reach ``reach`` from
    the sensor) that can reach the bounding circle of the moving object ``ob`` in their frame:
    the angle between a ray's heading and the object's centre is at most the circle's
    half-angle (as a cosine test) and the ray is not on the ground before the circle."""
    lo, hi = ob.rt.bounds
    radius = float(np.hypot(np.maximum(-lo[0], hi[0]), np.maximum(-lo[1], hi[1]))) + 0.05
    px, py = ob.poses[:, 0], ob.poses[:, 1]
    dist = np.hypot(px, py)
    safe = np.maximum(dist, 1e-9)
    half = np.arcsin(np.clip(radius / safe, 0.0, 1.0)) + 1e-3
    cos_half = np.where(dist <= radius, -2.0, np.cos(np.minimum(half, np.pi)))
    ux, uy, near = px / safe, py / safe, dist - radius
    dot = dirs[:, 0] * ux[frame] + dirs[:, 1] * uy[frame]
    return np.flatnonzero((dot >= cos_half[frame] * horiz) & (reach >= near[frame]))


def trace(scene: Scene, dirs: np.ndarray, frame: np.ndarray, cfg: RealConfig,
          rng: np.random.Generator):
    """Rays from the sensor through glass: ``(range (R,), reflectivity (R,), source (R,))``;
    range inf (source -1) where the ray is lost or hits nothing."""
    n = len(dirs)
    rng_out = np.full(n, np.inf)
    rho_out = np.zeros(n)
    src_out = np.full(n, -1, np.int64)
    through = np.zeros(n, bool)
    active = np.arange(n)
    origins = np.zeros((n, 3))
    offset = np.zeros(n)
    n_obj = len(scene.objects)
    rho_tab = [ob.rho for ob in scene.objects]
    for it in range(_MAX_PANES + 1):
        if len(active) == 0:
            break
        t, obj, face = cast_scene(scene, origins[active], dirs[active], frame[active],
                                  offset[active] if it else None)
        glass = np.zeros(len(active), bool)
        opening, loss = np.zeros(len(active)), np.zeros(len(active))
        rho = np.full(len(active), scene.ground_rho)
        src = np.full(len(active), 3, np.int64)
        for j, ob in enumerate(scene.objects):
            on = np.flatnonzero(obj == j)
            glass[on] = ob.glass[face[on]]
            rho[on] = rho_tab[j][face[on]]
            src[on] = ob.source
            if ob.opening is not None:
                opening[on] = ob.opening[face[on]]
            if ob.loss is not None:
                loss[on] = ob.loss[face[on]]
        src[obj < 0] = -1
        # glass: through, back from the pane or lost (glass_pass, glass_return); other faces:
        # through their openings (a grille), lost (a headlamp) or back (everything else)
        p_pass = np.where(glass, cfg.glass_pass, opening)
        p_back = np.where(glass, cfg.glass_return, 1.0 - opening - loss)
        if cfg.incidence_exponent > 0 or cfg.glass_fresnel:
            cos = incidence_cosine(scene, dirs[active], frame[active], obj, face)
            if cfg.incidence_exponent > 0:
                rho *= cos ** cfg.incidence_exponent
            if cfg.glass_fresnel:
                p_pass[glass] *= pane_transmission(cos[glass]) / pane_transmission(1.0)
        u = rng.random(len(active))
        go_on = (u < p_pass) & (it < _MAX_PANES)
        lost = ~go_on & (u >= p_pass + p_back)
        done = ~go_on & ~lost & (obj >= 0) & (obj <= n_obj)
        a = active[done]
        rng_out[a] = offset[a] + t[done]
        rho_out[a] = rho[done]
        src_out[a] = np.where((src[done] == 0) & through[a], 1, src[done])
        nxt = active[go_on]
        step = t[go_on] + _EPS
        origins[nxt] += dirs[nxt] * step[:, None]
        offset[nxt] += step
        through[nxt] |= src[go_on] == 0
        active = nxt
    return rng_out, rho_out, src_out


def pane_transmission(cos_in, n_glass: float = _N_GLASS):
    """Share of unpolarised light a glass pane (two parallel faces, no absorption, no multiple
    reflections) transmits at incidence ``arccos(cos_in)``: Fresnel's equations, mean of s and
    p of ``(1 - R) ** 2``. 0.917 at normal incidence, 0.83 at 60 deg, 0.58 at 75 deg, 0 at 90."""
    ci = np.clip(np.asarray(cos_in, dtype=np.float64), 0.0, 1.0)
    ct = np.sqrt(1.0 - (1.0 - ci**2) / n_glass**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = ((ci - n_glass * ct) / (ci + n_glass * ct)) ** 2
        rp = ((n_glass * ci - ct) / (n_glass * ci + ct)) ** 2
    return np.nan_to_num(0.5 * ((1 - rs) ** 2 + (1 - rp) ** 2))


def incidence_cosine(scene: Scene, dirs: np.ndarray, frame: np.ndarray, obj: np.ndarray,
                     face: np.ndarray) -> np.ndarray:
    """``|cos|`` of the angle between each ray ``dirs`` (R, 3) and the normal of the object
    face it hit (``obj``, ``face`` of :func:`cast_scene`); 1 for the ground and where nothing
    was hit. A moving object's face normal is turned by its yaw in ``frame``.

    The ground keeps 1: rough asphalt backscatters at grazing incidence far better than a
    Lambertian surface (real Argoverse 2 sweeps hold 80-170 ground returns within 2 m of cars
    22-29 m away, where a Lambertian road would leave a few dozen), so its
    ``ground_reflectivity`` is used as an effective value at every angle."""
    cos = np.ones(len(dirs))
    for j, ob in enumerate(scene.objects):
        on = np.flatnonzero(obj == j)
        if len(on) == 0:
            continue
        n = ob.rt.plane_normals[face[on]]
        if ob.poses is not None:
            yaw = ob.poses[frame[on], 3]
            c, s = np.cos(yaw), np.sin(yaw)
            n = np.stack([c * n[:, 0] - s * n[:, 1], s * n[:, 0] + c * n[:, 1], n[:, 2]], 1)
        cos[on] = np.abs(np.einsum("ij,ij->i", n, dirs[on]))
    return cos


def detection_probability(r, rho, sensor: LidarConfig, cfg: RealConfig) -> np.ndarray:
    """``(1 - base_dropout) / (1 + (r / R50) ** k)``, ``R50 = range_10pct sqrt(rho / 0.1)``:
    the received power of a Lambertian target goes as rho / r^2, so equal power at
    ``r ~ sqrt(rho)``."""
    r50 = sensor.range_10pct * np.sqrt(np.asarray(rho) / 0.1)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        p = 1.0 / (1.0 + (np.asarray(r) / r50) ** cfg.detection_sharpness)
    return np.nan_to_num(p) * (1.0 - cfg.base_dropout)


def _edges(rays: Rays, r: np.ndarray, gap: float) -> np.ndarray:
    """Rays whose azimuth neighbour in the same row returns from more than ``gap`` m away."""
    if len(r) < 2:
        return np.zeros(len(r), bool)
    same = rays.row[1:] == rays.row[:-1]
    a, b = r[1:], r[:-1]
    with np.errstate(invalid="ignore"):
        jump = same & (np.isfinite(a) != np.isfinite(b)) | (same & (np.abs(a - b) > gap))
    edge = np.zeros(len(r), bool)
    edge[1:] |= jump
    edge[:-1] |= jump
    return edge


def mixed_returns(scene, rays: Rays, r, rho, src, rot, sensor, cfg, rng):
    """Edge rays re-cast as five samples of the divergence cone (module doc); in place."""
    edge = np.flatnonzero(_edges(rays, r, cfg.edge_gap))
    if len(edge) == 0 or sensor.divergence_mrad <= 0:
        return r, rho, src
    half = sensor.divergence_mrad * 1e-3 / 2
    offs = ((half, 0.0), (-half, 0.0), (0.0, half), (0.0, -half))
    samples_r, samples_rho, samples_src = [r[edge]], [rho[edge]], [src[edge]]
    for de, da in offs:
        d = head_directions(rays.elev[edge] + de, rays.az[edge] + da, rot)
        sr, srho, ssrc = trace(scene, d, rays.frame[edge], cfg, rng)
        samples_r.append(sr)
        samples_rho.append(srho)
        samples_src.append(ssrc)
    sr, srho, ssrc = np.stack(samples_r, 1), np.stack(samples_rho, 1), np.stack(samples_src, 1)
    hit = np.isfinite(sr)
    n_hit = hit.sum(1)
    near = np.argmin(np.where(hit, sr, np.inf), 1)
    rows = np.arange(len(edge))
    r_near = sr[rows, near]
    r_far = np.where(hit, sr, -np.inf).max(1)
    mean = np.where(hit, sr, 0.0).sum(1) / np.maximum(n_hit, 1)
    mix = (n_hit >= 2) & (r_far - r_near > cfg.edge_gap) & (rng.random(len(edge)) < cfg.mixed_prob)
    new_r = np.where(mix, mean, r_near)
    new_r[n_hit * 2 < len(offs) + 1] = np.inf  # less than half the beam's energy returns
    r, rho, src = r.copy(), rho.copy(), src.copy()
    r[edge], rho[edge], src[edge] = new_r, srho[rows, near], ssrc[rows, near]
    src[edge[~np.isfinite(new_r)]] = -1
    return r, rho, src


def scan_scene(scene: Scene, rays: Rays, rot, sensor: LidarConfig, cfg: RealConfig,
               rng: np.random.Generator, n_frames: int):
    """All returns of the scan: per frame ``(points (N, 3) float32, source (N,) int8)``."""
    r, rho, src = trace(scene, rays.dirs, rays.frame, cfg, rng)
    r, rho, src = mixed_returns(scene, rays, r, rho, src, rot, sensor, cfg, rng)
    keep = np.isfinite(r) & sensor.in_range(r)
    keep &= rng.random(len(r)) < detection_probability(np.where(keep, r, 1.0), rho, sensor, cfg)
    idx = np.flatnonzero(keep)
    rr = sensor.noisy_ranges(r[idx], rng)  # the last draw of this generator
    pts = (rays.dirs[idx] * rr[:, None]).astype(np.float32)
    codes = src[idx].astype(np.int8)
    ends = np.searchsorted(rays.frame[idx], np.arange(n_frames + 1))  # frames are sorted
    return [(pts[a:b], codes[a:b]) for a, b in zip(ends[:-1], ends[1:], strict=True)]


# ------------------------------------------------------------------------- tracker crop


def tracker_box(pose, size, jitter: TrackerJitter, rng: np.random.Generator):
    """A tracker-like box around the true ``pose`` (4,) and ``size`` (3,): ``(pose, size)``."""
    p = np.asarray(pose, dtype=np.float64).copy()
    s = np.asarray(size, dtype=np.float64).copy()
    p[:2] += rng.normal(0.0, jitter.centre_std, 2)
    p[2] += rng.normal(0.0, jitter.centre_z_std)
    p[3] += np.deg2rad(rng.normal(0.0, jitter.yaw_std_deg))
    s *= np.exp(rng.normal(0.0, jitter.size_std, 3))
    s += [jitter.enlarge, jitter.enlarge, jitter.enlarge / 2]
    return p, s


def jitter_rng(seed: int, track: int, frame: int) -> np.random.Generator:
    """The generator of the crop jitter of (seed, track, frame)."""
    return np.random.default_rng(np.random.SeedSequence([seed, track, _TAG_JITTER, frame]))


def crop_frames(frames, poses, size, cfg: RealConfig, seed: int, track: int, plane):
    """Cut every frame with :func:`seqshape.data.crop.crop_vehicle` and a jittered box.

    ``frames``: per frame ``(points, source)`` from :func:`scan_scene`; ``plane``: the true
    ground ``(n, d)`` passed as the crop's sweep plane (used only where the local fit fails).
    Returns the cropped points per frame, the boxes used ``(T, 7)`` and per-source counts
    ``(T, len(SOURCES))``.
    """
    points, boxes, counts = [], [], np.zeros((len(frames), len(SOURCES)), np.int64)
    for t, (pts, src) in enumerate(frames):
        bp, bs = tracker_box(poses[t], size, cfg.jitter, jitter_rng(seed, track, t))
        boxes.append(np.concatenate([bp, bs]))
        cut = crop_vehicle(pts, bp, bs, cfg.crop, sweep_plane=plane)
        points.append(cut)
        if len(cut):
            codes = src[_row_index(pts, cut)]
            counts[t] = np.bincount(codes[codes >= 0], minlength=len(SOURCES))[:len(SOURCES)]
    return points, np.asarray(boxes).reshape(-1, 7), counts


def _row_index(rows: np.ndarray, sub: np.ndarray) -> np.ndarray:
    """Index in ``rows`` (N, 3) float32 of every row of ``sub`` (M, 3) (rows taken from it)."""
    key = np.dtype((np.void, 12))
    a = np.ascontiguousarray(rows, dtype=np.float32).view(key).ravel()
    b = np.ascontiguousarray(sub, dtype=np.float32).view(key).ravel()
    order = np.argsort(a, kind="stable")
    pos = np.searchsorted(a[order], b)
    return order[np.minimum(pos, len(a) - 1)]


def scene_rng(seed: int, track: int, tag: int = _TAG_SCENE) -> np.random.Generator:
    """The generator of a track's scene (sensor, mount, ground, clutter, paint) or rays."""
    return np.random.default_rng(np.random.SeedSequence([seed, track, tag]))


def ray_rng(seed: int, track: int) -> np.random.Generator:
    return scene_rng(seed, track, _TAG_RAYS)


def sample_mount(rng: np.random.Generator, cfg: RealConfig):
    """``(sensor, height, pitch, roll, slope_x, slope_y)`` of a track (angles in rad)."""
    w = np.asarray(cfg.sensor_weights, dtype=np.float64)
    sensor = get_sensor(cfg.sensors[int(rng.choice(len(w), p=w / w.sum()))])
    height = float(rng.uniform(*cfg.height_range))
    tilt = np.deg2rad(cfg.tilt_deg)
    pitch, roll = (float(x) for x in rng.uniform(-tilt, tilt, 2))
    sx, sy = (float(x) for x in rng.uniform(-cfg.max_slope, cfg.max_slope, 2))
    return sensor, height, pitch, roll, sx, sy


def scan_bounds(mesh_bounds: np.ndarray, context: float, ground_drop: float) -> np.ndarray:
    """Canonical bounds scanned around a vehicle: grown by ``context`` in x, y and down to
    ``ground_drop`` m below its lowest point."""
    lo, hi = mesh_bounds[0].copy(), mesh_bounds[1].copy()
    lo[:2] -= context
    hi[:2] += context
    lo[2] -= ground_drop
    hi[2] += 0.3
    return np.stack([lo, hi])
