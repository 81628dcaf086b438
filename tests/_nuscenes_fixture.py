"""Write a tiny nuScenes dataset in the official v1.0 schema (for tests).

Tables (``VERSION/*.json``): scene, sample, sample_data, sample_annotation, instance, category,
attribute, visibility, calibrated_sensor, ego_pose, sensor, log, map; LiDAR keyframes
``samples/LIDAR_TOP/*.pcd.bin`` (float32 x y z intensity ring); camera keyframes
``samples/CAM_*/*.jpg``; a RADAR_FRONT keyframe record and LIDAR_TOP sweeps between keyframes
(tables only: the reader must ignore them).

Everything here is computed independently of :mod:`seqshape.data.nuscenes`: rotations with
``scipy.spatial.transform.Rotation`` (scalar-LAST quaternions, converted to nuScenes'
scalar-first ``[w, x, y, z]`` on writing), the LiDAR points of a box placed the way the devkit
goes (global -> ego -> LiDAR), and ``num_lidar_pts`` counted like the devkit's
``points_in_box`` (box brought into the LiDAR frame, points tested against its corners).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from seqshape._io import atomic_write_json

#: nuScenes' LIDAR_TOP calibration (scene-0061): about -90 degrees about z.
LIDAR_TOP = {"translation": [0.943713, 0.0, 1.84023],
             "rotation": [0.7077955119163518, -0.006492242056004365, 0.010646214713995808,
                          -0.7063073142877817]}
#: camera calibrations close to nuScenes' (the car of scene-0061).
CAMERAS = {
    "CAM_FRONT": {
        "translation": [1.70079118954, 0.0159456324149, 1.51095763913],
        "rotation": [0.4998015430569128, -0.5030316162024876, 0.4997798114386805,
                     -0.49737083824542755],
        "camera_intrinsic": [[1266.417203046554, 0.0, 816.2670197447984],
                             [0.0, 1266.417203046554, 491.50706579294757], [0.0, 0.0, 1.0]]},
    "CAM_FRONT_LEFT": {
        "translation": [1.52387798135, 0.494631336551, 1.50932822144],
        "rotation": [0.6757265034669446, -0.6736266522251881, 0.21214015046209478,
                     -0.21122827103904068],
        "camera_intrinsic": [[1272.5979470598488, 0.0, 826.6154927353808],
                             [0.0, 1272.5979470598488, 479.75165386361925], [0.0, 0.0, 1.0]]},
}
IMAGE_SIZE = (1600, 900)

CATEGORIES = (
    "animal", "human.pedestrian.adult", "human.pedestrian.child",
    "human.pedestrian.construction_worker", "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer", "human.pedestrian.stroller",
    "human.pedestrian.wheelchair", "movable_object.barrier", "movable_object.debris",
    "movable_object.pushable_pullable", "movable_object.trafficcone",
    "static_object.bicycle_rack", "vehicle.bicycle", "vehicle.bus.bendy", "vehicle.bus.rigid",
    "vehicle.car", "vehicle.construction", "vehicle.emergency.ambulance",
    "vehicle.emergency.police", "vehicle.motorcycle", "vehicle.trailer", "vehicle.truck")
ATTRIBUTES = ("vehicle.moving", "vehicle.stopped", "vehicle.parked", "pedestrian.moving",
              "pedestrian.standing", "cycle.with_rider")
VISIBILITY = {"1": "v0-40", "2": "v40-60", "3": "v60-80", "4": "v80-100"}
LOGFILE = "n015-2018-07-24-11-22-45+0800"


def token(*parts) -> str:
    """A deterministic 32-hex-digit token, like nuScenes'."""
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def quat_wxyz(rot: Rotation) -> list[float]:
    x, y, z, w = rot.as_quat()
    return [float(w), float(x), float(y), float(z)]


def rot_wxyz(q) -> Rotation:
    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w])


