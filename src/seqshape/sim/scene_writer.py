"""Write camera + LiDAR scenes in the KITTI tracking layout with exact amodal ground truth.

One output folder (``seqshape scenes --out DIR``)::

    scene.json                 generator settings (checked on resume)
    scene/SSSS.json            the sequence's layout: road, ego and vehicle world poses, mesh
                               sources (rebuild with :func:`load_scene`); written LAST, it marks
                               the sequence complete
    velodyne/SSSS/FFFFFF.bin   all returns (vehicles + ground), x y z reflectance
    image_02/SSSS/FFFFFF.png   rendered image (1242 x 375)
    label_02/SSSS.txt          Car / Van boxes of the vehicles in the image
    calib/SSSS.txt, oxts/SSSS.txt
    amodal/SSSS.json           exact KINS ground truth (seqshape.data.kins)
    instances_2d/SSSS.json     visible masks as a 2D segmenter would give them (COCO)

Determinism: every random draw comes from ``numpy.random.default_rng([seed, sequence, ...])``,
so a sequence's files do not depend on ``--workers``, ``--shard`` or on which sequences were
resumed. Settings check, resume, shards and the worker pool are :mod:`seqshape._runner`'s (the
work unit is one sequence; shard ``K/N`` takes the sequences with ``index % N == K - 1``).

Label rules (per frame, per vehicle k, areas in pixels, see :mod:`seqshape.sim.render`):

* a vehicle is labelled in ``label_02`` when its amodal mask covers at least one image pixel;
  ``truncated = 1 - amodal_in_image / amodal_on_extended_plane``; with the occluded fraction
  ``f = 1 - visible / amodal_in_image``: ``occluded`` = 0 if f <= 0.05, 1 if f <= 0.5, 2 if
  f < 1, 3 (unknown) if nothing is visible; the 2D box is the amodal mask's extent in the
  image (pixel edges: ``[min_u - 0.5, min_v - 0.5, max_u + 0.5, max_v + 0.5]`` clipped to
  ``[0, W - 1] x [0, H - 1]``);
* it goes into ``amodal/`` and ``instances_2d/`` when its visible area is at least
  ``min_visible_area`` (default :data:`MIN_VISIBLE_AREA` px); the KINS annotation also lists
  ``occluded_by``, the track ids owning pixels of its amodal mask that it does not own.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from seqshape._io import atomic_write_bytes, atomic_write_json
from seqshape._runner import check_settings, plan_work, run_pool
from seqshape._version import __version__
from seqshape.camera import kitti_default_calib, write_calib
from seqshape.data import kitti
from seqshape.data.categories import KITTI_TYPE_TO_KINS
from seqshape.data.kins import (
    coco_annotation,
    image_entry,
    kins_annotation,
    occlusion_order,
    write_coco_instances,
    write_kins,
)
from seqshape.data.kitti import KittiLabel, pose_to_label_fields, poses_to_oxts
from seqshape.data.track import Track
from seqshape.errors import ConfigError, DataError
from seqshape.geometry import pose_to_matrix
from seqshape.sim.degrade import NO_DEGRADE, Instance2D, degrade_instances
from seqshape.sim.render import camera_rays, render_camera, render_lidar
from seqshape.sim.scenes import Agent, LayoutConfig, Road, Scene, build_scene, ground_material
from seqshape.sim.sensors import get_sensor
from seqshape.vehicles import procedural_vehicle, vehicle_library

log = logging.getLogger(__name__)

SCENE_FORMAT, SCENE_VERSION = "seqshape-scenes", 1
SETTINGS_FILE = "scene.json"
MIN_VISIBLE_AREA = 20
#: KINS category id of each KITTI type written (the one table, seqshape.data.categories)
CATEGORY = KITTI_TYPE_TO_KINS


@dataclass(frozen=True)
class SceneConfig:
    """Settings of a scene set: sequences, frames per sequence (inclusive range), vehicles."""

    preset: str
    n_sequences: int
    frames: tuple[int, int]
    n_vehicles: tuple[int, int]
    sensor: str = "hdl64"
    min_visible_area: int = MIN_VISIBLE_AREA
    rate_hz: float = 10.0

    def layout(self, n_frames: int) -> LayoutConfig:
        return LayoutConfig(n_frames=n_frames, n_vehicles=self.n_vehicles)


PRESETS = {
    "kitti-tiny": SceneConfig("kitti-tiny", 1, (20, 20), (5, 7)),
    "kitti-like": SceneConfig("kitti-like", 4, (60, 100), (10, 20)),
}


def scene_config(preset: str, **overrides) -> SceneConfig:
    """The preset called ``preset`` with ``overrides`` applied (:class:`ConfigError` if unknown)."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown scene preset {preset!r}; choose one of {sorted(PRESETS)}")
    cfg = replace(PRESETS[preset], **{k: v for k, v in overrides.items() if v is not None})
    get_sensor(cfg.sensor)  # validates the name
    if cfg.n_sequences < 1 or cfg.frames[0] < 1 or cfg.frames[0] > cfg.frames[1]:
        raise ConfigError(f"invalid scene settings {cfg}")
    return cfg


