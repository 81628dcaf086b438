"""The per-track work of :mod:`seqshape.sim.generate`, run in-process or in spawned workers.

A worker receives a :class:`WorkerPayload` once (the config, every vehicle's mesh arrays, the
CSV trajectories) and builds meshes, Embree intersectors and complete shapes lazily, caching
them for the vehicles it is given. Everything about track ``i`` is drawn from
``np.random.SeedSequence([seed, i])``, so where it runs does not change it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import trimesh

import seqshape.sim.real as real
from seqshape.data.dataset import manifest_entry
from seqshape.data.track import Track, save_track
from seqshape.errors import DataError
from seqshape.sim.kinematics import footprint_distance, footprints_overlap
from seqshape.sim.raycast import scan_track
from seqshape.sim.sensors import get_sensor, mount_rotation
from seqshape.sim.traffic import EGO_SIZE
from seqshape.sim.trajectories import sample_trajectory
from seqshape.vehicles import sample_outer_surface
from seqshape.vehicles.fleet import FLEET_KINDS

GENERATOR_VERSION = 1  #: recorded in every generated track's meta and the dataset config
MIN_CLEARANCE = 1.5      # m between a sampled vehicle's footprint and the sensor
CSV_MIN_CLEARANCE = 0.5  # m for trajectories read from CSV logs (closer: an error)
_COMPLETE_TAG = 0xC0_3E7E  # seed-sequence tag of the complete shapes


class TrackPlan:
    """Track numbering: track ``i`` is trajectory ``j`` of vehicle ``v``, ``i = v * tpv + j``."""

    def __init__(self, config, vehicle_ids: list[str], splits: list[str]):
        self.tpv = config.tracks_per_vehicle
        self.vehicle_ids = list(vehicle_ids)
        self.splits = list(splits)
        self.n_tracks = len(vehicle_ids) * self.tpv

    def track_indices(self, v: int) -> range:
        return range(v * self.tpv, (v + 1) * self.tpv)

    def track_id(self, i: int) -> str:
        v, j = divmod(i, self.tpv)
        return f"{self.vehicle_ids[v]}-{j:02d}"


@dataclass
class WorkerPayload:
    """What a worker needs, picklable: config, per-vehicle (id, kind, source, V, F), splits;
    for the real path also per-vehicle face labels and annotator box sizes (None: unknown)."""

    config: object
    vehicles: list[tuple[str, str, str, np.ndarray, np.ndarray]]
    splits: list[str]
    logs: list
    face_labels: list | None = None
    box_sizes: list | None = None

    @classmethod
    def build(cls, config, vehicles, splits, logs) -> WorkerPayload:
        real = getattr(config, "real", None) is not None
        return cls(config, [(v.vehicle_id, v.kind, v.source,
                             np.asarray(v.mesh.vertices, dtype=np.float64),
                             np.asarray(v.mesh.faces, dtype=np.int64)) for v in vehicles],
                   list(splits), list(logs),
                   [getattr(v, "face_labels", None) for v in vehicles] if real else None,
                   [getattr(v, "box_size", None) for v in vehicles] if real else None)


_STATE: dict = {}


def init_worker(payload: WorkerPayload) -> None:
    """Install the payload in this process and reset the per-vehicle caches."""
    sensor = get_sensor(payload.config.sensor)
    _STATE.clear()
    _STATE.update(payload=payload, meshes={}, complete={},
                  sensor=sensor if payload.config.noise else sensor.without_noise(),
                  plan=TrackPlan(payload.config, [v[0] for v in payload.vehicles],
                                 payload.splits))


def _mesh(v: int):
    meshes = _STATE["meshes"]
    if v not in meshes:
        _, _, _, verts, faces = _STATE["payload"].vehicles[v]
        meshes[v] = trimesh.Trimesh(verts, faces, process=False)
    return meshes[v]


def _complete(v: int) -> np.ndarray:
    cache = _STATE["complete"]
    if v not in cache:
        cfg = _STATE["payload"].config
        seed = int(np.random.SeedSequence([cfg.seed, _COMPLETE_TAG, v]).generate_state(1)[0])
        cache[v] = sample_outer_surface(_mesh(v), cfg.num_points, seed)
    return cache[v]


def _ground_z(mesh, sensor) -> float:
    """Pose z that puts the mesh's lowest point on the ground (``z = -sensor.height``)."""
    return float(-sensor.height - mesh.bounds[0, 2])