def yaw_rotation(yaw: float, roll: float = 0.0, pitch: float = 0.0) -> Rotation:
    """R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return Rotation.from_euler("ZYX", [yaw, pitch, roll])


@dataclass
class BoxSpec:
    """A box in the GLOBAL frame: centre, yaw (or a full rotation), size [w, l, h]."""

    instance: str
    category: str
    translation: tuple
    yaw: float
    size_wlh: tuple = (1.9, 4.5, 1.6)
    n_inside: int = 40
    visibility: str = "4"
    attributes: tuple = ("vehicle.parked",)
    rotation: Rotation | None = None

    @property
    def rot(self) -> Rotation:
        return self.rotation if self.rotation is not None else yaw_rotation(self.yaw)


@dataclass
class FrameSpec:
    """One keyframe: the ego pose at the LiDAR time, and per camera the ego motion to the
    image time (``(dt_us, forward_m, dyaw)`` in the ego frame)."""

    timestamp_us: int
    ego_translation: tuple
    ego_yaw: float
    ego_roll_pitch: tuple = (0.0, 0.0)
    boxes: list = field(default_factory=list)
    camera_motion: dict = field(default_factory=dict)

    @property
    def ego_rot(self) -> Rotation:
        return yaw_rotation(self.ego_yaw, *self.ego_roll_pitch)


@dataclass
class Fixture:
    root: Path
    version: str
    samples: dict          # scene name -> [sample token]
    points: dict           # (scene, frame) -> (N, 5) float32 as written (LiDAR frame)
    counts: dict           # (scene, frame, instance) -> num_lidar_pts written
    specs: dict            # scene name -> [FrameSpec]
    lidar_files: dict      # (scene, frame) -> Path


def _in_box_devkit(points: np.ndarray, centre, rot: Rotation, wlh) -> np.ndarray:
    """The devkit's points_in_box: corners of the box, then projections on its edges."""
    w, length, h = wlh
    xs = length / 2 * np.array([1, 1, 1, 1, -1, -1, -1, -1])
    ys = w / 2 * np.array([1, -1, -1, 1, 1, -1, -1, 1])
    zs = h / 2 * np.array([1, 1, -1, -1, 1, 1, -1, -1])
    corners = rot.apply(np.c_[xs, ys, zs]) + centre  # (8, 3)
    p1, p_x, p_y, p_z = corners[0], corners[4], corners[1], corners[3]
    i, j, k = p1 - p_x, p1 - p_y, p1 - p_z
    v = points - p1
    iv, jv, kv = v @ i, v @ j, v @ k
    return ((0 >= iv) & (iv >= -(i @ i)) & (0 >= jv) & (jv >= -(j @ j))
            & (0 >= kv) & (kv >= -(k @ k)))


def global_to_lidar(points, frame: FrameSpec, lidar=LIDAR_TOP) -> np.ndarray:
    """Global points -> LiDAR frame at the keyframe (devkit order)."""
    ego = frame.ego_rot.inv().apply(np.asarray(points, float) - np.asarray(frame.ego_translation))
    return rot_wxyz(lidar["rotation"]).inv().apply(ego - np.asarray(lidar["translation"]))


def camera_ego_pose(frame: FrameSpec, channel: str) -> tuple[np.ndarray, Rotation]:
    """(translation, rotation) of the ego at the camera's image time."""
    _, forward, dyaw = frame.camera_motion.get(channel, (0, 0.0, 0.0))
    rot = frame.ego_rot
    return (np.asarray(frame.ego_translation, float) + rot.apply([forward, 0.0, 0.0]),
            yaw_rotation(dyaw) * rot)