def _rng(seed: int, index: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(index), *stream])


def make_scene(cfg: SceneConfig, seed: int, index: int) -> Scene:
    """Build sequence ``index`` of a scene set deterministically (layout and meshes)."""
    rng = _rng(seed, index, 0)
    n_frames = int(rng.integers(cfg.frames[0], cfg.frames[1] + 1))
    lib_seed = int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0])
    vehicles = vehicle_library(cfg.n_vehicles[1], seed=lib_seed)
    return build_scene(cfg.layout(n_frames), vehicles, rng, get_sensor(cfg.sensor).height,
                       cfg.rate_hz)


def kitti_type(scene: Scene, k: int) -> str:
    return "Van" if scene.vehicles[scene.agents[k].vehicle_index].kind == "van" else "Car"


# ----------------------------------------------------------------------------- scene json


def scene_to_json(scene: Scene, sequence: str, extra: dict) -> dict:
    """The ``scene/SSSS.json`` document of ``scene``."""
    agents = []
    for k, a in enumerate(scene.agents):
        v = scene.vehicles[a.vehicle_index]
        agents.append({"track_id": a.track_id, "vehicle_id": v.vehicle_id, "kind": v.kind,
                       "source": v.source, "size": v.size.tolist(), "parked": a.parked,
                       "colour": scene.colours[k].tolist(), "world": a.world.tolist()})
    return {"format": SCENE_FORMAT, "version": SCENE_VERSION, "sequence": sequence,
            "n_frames": scene.n_frames, "rate_hz": scene.rate_hz,
            "sensor_height": scene.sensor_height, "road": asdict(scene.road),
            "ego": scene.ego.tolist(), "agents": agents, **extra}


def load_scene(root, sequence: str) -> tuple[Scene, dict]:
    """Rebuild a generated sequence (meshes from their sources) and return it with its JSON.

    Raises :class:`DataError` when ``scene/SSSS.json`` is missing or inconsistent.
    """
    path = Path(root) / "scene" / f"{sequence}.json"
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(path, "scene file not found (sequence not generated?)") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(path, f"unreadable scene file ({exc})") from None
    if doc.get("format") != SCENE_FORMAT or int(doc.get("version", 0)) > SCENE_VERSION:
        raise DataError(path, f"not a {SCENE_FORMAT} v{SCENE_VERSION} scene file")
    vehicles, agents = [], []
    for i, a in enumerate(doc["agents"]):
        kind, _, vseed = a["source"].partition("procedural:")[2].partition(":")
        if not kind:
            raise DataError(path, f"agents[{i}]: cannot rebuild mesh from {a['source']!r}")
        v = procedural_vehicle(kind, int(vseed))
        v.vehicle_id = a["vehicle_id"]
        if not np.allclose(v.size, a["size"], atol=1e-9):
            raise DataError(path, f"agents[{i}]: rebuilt mesh size {v.size} != {a['size']}")
        vehicles.append(v)
        agents.append(Agent(a["track_id"], i, a["parked"], np.asarray(a["world"], float)))
    scene = Scene(Road(**doc["road"]), np.asarray(doc["ego"], float), agents, vehicles,
                  doc["sensor_height"], doc["rate_hz"],
                  np.asarray([a["colour"] for a in doc["agents"]], float).reshape(-1, 3))
    return scene, doc


# ----------------------------------------------------------------------------- frames


def render_frame(scene: Scene, t: int, calib, lidar_cfg, rng: np.random.Generator):
    """LiDAR sweep and camera image of frame ``t``.

    Returns ``(points (N, 4) float32, owner (N,) int64, CameraFrame)`` (see
    :mod:`seqshape.sim.render`); ``owner`` indexes ``scene.agents`` (or GROUND).
    """
    meshes = [scene.mesh(k) for k in range(len(scene.agents))]
    poses = scene.sensor_poses(t)
    material = ground_material(scene, t)
    pts, owner = render_lidar(meshes, poses, scene.colours, lidar_cfg, rng,
                              ground_material=material)
    cam = render_camera(meshes, poses, scene.colours, camera_rays(calib),
                        -scene.sensor_height, material)
    return pts, owner, cam


def occlusion_level(visible: int, amodal_in_image: int) -> int:
    """KITTI occlusion level (see the module docstring) from pixel areas."""
    if visible <= 0:
        return 3
    f = 1.0 - visible / amodal_in_image
    return 0 if f <= 0.05 else 1 if f <= 0.5 else 2