def _trajectory(i: int, rng, size):
    cfg, sensor = _STATE["payload"].config, _STATE["sensor"]
    logs = _STATE["payload"].logs
    if logs:
        traj = logs[i % len(logs)]
        gap = footprint_distance(traj.x, traj.y, traj.yaw, size[0], size[1])
        if gap.min() < CSV_MIN_CLEARANCE:
            t = int(np.argmin(gap))
            raise DataError(traj.source, f"vehicle of length {size[0]:.2f} m would overlap the "
                                         f"sensor at t={traj.t[t]:g} s (x={traj.x[t]:.2f}, "
                                         f"y={traj.y[t]:.2f}); trajectories are in the sensor "
                                         f"frame and must keep clear of the origin")
        return traj
    return sample_trajectory(rng, length=size[0], width=size[1], rate_hz=sensor.rate_hz,
                                min_distance=cfg.min_distance, max_distance=cfg.max_distance,
                                min_clearance=MIN_CLEARANCE, min_frames=cfg.min_frames,
                                max_frames=cfg.max_frames, mean_frames=cfg.mean_frames,
                                placement=getattr(cfg, "placement", "crossing"))


def _ego_blocker(ego_x, slope_x: float = 0.0):
    """The ego car as a ``(poses (T, 4), size)`` blocker in the first frame's sensor frame
    (None without ego motion data: the crossing placement)."""
    if ego_x is None:
        return None
    poses = np.zeros((len(ego_x), 4))
    poses[:, 0], poses[:, 2] = ego_x, slope_x * ego_x
    return poses, np.array([*EGO_SIZE, 1.5])


def _occluder_poses(rng, poses, size, occ_size, parked: bool, ego_x=None):
    """Candidate occluder poses ``(T, 4)``: a neighbour lane / parking slot or a free track."""
    cfg, sensor = _STATE["payload"].config, _STATE["sensor"]
    if rng.random() < 0.5:
        if parked:
            lon, lat = rng.choice([-1, 1]) * rng.uniform(5.5, 8.0), rng.normal(0.0, 0.2)
        else:
            lon, lat = rng.uniform(-12, 12), rng.choice([-1, 1]) * rng.uniform(3.2, 4.0)
        c, s = np.cos(poses[:, 3]), np.sin(poses[:, 3])
        out = poses.copy()
        out[:, 0] += c * lon - s * lat
        out[:, 1] += s * lon + c * lat
        return out
    if ego_x is None:
        tr = sample_trajectory(rng, n_frames=len(poses), length=occ_size[0], width=occ_size[1],
                               rate_hz=sensor.rate_hz, min_distance=cfg.min_distance,
                               max_distance=cfg.max_distance, min_clearance=MIN_CLEARANCE)
    else:  # traffic: another road user seen from the same moving ego
        tr = sample_trajectory(rng, n_frames=len(poses), length=occ_size[0], width=occ_size[1],
                               rate_hz=sensor.rate_hz, min_distance=cfg.min_distance,
                               max_distance=cfg.max_distance, min_clearance=MIN_CLEARANCE,
                               placement="traffic", ego_x=ego_x)
    return tr.poses(0.0)


def _occluders(rng, v: int, poses, size, parked: bool, ego_x=None):
    """Up to ``max_occluders`` other vehicles of the same split that never collide (nor touch
    the ego car when ``ego_x`` is given: the traffic placement)."""
    cfg, sensor, splits = _STATE["payload"].config, _STATE["sensor"], _STATE["payload"].splits
    pool = [u for u in range(len(splits)) if u != v and splits[u] == splits[v]]
    if not pool or cfg.max_occluders == 0:
        return [], []
    placed, ids = [], []
    for _ in range(int(rng.integers(0, cfg.max_occluders + 1))):
        u = int(pool[rng.integers(len(pool))])
        mesh = _mesh(u)
        occ_size = mesh.extents
        for _attempt in range(8):
            cand = _occluder_poses(rng, poses, size, occ_size, parked, ego_x)
            cand[:, 2] = _ground_z(mesh, sensor)
            clear = footprint_distance(cand[:, 0], cand[:, 1], cand[:, 3], occ_size[0],
                                       occ_size[1]).min() >= MIN_CLEARANCE
            others = [(poses, size)] + [(p, m.extents) for m, p in placed]
            if ego_x is not None:  # the ego car, in each frame's sensor frame
                others.append((np.zeros_like(poses), _ego_blocker(ego_x)[1]))
            if clear and not any(footprints_overlap(p, s, cand, occ_size).any()
                                 for p, s in others):
                placed.append((mesh, cand))
                ids.append(_STATE["payload"].vehicles[u][0])
                break
    return placed, ids