def default_scenes() -> dict[str, list[FrameSpec]]:
    """Two scenes: scene-0061 (3 keyframes: a parked car, a moving truck, a pedestrian, a
    bendy bus) and scene-0103 (2 keyframes, one ambulance)."""
    frames = []
    heading = 0.6
    for k in range(3):
        ego_xy = np.array([400.0, 1100.0]) + 2.5 * k * np.array([np.cos(heading), np.sin(heading)])
        truck_xy = ego_xy + [12.0 + 0.5 * k, 6.0]
        frames.append(FrameSpec(
            timestamp_us=1532402927647951 + 500_000 * k,
            ego_translation=(*ego_xy, 0.3), ego_yaw=heading + 0.02 * k,
            ego_roll_pitch=(0.01, -0.015),
            camera_motion={"CAM_FRONT": (12_000, 0.06, 0.001),
                           "CAM_FRONT_LEFT": (-20_000, -0.1, -0.002)},
            boxes=[BoxSpec("parked-car", "vehicle.car", (412.0, 1108.0, 1.0), 1.2),
                   BoxSpec("truck", "vehicle.truck", (*truck_xy, 1.5), heading + 0.1,
                           size_wlh=(2.5, 7.0, 3.0), n_inside=80, visibility="3",
                           attributes=("vehicle.moving",)),
                   BoxSpec("walker", "human.pedestrian.adult", (405.0, 1096.0, 0.9), -0.4,
                           size_wlh=(0.6, 0.7, 1.8), n_inside=10, visibility="2",
                           attributes=("pedestrian.moving",)),
                   BoxSpec("bus", "vehicle.bus.bendy", (380.0, 1090.0, 1.8), 2.0,
                           size_wlh=(2.9, 18.0, 3.4), n_inside=60, visibility="1",
                           attributes=("vehicle.stopped",))]))
    other = [FrameSpec(timestamp_us=1533151603547590 + 500_000 * k,
                       ego_translation=(1200.0 + 3.0 * k, 800.0, 0.0), ego_yaw=0.0,
                       boxes=[BoxSpec("ambulance", "vehicle.emergency.ambulance",
                                      (1215.0, 803.0, 1.2), 0.1, size_wlh=(2.2, 6.0, 2.6))])
             for k in range(2)]
    return {"scene-0061": frames, "scene-0103": other}


class _Tables:
    def __init__(self):
        self.t = {name: [] for name in (
            "scene", "sample", "sample_data", "sample_annotation", "instance", "category",
            "attribute", "visibility", "calibrated_sensor", "ego_pose", "sensor", "log", "map")}

    def add(self, table: str, **rec) -> str:
        self.t[table].append(rec)
        return rec["token"]


def write_nuscenes(root, scenes: dict[str, list[FrameSpec]] | None = None,
                   version: str = "v1.0-mini", lidar=LIDAR_TOP, cameras=None,
                   n_background: int = 300, images: bool = True, seed: int = 0) -> Fixture:
    """Write ``scenes`` (default :func:`default_scenes`) under ``root`` in the official
    layout; returns what was written (tokens, LiDAR points, num_lidar_pts counts)."""
    root = Path(root)
    scenes = default_scenes() if scenes is None else scenes
    cameras = CAMERAS if cameras is None else cameras
    rng = np.random.default_rng(seed)
    tb = _Tables()
    fx = Fixture(root, version, {}, {}, {}, scenes, {})
    cat_tok = {c: tb.add("category", token=token("cat", c), name=c, description=c)
               for c in CATEGORIES}
    for a in ATTRIBUTES:
        tb.add("attribute", token=token("attr", a), name=a, description=a)
    for tok, level in VISIBILITY.items():
        tb.add("visibility", token=tok, level=level, description=f"visibility {level}")
    log_tok = tb.add("log", token=token("log"), logfile=LOGFILE, vehicle="n015",
                     date_captured="2018-07-24", location="singapore-onenorth")
    tb.add("map", token=token("map"), log_tokens=[log_tok], category="semantic_prior",
           filename="maps/53992ee3023e5494b90c316c183be829.png")
    calib = {}
    for channel, modality, cal in ([("LIDAR_TOP", "lidar", lidar),
                                    ("RADAR_FRONT", "radar", {"translation": [3.4, 0.0, 0.5],
                                                              "rotation": [1.0, 0, 0, 0]})]
                                   + [(c, "camera", cal) for c, cal in cameras.items()]):
        s_tok = tb.add("sensor", token=token("sensor", channel), channel=channel,
                       modality=modality)
        calib[channel] = tb.add("calibrated_sensor", token=token("calib", channel),
                                sensor_token=s_tok, translation=list(cal["translation"]),
                                rotation=list(cal["rotation"]),
                                camera_intrinsic=cal.get("camera_intrinsic", []))
    instances: dict[str, list[str]] = {}
    inst_cat: dict[str, str] = {}
    for name, frames in scenes.items():
        _write_scene(tb, fx, rng, name, frames, log_tok, calib, cameras, lidar, n_background,
                     images, instances, inst_cat)
    _link_annotations(tb, instances)
    for inst, anns in instances.items():
        tb.add("instance", token=token("inst", inst), category_token=cat_tok[inst_cat[inst]],
               nbr_annotations=len(anns), first_annotation_token=anns[0],
               last_annotation_token=anns[-1])
    for table, records in tb.t.items():
        atomic_write_json(root / version / f"{table}.json", records, indent=None)
    return fx