def box_2d(mask: np.ndarray) -> np.ndarray:
    """KITTI 2D box ``[left, top, right, bottom]`` of a non-empty (H, W) mask (module doc)."""
    h, w = mask.shape
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    return np.array([max(cols[0] - 0.5, 0.0), max(rows[0] - 0.5, 0.0),
                     min(cols[-1] + 0.5, w - 1.0), min(rows[-1] + 0.5, h - 1.0)])


@dataclass
class FrameTruth:
    """Ground truth of one frame: label rows, KINS and COCO annotations (ids assigned later)."""

    labels: list
    kins: list[dict]
    instances: list


def frame_truth(scene: Scene, t: int, cam, calib, min_visible_area: int) -> FrameTruth:
    """Label rows (``KittiLabel``), KINS annotation dicts (without ids) and exact 2D instances
    (``Instance2D``) of frame ``t`` from its :class:`~seqshape.sim.render.CameraFrame`."""
    poses = scene.sensor_poses(t)
    labels, kept = [], []
    for k, a in enumerate(scene.agents):
        a_in = int(cam.amodal[k].sum())
        if a_in == 0:
            continue
        vis = int(cam.visible[k].sum())
        trunc = 1.0 - a_in / (a_in + float(cam.outer_area[k]))
        fields = pose_to_label_fields(poses[k], scene.size(k), calib)
        labels.append(KittiLabel(frame=t, track_id=a.track_id, type=kitti_type(scene, k),
                                 truncated=round(trunc, 6), occluded=occlusion_level(vis, a_in),
                                 bbox=box_2d(cam.amodal[k]), **fields))
        if vis >= min_visible_area:
            kept.append(k)
    oco, ico = occlusion_order([cam.nearest[k] for k in kept], [cam.amodal[k] for k in kept])
    kins, instances = [], []
    for k, o, i in zip(kept, oco, ico, strict=True):
        cat = CATEGORY[kitti_type(scene, k)]
        tid = scene.agents[k].track_id
        ann = kins_annotation(0, t, cat, cam.amodal[k], cam.visible[k], o, i, tid)
        hidden = cam.owner[cam.amodal[k] & ~cam.visible[k]]
        ann["occluded_by"] = sorted(int(scene.agents[j].track_id)
                                    for j in np.unique(hidden[hidden >= 0]))
        ann["depth"] = float(cam.nearest[k])
        kins.append(ann)
        instances.append(Instance2D(cam.visible[k], 1.0, cat, tid))
    return FrameTruth(labels, kins, instances)


def _png(image: np.ndarray) -> bytes:
    import cv2  # heavy optional import (~0.3 s): only the image writer needs OpenCV

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image[:, :, ::-1]))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def _oxts_rows(scene: Scene, calib) -> np.ndarray:
    velo = pose_to_matrix(np.stack([scene.ego_pose(t) for t in range(scene.n_frames)]))
    velo = np.linalg.inv(velo[0]) @ velo  # velodyne t -> velodyne 0
    tv = calib.imu_to_velo
    imu = np.linalg.inv(tv) @ velo @ tv
    return poses_to_oxts(imu, heading0=float(scene.ego[0, 2]))


@dataclass
class SequenceResult:
    """What :func:`generate_sequence` made: ``tracks`` are the generator's own tracks (vehicle
    returns in the frames where the vehicle is labelled), present when requested."""

    sequence: str
    n_frames: int
    n_labels: int
    n_kins: int
    tracks: list | None = None