def make_track(i: int) -> Track:
    """Track ``i`` of the plan (see :class:`TrackPlan`), fully determined by (seed, i)."""
    payload, sensor, plan = _STATE["payload"], _STATE["sensor"], _STATE["plan"]
    cfg = payload.config
    if getattr(cfg, "real", None) is not None:
        return make_real_track(i)
    v = i // plan.tpv
    vid, kind, source = payload.vehicles[v][:3]
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, i]))
    mesh = _mesh(v)
    size = np.asarray(mesh.extents, dtype=np.float64)
    traj = _trajectory(i, rng, size)
    poses = traj.poses(_ground_z(mesh, sensor))
    occ, occ_ids = _occluders(rng, v, poses, size, traj.manoeuvre == "parked", traj.ego_x)
    points = scan_track(mesh, poses, sensor, rng, occ, cfg.ground)
    meta = {"mesh_id": vid, "kind": kind, "source": source, "sensor": sensor.name,
            "split": payload.splits[v], "generator": "seqshape.sim.generate",
            "generator_version": GENERATOR_VERSION, "preset": cfg.name, "seed": cfg.seed,
            "track_index": i, "manoeuvre": traj.manoeuvre, "trajectory_source": traj.source,
            "ground": cfg.ground, "noise": cfg.noise, "occluders": occ_ids,
            **_traffic_meta(traj, 0.0)}
    return Track(plan.track_id(i), points, poses, _complete(v), size, traj.t, meta)


def _traffic_meta(traj, slope_x: float) -> dict:
    """``placement``, ``situation`` and ``ego_poses`` (per frame the (4, 4) sensor frame ->
    first frame's sensor frame, as `seqshape.data.extract` writes it) of a traffic track;
    nothing for the crossing placement (older presets' meta unchanged)."""
    if traj.ego_x is None:
        return {}
    return {"placement": "traffic", "situation": traj.situation,
            "ego_poses": traj.ego_poses(slope_x).tolist()}