def _write_scene(tb, fx, rng, name, frames, log_tok, calib, cameras, lidar, n_background,
                 images, instances, inst_cat):
    scene_tok = token("scene", name)
    samples = [token("sample", name, k) for k in range(len(frames))]
    fx.samples[name] = samples
    channel_records: dict[str, list[dict]] = {}
    for k, frame in enumerate(frames):
        tb.add("sample", token=samples[k], timestamp=frame.timestamp_us, scene_token=scene_tok,
               prev=samples[k - 1] if k else "", next=samples[k + 1] if k + 1 < len(frames) else "")
        pts, counts = _lidar_points(rng, frame, lidar, n_background)
        rel = f"samples/LIDAR_TOP/{LOGFILE}__LIDAR_TOP__{frame.timestamp_us}.pcd.bin"
        path = fx.root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        pts.astype("<f4").tofile(path)
        fx.points[name, k], fx.lidar_files[name, k] = pts, path
        _sample_data(tb, channel_records, "LIDAR_TOP", samples[k], calib, rel, frame.timestamp_us,
                     frame.ego_translation, frame.ego_rot, True, 0, 0)
        if k + 1 < len(frames):  # one sweep between keyframes (ignored by the reader)
            ts = frame.timestamp_us + 250_000
            _sample_data(tb, channel_records, "LIDAR_TOP", samples[k + 1], calib,
                         f"sweeps/LIDAR_TOP/{LOGFILE}__LIDAR_TOP__{ts}.pcd.bin", ts,
                         frame.ego_translation, frame.ego_rot, False, 0, 0)
        _sample_data(tb, channel_records, "RADAR_FRONT", samples[k], calib,
                     f"samples/RADAR_FRONT/{LOGFILE}__RADAR_FRONT__{frame.timestamp_us}.pcd",
                     frame.timestamp_us, frame.ego_translation, frame.ego_rot, True, 0, 0)
        for channel in cameras:
            dt = frame.camera_motion.get(channel, (0, 0.0, 0.0))[0]
            ts = frame.timestamp_us + dt
            rel = f"samples/{channel}/{LOGFILE}__{channel}__{ts}.jpg"
            if images:
                _write_jpg(fx.root / rel)
            t, r = camera_ego_pose(frame, channel)
            _sample_data(tb, channel_records, channel, samples[k], calib, rel, ts, t, r, True,
                         *IMAGE_SIZE)
        for box in frame.boxes:
            ann = token("ann", name, k, box.instance)
            instances.setdefault(box.instance, []).append(ann)
            inst_cat[box.instance] = box.category
            fx.counts[name, k, box.instance] = counts[box.instance]
            tb.add("sample_annotation", token=ann, sample_token=samples[k],
                   instance_token=token("inst", box.instance),
                   visibility_token=box.visibility,
                   attribute_tokens=[token("attr", a) for a in box.attributes],
                   translation=[float(v) for v in box.translation],
                   size=[float(v) for v in box.size_wlh], rotation=quat_wxyz(box.rot),
                   prev="", next="", num_lidar_pts=int(counts[box.instance]), num_radar_pts=0)
    for recs in channel_records.values():
        recs.sort(key=lambda r: r["timestamp"])
        for a, b in zip(recs[:-1], recs[1:], strict=True):
            a["next"], b["prev"] = b["token"], a["token"]
    tb.add("scene", token=scene_tok, log_token=log_tok, nbr_samples=len(frames),
           first_sample_token=samples[0], last_sample_token=samples[-1], name=name,
           description=f"fixture {name}")