def generate_sequence(out, cfg: SceneConfig, seed: int, index: int, degrade=None,
                      on_frame=None, return_tracks: bool = False) -> SequenceResult:
    """Generate and write sequence ``index`` (name ``f"{index:04d}"``) under ``out``.

    ``degrade`` is a :class:`seqshape.sim.degrade.DegradeConfig` (None: no degradation);
    ``on_frame()`` is called after each frame (progress).
    """
    out, seq = Path(out), f"{index:04d}"
    degrade = degrade or NO_DEGRADE
    scene = make_scene(cfg, seed, index)
    calib, lidar = kitti_default_calib(), get_sensor(cfg.sensor)
    labels, kins, coco, images = [], [], [], []
    own: dict[int, list] = {}
    for t in range(scene.n_frames):
        pts, owner, cam = render_frame(scene, t, calib, lidar, _rng(seed, index, 1, t))
        kitti.write_velodyne(kitti.velodyne_path(out, seq, t), pts)
        atomic_write_bytes(kitti.image_path(out, seq, t), _png(cam.image))
        truth = frame_truth(scene, t, cam, calib, cfg.min_visible_area)
        labels += truth.labels
        images.append(image_entry(t, seq, t, calib.height, calib.width))
        for ann in truth.kins:
            ann["id"] = len(kins) + 1
            kins.append(ann)
        for inst in degrade_instances(truth.instances, degrade, _rng(seed, index, 2, t),
                                      (calib.height, calib.width)):
            coco.append(coco_annotation(len(coco) + 1, t, inst.category_id, inst.mask,
                                        inst.score, inst.track_id))
        if return_tracks:
            for lab in truth.labels:
                k = lab.track_id  # track ids are agent indices
                own.setdefault(k, []).append((t, pts[owner == k, :3]))
        if on_frame is not None:
            on_frame()
    kitti.write_labels(kitti.label_path(out, seq), labels)
    write_calib(kitti.calib_path(out, seq), calib)
    kitti.write_oxts(kitti.oxts_path(out, seq), _oxts_rows(scene, calib))
    write_kins(out / "amodal" / f"{seq}.json", images, kins)
    write_coco_instances(out / "instances_2d" / f"{seq}.json", images, coco)
    extra = {"seed": int(seed), "index": int(index), "sensor": cfg.sensor,
             "min_visible_area": cfg.min_visible_area, "degrade": asdict(degrade),
             "generator": f"seqshape {__version__}"}
    atomic_write_json(out / "scene" / f"{seq}.json", scene_to_json(scene, seq, extra))
    tracks = _own_tracks(scene, seq, own, cfg) if return_tracks else None
    return SequenceResult(seq, scene.n_frames, len(labels), len(kins), tracks)


def _own_tracks(scene: Scene, seq: str, own: dict, cfg: SceneConfig) -> list:
    tracks = []
    for k in sorted(own):
        frames = [f for f, _ in own[k]]
        v = scene.vehicles[scene.agents[k].vehicle_index]
        tracks.append(Track(
            track_id=f"{seq}_{scene.agents[k].track_id:04d}", points=[p for _, p in own[k]],
            poses=np.stack([scene.sensor_poses(f)[k] for f in frames]), complete=None,
            size=v.size, timestamps=np.array(frames, float) / scene.rate_hz,
            meta={"source": "seqshape-scenes", "sequence": seq, "frames": frames,
                  "mesh_id": v.vehicle_id, "mesh_source": v.source, "sensor": cfg.sensor}))
    return tracks


def _settings(cfg: SceneConfig, seed: int, degrade) -> dict:
    return {"format": SCENE_FORMAT, "version": SCENE_VERSION, "seed": int(seed),
            "config": json.loads(json.dumps(asdict(cfg))),
            "degrade": json.loads(json.dumps(asdict(degrade or NO_DEGRADE)))}


#: the settings a resume must repeat (``scene.json`` also records the sequence names and the
#: generator's version, which may differ)
_SETTINGS_KEYS = ("format", "seed", "config", "degrade")


def generate_scenes(out, cfg: SceneConfig, seed: int = 0, workers: int = 1, degrade=None,
                    progress_bar: bool | None = None,
                    shard: tuple[int, int] = (1, 1)) -> list[SequenceResult]:
    """Generate every sequence of ``cfg`` (of shard ``K/N``) under ``out``; complete sequences
    (their ``scene/SSSS.json`` exists) are skipped.

    Returns the results of the sequences generated by this call. Sequences run in parallel
    over ``workers`` processes (the files depend on neither the workers nor the shard).
    """
    out = Path(out)
    settings = _settings(cfg, seed, degrade)
    check_settings(out, SETTINGS_FILE, settings, keys=_SETTINGS_KEYS, made="scenes generated",
                   write=False)
    out.mkdir(parents=True, exist_ok=True)
    work = plan_work(range(cfg.n_sequences),
                     lambda i: (out / "scene" / f"{i:04d}.json").is_file(), shard)
    names = [f"{i:04d}" for i in range(cfg.n_sequences)]
    atomic_write_json(out / SETTINGS_FILE, {**settings, "sequences": names,
                                            "generator": f"seqshape {__version__}"})
    if work.done:
        log.info("resuming: %d of %d sequences already complete", len(work.done),
                 len(work.items))
    frames = {i: int(_rng(seed, i, 0).integers(cfg.frames[0], cfg.frames[1] + 1))
              for i in work.todo}
    units = [(str(out), cfg, seed, i, degrade) for i in work.todo]
    results = list(run_pool(_sequence_unit, units, workers,
                            weight=lambda u, _r: frames[u[3]], total=sum(frames.values()),
                            desc="scenes", unit="frame", progress_bar=progress_bar))
    return sorted(results, key=lambda r: r.sequence)


def _sequence_unit(unit) -> SequenceResult:
    """:func:`generate_sequence` of ``(out, cfg, seed, index, degrade)`` (a pool work unit)."""
    out, cfg, seed, index, degrade = unit
    return generate_sequence(out, cfg, seed, index, degrade)