def make_real_track(i: int) -> Track:
    """Track ``i`` on the real path (:mod:`seqshape.sim.real`): scene scan, tracker-box crop."""
    payload, plan = _STATE["payload"], _STATE["plan"]
    cfg = payload.config
    rc = cfg.real
    v = i // plan.tpv
    vid, kind, source = payload.vehicles[v][:3]
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, i]))
    srng = real.scene_rng(cfg.seed, i)
    mesh = _mesh(v)
    size = np.asarray(mesh.extents, dtype=np.float64)
    sensor, height, pitch, roll, sx, sy = real.sample_mount(srng, rc)
    n, d = real.ground_plane(height, sx, sy)
    traj = _trajectory(i, rng, size)
    poses = traj.poses(0.0)
    poses[:, 2] = real.ground_height(n, d, poses[:, 0], poses[:, 1]) - mesh.bounds[0, 2]
    occ, occ_ids = _occluders(rng, v, poses, size, traj.manoeuvre == "parked", traj.ego_x)
    index = {u[0]: k for k, u in enumerate(payload.vehicles)}
    labels = payload.face_labels or [None] * len(payload.vehicles)
    paint, grille = real.sample_paint(srng, rc), real.sample_grille(srng, rc)
    objects = [real.vehicle_object(mesh, poses, labels[v], paint, rc, 0, grille)]
    for (m, p), oid in zip(occ, occ_ids, strict=True):
        p[:, 2] = real.ground_height(n, d, p[:, 0], p[:, 1]) - m.bounds[0, 2]
        paint, grille = real.sample_paint(srng, rc), real.sample_grille(srng, rc)
        objects.append(real.vehicle_object(m, p, labels[index[oid]], paint, rc, 2, grille))
    clutter, extra = _static_clutter(srng, poses, size, occ, traj.ego_x, sx, (n, d), rc)
    objects += extra
    scene = real.Scene(objects, n, d, float(srng.uniform(*rc.ground_reflectivity)))
    rot = mount_rotation(pitch, roll)
    drop = 0.5 + rc.max_slope * (size[0] / 2 + rc.context) * 2
    rays = real.scan_rays(sensor, mesh.bounds, poses, rot, abs(pitch) + abs(roll), rc.context,
                          drop)
    frames = real.scan_scene(scene, rays, rot, sensor, rc, real.ray_rng(cfg.seed, i), len(poses))
    box = payload.box_sizes[v] if payload.box_sizes and payload.box_sizes[v] is not None else size
    points, boxes, counts = real.crop_frames(frames, poses, np.asarray(box, dtype=np.float64), rc,
                                             cfg.seed, i, (n, d))
    meta = {"mesh_id": vid, "kind": kind, "source": source, "sensor": sensor.name,
            "split": payload.splits[v], "generator": "seqshape.sim.generate",
            "generator_version": GENERATOR_VERSION, "preset": cfg.name, "seed": cfg.seed,
            "track_index": i, "manoeuvre": traj.manoeuvre, "trajectory_source": traj.source,
            "ground": True, "noise": True, "occluders": occ_ids, "class": _vehicle_class(kind),
            "real": {"sensor_height": height, "pitch_deg": float(np.degrees(pitch)),
                     "roll_deg": float(np.degrees(roll)), "ground_slope": [sx, sy],
                     "paint_reflectivity": paint, "clutter": [k for _, _, k in clutter],
                     "ground_reflectivity": scene.ground_rho},
            "jitter": asdict(rc.jitter), "crop": rc.crop.to_dict(),
            "crop_boxes": np.round(boxes, 4).tolist(),
            "sources": {name: counts[:, k].tolist() for k, name in enumerate(real.SOURCES)},
            **_traffic_meta(traj, sx)}
    return Track(plan.track_id(i), points, poses, _complete(v), size, traj.t, meta)


def _static_clutter(srng, poses, size, occ, ego_x, slope_x: float, plane, rc):
    """The clutter of a real track: ``(real.sample_clutter's list, scene objects (0 or 1))``.

    Clutter stands still in the world: with ego motion (``ego_x``) it is sampled in the first
    frame's sensor frame, around the vehicles' poses moved there (the ego car's swept footprint
    is a blocker too), and moves by ``-ego`` in each frame's sensor frame; the ground plane is
    the same in every frame (the ego drives along it). Without ``ego_x``: the sensor frame.
    """
    blockers = [(poses, size)] + [(p, m.extents) for m, p in occ]
    ego = _ego_blocker(ego_x, slope_x)
    shift = None
    if ego is not None:
        shift = ego[0][:, :3]  # (T, 3) ego position in the first frame's sensor frame
        blockers = [(_moved(p, shift), s) for p, s in blockers] + [ego]
        poses = _moved(poses, shift)
    clutter = real.sample_clutter(srng, poses, size, blockers, *plane, rc)
    obj = real.clutter_object(clutter)
    if obj is None:
        return clutter, []
    if shift is not None and np.ptp(shift[:, 0]) > 0:
        obj.poses = np.concatenate([-shift, np.zeros((len(shift), 1))], 1)  # (T, 4)
    return clutter, [obj]


def _moved(poses, shift):
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, :3] += shift
    return out


def _vehicle_class(kind: str) -> str | None:
    """seqshape's vehicle class of a fleet or procedural kind (None for user meshes)."""
    if kind in FLEET_KINDS:
        return FLEET_KINDS[kind]
    return {"van": "van", "user": None}.get(kind, "car")


def work_unit(unit) -> list[dict]:
    """Generate and save the tracks ``indices`` of vehicle ``v`` into ``out``; their entries."""
    _v, indices, out = unit
    entries = []
    for i in indices:
        track = make_track(i)
        file = f"tracks/{track.track_id}.npz"
        save_track(Path(out) / file, track)
        entries.append(manifest_entry(track, file))
    return entries