def _sample_data(tb, channel_records, channel, sample_tok, calib, filename, ts, ego_t, ego_r,
                 key, width, height):
    ego_tok = tb.add("ego_pose", token=token("ego", channel, ts), timestamp=ts,
                     translation=[float(v) for v in ego_t], rotation=quat_wxyz(ego_r))
    rec = {"token": token("sd", channel, ts), "sample_token": sample_tok,
           "ego_pose_token": ego_tok, "calibrated_sensor_token": calib[channel],
           "timestamp": ts, "fileformat": filename.rsplit(".", 1)[-1]
           if not filename.endswith(".pcd.bin") else "pcd",
           "is_key_frame": key, "height": height, "width": width, "filename": filename,
           "prev": "", "next": ""}
    tb.t["sample_data"].append(rec)
    channel_records.setdefault(channel, []).append(rec)


def _lidar_points(rng, frame: FrameSpec, lidar, n_background):
    """LiDAR-frame points (N, 5): background plus ``n_inside`` per box; per-box devkit counts."""
    r = rng.uniform(3.0, 40.0, n_background)
    a = rng.uniform(-np.pi, np.pi, n_background)
    parts = [np.c_[r * np.cos(a), r * np.sin(a), rng.uniform(-1.9, 0.5, n_background)]]
    for box in frame.boxes:
        w, length, h = box.size_wlh
        local = rng.uniform(-0.45, 0.45, (box.n_inside, 3)) * [length, w, h]
        parts.append(global_to_lidar(box.rot.apply(local) + box.translation, frame, lidar))
    xyz = np.concatenate(parts).astype(np.float32)
    n = len(xyz)
    pts = np.c_[xyz, rng.integers(0, 256, n), rng.integers(0, 32, n)].astype(np.float32)
    counts = {}
    ego_inv = frame.ego_rot.inv()
    lidar_inv = rot_wxyz(lidar["rotation"]).inv()
    for box in frame.boxes:  # devkit: box.translate(-ego), rotate(ego^-1), ... into the LiDAR
        centre = lidar_inv.apply(ego_inv.apply(np.asarray(box.translation) -
                                               frame.ego_translation) - lidar["translation"])
        rot = lidar_inv * ego_inv * box.rot
        counts[box.instance] = int(_in_box_devkit(pts[:, :3].astype(float), centre, rot,
                                                  box.size_wlh).sum())
    return pts, counts


def _link_annotations(tb, instances):
    by_tok = {rec["token"]: rec for rec in tb.t["sample_annotation"]}
    for anns in instances.values():
        for a, b in zip(anns[:-1], anns[1:], strict=True):
            by_tok[a]["next"], by_tok[b]["prev"] = b, a


def _write_jpg(path: Path) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.zeros((IMAGE_SIZE[1], IMAGE_SIZE[0], 3), np.uint8)
    img[::50] = 255
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    path.write_bytes(buf.tobytes())
